"""BALM OS0 AUROC beside OctoMap (issue 13): `gmmap replay` at 0.2 m by the fraction of points kept.

For each keep fraction the scans are read as `gmmap replay --format pcd --poses poses.txt
--resolution 0.2 --keep-fraction f` reads them (seeded per scan, then the default keyframe policy)
and mapped three ways on one grid:
- GMM: `services.replay.replay(method="mc")` with the product's defaults (`load_config()`: fit
  section resolved for 3D, reconstruction section, seed 0, `q` wire codec), as the CLI calls it;
- raw counting grid of the same points (`method="raw"`);
- OctoMap (octomap-python): `OcTree(0.2).insertPointCloud` of each scan's points in the world
  frame from its sensor origin, read at the grid's cell centres (`search`; never seen: 0.5).
Ground truth: the raw counting grid of every point of every scan (keep fraction 1, no keyframe
policy); cells it never observed are left out (`grid_auroc`).

BALM stores only returned points, so `max_range` (10 m; it ends no-return beams) shortens no ray
of the GMM or the raw grid. OctoMap therefore gets full beams (maxrange -1, the same rays) and, in
a second column, maxrange = max_range, which cuts longer beams at 10 m and drops their end points.

Grid: the trajectory's x-y extent +- MARGIN m and z Z_BAND m (every hit of the data lies in that
band: floor near -2.5 m, ceiling near 8.5 m), on multiples of 0.2 m so that its cells are exactly
OctoMap's voxels. GMM bytes: each scan's ScanMessage in `q`, from a second fit of the same scans
(fits are deterministic; the component totals are checked against the replay's).

    .venv/bin/python bench/auroc_balm.py [--fractions 1.0 0.3 0.1] [--scans N]   (needs .[bench])
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np
from octomap_compare import aligned_bbox, gmm_map, machine_line, octomap_prob, octomap_tree, timed

from gmm_core.metrics import grid_auroc
from protocol import encode
from services.config import load_config
from services.datasets import RangeScan, read_scans
from services.datasets.keyframes import keyframes
from services.replay import fit_scans, replay, scan_message

DATA = ROOT.parent / "shared" / "data" / "3d" / "balm-os0"
RESOLUTION = 0.2
MARGIN = 20.0  # m around the trajectory in x and y
Z_BAND = (-3.0, 9.0)  # m, world z


def evaluation_bbox(scans: list[RangeScan]) -> list[float]:
    """x-y: the sensor positions' extent +- MARGIN; z: Z_BAND; corners outward to multiples of RESOLUTION."""
    origins = np.array([s.pose.t for s in scans])
    lo = np.append(origins[:, :2].min(axis=0) - MARGIN, Z_BAND[0])
    hi = np.append(origins[:, :2].max(axis=0) + MARGIN, Z_BAND[1])
    return aligned_bbox(lo, hi, RESOLUTION)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", type=Path, default=DATA, help="the balm-os0 folder")
    parser.add_argument("--fractions", type=float, nargs="+", default=[1.0, 0.3, 0.1], help="keep fractions")
    parser.add_argument("--scans", type=int, default=None, help="only the first N scans (a quick check)")
    args = parser.parse_args()
    settings = load_config()
    config = settings.fit.for_dimension(3)

    def read(fraction: float) -> list[RangeScan]:
        scans = read_scans(args.data, "pcd", poses=args.data / "poses.txt", keep_fraction=fraction, seed=0)
        return list(scans)[: args.scans]

    every = read(1.0)
    bbox = evaluation_bbox(every)
    truth_map = replay(every, resolution=RESOLUTION, bbox=bbox, method="raw", config=config)
    grid, truth = truth_map.grid, (truth_map.hits, truth_map.misses)
    observed = (truth[0] + truth[1]) > 0
    print(machine_line())
    print(
        f"BALM OS0 {args.data}: {len(every)} scans; grid {RESOLUTION} m, bbox x {bbox[0]:g}..{bbox[3]:g}, "
        f"y {bbox[1]:g}..{bbox[4]:g}, z {bbox[2]:g}..{bbox[5]:g} m "
        f"({'x'.join(map(str, grid.shape))} = {grid.n_cells:,} cells); ground truth observes "
        f"{observed.sum():,} cells, {(truth[0] > truth[1]).sum():,} occupied; fit {config}; "
        f"reconstruction {settings.reconstruction}; keyframes {settings.keyframe}"
    )
    rows = []
    for fraction in args.fractions:
        scans = list(keyframes(read(fraction), settings.keyframe, lambda s: (s.pose, s.stamp)))
        gmm, t_gmm = timed(gmm_map, scans, RESOLUTION, bbox, config, settings.reconstruction)
        raw = replay(scans, resolution=RESOLUTION, bbox=bbox, method="raw", config=config)
        models = fit_scans(scans, config)
        if sum(m.n_components for m in models) != gmm.components:
            raise RuntimeError("the second fit gave other models than the replay's; bytes would not be its bytes")
        q_bytes = np.mean([len(encode(scan_message(m, s), "q")) for m, s in zip(models, scans)])
        xyz_bytes = 12.0 * np.mean([len(s.hits) for s in scans])  # float32 x, y, z per point
        full, t_insert = timed(octomap_tree, scans, RESOLUTION, -1.0)
        full_prob, t_query = timed(octomap_prob, full, grid, observed)
        del full
        cut = octomap_tree(scans, RESOLUTION, config.max_range)
        a_cut = grid_auroc(octomap_prob(cut, grid, observed), *truth)
        del cut
        rows.append(
            (fraction, len(scans), grid_auroc(gmm.prob, *truth), grid_auroc(full_prob, *truth), a_cut)
            + (grid_auroc(raw.prob, *truth),)
            + (gmm.components / gmm.scans, q_bytes, xyz_bytes, t_gmm, t_insert, t_query)
        )
        print(f"keep {fraction}: done, GMM {t_gmm:.0f} s, OctoMap insert {t_insert:.0f} s, query {t_query:.0f} s")
    print(
        f"\n| points kept | scans | AUROC GMM | AUROC OctoMap | AUROC OctoMap, maxrange {config.max_range:g} m "
        "| AUROC raw grid "
        "| GMM components/scan | GMM bytes/scan (q) | raw xyz bytes/scan | GMM replay s | OctoMap insert s "
        "| OctoMap query s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for f, n, a_gmm, a_full, a_cut, a_raw, k, b_q, b_xyz, t_gmm, t_ins, t_q in rows:
        print(
            f"| {f:.0%} | {n} | {a_gmm:.4f} | {a_full:.4f} | {a_cut:.4f} | {a_raw:.4f} | {k:.0f} | {b_q:,.0f} "
            f"| {b_xyz:,.0f} | {t_gmm:.1f} | {t_ins:.1f} | {t_q:.1f} |"
        )


if __name__ == "__main__":
    main()
