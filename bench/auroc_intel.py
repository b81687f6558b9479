"""Intel AUROC table (issue 2): GMM vs raw counting grid, by resolution and beams removed.

Ground truth at each resolution is the raw grid of every beam (no-return beams cut at 10 m);
cells it never observed are left out. Beside each AUROC, the share of the truth's occupied cells
that the map calls free (Eq. 12), the error a planner must not make. Also: the prior N_p and points
per component that the defaults use, and the time of the whole replay at 5 cm.

    .venv/bin/python bench/auroc_intel.py [--quick]
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from gmm_core import FitConfig, Grid
from gmm_core.metrics import called_free, grid_auroc
from gmm_core.occupancy import map_estimate
from gmm_core.reconstruct import ReconstructionConfig, count_beams
from services.datasets import keep_beams, read_scans
from services.replay import data_extent, replay

LOG = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "carmen" / "intel-corrected.log.gz"
MAX_RANGE = 10.0


def wire_bytes(models_components: int, scans: int) -> float:
    """Bytes per scan on the wire; the protocol's `q` encoding when present, else float32 (24 B per 2D component)."""
    return 24.0 * models_components / scans


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true", help="skip 1 cm")
    args = parser.parse_args()
    scans = list(read_scans(LOG))
    lo, hi = data_extent(scans, MAX_RANGE)
    bbox = [*lo, *hi]
    resolutions = [0.1, 0.05] if args.quick else [0.1, 0.05, 0.01]
    removed = [0.0, 0.5, 0.7, 0.9]
    raw_bytes = 4.0 * np.mean([len(s.hits) + len(s.no_return) for s in scans])
    print(
        f"machine: {platform.processor() or platform.machine()}, {__import__('os').cpu_count()} cores; "
        f"date {time.strftime('%Y-%m-%d')}"
    )
    rows = []
    variance = ReconstructionConfig().variance
    for res in resolutions:
        grid = Grid.from_bbox(lo, hi, res)
        truth = count_beams(grid, [(s.hits, s.no_return, s.pose) for s in scans], MAX_RANGE)
        occupied = truth[0] > truth[1]
        for frac in tqdm(removed, desc=f"{res} m", leave=False):
            sub = [keep_beams(s, 1.0 - frac, 0) for s in scans] if frac else scans
            t0 = time.perf_counter()
            gmm = replay(sub, resolution=res, bbox=bbox, method="mc")
            t_gmm = time.perf_counter() - t0
            raw = replay(sub, resolution=res, bbox=bbox, method="raw")
            rows.append(
                (
                    res,
                    frac,
                    grid_auroc(gmm.prob, *truth),
                    grid_auroc(raw.prob, *truth),
                    called_free(gmm.prob, occupied, variance),
                    called_free(raw.prob, occupied, variance),
                    wire_bytes(gmm.components, gmm.scans),
                    raw_bytes * (1 - frac),
                    t_gmm,
                )
            )
        del truth
    print(
        "\n| resolution | beams removed | AUROC GMM | AUROC raw grid | occupied called free, GMM / raw grid "
        "| GMM bytes/scan (f32) | raw bytes/scan | GMM replay s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for res, frac, a_gmm, a_raw, f_gmm, f_raw, b_gmm, b_raw, t in rows:
        print(
            f"| {res} m | {frac:.0%} | {a_gmm:.4f} | {a_raw:.4f} | {100 * f_gmm:.2f} / {100 * f_raw:.2f} % "
            f"| {b_gmm:.0f} | {b_raw:.0f} | {t:.1f} |"
        )

    # The defaults: prior N_p and points per component, at 5 cm with 70 % removed.
    grid = Grid.from_bbox(lo, hi, 0.05)
    truth = count_beams(grid, [(s.hits, s.no_return, s.pose) for s in scans], MAX_RANGE)
    sub = [keep_beams(s, 0.3, 0) for s in scans]
    print("\n| 5 cm, 70 % removed | AUROC |\n|---|---|")
    for ppc in (1.5, 3.0, 9.0):
        m = replay(sub, resolution=0.05, bbox=bbox, config=FitConfig(points_per_component=ppc))
        for prior in (0.2, 1.0):
            print(
                f"| {ppc} points/component, N_p = {prior} | "
                f"{grid_auroc(map_estimate(m.hits, m.misses, prior), *truth):.4f} |"
            )
    for spc in (1.0, 4.0):
        m = replay(sub, resolution=0.05, bbox=bbox, reconstruction=ReconstructionConfig(samples_per_cell=spc))
        print(f"| {spc} samples per cell | {grid_auroc(m.prob, *truth):.4f} |")

    t0 = time.perf_counter()
    replay(scans, resolution=0.05, bbox=bbox)
    print(f"\nwhole Intel replay (910 scans, fit + reconstruct at 5 cm, warm): {time.perf_counter() - t0:.2f} s")


if __name__ == "__main__":
    main()
