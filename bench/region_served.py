"""The cold 3D region and a correction as `gmmap server` serves them over HTTP, on one core (issue 15).

    PYTHONPATH=. .venv/bin/python bench/region_served.py [--runs 2] [--shift 0.05]

bench/query3d.py times the reconstruction in process, every sample at once. This runs the product:
a `gmmap server` (one tracer thread, pinned to one core with `taskset -c 0`) is sent the map of
bench/mine_map.py over Zenoh as the robots send it (every scan acknowledged, then each robot's
pose-graph update), and a client asks `GET /v1/occupancy` for the region of query3d.py (200 x 200
x 40 cells at 0.1 m around the last robot, npy) on the server's empty tile cache:

- first answer: the time to it, the samples per cell it holds (X-Map-Samples-Per-Cell: a large
  update is traced with the busy samples per cell first, tile_updates.py) and its AUROC against the mine
  world's truth over the cells the refined answer has evidence in;
- refined: asked every POLL_S (0.05 s), the time until an answer holds the map's 4 samples per cell
  (asked again a second later: "changed after!" where that answer differs, which it must not);
- correction: every node of the last robot moved by `--shift` m along x (a PoseGraphUpdate at a
  new revision, published as its agent would); the time from publishing it to the first answer
  that accounts for it (the server holds the revision and X-Map-Age is 0), and until that is refined.

Each run is a fresh server. The kernels are loaded at the server's start, before it says "ready".
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent))

import mine_map  # noqa: E402
from live_server import BLOCK, AckedScans, start_server  # noqa: E402
from query3d import REGION_CELLS, RESOLUTION, machine_line  # noqa: E402

from gmm_core import Grid  # noqa: E402
from gmm_core.metrics import auroc  # noqa: E402
from protocol import PoseGraphUpdate, ScanMessage, decode, encode, poses_key, scan_key  # noqa: E402
from services.sim.processes import free_port  # noqa: E402
from services.sim.worlds import make_world  # noqa: E402
from services.zenoh_config import zenoh_config  # noqa: E402

POLL_S = 0.05  # the answer that shows a change is seen within this (and a request's 0.2 s patience)


class Served:
    """One `gmmap server` on one core, filled with the mine map, and a Zenoh session to it."""

    def __init__(self, data: str):
        zport, self.hport = free_port(), free_port()
        flags = ["--zenoh-listen", f"tcp/127.0.0.1:{zport}", "--http", f"127.0.0.1:{self.hport}"]
        self.process = start_server([*flags, "--data-dir", data, "--trace-threads", "1"], one_core=True)
        self.session = zenoh.open(zenoh_config("peer", connect=[f"tcp/127.0.0.1:{zport}"]))

    def fill(self, messages: list[bytes], updates: list[bytes]) -> None:
        """Every scan, acknowledged, then every pose-graph update, held."""
        scans = [decode(raw, expect=ScanMessage) for raw in messages]
        acks = AckedScans(self.session, mine_map.FLEET, sorted({s.robot for s in scans}))
        acks.put([(scan_key(s.fleet, s.robot, s.node), raw) for s, raw in zip(scans, messages)])
        if not acks.wait(120):
            raise SystemExit(f"only {len(acks.acked)} of {len(scans)} scans acknowledged")
        acks.close()
        graphs = [decode(raw, expect=PoseGraphUpdate) for raw in updates]
        for update in graphs:
            self.publish(update)
        while any(self.revision(g.robot) != g.revision for g in graphs):
            time.sleep(0.05)

    def publish(self, update: PoseGraphUpdate) -> None:
        self.session.put(poses_key(update.fleet, update.robot), encode(update), congestion_control=BLOCK)

    def revision(self, robot: str) -> int:
        robots = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{self.hport}/v1/robots", timeout=30).read())
        return next(r["pose_revision"] for r in robots if r["robot"] == robot)

    def region(self, grid: Grid) -> tuple[np.ndarray, float, float]:
        """(p(occupied), samples per cell, age) of GET /v1/occupancy for `grid`, as npy."""
        lo, hi = grid.origin, grid.upper
        bbox = ",".join(f"{v:.4f}" for v in (*lo, *hi))
        url = f"http://127.0.0.1:{self.hport}/v1/occupancy?bbox={bbox}&resolution={grid.resolution}&format=npy"
        with urllib.request.urlopen(url, timeout=120) as reply:
            prob = np.load(io.BytesIO(reply.read()))
            return prob, float(reply.headers["X-Map-Samples-Per-Cell"]), float(reply.headers["X-Map-Age"])

    def close(self) -> None:
        self.session.close()
        self.process.terminate()
        self.process.wait(30)


def until(ask, done, limit_s: float = 120.0):
    """Ask every POLL_S until `done(answer)`; (seconds since the call, answer)."""
    start = time.perf_counter()
    while True:
        answer = ask()
        if done(answer):
            return time.perf_counter() - start, answer
        if time.perf_counter() - start > limit_s:
            raise SystemExit(f"no such answer in {limit_s:g} s")
        time.sleep(POLL_S)


def run(messages: list[bytes], updates: list[bytes], region: Grid, truth: np.ndarray, shift: float) -> dict:
    with tempfile.TemporaryDirectory() as data:
        server = Served(data)
        try:
            server.fill(messages, updates)
            last = decode(updates[-1], expect=PoseGraphUpdate)
            ask = lambda: server.region(region)  # noqa: E731
            start = time.perf_counter()
            first_s, (first, first_spc, _) = until(ask, lambda a: True)
            _, (refined, _, _) = until(ask, lambda a: a[1] == 4.0 and a[2] == 0.0)
            refined_s = time.perf_counter() - start
            # Nothing changes now: an answer that says it holds every sample is the last one (a
            # refinement once said so before it published its state: docs/BENCHMARKS.md, twentieth session).
            time.sleep(1.0)
            refined_held = np.array_equal(ask()[0], refined)
            seen = refined != 0.5
            moved = mine_map.shifted(last, revision=last.revision + 1, shift=shift)
            start = time.perf_counter()
            server.publish(moved)

            def accounts(answer) -> bool:  # asked after the server held the revision, and up to date
                return answer[2] == 0.0 and answer[3] == moved.revision

            def ask_after():
                held = server.revision(last.robot)
                return (*server.region(region), held)

            _, (_, fixed_spc, _, _) = until(ask_after, accounts)
            visible_s = time.perf_counter() - start
            _, (fixed_refined, _, _, _) = until(ask_after, lambda a: accounts(a) and a[1] == 4.0)
            return {
                "first_s": first_s,
                "first_spc": first_spc,
                "first_auroc": auroc(first[seen], truth[seen]),
                "refined_s": refined_s,
                "refined_auroc": auroc(refined[seen], truth[seen]),
                "refined_held": refined_held,
                "correction_s": visible_s,
                "correction_spc": fixed_spc,
                "correction_changed": not np.array_equal(fixed_refined, refined),
                "correction_refined_s": time.perf_counter() - start,
            }
        finally:
            server.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--shift", type=float, default=0.05, help="m every node of the last robot moves")
    args = parser.parse_args()
    messages, updates, position = mine_map.load()
    region = Grid(position - np.array(REGION_CELLS) * RESOLUTION / 2, RESOLUTION, REGION_CELLS)
    truth = make_world(mine_map.WORLD).ground_truth(region)
    print(machine_line())
    print(f"mine sim map: {len(messages)} nodes; region {'x'.join(map(str, REGION_CELLS))} at {RESOLUTION} m")
    print(
        "| run | first answer | its samples per cell, AUROC | refined (4), AUROC "
        "| correction visible | its samples per cell | refined |"
    )
    print("|---|---|---|---|---|---|---|")
    for i in range(args.runs):
        r = run(messages, updates, region, truth, args.shift)
        print(
            f"| {i} | {r['first_s']:.2f} s | {r['first_spc']:g}, {r['first_auroc']:.5f} | {r['refined_s']:.2f} s, "
            f"{r['refined_auroc']:.5f}{'' if r['refined_held'] else ' (changed after!)'} | {r['correction_s']:.2f} s "
            f"| {r['correction_spc']:g} | "
            f"{r['correction_refined_s']:.2f} s{'' if r['correction_changed'] else ' (unchanged!)'} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
