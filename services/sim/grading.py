"""Grade a RunRecord: bytes against the alternatives, map AUROC against ground truth, latencies,
processor time and memory, into a SimReport (render.MEASUREMENT_NOTES says how each is measured)."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from gmm_core.metrics import auroc
from services.host import cpu_cores
from services.sim.byte_models import observed_masks
from services.sim.fleet import robot_name
from services.sim.rebuild import offline_maps
from services.sim.record import RunRecord
from services.sim.replays import BeamReplays
from services.sim.report import AurocPoint, MissionWindow, RobotReport, SimReport

MISSION_WINDOWS = 30  # of report.json's over_mission_time


@dataclass
class Grading:
    report: SimReport
    per_scan: dict[str, dict[str, np.ndarray]]  # robot -> "t", "raw", "grid", "octomap" per scan
    final_maps: dict[str, np.ndarray]  # "served", "odometry", "truth" (labels), "observed" (mask)
    t0: float  # epoch seconds of the first scan on the wire: time zero of the plots


def percentile(values, q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def graded_auroc(prob: np.ndarray, truth: np.ndarray, observed: np.ndarray) -> float | None:
    labels = truth[observed]
    if labels.all() or not labels.any():
        return None
    return auroc(prob[observed], labels)


def wire_figures(record: RunRecord) -> tuple[dict, dict, dict]:
    """Per robot: payload bytes and messages by kind; first-seen time of each scan; ingest lags.

    A scan's ingest lag runs from when its sensor took it to its Ack: the robot's scan k is taken
    k / rate wall seconds after its first (as the agent schedules them; the rate times the time
    scale), so time a scan spent held back in an outbox counts, not only its time on the wire and
    in the server's queue.
    """
    by_robot: dict[str, dict] = defaultdict(lambda: defaultdict(lambda: [0, 0]))  # kind -> [messages, bytes]
    seen: dict[tuple[str, int], float] = {}
    acked: dict[tuple[str, int], float] = {}
    for e in record.events:
        tally = by_robot[e.robot]["ack" if e.kind == "ack" else e.kind]
        tally[0] += 1
        tally[1] += e.size
        if e.kind == "scan":
            seen.setdefault((e.robot, e.ids[0]), e.t)
        elif e.kind == "ack" and e.acked == "scan":
            for node in e.ids:
                acked.setdefault((e.robot, node), e.t)
    first = {}  # robot -> (node, seen) of its first scan
    for (robot, node), t in seen.items():
        if robot not in first or node < first[robot][0]:
            first[robot] = (node, t)
    rate = record.options.wall_rate
    taken = {(r, n): first[r][1] + (n - first[r][0]) / rate for r, n in seen}
    lags = {key: acked[key] - t for key, t in taken.items() if key in acked}
    return by_robot, seen, lags


def robot_report(record: RunRecord, name: str, kinds: dict, sizes: dict, stored: int, lags: list[float]) -> RobotReport:
    up, down = record.link_bytes.get(name, (0, 0))
    payload_up = kinds["scan"][1] + kinds["poses"][1]
    messages_up = kinds["scan"][0] + kinds["poses"][0]
    return RobotReport(
        scans_published=record.published.get(name, 0),
        scans_stored=stored,
        bytes_on_wire=up,
        bytes_on_wire_down=down,
        payload_bytes={kind: kinds[kind][1] for kind in ("scan", "poses", "ack")},
        messages={kind: kinds[kind][0] for kind in ("scan", "poses", "ack")},
        scans_resent=max(0, kinds["scan"][0] - record.published.get(name, 0)),  # unacknowledged after 1 s
        framing_bytes_per_message=(up - payload_up) / messages_up if messages_up else None,
        raw_scan_bytes=int(sizes["raw"].sum()),
        grid_delta_bytes=int(sizes["grid"].sum()),
        octomap_delta_bytes=int(sizes["octomap"].sum()) if "octomap" in sizes else None,
        components=record.components.get(name, 0),
        ingest_lag_p99_s=percentile(lags, 99),
        agent_exit=record.agent_exit.get(name),
    )


def grade(record: RunRecord, replays: BeamReplays | None = None) -> Grading:
    """`replays`: the run's beam replays, made ready when its robots were done (None: start them
    now); the offline maps are rebuilt while they run."""
    from tqdm import tqdm

    o, grid = record.options, record.grid
    names = [robot_name(i) for i in range(o.robots)]
    snapshots = record.snapshots
    stored_at = [s.stored for s in snapshots[:-1]] + [{n: sum(1 for r, _ in record.stored if r == n) for n in names}]
    replays = replays or BeamReplays(record)
    replays.begin()
    try:
        with tqdm(total=sum(record.published.values()) + len(snapshots), desc="grading", unit="step") as bar:
            offline = offline_maps(record, stored_at, bar.update)
            per_scan, first_seen = replays.results(bar.update)
    finally:
        replays.close()
    observed = observed_masks(grid, first_seen, stored_at)
    truth = record.fleet.world.ground_truth(grid)
    by_robot, seen, lags = wire_figures(record)
    t0 = min(seen.values(), default=record.started)
    for name in names:
        times = np.array([seen.get((name, k), np.nan) for k in range(record.published.get(name, 0))]) - t0
        per_scan[name]["t"] = times

    timeline = []
    for j, snap in enumerate(snapshots):
        served = np.load(snap.path)
        timeline.append(
            AurocPoint(
                t_s=round(snap.t - t0, 2),
                scans=sum(stored_at[j].values()),
                served=graded_auroc(served, truth, observed[j]),
                published_estimates=graded_auroc(offline["published_estimates"][j], truth, observed[j]),
                odometry=graded_auroc(offline["odometry"][j], truth, observed[j]),
            )
        )
    final_served = np.load(snapshots[-1].path)

    robots = {
        name: robot_report(
            record,
            name,
            by_robot[name],
            per_scan[name],
            stored_at[-1].get(name, 0),
            [lag for (r, _), lag in lags.items() if r == name],
        )
        for name in names
    }

    def total(key):
        values = [getattr(r, key) for r in robots.values()]
        return None if any(v is None for v in values) else sum(values)

    all_lags = list(lags.values())
    tile_latencies = [latency for _, latency, _ in record.tile_latencies]
    tile_ages = [age for _, _, age in record.tile_latencies if np.isfinite(age)]
    shed = record.tile_errors.get("HTTP 503", 0)
    slip = [
        np.nanmax(per_scan[n]["t"]) - np.nanmin(per_scan[n]["t"]) - (len(per_scan[n]["t"]) - 1) / o.wall_rate
        for n in names
        if np.isfinite(per_scan[n]["t"]).any()
    ]
    busy = record.cpu_s["server"] + record.cpu_s["agents"]
    messages_up = sum(r.messages["scan"] + r.messages["poses"] for r in robots.values())
    payload_up = sum(r.payload_bytes["scan"] + r.payload_bytes["poses"] for r in robots.values())
    final = timeline[-1]
    report = SimReport(
        world=o.world,
        dimension=grid.dim,
        robots=o.robots,
        duration_s=o.duration,
        rate_hz=o.rate,
        time_scale=o.time_scale,
        seed=o.seed,
        http_clients=o.http_clients,
        component_size=record.config.fit.component_size,
        wall_s=round(record.wall_s, 2),
        restart_s=None if record.restart_s is None else round(record.restart_s, 2),
        scans_published=total("scans_published"),
        scans_stored=total("scans_stored"),
        scans_resent=total("scans_resent"),
        bytes_on_wire=total("bytes_on_wire"),
        bytes_on_wire_down=total("bytes_on_wire_down"),
        payload_bytes={k: sum(r.payload_bytes[k] for r in robots.values()) for k in ("scan", "poses", "ack")},
        scan_payload_bytes=sum(r.payload_bytes["scan"] for r in robots.values()),
        pose_payload_bytes=sum(r.payload_bytes["poses"] for r in robots.values()),
        framing_bytes_per_message=(total("bytes_on_wire") - payload_up) / messages_up if messages_up else None,
        raw_scan_bytes=total("raw_scan_bytes"),
        grid_delta_bytes=total("grid_delta_bytes"),
        octomap_delta_bytes=total("octomap_delta_bytes"),
        components=total("components"),
        auroc=final.served,
        auroc_before_correction=final.odometry,
        auroc_published_estimates=final.published_estimates,
        auroc_resolution_m=grid.resolution,
        auroc_cells=int(observed[-1].sum()),
        ingest_lag_p50_s=percentile(all_lags, 50),
        ingest_lag_p99_s=percentile(all_lags, 99),
        ingest_lag_max_s=max(all_lags, default=None),
        tile_requests=len(tile_latencies),
        tile_errors=sum(record.tile_errors.values()),
        tile_error_kinds=record.tile_errors,
        tile_latency_p50_s=percentile(tile_latencies, 50),
        tile_latency_p99_s=percentile(tile_latencies, 99),
        tile_shed=shed,
        tile_shed_fraction=shed / (len(tile_latencies) + sum(record.tile_errors.values()) or 1),
        tile_age_p99_s=percentile(tile_ages, 99),
        tile_age_max_s=max(tile_ages, default=None),
        cpu_s={k: round(v, 2) for k, v in record.cpu_s.items()},
        host_cpu=record.host_cpu,
        realtime_factor=o.duration * cpu_cores() / busy,
        schedule_slip_s=max(slip, default=None),
        **memory_growth(record.server_rss),
        server_rss_over_time=memory_series(record.server_rss, record.started),
        over_mission_time=mission_windows(record),
        per_robot=robots,
        auroc_over_time=timeline,
        config=record.config.to_dict(),
    )
    maps = {"served": final_served, "odometry": offline["odometry"][-1], "truth": truth, "observed": observed[-1]}
    return Grading(report, per_scan, maps, t0)


def memory_growth(rss: list[tuple[float, int]]) -> dict:
    """Server resident memory when the robots start, at the end, at most, and the growth between."""
    rss = [b for _, b in rss if b]
    if not rss:
        return {
            "server_rss_start_mb": None,
            "server_rss_end_mb": None,
            "server_rss_max_mb": None,
            "server_rss_growth_mb": None,
        }
    mb = [b / 2**20 for b in rss]
    return {
        "server_rss_start_mb": mb[0],
        "server_rss_end_mb": mb[-1],
        "server_rss_max_mb": max(mb),
        "server_rss_growth_mb": mb[-1] - mb[0],
    }


def mission_windows(record: RunRecord, windows: int = MISSION_WINDOWS) -> list[MissionWindow]:
    """The run cut into `windows` of equal wall time: memory, tile latency and payload per window,
    against simulated (mission) time."""
    o = record.options
    end = max([record.started + 1e-9] + [t for t, _ in record.server_rss] + [e.t for e in record.events])
    width = (end - record.started) / windows
    which = lambda t: min(windows - 1, max(0, int((t - record.started) // width)))  # noqa: E731
    rss: list[int | None] = [None] * windows
    for t, b in record.server_rss:
        rss[which(t)] = b or rss[which(t)]
    latencies: list[list[float]] = [[] for _ in range(windows)]
    for t, latency, _ in record.tile_latencies:
        latencies[which(t)].append(latency)
    payload = {kind: [0] * windows for kind in ("scan", "poses")}
    for e in record.events:
        if e.kind in payload:
            payload[e.kind][which(e.t)] += e.size
    return [
        MissionWindow(
            mission_s=round((w + 1) * width * o.time_scale, 1),
            server_rss_mb=None if rss[w] is None else round(rss[w] / 2**20, 1),
            tile_requests=len(latencies[w]),
            tile_latency_p99_s=percentile(latencies[w], 99),
            scan_payload_bytes=payload["scan"][w],
            pose_payload_bytes=payload["poses"][w],
        )
        for w in range(windows)
    ]


def memory_series(rss: list[tuple[float, int]], started: float) -> list[tuple[float, float]]:
    """(seconds since the robots started, MiB), one sample a second at most."""
    series, last = [], -1.0
    for t, b in rss:
        if b and t - started >= last + 1.0:
            last = t - started
            series.append((round(last, 1), round(b / 2**20, 1)))
    return series
