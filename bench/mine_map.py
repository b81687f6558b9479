"""The map of `gmmap sim --world mine --robots 2 --duration 30`, built offline for the 3D benchmarks.

The same fleet (world, paths, odometry, beams) the sim's robots build, through the agent's keyframe
policy and fit; each scan published at the robot's own estimate, as the agent sends it, and one
final pose-graph update per robot that moves every node to its true pose (the sim's last
closure converges to the truth). Encoded as on the wire and kept in a cache file (npz of wire
bytes), so a benchmark run spends its time on the queries, not on the world and the fit. The file
holds a fingerprint of the code that builds the map: a change of the fit, the wire format or the
sim makes the next run build it again (a stale map once measured the old fit's region).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from gmm_core import FitConfig, Pose, fit_scan
from protocol import PoseGraphUpdate, ScanMessage, encode
from services.datasets.keyframes import KeyframeConfig, KeyframeFilter
from services.sim.fleet import DEFAULT_RATE, SimulatedFleet, correction_interval, robot_name

WORLD, ROBOTS, DURATION_S = "mine", 2, 30.0
FLEET = "default"
CACHE = Path(__file__).resolve().parent / ".cache" / "mine_map.npz"
ROOT = Path(__file__).resolve().parent.parent
BUILT_BY = ("gmm_core", "protocol", "services/sim", "services/datasets")  # the code whose output the cache holds


def fingerprint() -> str:
    """SHA-256 of the sources under BUILT_BY, path and contents, in path order."""
    digest = hashlib.sha256()
    for path in sorted(p for folder in BUILT_BY for p in (ROOT / folder).rglob("*.py")):
        digest.update(str(path.relative_to(ROOT)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def build(seed: int = 0) -> tuple[list[bytes], list[bytes], np.ndarray]:
    """(scan messages, one final pose-graph update per robot, the last robot's final true position)."""
    scans = int(np.ceil(DURATION_S * DEFAULT_RATE))
    fleet = SimulatedFleet(WORLD, ROBOTS, scans, DEFAULT_RATE, seed)
    fit = FitConfig().for_dimension(3)
    messages, updates = [], []
    last_position = np.zeros(3)
    for index in range(ROBOTS):
        robot, keyframes, truth = robot_name(index), KeyframeFilter(KeyframeConfig()), []
        for scan in fleet.scans(index, correction_interval(DEFAULT_RATE)):
            if not keyframes.keep(scan.odom_pose, scan.stamp):
                continue
            model = fit_scan(scan.hits, scan.no_return, fit)
            messages.append(encode(ScanMessage(FLEET, robot, scan.index, scan.stamp, model, scan.odom_pose)))
            truth.append((scan.index, scan.pose))
            last_position = scan.pose.t
        updates.append(encode(PoseGraphUpdate(FLEET, robot, 1, tuple(truth))))
    return messages, updates, last_position


def load(cache: Path = CACHE) -> tuple[list[bytes], list[bytes], np.ndarray]:
    """`build()`, from the cache file when it was made by the code as it is now (else made again)."""
    code = fingerprint()
    if cache.exists():
        data = np.load(cache, allow_pickle=True)
        if "fingerprint" in data.files and str(data["fingerprint"]) == code:
            return list(data["messages"]), list(data["updates"]), data["position"]
    messages, updates, position = build()
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.savez(
        cache,
        messages=np.array(messages, dtype=object),
        updates=np.array(updates, dtype=object),
        position=position,
        fingerprint=code,
    )
    return messages, updates, position


def shifted(update: PoseGraphUpdate, revision: int, shift: float) -> PoseGraphUpdate:
    """`update` with every pose moved by `shift` metres along x: a correction of every node."""
    moved = tuple((node, Pose(pose.R, pose.t + [shift, 0.0, 0.0])) for node, pose in update.poses)
    return PoseGraphUpdate(update.fleet, update.robot, revision, moved, update.anchor)
