"""3D queries on the map of `gmmap sim --world mine --robots 2 --duration 30` (issue 15).

    PYTHONPATH=. .venv/bin/python bench/query3d.py [--samples-per-cell 4] [--runs 3]

The map: bench/mine_map.py (300 nodes of a 16-ring lidar, fitted as the agent fits them; built on
the first run and cached). A FleetMap with one tracer thread holds every scan at the robot's
estimate, then takes each robot's final pose-graph update (every node to its true pose).

- cold region: the 200 x 200 x 40 cells at 0.1 m (20 x 20 x 4 m) centred on the last robot's last
  position, on a fresh FleetMap (empty caches) after numba's kernels ran once on another map;
- correction: then every node of the last robot moved 5 cm (one PoseGraphUpdate) and the same
  region asked again: the time from applying the update to the answer that shows it.

Times are processor seconds of the process (all its threads: one tracer, so one core) and wall
seconds, the median of `--runs` maps; on a shared machine the processor time is the steadier.

`--auroc SPC [SPC ...]`: instead, the region's quality at each of those samples per cell: AUROC
of the probabilities a server serves (a cell's prior from its neighbourhood, gmm_core.smoothing) against the mine
world's truth over the cells with any evidence (those of the first value), and the processor
seconds of the cold region, one fresh map each.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import mine_map  # noqa: E402

from gmm_core import Grid  # noqa: E402
from gmm_core.metrics import auroc  # noqa: E402
from gmm_core.occupancy import monte_carlo_estimate  # noqa: E402
from protocol import PoseGraphUpdate, ScanMessage, decode  # noqa: E402
from services.map_server.fleet_map import FleetMap  # noqa: E402
from services.sim.worlds import make_world  # noqa: E402

REGION_CELLS = (200, 200, 40)
RESOLUTION = 0.1


def machine_line() -> str:
    cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    return f"{cpu}, {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC"


def timed(*calls) -> tuple[float, float]:
    """(processor s, wall s) of calling each of `calls` in turn."""
    cpu, wall = time.process_time(), time.perf_counter()
    for call in calls:
        call()
    return time.process_time() - cpu, time.perf_counter() - wall


def fleet(messages: list[bytes], updates: list[bytes], samples_per_cell: float) -> FleetMap:
    fleet_map = FleetMap(mine_map.FLEET, samples_per_cell=samples_per_cell, trace_threads=1)
    fleet_map.add_scans([(decode(raw, expect=ScanMessage), len(raw), raw) for raw in messages])
    for raw in updates:
        fleet_map.apply_poses(decode(raw))
    return fleet_map


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples-per-cell", type=float, default=4.0)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument(
        "--auroc", type=float, nargs="+", metavar="SPC", help="the region's AUROC at these samples per cell"
    )
    args = parser.parse_args()
    messages, updates, position = mine_map.load()
    region = Grid(position - np.array(REGION_CELLS) * RESOLUTION / 2, RESOLUTION, REGION_CELLS)
    if args.auroc:
        return region_quality(messages, updates, region, args.auroc)
    last = decode(updates[-1], expect=PoseGraphUpdate)
    fleet(messages, updates, args.samples_per_cell).occupancy(region)  # numba's kernels, compiled or loaded
    rows = []
    for run in range(args.runs):
        fleet_map = fleet(messages, updates, args.samples_per_cell)
        ask = functools.partial(fleet_map.occupancy, region)
        cold = timed(ask)
        before = ask()
        moved = mine_map.shifted(last, revision=2 + run, shift=0.05)
        correction = timed(functools.partial(fleet_map.apply_poses, moved), ask)
        assert not np.array_equal(before, fleet_map.occupancy(region))  # the correction is visible
        rows.append([*cold, *correction])
    cpu_cold, wall_cold, cpu_fix, wall_fix = np.median(rows, axis=0)
    print(machine_line())
    print(
        f"mine sim map: {len(messages)} nodes, samples_per_cell {args.samples_per_cell:g}; "
        f"region {'x'.join(map(str, REGION_CELLS))} at {RESOLUTION} m around {np.round(position, 2).tolist()}"
    )
    print(f"cold region:  {cpu_cold:.2f} s processor, {wall_cold:.2f} s wall (median of {args.runs})")
    print(f"correction of {len(last.poses)} nodes, to the answer: {cpu_fix:.2f} s processor, {wall_fix:.2f} s wall")


def region_quality(messages: list[bytes], updates: list[bytes], region: Grid, samples_per_cell: list[float]) -> None:
    """The region's AUROC against the mine world's truth and its cold processor seconds, per samples per cell."""
    truth = make_world(mine_map.WORLD).ground_truth(region)
    fleet(messages, updates, samples_per_cell[0]).counts(region)  # numba's kernels, compiled or loaded
    observed = None
    print(machine_line())
    print("| samples per cell | AUROC against the world | cold region, processor s |\n|---|---|---|")
    for spc in samples_per_cell:
        fleet_map = fleet(messages, updates, spc)
        start = time.process_time()
        hits, misses = fleet_map.counts(region)
        cpu = time.process_time() - start
        observed = (hits + misses) > 0 if observed is None else observed
        quality = auroc(monte_carlo_estimate(hits, misses, spc)[observed], truth[observed])
        print(f"| {spc:g} | {quality:.5f} | {cpu:.2f} |", flush=True)


if __name__ == "__main__":
    main()
