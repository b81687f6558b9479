"""report.md, report.json and the figures of a graded run, and the summary `gmmap sim` prints."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from services.sim import plots
from services.sim.grading import Grading
from services.sim.record import RunRecord
from services.sim.report import SimReport

# report.md's "How it is measured", word for word.
MEASUREMENT_NOTES = """\
Bytes. `bytes_on_wire` is what the robots' TCP links carried to the server, counted by the
relays: payloads plus Zenoh framing, handshakes and keep-alives. Alternatives, per scan of the
same run: raw scans (float32 per beam in 2D, float32 x, y, z per beam in 3D, as `gmmap inspect`),
occupancy-grid deltas at 0.1 m (the robot's counting grid of its beams; every cell whose state,
unknown / free / occupied, changes costs 4 B index + 1 B value), and OctoMap deltas (the `.bt`
of a fresh 0.1 m OcTree holding just that scan; only when `octomap-python` is installed; in a
run of more than 2000 scans in 2D or 100 in 3D, where a scan's tree takes 15 times as long, every
n-th scan of each robot is built and the scans between count the last one built, so that grading
takes minutes however long the mission).
Grid and OctoMap deltas are lower bounds: neither can be re-posed, so a pose-graph correction
would cost them a resend that is not counted here.

Maps. Every map is graded at 0.1 m against the world's exact ground truth, on the cells the
raw beams of the stored scans observed (their counting grid at the true poses). Three maps of
the same stored scan models: `served` (the server's, pose-graph updates applied),
`published_estimates` (each scan at the pose it was published with: updates withheld from the
server) and `odometry` (each scan at the robot's pure odometry: no loop closure ever, neither
at the server nor in the robot's estimate). `auroc_before_correction` is the odometry one.
A 2D world is graded whole; a 3D one in the box of the robots' paths grown by 8 m (3 m up and
down), and its grid deltas are counted in that box only (fewer than a robot would send).

Times. Ingest lag: per scan, from when its sensor took it to when a Zenoh client on the server
(the tap) sees the server's Ack of it. A robot's scan k is taken k / rate after its first, which
the tap saw; so a scan held back in the robot's outbox (flow control) lags by the time it waited
there, not only by its time in the server's queue. Tile latency: HTTP round trips
of the `--http-clients`, each fetching random 256 x 256 PNG tiles of the viewer's tiling. Faster
than real time: simulated seconds x cores / CPU seconds of the server and agent processes (the
harness's relays, tap and map fetches are not counted; the server's answers to them are).

Memory. The server's resident set with its tracer processes' (VmRSS in /proc), sampled by the
harness five times a second from when the robots start until they are done; growth = last sample
- first.
"""


def write_report(grading: Grading, record: RunRecord, out: Path) -> None:
    """DIR/report.json, DIR/report.md and its four PNGs."""
    out.mkdir(parents=True, exist_ok=True)
    r = grading.report
    (out / "report.json").write_text(json.dumps(r.to_json(), indent=2) + "\n")
    wire_times = {}
    for name, robot in r.per_robot.items():
        events = [e for e in record.events if e.robot == name and e.kind in ("scan", "poses")]
        framing = robot.framing_bytes_per_message or 0.0
        wire_times[name] = (np.array([e.t - grading.t0 for e in events]), np.array([e.size + framing for e in events]))
    corrections = sorted(e.t - grading.t0 for e in record.events if e.kind == "poses")
    plots.bytes_over_time(out / "bytes_over_time.png", grading.per_scan, wire_times)
    plots.auroc_over_time(out / "auroc_over_time.png", r.auroc_over_time, corrections)
    z = float(np.median(np.concatenate([p[:, 2] for p in record.fleet.paths]))) if record.grid.dim == 3 else None
    plots.map_vs_truth(out / "map_vs_truth.png", grading.final_maps, record.grid, z)
    plots.over_mission_time(out / "over_mission_time.png", r.over_mission_time)
    (out / "report.md").write_text(markdown(r))


def _fmt(value, digits: int = 4) -> str:
    if value is None:
        return "-"
    return f"{value:,.{digits}g}" if isinstance(value, float) else f"{value:,}"


def command_line(r: SimReport) -> str:
    fit = f" --component-size {r.component_size:g}" if r.component_size else ""
    scale = f" --time-scale {r.time_scale:g}" if r.time_scale != 1 else ""
    return (
        f"gmmap sim --world {r.world} --robots {r.robots} --duration {r.duration_s:g} "
        f"--rate {r.rate_hz:g}{scale} --seed {r.seed} --http-clients {r.http_clients}{fit}"
    )


def markdown(r: SimReport) -> str:
    def versus(key):
        value = getattr(r, key)
        return f"{_fmt(value)} (wire / this = {r.bytes_on_wire / value:.3g}x)" if value else "-"

    lag = " / ".join(_fmt(v, 3) for v in (r.ingest_lag_p50_s, r.ingest_lag_p99_s, r.ingest_lag_max_s))
    tiles = " / ".join(_fmt(v, 3) for v in (r.tile_latency_p50_s, r.tile_latency_p99_s))
    cpu = " / ".join(str(r.cpu_s[k]) for k in ("server", "agents", "harness"))
    error_kinds = ", ".join(f"{k}: {n}" for k, n in r.tile_error_kinds.items())
    rows = [
        (
            "scans published / stored / resent",
            " / ".join(_fmt(v) for v in (r.scans_published, r.scans_stored, r.scans_resent)),
        ),
        ("bytes on the wire, robots to server (measured TCP)", _fmt(r.bytes_on_wire)),
        (
            "of which payload: scans / pose-graph updates",
            f"{_fmt(r.payload_bytes['scan'])} / {_fmt(r.payload_bytes['poses'])}",
        ),
        ("Zenoh framing per message (measured)", f"{_fmt(r.framing_bytes_per_message, 3)} B"),
        (
            "bytes back, server to robots (measured TCP; Ack payloads)",
            f"{_fmt(r.bytes_on_wire_down)} ({_fmt(r.payload_bytes['ack'])})",
        ),
        ("raw scans", versus("raw_scan_bytes")),
        ("0.1 m grid deltas", versus("grid_delta_bytes")),
        ("OctoMap .bt deltas", versus("octomap_delta_bytes")),
        ("components", _fmt(r.components)),
        ("AUROC at 0.1 m, served map (after corrections)", _fmt(r.auroc)),
        ("AUROC, odometry only (before correction)", _fmt(r.auroc_before_correction)),
        ("AUROC, published estimates (updates withheld)", _fmt(r.auroc_published_estimates)),
        ("graded cells", _fmt(r.auroc_cells)),
        ("ingest lag p50 / p99 / max (s)", lag),
        (
            "tiles shed (503) / fraction; X-Map-Age p99 / max (s)",
            f"{_fmt(r.tile_shed)} / {_fmt(r.tile_shed_fraction, 3)}; "
            f"{_fmt(r.tile_age_p99_s, 3)} / {_fmt(r.tile_age_max_s, 3)}",
        ),
        (
            "tiles fetched / errors; latency p50 / p99 (s)",
            f"{_fmt(r.tile_requests)} / {_fmt(r.tile_errors)}{f' ({error_kinds})' if r.tile_errors else ''}; {tiles}",
        ),
        ("CPU s: server / agents / harness", cpu),
        (
            "the machine's CPU while driving: busy / idle / stolen by other guests",
            " / ".join(f"{r.host_cpu[k]:.0%}" for k in ("busy", "idle", "steal"))
            if r.host_cpu and "busy" in r.host_cpu
            else "-",
        ),
        (
            "a bare Python loop on one core just before the drive (M iterations/s; falls on a busy host)",
            _fmt(r.host_cpu.get("loop_rate_before"), 3) if r.host_cpu else "-",
        ),
        ("faster than real time (simulated s x cores / CPU s of server + agents)", f"{_fmt(r.realtime_factor, 3)}x"),
        ("schedule slip (last scan later than planned, s)", _fmt(r.schedule_slip_s, 3)),
        (
            "server memory (RSS) at start / end / max; growth (MiB)",
            " / ".join(_fmt(v, 4) for v in (r.server_rss_start_mb, r.server_rss_end_mb, r.server_rss_max_mb))
            + f"; {_fmt(r.server_rss_growth_mb, 3)}",
        ),
        ("server restart on the run's data, until it serves every node (s)", _fmt(r.restart_s, 3)),
    ]
    lines = [
        f"# gmmap sim: {r.world}, {r.robots} robot(s), {r.duration_s:g} s at {r.rate_hz:g} Hz"
        + (f", {r.time_scale:g}x compressed" if r.time_scale != 1 else ""),
        "",
        f"`{command_line(r)}`; wall time {r.wall_s:.1f} s.",
        "",
        "| measure | value |",
        "|---|---|",
    ]
    lines += [f"| {measure} | {value} |" for measure, value in rows]
    columns = [
        ("scans_published", 4),
        ("scans_stored", 4),
        ("bytes_on_wire", 4),
        ("raw_scan_bytes", 4),
        ("grid_delta_bytes", 4),
        ("octomap_delta_bytes", 4),
        ("framing_bytes_per_message", 3),
        ("ingest_lag_p99_s", 3),
    ]
    lines += [
        "",
        "| robot | published | stored | wire bytes | raw | grid deltas | OctoMap | framing B/msg | lag p99 s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [
        "| " + " | ".join([name] + [_fmt(getattr(robot, key), digits) for key, digits in columns]) + " |"
        for name, robot in r.per_robot.items()
    ]
    lines += [
        "",
        "![bytes over time](bytes_over_time.png)",
        "",
        "![AUROC over time](auroc_over_time.png)",
        "",
        "![final map and ground truth](map_vs_truth.png)",
        "",
        "![server memory, tile latency and pose-graph bytes over the mission](over_mission_time.png)",
        "",
        "## How it is measured",
        "",
        MEASUREMENT_NOTES.strip(),
        "",
        "## Configuration",
        "",
        *configuration(r.config),
        "",
    ]
    return "\n".join(lines)


def configuration(config: dict) -> list[str]:
    """report.md lines of the resolved configuration (report.json's `config`)."""
    if not config:
        return ["None recorded (`config` in report.json is empty)."]
    return [
        "The resolved configuration of the run, as `config` in report.json:",
        "",
        "```json",
        json.dumps(config, indent=2),
        "```",
    ]


def summary(report: SimReport) -> str:
    """What `gmmap sim` prints when it is done."""
    keys = [
        "robots",
        "duration_s",
        "scans_published",
        "scans_stored",
        "bytes_on_wire",
        "raw_scan_bytes",
        "grid_delta_bytes",
        "octomap_delta_bytes",
        "components",
        "auroc",
        "auroc_before_correction",
        "ingest_lag_p99_s",
        "tile_latency_p99_s",
        "realtime_factor",
        "server_rss_growth_mb",
        "restart_s",
    ]
    values = {key: getattr(report, key) for key in keys}
    return "\n".join(f"{k:>24}: {v:.4g}" if isinstance(v, float) else f"{k:>24}: {v}" for k, v in values.items())
