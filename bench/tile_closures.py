"""What loop closures cost a map server's tiles (issue 16): tracer seconds to bring the viewer's tiles
up to date after new scans and after each fleet-wide closure, in process, one tracer thread.

The office simulation of `gmmap sim` (robots driving at --rate, a loop closure every 10 simulated
seconds, all robots at once, each moving every node of its last 20 closures half the way to the
truth: services.agent.sources.RelaxingCorrections) is fitted and encoded once; then, second by
second of the mission, its scans are added to a FleetMap and every viewer tile (256 x 256 cells at
0.05, 0.1 and 0.2 m over the world) is brought up to date, and at each closure the pose-graph
updates are applied and the tiles brought up to date again. Printed per closure: nodes moved, tiles'
update seconds with the quarter-cell re-pose tolerance (tiles.REPOSE_CELLS) and with every move
traced (0), and the seconds of the new scans per mission second. Usage:

    .venv/bin/python bench/tile_closures.py [--robots 20] [--seconds 30] [--rate 10]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gmm_core import Grid, fit_scan  # noqa: E402
from protocol import PoseGraphUpdate, ScanMessage, decode, encode  # noqa: E402
from services.agent.sources import Node, RelaxingCorrections  # noqa: E402
from services.map_server import tiles  # noqa: E402
from services.map_server.fleet_map import FleetMap  # noqa: E402
from services.sim.fleet import correction_interval, robot_name, shared_fleet  # noqa: E402
from services.sim.record import evaluation_grid  # noqa: E402
from services.sim.run import TILE  # noqa: E402


def viewer_grids(box: Grid) -> list[Grid]:
    """The viewer's tiles over `box`, as `gmmap sim --http-clients` asks for them (run.tile_urls)."""
    grids = []
    for res in (0.05, 0.1, 0.2):
        size = TILE * res
        for ix in range(int(box.origin[0] // size), int(-(-box.upper[0] // size))):
            for iy in range(int(box.origin[1] // size), int(-(-box.upper[1] // size))):
                grids.append(Grid([ix * size, iy * size], res, (TILE, TILE)))
    return grids


def mission(robots: int, seconds: float, rate: float, seed: int):
    """Per mission second: the encoded scans of every robot, then the closures (updates) due."""
    scans = int(seconds * rate)
    fleet = shared_fleet("office", robots, scans, rate, seed)
    every = correction_interval(rate)
    streams = [fleet.scans(i, every) for i in range(robots)]
    backs = [RelaxingCorrections() for _ in range(robots)]
    nodes: list[dict[int, Node]] = [{} for _ in range(robots)]
    steps = []
    per_step = int(rate)
    for first in range(0, scans, per_step):
        messages, updates = [], []
        for i in range(robots):
            name = robot_name(i)
            for k in range(first, min(scans, first + per_step)):
                scan = next(streams[i])
                message = ScanMessage("f", name, k, scan.stamp, fit_scan(scan.hits, scan.no_return), scan.odom_pose)
                raw = encode(message)
                messages.append((decode(raw), len(raw), raw))
                nodes[i][k] = Node(k, None, scan.odom_pose, scan.pose)
                if (k + 1) % every == 0:
                    poses = backs[i].closure(nodes[i], final=False)
                    updates.append(PoseGraphUpdate("f", name, (k + 1) // every, tuple(poses.items())))
        steps.append((messages, updates))
    return fleet, steps


def update_all(fleet_map: FleetMap, grids: list[Grid]) -> float:
    start = time.process_time()
    for grid in grids:
        fleet_map.occupancy(grid)
    return time.process_time() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--rate", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    start = time.perf_counter()
    fleet, steps = mission(args.robots, args.seconds, args.rate, args.seed)
    grids = viewer_grids(evaluation_grid(fleet))
    print(f"{sum(len(m) for m, _ in steps)} scans fitted in {time.perf_counter() - start:.0f} s; {len(grids)} tiles")
    tiles_cells = tiles.REPOSE_CELLS
    maps = {cells: FleetMap("f", trace_threads=1) for cells in (tiles_cells, 0.0)}
    new_s = {cells: 0.0 for cells in maps}
    print("| mission s | nodes moved | tiles after the closure, CPU s: re-pose 1/4 cell | every move |")
    print("|---|---|---|---|")
    for second, (messages, updates) in enumerate(steps, 1):
        closure = {}
        for cells, fleet_map in maps.items():
            tiles.REPOSE_CELLS = cells
            fleet_map.add_scans(messages)
            new_s[cells] += update_all(fleet_map, grids)
            for update in updates:
                fleet_map.apply_poses(update)
            if updates:
                closure[cells] = update_all(fleet_map, grids)
        if updates:
            moved = sum(len(u.poses) for u in updates)
            print(f"| {second} | {moved} | {closure[tiles_cells]:.2f} | {closure[0.0]:.2f} |", flush=True)
    seconds = len(steps)
    print(
        "new scans, CPU s per mission second: "
        + ", ".join(f"re-pose {cells} cell {s / seconds:.3f}" for cells, s in new_s.items())
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
