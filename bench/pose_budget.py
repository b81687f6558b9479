"""Pose-graph bytes against scan payload over an hour's mission, by resend rule and protocol version
(issue 16, "Bounded cost over a shift": pose-graph payload <= 10% of scan payload).

Robots of the office fleet of `gmmap sim --world office --robots 10 --rate 5 --duration 3600`
(seed 0): each scan's published estimate and true pose, as services/agent/sources.py
SimulatedNodes gives them, and its reach (farthest beam end from the sensor, as the agent records
it). The simulated optimiser (RelaxingCorrections) closes a loop every correction_interval scans
and once at the end, as Agent.publish_all drives it; every closure's poses pass a resend rule and
the poses that pass are encoded as the update a robot sends:

* `v2 rule`: today's before issue 16: a node goes out when its translation moved more than 1 mm
  or it turned more than 1 mrad since the correction last sent for it; a node never corrected goes
  out at its first closure.
* `tol X`: services/agent/sent_poses.SentPoses, the agent's rule: some beam end of the node's scan
  would move by more than X metres from the pose the server holds (the scan's own until corrected).

Each rule's updates are encoded in protocol version 2 (node ids u64, float64 poses: the bytes of
tests/support/golden.version_2_update, the old encoder) and version 3 (protocol.encode). The scan
payload is `--scan-bytes` per scan (default 995 B: the hour-long run's 179.1 MB over 180,000 scans,
docs/RELIABILITY.md). Then the encode and decode time of a 300-node 2D update, both versions.

    PYTHONPATH=. .venv/bin/python bench/pose_budget.py [--robots 3] [--scans 18000]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # runnable from a checkout; tests/support

from gmm_core import FitConfig, Pose  # noqa: E402
from protocol import PoseGraphUpdate, decode, encode  # noqa: E402
from services.agent.sent_poses import SentPoses, beam_reach  # noqa: E402
from services.agent.sources import RelaxingCorrections, simulated_nodes  # noqa: E402
from services.datasets.keyframes import turned  # noqa: E402
from services.sim.fleet import correction_interval  # noqa: E402
from support.golden import version_2_update  # noqa: E402

V2_TOLERANCE = 1e-3  # m and rad, the rule before issue 16


class V2Rule:
    """The agent's rule before issue 16, as it was (no seeding with the scan's pose)."""

    def __init__(self) -> None:
        self.sent: dict[int, Pose] = {}

    def moved(self, poses: dict[int, Pose]) -> dict[int, Pose]:
        out = {}
        for node, pose in poses.items():
            last = self.sent.get(node)
            if (
                last is None
                or np.linalg.norm(pose.t - last.t) > V2_TOLERANCE
                or math.radians(turned(last, pose)) > V2_TOLERANCE
            ):
                out[node] = pose
        self.sent.update(out)
        return out


class ToleranceRule:
    def __init__(self, tolerance: float) -> None:
        self.tolerance = tolerance
        self.sent = SentPoses()

    def moved(self, poses: dict[int, Pose]) -> dict[int, Pose]:
        out = self.sent.moved(poses, self.tolerance)
        self.sent.corrections_sent(out)
        return out


def run_robot(index: int, robots: int, scans: int, rate: float, tolerances: list[float]) -> dict:
    every = correction_interval(rate)
    nodes = simulated_nodes(f"sim:office:{index}:{robots}:0", f"0:{scans}", rate, every)
    max_range = FitConfig().for_dimension(2).max_range
    rules: dict[str, V2Rule | ToleranceRule] = {"v2 rule": V2Rule()}
    rules |= {f"tol {tolerance * 100:g} cm": ToleranceRule(tolerance) for tolerance in tolerances}
    totals = {name: {"poses": 0, "updates": 0, "v2": 0, "v3": 0} for name in rules}
    back_end, corrected, reaches = RelaxingCorrections(), {}, []

    def close(final: bool) -> None:
        poses = back_end.closure(corrected, final)
        for name, rule in rules.items():
            moved = rule.moved(poses)
            if not moved:
                continue
            update = PoseGraphUpdate("default", f"robot_{index}", 1 + totals[name]["updates"], tuple(moved.items()))
            total = totals[name]
            total["poses"] += len(moved)
            total["updates"] += 1
            total["v2"] += len(version_2_update(update))
            total["v3"] += len(encode(update))

    for count, node in enumerate(tqdm(nodes, desc=f"robot {index}", leave=False, file=sys.stderr), 1):
        scan = node.scan
        reach = beam_reach(scan.hits, scan.no_return, max_range)
        reaches.append(reach)
        for rule in rules.values():
            if isinstance(rule, ToleranceRule):
                rule.sent.scan_sent(node.node, node.estimate, reach)
        corrected[node.node] = node
        if nodes.closures.closes_after(count) and count < len(nodes):
            close(final=False)
    close(final=True)
    return {"totals": totals, "reach": np.percentile(reaches, [5, 50, 95]).tolist()}


def codec_times(count: int = 300, repeats: int = 200) -> dict[str, float]:
    """Best-of-`repeats` microseconds to encode and decode an update of `count` 2D poses."""
    rng = np.random.default_rng(0)
    poses = tuple(
        (1000 + node, Pose.from_xytheta(*rng.uniform(-50, 50, 2), rng.uniform(-math.pi, math.pi)))
        for node in range(count)
    )
    update = PoseGraphUpdate("default", "robot_0", 7, poses)
    v2, v3 = version_2_update(update), encode(update)
    times = {}
    for name, call in (
        ("v2 encode", lambda: version_2_update(update)),
        ("v3 encode", lambda: encode(update)),
        ("v2 decode", lambda: decode(v2)),
        ("v3 decode", lambda: decode(v3)),
    ):
        best = math.inf
        for _ in range(repeats):
            start = time.perf_counter()
            call()
            best = min(best, time.perf_counter() - start)
        times[name] = best * 1e6
    times["v2 bytes"], times["v3 bytes"] = len(v2), len(v3)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=3, help="robots of the fleet of 10 to run (default 3)")
    parser.add_argument("--scans", type=int, default=18000, help="scans per robot (default 18000: an hour at 5 Hz)")
    parser.add_argument("--rate", type=float, default=5.0)
    parser.add_argument("--scan-bytes", type=float, default=995.0, help="scan payload per scan, bytes")
    parser.add_argument("--tolerances", type=float, nargs="+", default=[0.005, 0.01, 0.02], help="metres")
    args = parser.parse_args()
    times = codec_times()
    print(
        f"300-node 2D update: v2 {times['v2 bytes']:.0f} B, encode {times['v2 encode']:.0f} us, "
        f"decode {times['v2 decode']:.0f} us; v3 {times['v3 bytes']:.0f} B, encode {times['v3 encode']:.0f} us, "
        f"decode {times['v3 decode']:.0f} us (best of 200)"
    )
    results = [run_robot(index, 10, args.scans, args.rate, args.tolerances) for index in range(args.robots)]
    payload = args.scan_bytes * args.scans * args.robots
    names = list(results[0]["totals"])
    baseline = sum(r["totals"]["v2 rule"]["v2"] for r in results)
    print(f"{args.robots} robots x {args.scans} scans at {args.rate:g} Hz, scan payload {payload / 1e6:.1f} MB")
    print("reach p5/p50/p95 per robot (m): " + "; ".join("/".join(f"{v:.1f}" for v in r["reach"]) for r in results))
    columns = ("poses/scan", "updates", "v2 MB", "v2 share", "v3 MB", "v3 share")
    print(f"{'rule':12s} " + " ".join(f"{column:>10s}" for column in columns))
    for name in names:
        poses = sum(r["totals"][name]["poses"] for r in results)
        updates = sum(r["totals"][name]["updates"] for r in results)
        v2 = sum(r["totals"][name]["v2"] for r in results)
        v3 = sum(r["totals"][name]["v3"] for r in results)
        print(
            f"{name:12s} {poses / (args.scans * args.robots):10.2f} {updates:10d} {v2 / 1e6:10.2f} "
            f"{v2 / payload:10.1%} {v3 / 1e6:10.2f} {v3 / payload:10.1%}   (v3 / v2 rule in v2: {v3 / baseline:.3f})"
        )


if __name__ == "__main__":
    main()
