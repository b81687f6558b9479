"""A map server's restart on a large store, and what one pose-graph update costs the store.

put_poses: into a fresh store, one update listing every node of a robot's graph (--put-sizes
nodes), then --put-updates updates of 50 nodes each (a loop closure moving recent nodes); the
median and worst time of those small updates.

restart: a store of --robots robots x --nodes scans, built quickly from a few fitted Intel scans
re-keyed (their msgpack maps get another robot and node id, the rest of the bytes are as fitted),
and per robot a pose graph over every node: one update listing them all, then --revisions loop
closures of 100 nodes each, at newer revisions. Timed: Store.load alone (read and decode), and
Store.load + Ingest.replay into a FleetMap (what `gmmap server` does before it subscribes), until
every node is held and posed. Usage:

    .venv/bin/python bench/restart.py [--robots 10] [--nodes 20000] [--scans N] [--revisions 20]
                                      [--load-alone] [--put-sizes 1000,10000,20000] [--data DIR]
"""

from __future__ import annotations

import argparse
import resource
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

import msgpack
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gmm_core import Pose, fit_scan  # noqa: E402
from protocol import PoseGraphUpdate, ScanMessage, decode, encode  # noqa: E402
from services.datasets import read_scans  # noqa: E402
from services.map_server.fleet_map import FleetMap  # noqa: E402
from services.map_server.ingest import Ingest  # noqa: E402
from services.map_server.state import ServerState  # noqa: E402
from services.map_server.store import Store  # noqa: E402

LOG = ROOT.parent / "shared" / "data" / "carmen" / "intel-corrected.log.gz"
FLEET = "default"
FITTED = 8  # distinct scans; every stored scan is one of them re-keyed
BATCH = 4096  # scans per put_scans transaction while building


class Clock:
    """Wall and CPU seconds since it was made (CPU: this process's, which a loaded machine inflates less)."""

    def __init__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def read(self) -> tuple[float, float]:
        return time.perf_counter() - self.wall, time.process_time() - self.cpu

    def __str__(self) -> str:
        wall, cpu = self.read()
        return f"{wall:.2f} s ({cpu:.2f} s CPU)"


def graph_update(robot: str, revision: int, nodes, shift: float = 0.0, anchor: Pose | None = None):
    poses = tuple((int(n), Pose.from_xytheta(0.1 * n + shift, 0.0, 0.01 * n)) for n in nodes)
    return PoseGraphUpdate(FLEET, robot, revision, poses, anchor)


def bench_put_poses(sizes: list[int], updates: int) -> None:
    rng = np.random.default_rng(0)
    print("put_poses: a 50-node update into a graph of N nodes (ms; CPU ms)")
    print("| nodes | median | worst | median CPU |")
    print("|---|---|---|---|")
    for size in sizes:
        with tempfile.TemporaryDirectory() as data:
            store = Store(data)
            whole = graph_update("r", 1, range(size), anchor=Pose.identity(2))
            store.put_poses(whole)
            times = []
            for revision in range(2, updates + 2):
                start = int(rng.integers(0, max(1, size - 50)))
                small = graph_update("r", revision, range(start, start + 50), shift=0.01 * revision)
                clock = Clock()
                assert store.put_poses(small)
                times.append(clock.read())
            store.close()
        wall, cpu = (1e3 * np.array(times)).T
        print(f"| {size:,} | {np.median(wall):.2f} | {wall.max():.2f} | {np.median(cpu):.2f} |", flush=True)


def fitted_scans() -> list[ScanMessage]:
    """A few fitted Intel scans, to be stored under other keys."""
    scans = [s for _, s in zip(range(FITTED), read_scans(LOG))]
    return [ScanMessage(FLEET, "r", 0, s.stamp, fit_scan(s.hits, s.no_return), s.pose) for s in scans]


