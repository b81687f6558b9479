"""Grade a simulated run: bytes against the alternatives, map AUROC against ground truth, latencies.

Bytes. `bytes_on_wire` is what the robots' TCP links carried to the server, counted by the
relays: payloads plus Zenoh framing, handshakes and keep-alives. Alternatives, per scan of the
same run: raw scans (float32 per beam in 2D, float32 x, y, z per beam in 3D, as `gmmap inspect`),
occupancy-grid deltas at 0.1 m (the robot's counting grid of its beams; every cell whose state,
unknown / free / occupied, changes costs 4 B index + 1 B value), and OctoMap deltas (the `.bt`
of a fresh 0.1 m OcTree holding just that scan; only when `octomap-python` is installed).
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

Times. Ingest lag: per scan, from when a Zenoh client on the server (the tap) sees it to when
the tap sees the server's Ack of it, so both ends are at the server (an Ack is sent express and
may overtake by a millisecond: a few lags are slightly negative). Tile latency: HTTP round trips
of the `--http-clients`, each fetching random 256 x 256 PNG tiles of the viewer's tiling. Faster
than real time: simulated seconds x cores / CPU seconds of the server and agent processes (the
harness's relays, tap and map fetches are not counted; the server's answers to them are).

Memory. The server's resident set (VmRSS in /proc), sampled by the harness five times a second
from when the robots start until they are done; growth = last sample - first.
"""
from __future__ import annotations

import importlib.util
import itertools
import json
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from gmm_core import FitConfig, Grid
from gmm_core.metrics import auroc
from gmm_core.reconstruct import count_beams
from protocol import ScanMessage, decode
from services.datasets.common import RangeScan
from services.map_server.fleet_map import FleetMap
from services.sim.fleet import robot_name
from services.host import cpu_cores
from services.sim.run import RunRecord, slabs
from services.sim.trajectory import path_pose

GRID_DELTA_CELL_BYTES = 5  # 4 B cell index + 1 B state


@dataclass
class Grading:
    report: dict
    per_scan: dict[str, dict[str, np.ndarray]]  # robot -> "t", "raw", "grid", "octomap" per scan
    final_maps: dict[str, np.ndarray]  # "served", "odometry", "truth" (labels), "observed" (mask)
    t0: float  # epoch seconds of the first scan on the wire: time zero of the plots


