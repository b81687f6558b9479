"""A synthetic outdoor 64-ring lidar sequence, for `bench/lidar.py --data`: clean geometry at range.

A street of box buildings on flat ground (z = 0), 16 more boxes scattered to 170 m, seen by an
OS1-64-like sensor (1,024 x 64 beams, elevations -22.5..22.5 deg, 1.8 m above the ground, 2 cm range
noise) driving along x, 5 m a scan; 45 % of the beams drop their return at random, so that a scan
holds ~30k points (the issue's outdoor OS1-64: 36-37k), its median range 17 m, its farthest 170 m.
Written as organised binary PCDs (no return: 0, 0, 0, as ouster-ros writes it) with KITTI poses,
and the boxes' corners (boxes.npy, (n, 2, 3)) for bench/street_truth.py:

    .venv/bin/python bench/street_scans.py /tmp/street
    .venv/bin/python bench/lidar.py --data /tmp/street --format pcd --poses /tmp/street/poses.txt
    .venv/bin/python bench/street_truth.py /tmp/street

Walls and ground are exact planes: the raw grid of every point (bench/lidar.py's truth) is what
OctoMap's ray casting of the same points reproduces, the hardest case for a model that spans the
rings; bench/street_truth.py grades the maps against the street itself (docs/BENCHMARKS.md,
thirty-third session).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

COLUMNS, RINGS = 1024, 64
SENSOR_HEIGHT = 1.8  # m
STEP = 5.0  # m between scans along x
FAR = 170.0  # m: beams reach no farther
DROPPED = 0.45  # of the beams, returning nothing


def street(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) corners of the boxes: both sides of the street every 25 m, and scattered ones."""
    boxes = []
    for x in np.arange(-150.0, 250.0, 25.0):
        for side in (-1.0, 1.0):
            near, depth = side * rng.uniform(12.0, 20.0), side * rng.uniform(8.0, 15.0)
            y0, y1 = sorted((near, near + depth))
            boxes.append(((x, y0, 0.0), (x + rng.uniform(10.0, 20.0), y1, rng.uniform(6.0, 30.0))))
    for _ in range(16):
        x, y = rng.uniform(-170.0, 170.0, 2)
        boxes.append(((x, y, 0.0), (x + 8.0, y + 8.0, rng.uniform(10.0, 40.0))))
    corners = np.array(boxes)
    return corners[:, 0], corners[:, 1]


def beam_directions() -> np.ndarray:
    """(RINGS * COLUMNS, 3) unit vectors, ring by ring (an organised cloud's row order)."""
    azimuth = np.linspace(0.0, 2.0 * np.pi, COLUMNS, endpoint=False)
    elevation = np.radians(np.linspace(-22.5, 22.5, RINGS))
    a, e = np.meshgrid(azimuth, elevation)
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)


def ranges(origin: np.ndarray, directions: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance along each direction to the first box or the ground (inf: nothing within reach)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / directions
        t0, t1 = (lo[None] - origin) * inverse[:, None], (hi[None] - origin) * inverse[:, None]
        enter, leave = np.nanmax(np.minimum(t0, t1), axis=2), np.nanmin(np.maximum(t0, t1), axis=2)
        boxes = np.where(leave >= np.maximum(enter, 0.0), np.maximum(enter, 0.0), np.inf).min(axis=1)
        ground = np.where(directions[:, 2] < 0.0, -origin[2] / directions[:, 2], np.inf)
    hit = np.minimum(boxes, ground)
    return np.where(hit <= FAR, hit, np.inf)


def write_pcd(path: Path, xyz: np.ndarray) -> None:
    header = (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {COLUMNS}\nHEIGHT {RINGS}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(xyz)}\nDATA binary\n"
    )
    path.write_bytes(header.encode() + xyz.astype("<f4").tobytes())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="directory for 000000.pcd ... and poses.txt")
    parser.add_argument("--scans", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    lo, hi = street(rng)
    directions = beam_directions()
    args.out.mkdir(parents=True, exist_ok=True)
    poses = []
    for k in range(args.scans):
        origin = np.array([k * STEP, 0.0, SENSOR_HEIGHT])
        r = ranges(origin, directions, lo, hi) + rng.normal(0.0, 0.02, len(directions))
        r[~np.isfinite(r) | (rng.random(len(r)) < DROPPED)] = 0.0
        write_pcd(args.out / f"{k:06d}.pcd", directions * r[:, None])
        poses.append(f"1 0 0 {origin[0]:g} 0 1 0 {origin[1]:g} 0 0 1 {origin[2]:g}\n")
        print(f"{k:06d}.pcd: {np.count_nonzero(r)} points, median range {np.median(r[r > 0]):.1f} m")
    (args.out / "poses.txt").write_text("".join(poses))
    np.save(args.out / "boxes.npy", np.stack([lo, hi], axis=1))


if __name__ == "__main__":
    main()
