"""Tiles under ingest and tile load, in process (issue 16): how answers degrade.

A FleetMap holds the first `--preload` scans of the Intel log; then one thread adds the next
scans at `--rate` scans/s while `--clients` threads ask for random 256 x 256 viewer tiles
(0.05, 0.1 and 0.2 m) over the scans' box, with shedding allowed as the HTTP API does, for
`--seconds`; a shed client waits its Retry-After. Printed: answers by kind, the share shed,
X-Map-Age (and the oldest by kind) and latency percentiles, and the ingest rate achieved.
`--policy off` is the rule before issue 16 (the previous state, however old, while another
request updates the tile; never coalesced nor shed), for comparison.

`--robots N` replaces the Intel log by the office mission of bench/tile_closures.py (N robots at
10 Hz with their loop closures, spread over the interval, as `gmmap sim` runs them): each mission
second's scans are added and its pose-graph updates applied as the clock reaches it (no preload),
and the clients ask for the viewer's tiles of the office.

`--snapshot-every S` adds what `gmmap sim` grades with: every S s (at least 3x the last one's time
apart, as the sim spaces them) the whole box at 0.1 m with every change (max_age 0), whose traces
run in the background (tracers.BACKGROUND_MAX_WAIT_S); `--background off` queues their parts
with the others', first come first served, as before c1e6a9b (but on every tracer thread, as an
interactive trace's since 30d183a, not on all but one as then).

    nice -n 19 .venv/bin/python bench/tile_load.py [--clients 16] [--seconds 20] [--rate 20]
"""

from __future__ import annotations

import argparse
import math
import random
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

from gmm_core import Grid, fit_scan
from protocol import ScanMessage
from services.datasets import read_scans
from services.map_server import tile_serving, tiles, tracers
from services.map_server.fleet_map import FleetMap
from services.map_server.nodes import ScanEntry
from services.map_server.tracers import TracersSaturated
from services.sim.record import evaluation_grid

sys.path.insert(0, str(Path(__file__).resolve().parent))
import tile_closures  # noqa: E402 - the office mission

LOG = Path(__file__).resolve().parents[2] / "shared" / "data" / "carmen" / "intel-corrected.log.gz"
TILE = 256