def percentile(values, q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def grid_state(hits: np.ndarray, misses: np.ndarray) -> np.ndarray:
    """0 unknown, 1 free, 2 occupied, as a counting grid decides."""
    return np.where(hits + misses == 0, 0, np.where(hits > misses, 2, 1)).astype(np.int8)


def scan_window(grid: Grid, scan: RangeScan, max_range: float):
    """(array slices, sub-grid) of `grid` around the scan's rays, or None when it misses the grid."""
    ends = scan.pose.apply(np.concatenate([scan.hits, scan.no_return * max_range]))
    points = np.vstack([ends, scan.pose.t[None]])
    first = np.clip(np.floor((points.min(axis=0) - grid.origin) / grid.resolution).astype(int), 0, grid.shape)
    last = np.clip(np.floor((points.max(axis=0) - grid.origin) / grid.resolution).astype(int) + 1, 0, grid.shape)
    if np.any(last <= first):
        return None
    window = tuple(slice(a, b) for a, b in zip(first[::-1], last[::-1]))
    return window, Grid(grid.origin + first * grid.resolution, grid.resolution, tuple(last - first))


def octomap_delta_bytes(scan: RangeScan, resolution: float) -> int:
    """Size of the `.bt` of a fresh OcTree holding this one scan's returns (2D: one layer)."""
    import octomap

    tree = octomap.OcTree(resolution)
    origin, points = scan.pose.t, scan.pose.apply(scan.hits)
    if len(origin) == 2:  # the mid-plane of the voxel layer above z = 0
        z = resolution / 2
        origin, points = np.append(origin, z), np.column_stack([points, np.full(len(points), z)])
    tree.insertPointCloud(np.ascontiguousarray(points), np.ascontiguousarray(origin))
    return len(tree.writeBinary())


def replay_beams(record: RunRecord, stored_at: list[dict[str, int]], progress) -> tuple[dict, list[np.ndarray]]:
    """Per robot and scan: raw, grid-delta and OctoMap bytes; and the cells observed by each snapshot."""
    with_octomap = importlib.util.find_spec("octomap") is not None  # the [bench] extra
    grid, dim, max_range = record.grid, record.grid.dim, FitConfig().max_range
    observed = [np.zeros(grid.array_shape, bool) for _ in stored_at]
    per_scan = {}
    for index in range(record.fleet.robots):
        name = robot_name(index)
        n = record.published.get(name, 0)
        hits, misses = np.zeros(grid.array_shape, np.float32), np.zeros(grid.array_shape, np.float32)
        sizes = {key: np.zeros(n, np.int64) for key in ("raw", "grid", "octomap")}
        for k, scan in enumerate(itertools.islice(record.fleet.scans(index, record.update_every), n)):
            beams = len(scan.hits) + len(scan.no_return)
            sizes["raw"][k] = 4 * beams * (1 if dim == 2 else 3)
            found = scan_window(grid, scan, max_range)
            if found is not None:
                window, sub = found
                h, m = count_beams(sub, [(scan.hits, scan.no_return, scan.pose)], max_range)
                before = grid_state(hits[window], misses[window])
                hits[window] += h
                misses[window] += m
                changed = grid_state(hits[window], misses[window]) != before
                sizes["grid"][k] = GRID_DELTA_CELL_BYTES * np.count_nonzero(changed)
            if with_octomap:
                sizes["octomap"][k] = octomap_delta_bytes(scan, grid.resolution)
            for j, stored in enumerate(stored_at):
                if stored.get(name, 0) == k + 1:
                    observed[j] |= (hits + misses) > 0
            progress(1)
        per_scan[name] = sizes if with_octomap else {k: v for k, v in sizes.items() if k != "octomap"}
    return per_scan, observed


def offline_maps(record: RunRecord, stored_at: list[dict[str, int]], progress) -> dict[str, list[np.ndarray]]:
    """The published-estimate and odometry maps of the scans stored by each snapshot (server code)."""
    messages = {key: decode(raw, expect=ScanMessage) for key, raw in record.stored.items()}
    maps = {"published_estimates": FleetMap(record.options.fleet), "odometry": FleetMap(record.options.fleet)}
    robots = {robot_name(i): i for i in range(record.fleet.robots)}
    added: dict[str, int] = defaultdict(int)
    out: dict[str, list[np.ndarray]] = {name: [] for name in maps}
    for stored in stored_at:
        for robot, count in stored.items():
            for node in range(added[robot], count):
                message = messages.get((robot, node))
                if message is None:
                    continue
                odometry = path_pose(record.fleet.odometry[robots[robot]][node])
                maps["published_estimates"].add_scan(message)
                maps["odometry"].add_scan(replace(message, pose=odometry))
            added[robot] = max(added[robot], count)
        for name, fleet_map in maps.items():
            out[name].append(np.concatenate([fleet_map.occupancy(slab) for slab in slabs(record.grid)]))
        progress(1)
    return out


def graded_auroc(prob: np.ndarray, truth: np.ndarray, observed: np.ndarray) -> float | None:
    labels = truth[observed]
    if labels.all() or not labels.any():
        return None
    return auroc(prob[observed], labels)


def wire_figures(record: RunRecord) -> tuple[dict, dict, dict]:
    """Per robot: payload bytes and messages by kind; first-seen time of each scan; ingest lags."""
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
    lags = {key: acked[key] - t for key, t in seen.items() if key in acked}
    return by_robot, seen, lags


def robot_report(record: RunRecord, name: str, kinds: dict, sizes: dict, stored: int, lags: list[float]) -> dict:
    up, down = record.link_bytes.get(name, (0, 0))
    payload_up = kinds["scan"][1] + kinds["poses"][1]
    messages_up = kinds["scan"][0] + kinds["poses"][0]
    return {
        "scans_published": record.published.get(name, 0), "scans_stored": stored,
        "bytes_on_wire": up, "bytes_on_wire_down": down,
        "payload_bytes": {kind: kinds[kind][1] for kind in ("scan", "poses", "ack")},
        "messages": {kind: kinds[kind][0] for kind in ("scan", "poses", "ack")},
        "scans_resent": max(0, kinds["scan"][0] - record.published.get(name, 0)),  # unacknowledged after 1 s
        "framing_bytes_per_message": (up - payload_up) / messages_up if messages_up else None,
        "raw_scan_bytes": int(sizes["raw"].sum()), "grid_delta_bytes": int(sizes["grid"].sum()),
        "octomap_delta_bytes": int(sizes["octomap"].sum()) if "octomap" in sizes else None,
        "components": record.components.get(name, 0), "ingest_lag_p99_s": percentile(lags, 99),
        "agent_exit": record.agent_exit.get(name),
    }


def grade(record: RunRecord) -> Grading:
    from tqdm import tqdm

    o, grid = record.options, record.grid
    names = [robot_name(i) for i in range(o.robots)]
    snapshots = record.snapshots
    stored_at = [s.stored for s in snapshots[:-1]] + [{n: sum(1 for r, _ in record.stored if r == n) for n in names}]
    with tqdm(total=sum(record.published.values()) + len(snapshots), desc="grading", unit="step") as bar:
        per_scan, observed = replay_beams(record, stored_at, bar.update)
        offline = offline_maps(record, stored_at, bar.update)
    truth = record.fleet.world.ground_truth(grid)
    by_robot, seen, lags = wire_figures(record)
    t0 = min(seen.values(), default=record.started)
    for name in names:
        times = np.array([seen.get((name, k), np.nan) for k in range(record.published.get(name, 0))]) - t0
        per_scan[name]["t"] = times

    timeline = []
    for j, snap in enumerate(snapshots):
        served = np.load(snap.path)
        timeline.append({"t_s": round(snap.t - t0, 2), "scans": sum(stored_at[j].values()),
                         "served": graded_auroc(served, truth, observed[j]),
                         "published_estimates": graded_auroc(offline["published_estimates"][j], truth, observed[j]),
                         "odometry": graded_auroc(offline["odometry"][j], truth, observed[j])})
    final_served = np.load(snapshots[-1].path)

    robots = {name: robot_report(record, name, by_robot[name], per_scan[name], stored_at[-1].get(name, 0),
                                 [lag for (r, _), lag in lags.items() if r == name]) for name in names}

    def total(key):
        values = [r[key] for r in robots.values()]
        return None if any(v is None for v in values) else sum(values)

    all_lags = list(lags.values())
    slip = [np.nanmax(per_scan[n]["t"]) - np.nanmin(per_scan[n]["t"]) - (len(per_scan[n]["t"]) - 1) / o.rate
            for n in names if np.isfinite(per_scan[n]["t"]).any()]
    busy = record.cpu_s["server"] + record.cpu_s["agents"]
    messages_up = sum(r["messages"]["scan"] + r["messages"]["poses"] for r in robots.values())
    payload_up = sum(r["payload_bytes"]["scan"] + r["payload_bytes"]["poses"] for r in robots.values())
    final = timeline[-1]
    report = {
        "world": o.world, "dimension": grid.dim, "robots": o.robots, "duration_s": o.duration, "rate_hz": o.rate,
        "seed": o.seed, "http_clients": o.http_clients, "component_size": o.component_size,
        "wall_s": round(record.wall_s, 2),
        "scans_published": total("scans_published"), "scans_stored": total("scans_stored"),
        "scans_resent": total("scans_resent"),
        "bytes_on_wire": total("bytes_on_wire"), "bytes_on_wire_down": total("bytes_on_wire_down"),
        "payload_bytes": {k: sum(r["payload_bytes"][k] for r in robots.values()) for k in ("scan", "poses", "ack")},
        "framing_bytes_per_message": (total("bytes_on_wire") - payload_up) / messages_up if messages_up else None,
        "raw_scan_bytes": total("raw_scan_bytes"), "grid_delta_bytes": total("grid_delta_bytes"),
        "octomap_delta_bytes": total("octomap_delta_bytes"), "components": total("components"),
        "auroc": final["served"], "auroc_before_correction": final["odometry"],
        "auroc_published_estimates": final["published_estimates"],
        "auroc_resolution_m": grid.resolution, "auroc_cells": int(observed[-1].sum()),
        "ingest_lag_p50_s": percentile(all_lags, 50), "ingest_lag_p99_s": percentile(all_lags, 99),
        "ingest_lag_max_s": max(all_lags, default=None),
        "tile_requests": len(record.tile_latencies), "tile_errors": sum(record.tile_errors.values()),
        "tile_error_kinds": record.tile_errors,
        "tile_latency_p50_s": percentile(record.tile_latencies, 50),
        "tile_latency_p99_s": percentile(record.tile_latencies, 99),
        "cpu_s": {k: round(v, 2) for k, v in record.cpu_s.items()},
        "realtime_factor": o.duration * cpu_cores() / busy,
        "schedule_slip_s": max(slip, default=None),
        **memory_growth(record.server_rss),
        "server_rss_over_time": memory_series(record.server_rss, record.started),
        "per_robot": robots, "auroc_over_time": timeline,
    }
    maps = {"served": final_served, "odometry": offline["odometry"][-1], "truth": truth, "observed": observed[-1]}
    return Grading(report, per_scan, maps, t0)


def memory_growth(rss: list[tuple[float, int]]) -> dict:
    """Server resident memory when the robots start, at the end, at most, and the growth between."""
    rss = [b for _, b in rss if b]
    if not rss:
        return {"server_rss_start_mb": None, "server_rss_end_mb": None, "server_rss_max_mb": None,
                "server_rss_growth_mb": None}
    mb = [b / 2**20 for b in rss]
    return {"server_rss_start_mb": mb[0], "server_rss_end_mb": mb[-1], "server_rss_max_mb": max(mb),
            "server_rss_growth_mb": mb[-1] - mb[0]}


def memory_series(rss: list[tuple[float, int]], started: float) -> list[tuple[float, float]]:
    """(seconds since the robots started, MiB), one sample a second at most."""
    series, last = [], -1.0
    for t, b in rss:
        if b and t - started >= last + 1.0:
            last = t - started
            series.append((round(last, 1), round(b / 2**20, 1)))
    return series


def write_report(grading: Grading, record: RunRecord, out: Path) -> None:
    """DIR/report.json, DIR/report.md and its four PNGs."""
    from services.sim import plots

    out.mkdir(parents=True, exist_ok=True)
    r = grading.report
    (out / "report.json").write_text(json.dumps(r, indent=2) + "\n")
    wire_times = {}
    for name, robot in r["per_robot"].items():
        events = [e for e in record.events if e.robot == name and e.kind in ("scan", "poses")]
        framing = robot["framing_bytes_per_message"] or 0.0
        wire_times[name] = (np.array([e.t - grading.t0 for e in events]),
                            np.array([e.size + framing for e in events]))
    corrections = sorted(e.t - grading.t0 for e in record.events if e.kind == "poses")
    plots.bytes_over_time(out / "bytes_over_time.png", grading.per_scan, wire_times)
    plots.auroc_over_time(out / "auroc_over_time.png", r["auroc_over_time"], corrections)
    z = float(np.median(np.concatenate([p[:, 2] for p in record.fleet.paths]))) if record.grid.dim == 3 else None
    plots.map_vs_truth(out / "map_vs_truth.png", grading.final_maps, record.grid, z)
    plots.memory_over_time(out / "server_memory.png", r["server_rss_over_time"])
    (out / "report.md").write_text(markdown(r))


def _fmt(value, digits: int = 4) -> str:
    if value is None:
        return "-"
    return f"{value:,.{digits}g}" if isinstance(value, float) else f"{value:,}"


def command_line(r: dict) -> str:
    fit = f" --component-size {r['component_size']:g}" if r["component_size"] else ""
    return (f"gmmap sim --world {r['world']} --robots {r['robots']} --duration {r['duration_s']:g} "
            f"--rate {r['rate_hz']:g} --seed {r['seed']} --http-clients {r['http_clients']}{fit}")


def markdown(r: dict) -> str:
    def versus(key):
        return f"{_fmt(r[key])} (wire / this = {r['bytes_on_wire'] / r[key]:.3g}x)" if r[key] else "-"

    lag = " / ".join(_fmt(r[f"ingest_lag_{q}_s"], 3) for q in ("p50", "p99", "max"))
    tiles = " / ".join(_fmt(r[f"tile_latency_{q}_s"], 3) for q in ("p50", "p99"))
    cpu = " / ".join(str(r["cpu_s"][k]) for k in ("server", "agents", "harness"))
    rows = [
        ("scans published / stored / resent", " / ".join(_fmt(r[k]) for k in ("scans_published", "scans_stored",
                                                                             "scans_resent"))),
        ("bytes on the wire, robots to server (measured TCP)", _fmt(r["bytes_on_wire"])),
        ("of which payload: scans / pose-graph updates",
         f"{_fmt(r['payload_bytes']['scan'])} / {_fmt(r['payload_bytes']['poses'])}"),
        ("Zenoh framing per message (measured)", f"{_fmt(r['framing_bytes_per_message'], 3)} B"),
        ("bytes back, server to robots (measured TCP; Ack payloads)",
         f"{_fmt(r['bytes_on_wire_down'])} ({_fmt(r['payload_bytes']['ack'])})"),
        ("raw scans", versus("raw_scan_bytes")),
        ("0.1 m grid deltas", versus("grid_delta_bytes")),
        ("OctoMap .bt deltas", versus("octomap_delta_bytes")),
        ("components", _fmt(r["components"])),
        ("AUROC at 0.1 m, served map (after corrections)", _fmt(r["auroc"])),
        ("AUROC, odometry only (before correction)", _fmt(r["auroc_before_correction"])),
        ("AUROC, published estimates (updates withheld)", _fmt(r["auroc_published_estimates"])),
        ("graded cells", _fmt(r["auroc_cells"])),
        ("ingest lag p50 / p99 / max (s)", lag),
        ("tiles fetched / errors; latency p50 / p99 (s)",
         f"{_fmt(r['tile_requests'])} / {_fmt(r['tile_errors'])}"
         f"{' (' + ', '.join(f'{k}: {n}' for k, n in r['tile_error_kinds'].items()) + ')' if r['tile_errors'] else ''}"
         f"; {tiles}"),
        ("CPU s: server / agents / harness", cpu),
        ("faster than real time (simulated s x cores / CPU s of server + agents)",
         f"{_fmt(r['realtime_factor'], 3)}x"),
        ("schedule slip (last scan later than planned, s)", _fmt(r["schedule_slip_s"], 3)),
        ("server memory (RSS) at start / end / max; growth (MiB)",
         " / ".join(_fmt(r[f"server_rss_{k}_mb"], 4) for k in ("start", "end", "max"))
         + f"; {_fmt(r['server_rss_growth_mb'], 3)}"),
    ]
    lines = [f"# gmmap sim: {r['world']}, {r['robots']} robot(s), {r['duration_s']:g} s at {r['rate_hz']:g} Hz",
             "", f"`{command_line(r)}`; wall time {r['wall_s']:.1f} s.", "", "| measure | value |", "|---|---|"]
    lines += [f"| {measure} | {value} |" for measure, value in rows]
    columns = [("scans_published", 4), ("scans_stored", 4), ("bytes_on_wire", 4), ("raw_scan_bytes", 4),
               ("grid_delta_bytes", 4), ("octomap_delta_bytes", 4), ("framing_bytes_per_message", 3),
               ("ingest_lag_p99_s", 3)]
    lines += ["", "| robot | published | stored | wire bytes | raw | grid deltas | OctoMap | framing B/msg "
              "| lag p99 s |", "|---|---|---|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join([name] + [_fmt(x[key], digits) for key, digits in columns]) + " |"
              for name, x in r["per_robot"].items()]
    lines += ["", "![bytes over time](bytes_over_time.png)", "", "![AUROC over time](auroc_over_time.png)", "",
              "![final map and ground truth](map_vs_truth.png)", "", "![server memory](server_memory.png)", "",
              "## How it is measured", "",
              __doc__.split("\n\n", 1)[1].strip(), ""]
    return "\n".join(lines)