def build_store(data: Path, robots: int, nodes: int, scans: int, revisions: int) -> None:
    fitted = fitted_scans()
    templates = [msgpack.unpackb(encode(m), raw=False) for m in fitted]
    decoded = [decode(encode(m)) for m in fitted]  # put_scans reads the key, stamp, model and pose: as received
    store = Store(data)
    clock = Clock()
    for r in range(robots):
        robot = f"r{r}"
        for first in range(0, scans, BATCH):
            batch = []
            for node in range(first, min(scans, first + BATCH)):
                fields = {**templates[node % FITTED], "r": robot, "n": node, "s": float(node)}
                template = decoded[node % FITTED]
                message = ScanMessage(FLEET, robot, node, float(node), template.model, template.pose)
                batch.append((message, msgpack.packb(fields, use_bin_type=True)))
            store.put_scans(batch)
    scans_s, clock = str(clock), Clock()
    rng = np.random.default_rng(1)
    for r in range(robots):
        robot = f"r{r}"
        whole = graph_update(robot, 1, range(nodes), anchor=Pose.from_xytheta(r, 0.0, 0.0))
        store.put_poses(whole)
        for revision in range(2, revisions + 2):
            start = int(rng.integers(0, max(1, nodes - 100)))
            closure = graph_update(robot, revision, range(start, start + 100), shift=0.01 * revision)
            store.put_poses(closure)
    poses_s = str(clock)
    store.close()
    size = sum(f.stat().st_size for f in data.iterdir()) / 2**20
    print(f"built {robots} x {scans:,} scans in {scans_s}, their pose graphs in {poses_s}; {size:.0f} MiB")


def bench_restart(data: Path, robots: int, nodes: int, scans: int, revisions: int, load_alone: bool) -> None:
    clock = Clock()
    store = Store(data)
    held = store._db.execute("SELECT COUNT(*) FROM scans WHERE entry IS NOT NULL").fetchone()[0]
    print(f"{held:,} scans with their entry columns (the others are decoded)")
    print(f"Store open (a conversion included, if the store needs one) {clock}", flush=True)
    if load_alone:
        clock = Clock()
        records = sum(1 for _ in store.load(FLEET))
        print(f"Store.load alone (read and decode) {clock}: {records:,} records", flush=True)
    store.close()

    clock = Clock()
    state = ServerState(FLEET, FleetMap(FLEET), Store(data))
    replayed = Ingest(state, lambda *_: None).replay()
    served = str(clock)
    rows = state.fleet_map.robots()
    assert replayed == robots * scans, replayed
    assert [r["nodes"] for r in rows] == [scans] * robots, rows
    assert [r["pose_revision"] for r in rows] == [revisions + 1] * robots, rows
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10
    print(
        f"Store.load + Ingest.replay: every one of {replayed:,} scans served after {served} (peak RSS {peak:.0f} MiB)"
    )
    state.store.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=10)
    parser.add_argument("--nodes", type=int, default=20_000, help="scans (and pose-graph nodes) per robot")
    parser.add_argument("--scans", type=int, help="scans per robot (default: --nodes; fewer: time the poses alone)")
    parser.add_argument("--revisions", type=int, default=20, help="loop closures per robot after the first update")
    parser.add_argument("--put-sizes", default="1000,10000,20000", help="graph sizes for put_poses; empty: skip")
    parser.add_argument("--put-updates", type=int, default=20)
    parser.add_argument("--load-alone", action="store_true", help="also time Store.load without a FleetMap")
    parser.add_argument("--data", type=Path, help="keep the built store here (reused if it holds one)")
    parser.add_argument(
        "--decoded", action="store_true", help="then restart again with every scan decoded (the entry columns cleared)"
    )
    args = parser.parse_args()

    scans = args.nodes if args.scans is None else args.scans
    sizes = [int(s) for s in args.put_sizes.split(",") if s]
    if sizes:
        bench_put_poses(sizes, args.put_updates)
    if args.robots == 0:
        return 0
    with tempfile.TemporaryDirectory() as scratch:
        data = args.data or Path(scratch)
        if not (data / "gmmap.db").exists():
            build_store(data, args.robots, args.nodes, scans, args.revisions)
        bench_restart(data, args.robots, args.nodes, scans, args.revisions, args.load_alone)
        if args.decoded:
            with sqlite3.connect(data / "gmmap.db") as db:  # as a store written before the entry columns
                db.execute("UPDATE scans SET entry = NULL, components = NULL")
            bench_restart(data, args.robots, args.nodes, scans, args.revisions, args.load_alone)
    return 0


if __name__ == "__main__":
    sys.exit(main())
