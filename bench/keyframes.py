"""Keyframe policy table (issue 13): scans kept, bytes and AUROC by --keyframe-distance / -angle.

For each real 2D log, every scan is fitted once (through the `q` wire encoding, as a server
receives it); each policy then keeps the scans `services.datasets.keyframes` keeps and the map
at 5 cm is reconstructed from those alone (Eq. 11). Ground truth is the raw counting grid of
every beam of every scan (no-return beams cut at max_range); cells it never observed are left out.

    .venv/bin/python bench/keyframes.py [--logs intel,freiburg]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gmm_core import FitConfig, Grid
from gmm_core.metrics import grid_auroc
from gmm_core.occupancy import map_estimate
from gmm_core.reconstruct import ReconstructionConfig, count_beams, reconstruct
from gmm_core.sampling import scan_seed
from protocol import encode
from services.datasets import read_scans
from services.datasets.keyframes import KeyframeConfig, keyframes
from services.replay import data_extent, fit_scans, scan_message, through_wire

DATA = ROOT.parent / "shared" / "data" / "carmen"
LOGS = {"intel": DATA / "intel-corrected.log.gz", "freiburg": DATA / "freiburg-079-corrected.log.gz"}
RESOLUTION = 0.05
POLICIES = [(0.0, 0.0), (0.1, 5.0), (0.15, 7.5), (0.15, 10.0), (0.2, 10.0), (0.25, 10.0), (0.2, 15.0), (0.3, 15.0)]
POLICIES += [(0.5, 20.0), (0.2, 0.0), (0.5, 0.0), (1.0, 30.0)]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--logs", default="intel,freiburg")
    args = parser.parse_args()
    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), "?")
    print(f"machine: {cpu or platform.machine()}, {os.cpu_count()} cores; date {time.strftime('%Y-%m-%d')}")
    fit = FitConfig()
    recon = ReconstructionConfig()
    print("\n| log | distance m | angle deg | scans kept | share | bytes (q) | AUROC 5 cm | AUROC - all scans |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.logs.split(","):
        scans = list(read_scans(LOGS[name]))
        lo, hi = data_extent(scans, fit.max_range)
        grid = Grid.from_bbox(lo, hi, RESOLUTION)
        truth = count_beams(grid, [(s.hits, s.no_return, s.pose) for s in scans], fit.max_range)
        models = fit_scans(scans, fit)
        sizes = [len(encode(scan_message(m, s), "q")) for m, s in zip(models, scans)]
        models = [through_wire(m, "q") for m in models]
        baseline = None
        for distance, angle in POLICIES:
            policy = KeyframeConfig(distance=distance, angle=angle, period=0.0)
            kept = [i for i, _ in keyframes(enumerate(scans), policy, lambda item: (item[1].pose, item[1].stamp))]
            hits, misses = reconstruct(
                grid,
                [(models[i], scans[i].pose, scan_seed(0, scans[i].index)) for i in kept],
                samples_per_cell=recon.samples_per_cell,
            )
            score = grid_auroc(map_estimate(hits, misses, recon.prior), *truth)
            baseline = score if baseline is None else baseline
            print(
                f"| {name} | {distance} | {angle} | {len(kept)} of {len(scans)} | {len(kept) / len(scans):.0%} "
                f"| {sum(sizes[i] for i in kept)} | {score:.4f} | {score - baseline:+.4f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
