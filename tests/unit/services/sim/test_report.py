"""report.json's keys are a contract: the typed report writes exactly them, in their order; report.md
renders it, with the run's configuration."""

import json
from dataclasses import fields

from services.sim.render import markdown, summary
from services.sim.report import AurocPoint, MissionWindow, RobotReport, SimReport

# report.json as scripts outside the repository read it (the keys before `config` predate the typed report)
REPORT_KEYS = [
    "world",
    "dimension",
    "robots",
    "duration_s",
    "rate_hz",
    "time_scale",
    "seed",
    "http_clients",
    "component_size",
    "wall_s",
    "restart_s",
    "scans_published",
    "scans_stored",
    "scans_resent",
    "bytes_on_wire",
    "bytes_on_wire_down",
    "payload_bytes",
    "scan_payload_bytes",
    "pose_payload_bytes",
    "framing_bytes_per_message",
    "raw_scan_bytes",
    "grid_delta_bytes",
    "octomap_delta_bytes",
    "components",
    "auroc",
    "auroc_before_correction",
    "auroc_published_estimates",
    "auroc_resolution_m",
    "auroc_cells",
    "ingest_lag_p50_s",
    "ingest_lag_p99_s",
    "ingest_lag_max_s",
    "tile_requests",
    "tile_errors",
    "tile_error_kinds",
    "tile_latency_p50_s",
    "tile_latency_p99_s",
    "tile_shed",
    "tile_shed_fraction",
    "tile_age_p99_s",
    "tile_age_max_s",
    "cpu_s",
    "host_cpu",
    "realtime_factor",
    "schedule_slip_s",
    "server_rss_start_mb",
    "server_rss_end_mb",
    "server_rss_max_mb",
    "server_rss_growth_mb",
    "server_rss_over_time",
    "over_mission_time",
    "per_robot",
    "auroc_over_time",
    "config",
]
ROBOT_KEYS = [
    "scans_published",
    "scans_stored",
    "bytes_on_wire",
    "bytes_on_wire_down",
    "payload_bytes",
    "messages",
    "scans_resent",
    "framing_bytes_per_message",
    "raw_scan_bytes",
    "grid_delta_bytes",
    "octomap_delta_bytes",
    "components",
    "ingest_lag_p99_s",
    "agent_exit",
]
SNAPSHOT_KEYS = ["t_s", "scans", "served", "published_estimates", "odometry"]


def robot(published: int) -> RobotReport:
    return RobotReport(
        scans_published=published,
        scans_stored=published,
        bytes_on_wire=9000,
        bytes_on_wire_down=800,
        payload_bytes={"scan": 7000, "poses": 500, "ack": 300},
        messages={"scan": 10, "poses": 1, "ack": 11},
        scans_resent=0,
        framing_bytes_per_message=136.4,
        raw_scan_bytes=14400,
        grid_delta_bytes=5000,
        octomap_delta_bytes=None,
        components=120,
        ingest_lag_p99_s=0.05,
        agent_exit=0,
    )


def sample_report(config: dict) -> SimReport:
    return SimReport(
        world="office",
        dimension=2,
        robots=2,
        duration_s=2.0,
        rate_hz=5.0,
        time_scale=1.0,
        seed=0,
        http_clients=1,
        component_size=None,
        wall_s=12.3,
        restart_s=1.5,
        scans_published=20,
        scans_stored=20,
        scans_resent=0,
        bytes_on_wire=18000,
        bytes_on_wire_down=1600,
        payload_bytes={"scan": 14000, "poses": 1000, "ack": 600},
        scan_payload_bytes=14000,
        pose_payload_bytes=1000,
        framing_bytes_per_message=136.4,
        raw_scan_bytes=28800,
        grid_delta_bytes=10000,
        octomap_delta_bytes=None,
        components=240,
        auroc=0.93,
        auroc_before_correction=0.81,
        auroc_published_estimates=0.88,
        auroc_resolution_m=0.1,
        auroc_cells=4321,
        ingest_lag_p50_s=0.01,
        ingest_lag_p99_s=0.05,
        ingest_lag_max_s=0.07,
        tile_requests=40,
        tile_errors=1,
        tile_error_kinds={"HTTP 503": 1},
        tile_latency_p50_s=0.02,
        tile_latency_p99_s=0.2,
        tile_shed=0,
        tile_shed_fraction=0.0,
        tile_age_p99_s=0.5,
        tile_age_max_s=1.0,
        cpu_s={"server": 3.1, "agents": 4.2, "harness": 1.0},
        host_cpu={"busy": 0.7, "idle": 0.1, "steal": 0.2},
        realtime_factor=0.55,
        schedule_slip_s=0.1,
        server_rss_start_mb=120.0,
        server_rss_end_mb=130.0,
        server_rss_max_mb=131.0,
        server_rss_growth_mb=10.0,
        server_rss_over_time=[(0.0, 120.0), (1.0, 130.0)],
        over_mission_time=[MissionWindow(10.0, 130.0, 5, 0.2, 14000, 1000)],
        per_robot={"r0": robot(10), "r1": robot(10)},
        auroc_over_time=[AurocPoint(2.0, 10, 0.9, None, 0.8), AurocPoint(4.0, 20, 0.93, 0.88, 0.81)],
        config=config,
    )


def test_report_fields_are_the_json_keys_in_order():
    assert [f.name for f in fields(SimReport)] == REPORT_KEYS
    assert [f.name for f in fields(RobotReport)] == ROBOT_KEYS
    assert [f.name for f in fields(AurocPoint)] == SNAPSHOT_KEYS


def test_to_json_nests_plain_objects_that_round_trip():
    config = {"fit": {"max_range": 10.0}, "robots": 2}
    written = json.loads(json.dumps(sample_report(config).to_json()))
    assert list(written) == REPORT_KEYS and written["config"] == config
    assert list(written["per_robot"]["r1"]) == ROBOT_KEYS and written["per_robot"]["r1"]["payload_bytes"]["ack"] == 300
    assert written["auroc_over_time"][0] == dict(zip(SNAPSHOT_KEYS, [2.0, 10, 0.9, None, 0.8]))
    assert written["server_rss_over_time"] == [[0.0, 120.0], [1.0, 130.0]]


def test_markdown_shows_the_figures_and_the_configuration():
    text = markdown(sample_report({"fit": {"max_range": 10.0}}))
    assert text.startswith("# gmmap sim: office, 2 robot(s), 2 s at 5 Hz")
    assert "`gmmap sim --world office --robots 2 --duration 2 --rate 5 --seed 0 --http-clients 1`" in text
    assert "| raw scans | 28,800 (wire / this = 0.625x) |" in text
    assert "| OctoMap .bt deltas | - |" in text
    assert "| tiles fetched / errors; latency p50 / p99 (s) | 40 / 1 (HTTP 503: 1); 0.02 / 0.2 |" in text
    assert "| r1 | 10 | 10 | 9,000 | 14,400 | 5,000 | - | 136 | 0.05 |" in text
    assert "## How it is measured\n\nBytes. `bytes_on_wire`" in text
    assert text.endswith(
        "## Configuration\n\nThe resolved configuration of the run, as `config` in report.json:\n\n"
        '```json\n{\n  "fit": {\n    "max_range": 10.0\n  }\n}\n```\n'
    )
    assert "None recorded" in markdown(sample_report({}))


def test_summary_lists_the_headline_figures():
    lines = summary(sample_report({})).splitlines()
    assert lines[0] == "                  robots: 2" and "                   auroc: 0.93" in lines
    assert len(lines) == 16 and "               restart_s: 1.5" in lines
