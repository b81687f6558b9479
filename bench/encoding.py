"""Wire encodings against map quality and size (issue 4).

AUROC of `q` and `f32` against the unencoded models (Intel at 10 cm and 1 cm, Kurt3D at 10 cm;
ground truth: the raw counting grid of every beam), and bytes per scan against raw scans and
OctoMap's binary `.bt` of the same scan at 0.1 m (when octomap-python is installed).

    .venv/bin/python bench/encoding.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from gmm_core import FitConfig, Grid
from gmm_core.metrics import grid_auroc
from gmm_core.occupancy import map_estimate
from gmm_core.reconstruct import count_beams, reconstruct
from gmm_core.sampling import scan_seed
from protocol import encode
from services.datasets import read_scans
from services.replay import data_extent, fit_scans, scan_message, through_wire

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
MAX_RANGE = 10.0


def auroc_by_encoding(scans, models, resolution, bbox=None):
    lo, hi = data_extent(scans, MAX_RANGE) if bbox is None else bbox
    grid = Grid.from_bbox(lo, hi, resolution)
    truth = count_beams(grid, [(s.hits, s.no_return, s.pose) for s in scans], MAX_RANGE)
    out = {}
    for encoding in ("none", "f32", "q"):
        wired = [through_wire(m, encoding) for m in models]
        h, m = reconstruct(
            grid, [(w, s.pose, scan_seed(0, s.index)) for w, s in zip(wired, scans)], samples_per_cell=4.0
        )
        out[encoding] = grid_auroc(map_estimate(h, m), *truth)
    return out


def octomap_bt_bytes(scan, resolution=0.1) -> int | None:
    try:
        import octomap
    except ImportError:
        return None
    tree = octomap.OcTree(resolution)
    points = scan.pose.apply(scan.hits)
    tree.insertPointCloud(
        np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(scan.pose.t, dtype=np.float64)
    )
    with tempfile.NamedTemporaryFile(suffix=".bt") as f:
        tree.writeBinary(f.name.encode())
        return Path(f.name).stat().st_size


def main() -> None:
    intel = list(read_scans(DATA / "carmen" / "intel-corrected.log.gz"))
    intel_models = fit_scans(intel, FitConfig())
    kurt = list(read_scans(DATA / "3d" / "kurt3d"))
    kurt_models = fit_scans(kurt, FitConfig(component_size=1.0))

    print("| data | resolution | AUROC none | AUROC f32 | AUROC q | q - f32 |\n|---|---|---|---|---|---|")
    for name, scans, models, res, bbox in [
        ("Intel", intel, intel_models, 0.1, None),
        ("Intel", intel, intel_models, 0.01, None),
        ("Kurt3D (3 scans)", kurt, kurt_models, 0.1, (np.array([-12.0, -12.0, -3.0]), np.array([12.0, 12.0, 5.0]))),
    ]:
        a = auroc_by_encoding(scans, models, res, bbox)
        print(f"| {name} | {res} m | {a['none']:.4f} | {a['f32']:.4f} | {a['q']:.4f} | {a['q'] - a['f32']:+.4f} |")

    print(
        "\n| data | components/scan | q B/component | q B/scan | f32 B/scan | raw B/scan | OctoMap .bt 0.1 m B/scan |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, scans, models, raw_per_beam in [("Intel 2D", intel, intel_models, 4), ("Kurt3D", kurt, kurt_models, 12)]:
        q = [len(encode(scan_message(m, s), "q")) for m, s in zip(models, scans)]
        f = [len(encode(scan_message(m, s), "f32")) for m, s in zip(models, scans)]
        raw = [raw_per_beam * (len(s.hits) + len(s.no_return)) for s in scans]
        comps = np.mean([m.n_components for m in models])
        bt = octomap_bt_bytes(scans[0]) if scans[0].pose.dim == 3 else None
        print(
            f"| {name} | {comps:.0f} | {np.sum(q) / (comps * len(scans)):.2f} | {np.mean(q):.0f} | {np.mean(f):.0f} | "
            f"{np.mean(raw):.0f} | {bt if bt is not None else 'n/a (2D)'} |"
        )


if __name__ == "__main__":
    main()
