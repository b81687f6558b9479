"""What loop closures cost a map server's tiles (issue 16): tracer seconds to bring the viewer's tiles
up to date after new scans and after the loop closures of each mission second, in process, one
tracer thread, with the robots' closures at one instant and spread over the closure interval.

The office simulation of `gmmap sim` (robots driving at --rate, each closing a loop every 10
simulated seconds, each closure moving every node of the robot's last 20 closures half the way to
the truth: services.agent.sources.RelaxingCorrections) is fitted and encoded once per closure
schedule: every robot at the same instant (one optimiser for the whole fleet, the worst case) and
robot i of n i/n of an interval early (independent back ends, services.sim.trajectory.ClosureSchedule,
what `gmmap sim` runs). Then, second by second of the mission, the scans are added to a FleetMap
and every viewer tile (256 x 256 cells at 0.05, 0.1 and 0.2 m over the world) is brought up to date,
then the second's pose-graph updates are applied and the tiles brought up to date again. Printed
per mission second with closures: nodes moved and the tiles' update CPU s, for both schedules;
then the seconds of the new scans per mission second. Usage:

    .venv/bin/python bench/tile_closures.py [--robots 20] [--seconds 30] [--rate 10] \
        [--samples-per-cell 4] [--repose-cells 0.25]

`--samples-per-cell 1 --repose-cells 1` prices what a server's updates with busy tracers trace
(server.busy_samples_per_cell, tile_updates.BUSY_REPOSE_CELLS).
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
from services.map_server import tile_updates  # noqa: E402
from services.map_server.fleet_map import FleetMap  # noqa: E402
from services.map_server.nodes import ScanEntry  # noqa: E402
from services.sim.fleet import SimulatedFleet, correction_interval, robot_name  # noqa: E402
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


def mission(robots: int, seconds: float, rate: float, seed: int, spread: bool):
    """Per mission second: the encoded scans of every robot, then the closures (updates) due."""
    scans = int(seconds * rate)
    fleet = SimulatedFleet("office", robots, scans, rate, seed, spread_closures=spread)
    every = correction_interval(rate)
    streams = [fleet.scans(i, every) for i in range(robots)]
    closures = [fleet.closures(i, every) for i in range(robots)]
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
                if closures[i].closes_after(k + 1):
                    poses = backs[i].closure(nodes[i], final=False)
                    updates.append(PoseGraphUpdate("f", name, closures[i].revision(k + 1), tuple(poses.items())))
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
    parser.add_argument("--samples-per-cell", type=float, default=4.0)
    parser.add_argument("--repose-cells", type=float, default=tile_updates.REPOSE_CELLS)
    args = parser.parse_args()
    tile_updates.REPOSE_CELLS = args.repose_cells
    schedules = {"at one instant": False, "spread": True}
    closure_s, moved, new_s = {}, {}, {}
    for name, spread in schedules.items():
        start = time.perf_counter()
        fleet, steps = mission(args.robots, args.seconds, args.rate, args.seed, spread)
        grids = viewer_grids(evaluation_grid(fleet))
        print(f"{name}: {sum(len(m) for m, _ in steps)} scans fitted in {time.perf_counter() - start:.0f} s")
        fleet_map = FleetMap("f", trace_threads=1, samples_per_cell=args.samples_per_cell)
        closure_s[name], moved[name], new_s[name] = {}, {}, 0.0
        for second, (messages, updates) in enumerate(steps, 1):
            # As ingest does: the new nodes' samplers made from the models it decoded (FleetMap.add_entries).
            fleet_map.add_entries([ScanEntry.of(*m) for m in messages], [m[0].model for m in messages])
            new_s[name] += update_all(fleet_map, grids)
            for update in updates:
                fleet_map.apply_poses(update)
            if updates:
                closure_s[name][second] = update_all(fleet_map, grids)
                moved[name][second] = sum(len(u.poses) for u in updates)
    print(f"{len(grids)} tiles; tiles' update CPU s after the closures of each mission second (nodes moved)")
    print("| mission s | " + " | ".join(schedules) + " |")
    print("|---|" + "---|" * len(schedules))
    for second in sorted(set().union(*(c.keys() for c in closure_s.values()))):
        cells = [f"{closure_s[n][second]:.2f} ({moved[n][second]})" if second in closure_s[n] else "" for n in moved]
        print(f"| {second} | " + " | ".join(cells) + " |")
    seconds = len(steps)
    for name in schedules:
        costs = list(closure_s[name].values())
        closures = (
            f"closures {sum(costs) / seconds:.3f} CPU s per mission second, at most {max(costs):.2f} after one second's"
            if costs
            else f"no loop closure in {seconds} s (one every {correction_interval(args.rate):g} scans a robot)"
        )
        print(f"{name}: {closures}; new scans {new_s[name] / seconds:.3f} CPU s per mission second")
    return 0


if __name__ == "__main__":
    sys.exit(main())