def viewer_tiles(lo: np.ndarray, hi: np.ndarray) -> list[Grid]:
    out = []
    for res in (0.05, 0.1, 0.2):
        size = TILE * res
        for ix in range(math.floor(lo[0] / size), math.ceil(hi[0] / size)):
            for iy in range(math.floor(lo[1] / size), math.ceil(hi[1] / size)):
                out.append(Grid([ix * size, iy * size], res, (TILE, TILE)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--clients", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--rate", type=float, default=20.0, help="scans offered per second")
    parser.add_argument("--preload", type=int, default=100)
    parser.add_argument("--trace-threads", type=int, default=2)
    parser.add_argument("--policy", choices=("on", "off"), default="on")
    parser.add_argument("--snapshot-every", type=float, default=0.0, help="s between whole-box snapshots (0: none)")
    parser.add_argument("--background", choices=("on", "off"), default="on")
    parser.add_argument("--robots", type=int, default=0, help="the office mission of N robots (0: the Intel log)")
    args = parser.parse_args()
    if args.background == "off":
        trace = tracers.TracerPool.trace
        tracers.TracerPool.trace = lambda pool, grid, plus, minus, background=False: trace(pool, grid, plus, minus)
    if args.policy == "off":
        tiles.MAX_STALE_S, tile_serving.COALESCE_S = math.inf, -1.0
        tracers.SATURATED_QUEUE_PER_THREAD, tracers.SATURATED_WAIT_S = 1 << 30, math.inf
    fleet = FleetMap("f", trace_threads=args.trace_threads)
    if args.robots:
        simulated, steps = tile_closures.mission(args.robots, args.seconds, 10.0, 0, spread=True)
        graded = evaluation_grid(simulated)  # the box `gmmap sim` grades, at 0.1 m
        grids = tile_closures.viewer_grids(graded)
        messages, args.preload, args.rate = [], 0, 10.0 * args.robots
        for scans, updates in steps:  # (entry, model, updates applied after it): each second's after its scans
            messages += [(ScanEntry.of(*m), m[0].model, []) for m in scans]
            messages[-1][2].extend(updates)
    else:
        scans = []
        for scan in read_scans(LOG):
            scans.append(scan)
            if len(scans) == args.preload + int(args.rate * args.seconds) + 1:
                break
        messages = [ScanMessage("f", "r1", s.index, s.stamp, fit_scan(s.hits, s.no_return), s.pose) for s in scans]
        for msg in messages[: args.preload]:
            fleet.add_scan(msg)
        grids = viewer_tiles(*fleet.extent())
        graded = Grid.from_bbox(fleet.extent()[0] - 1.0, fleet.extent()[1] + 1.0, 0.1)
    stop = threading.Event()
    kinds, ages, latencies, lock = Counter(), [], [], threading.Lock()

    def client(seed: int) -> None:
        rng = random.Random(seed)
        while not stop.is_set():
            start = time.perf_counter()
            try:
                answer = fleet.occupancy_answer(rng.choice(grids), may_shed=True)
            except TracersSaturated as shed:
                with lock:
                    kinds["shed"] += 1
                stop.wait(shed.retry_after)  # as a client honouring Retry-After
                continue
            with lock:
                kinds[answer.kind] += 1
                ages.append((answer.kind, answer.age))
                latencies.append(time.perf_counter() - start)

    snapshot_seconds = []

    def snapshots() -> None:
        wait = args.snapshot_every
        while not stop.wait(wait):
            start = time.perf_counter()
            fleet.occupancy_answer(graded, max_age=0.0)
            snapshot_seconds.append(time.perf_counter() - start)
            wait = max(args.snapshot_every, 3 * snapshot_seconds[-1])

    added = args.preload
    threads = [threading.Thread(target=client, args=(i,)) for i in range(args.clients)]
    if args.snapshot_every > 0:
        threads.append(threading.Thread(target=snapshots))
    for thread in threads:
        thread.start()
    begin = time.perf_counter()
    add_seconds = []
    while (elapsed := time.perf_counter() - begin) < args.seconds:
        due = args.preload + int(elapsed * args.rate)
        while added < min(due, len(messages)):
            start = time.perf_counter()
            if isinstance(messages[added], tuple):  # as ingest adds: the model it decoded
                entry, model, updates = messages[added]
                fleet.add_entries([entry], [model])
                for update in updates:
                    fleet.apply_poses(update)
            else:
                fleet.add_scan(messages[added])
            add_seconds.append(time.perf_counter() - start)
            added += 1
        time.sleep(0.005)
    stop.set()
    for thread in threads:
        thread.join()
    total = sum(kinds.values())
    age = np.percentile([a for _, a in ages], [50, 99, 100])
    oldest = {kind: max(a for k, a in ages if k == kind) for kind in kinds if kind != "shed"}
    ms = 1000 * np.percentile(latencies, [50, 99])
    print(
        f"policy {args.policy}: {len(grids)} tiles, {args.clients} clients, {args.trace_threads} tracer threads; "
        f"background {args.background}: {len(snapshot_seconds)} snapshots of "
        + ", ".join(f"{t:.1f}" for t in snapshot_seconds)
        + " s"
    )
    print(f"answers {total} ({total / args.seconds:.0f}/s): " + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())))
    print(
        f"shed {100 * kinds['shed'] / total:.2f} %; "
        f"X-Map-Age p50 {age[0]:.3f} s, p99 {age[1]:.3f} s, max {age[2]:.3f} s"
    )
    print("oldest by kind: " + ", ".join(f"{k} {a:.3f} s" for k, a in sorted(oldest.items())))
    print(f"latency p50 {ms[0]:.0f} ms, p99 {ms[1]:.0f} ms")
    print(
        f"ingest {added - args.preload} of {int(args.rate * args.seconds)} scans offered; "
        f"add_scan p99 {1000 * np.percentile(add_seconds, 99):.1f} ms"
    )


if __name__ == "__main__":
    main()
