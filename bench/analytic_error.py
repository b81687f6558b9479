"""Fig. 3: error of the analytic p(occupied) against Monte Carlo, one component seen from the origin.

    .venv/bin/python bench/analytic_error.py [--samples 1000000] [--quick]

A component of N pi = COUNT points sits at distance d on the x-axis, seen from a sensor at the
origin; cells (1 cm squares in 2D, 10 cm cubes in 3D) are centred on the beam at d + offset.
Per (d, offset) the script compares p(occupied) (Eq. 11, the project's prior N_p) computed
  - analytically: gmm_core.analytic.cells.component_evidence (hits Eq. 10, misses Eq. 3-9), and for
    2D also from Eq. 5 alone, as printed (r' = the cell's closest radial distance, hits removed);
  - by Monte Carlo: `--samples` points of the component, one ray from the origin to each, counted
    per cell as the ray tracer does (crosses the cell and ends outside: miss; inside: hit).
"aligned": the component's thin axis lies along the beam (the paper's case); "oblique": the
surface is turned 45 degrees about z. "MC noise" compares a second, independent Monte-Carlo run
with the first: the floor under which no method can be told apart from Monte Carlo.

Writes docs/analytic_error_2d.png and docs/analytic_error_3d.png (|error| maps, N pi = COUNT)
and prints the peak errors for several N pi, the cost per evaluated (cell, component) pair, and
with ../shared/data present the Intel map at 10 cm: time and AUROC of the analytic and the
Monte-Carlo maps, the cost of local evaluation and its break-even against the whole MC map.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
from PIL import Image, ImageDraw, ImageFont

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # runnable from a checkout; Eq. 5 as printed is in tests/support

from gmm_core.analytic.cells import component_evidence, occupancy_at_cells  # noqa: E402
from gmm_core.analytic.evidence_2d import analytic_map_2d  # noqa: E402
from gmm_core.occupancy import DEFAULT_PRIOR, map_estimate  # noqa: E402
from support.paper import eq5_by_angles, eq5_geometry  # noqa: E402


@dataclass(frozen=True)
class Setup:
    dim: int
    cell: float  # side, metres
    sigmas: tuple[float, ...]  # along the surface normal first, metres
    count: float  # N pi: expected points of the component
    distances: np.ndarray  # mean distance d, metres (map rows)
    offsets: np.ndarray  # cell centre - d along the beam, metres (map columns)


def covariance(setup: Setup, tilt_deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    rot = np.eye(setup.dim)
    rot[:2, :2] = [[c, -s], [s, c]]
    return rot @ np.diag(np.square(setup.sigmas)) @ rot.T


def monte_carlo(setup: Setup, cov: np.ndarray, d: float, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Hit and miss fractions of the cells on the beam, from n rays origin -> sample."""
    mean = np.zeros(setup.dim)
    mean[0] = d
    x = rng.multivariate_normal(mean, cov, n)
    half = setup.cell / 2
    lateral = np.abs(x[:, 1:]).max(axis=1)
    # The ray stays inside the tube |y|, |z| <= half up to depth x_out: it crosses every cell on the
    # beam that starts before x_out. It ends inside the cell holding x when |y|, |z| <= half.
    x_out = np.sort(x[:, 0] * np.minimum(1.0, half / np.maximum(lateral, 1e-300)))
    ends = np.sort(x[lateral <= half, 0])
    near = d + setup.offsets - half
    far = d + setup.offsets + half
    crossing = n - np.searchsorted(x_out, near, side="left")
    inside = np.searchsorted(ends, far, side="right") - np.searchsorted(ends, near, side="left")
    return inside / n, (crossing - inside) / n


def analytic(setup: Setup, cov: np.ndarray, d: float, paper_eq5: bool) -> tuple[np.ndarray, np.ndarray]:
    """Hit and miss fractions of the cells on the beam."""
    mean = np.zeros(setup.dim)
    mean[0] = d
    centers = np.zeros((len(setup.offsets), setup.dim))
    centers[:, 0] = d + setup.offsets
    origin = np.zeros(setup.dim)
    hits, misses = component_evidence(mean, cov, origin, centers, setup.cell)
    if paper_eq5:  # Eq. 5 counts the mass beyond the cell's near side: remove what ends inside
        misses = np.maximum(eq5_by_angles(*eq5_geometry(mean, cov, origin, centers, setup.cell)) - hits, 0.0)
    return hits, misses


def error_maps(setup: Setup, cov: np.ndarray, samples: int, methods, counts) -> dict:
    """|p - p_MC| per (d, offset) for each method, and for a second, independent Monte-Carlo
    run (the noise floor), for each N pi in counts: {(name, count): map}."""
    rng = np.random.default_rng(20190412)
    names = [name for name, _ in methods] + ["MC noise"]
    errors = {(n, c): np.zeros((len(setup.distances), len(setup.offsets))) for n in names for c in counts}
    for i, d in enumerate(setup.distances):
        reference = monte_carlo(setup, cov, d, samples, rng)
        estimates = [analytic(setup, cov, d, paper) for _, paper in methods] + [
            monte_carlo(setup, cov, d, samples, rng)
        ]
        for c in counts:
            p_mc = map_estimate(c * reference[0], c * reference[1], DEFAULT_PRIOR).astype(np.float64)
            for name, (hits, misses) in zip(names, estimates):
                errors[name, c][i] = np.abs(map_estimate(c * hits, c * misses, DEFAULT_PRIOR) - p_mc)
    return errors


# --- rendering (pillow only) -----------------------------------------------------------------

_VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], float)


def colour(values: np.ndarray, vmax: float) -> np.ndarray:
    t = np.clip(values / vmax, 0.0, 1.0) * (len(_VIRIDIS) - 1)
    i = np.minimum(t.astype(int), len(_VIRIDIS) - 2)
    f = (t - i)[..., None]
    return ((1 - f) * _VIRIDIS[i] + f * _VIRIDIS[i + 1]).astype(np.uint8)


def panel(err: np.ndarray, noise: float, setup: Setup, title: str, vmax: float, font) -> Image.Image:
    scale = max(2, 360 // err.shape[1])
    heat = Image.fromarray(colour(err, vmax)).resize((err.shape[1] * scale, err.shape[0] * scale), Image.NEAREST)
    left, top, bottom = 70, 40, 50
    img = Image.new("RGB", (heat.width + left + 70, heat.height + top + bottom), "white")
    img.paste(heat, (left, top))
    draw = ImageDraw.Draw(img)
    draw.text((left, 8), f"{title}: peak {err.max():.4f} (MC vs MC {noise:.4f})", fill="black", font=font)
    for frac, d in ((0.0, setup.distances[0]), (1.0, setup.distances[-1])):
        draw.text((4, top + frac * (heat.height - 14)), f"{d:.1f} m", fill="black", font=font)
    for frac, o in ((0.0, setup.offsets[0]), (0.5, 0.0), (1.0, setup.offsets[-1])):
        x = left + frac * (heat.width - 40)
        draw.text((x, top + heat.height + 4), f"{100 * o:+.0f} cm", fill="black", font=font)
    draw.text((left, top + heat.height + 24), "cell offset from the mean along the beam", fill="black", font=font)
    return img


def figure(panels: list[Image.Image], vmax: float, caption: list[str], font, columns: int) -> Image.Image:
    rows = -(-len(panels) // columns)
    w, h = panels[0].width, panels[0].height
    text_h = 20 * len(caption)
    img = Image.new("RGB", (max(w * columns, 520), h * rows + text_h + 50), "white")
    for k, p in enumerate(panels):
        img.paste(p, ((k % columns) * w, (k // columns) * h))
    draw = ImageDraw.Draw(img)
    for i, line in enumerate(caption):
        draw.text((10, 6 + h * rows + 20 * i), line, fill="black", font=font)
    ramp = Image.fromarray(colour(np.linspace(0, vmax, 300)[None].repeat(14, 0), vmax))
    y = h * rows + text_h + 16
    img.paste(ramp, (70, y))
    draw.text((20, y), "0", fill="black", font=font)
    draw.text((380, y), f"{vmax:g} = |p error|", fill="black", font=font)
    return img


# --- the map-scale numbers --------------------------------------------------------------------


def intel_numbers() -> None:
    """The paper's 2D data at 10 cm: map time and AUROC (against the counting grid of the raw
    beams) of the analytic map and of the Monte-Carlo one, and the local evaluation cost."""
    from gmm_core import FitConfig, Grid
    from gmm_core.metrics import grid_auroc
    from gmm_core.reconstruct import count_beams, reconstruct
    from gmm_core.sampling import scan_seed
    from services.datasets import read_scans
    from services.replay import data_extent, fit_scans

    scans = list(read_scans(DATA / "carmen" / "intel-corrected.log.gz"))
    config = FitConfig()
    models = fit_scans(scans, config)
    with_poses = [(m, s.pose) for m, s in zip(models, scans)]
    lo, hi = data_extent(scans, config.max_range)
    grid = Grid.from_bbox(lo, hi, 0.1)
    truth = count_beams(grid, [(s.hits, s.no_return, s.pose) for s in scans], config.max_range)
    seeded = [(m, s.pose, scan_seed(0, s.index)) for m, s in zip(models, scans)]
    analytic_map_2d(with_poses[:2], grid)  # compile
    reconstruct(grid, seeded[:2], samples_per_cell=4.0)
    start = time.perf_counter()
    analytic_counts = analytic_map_2d(with_poses, grid)
    analytic_s = time.perf_counter() - start
    start = time.perf_counter()
    mc_counts = reconstruct(grid, seeded, samples_per_cell=4.0)
    mc_s = time.perf_counter() - start
    n_comp = sum(m.n_components for m in models)
    print(
        f"Intel, 10 cm, {grid.shape[0]}x{grid.shape[1]} cells, {len(scans)} scans, {n_comp} components, "
        f"{numba.get_num_threads()} threads:"
    )
    for name, counts, seconds in (
        ("analytic_map_2d", analytic_counts, analytic_s),
        ("Monte Carlo (reconstruct, 4 samples/cell)", mc_counts, mc_s),
    ):
        auroc = grid_auroc(map_estimate(*counts, DEFAULT_PRIOR), *truth)
        print(f"  {name}: {seconds:.2f} s, AUROC {auroc:.4f}")
    rng = np.random.default_rng(0)
    cells = lo + rng.random((2000, 2)) * (hi - lo)
    occupancy_at_cells(with_poses, cells[:2], 0.1)  # compile
    start = time.perf_counter()
    occupancy_at_cells(with_poses, cells, 0.1)
    per_cell = (time.perf_counter() - start) / len(cells)
    print(
        f"  occupancy_at_cells, random cells, every component tested: {1e6 * per_cell:.0f} us per cell; "
        f"break-even with the Monte-Carlo map: {mc_s / per_cell:.0f} cells"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=10**6, help="Monte-Carlo samples per distance")
    parser.add_argument("--quick", action="store_true", help="coarse maps, for a smoke run")
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    args = parser.parse_args()
    rows = 8 if args.quick else 40
    cols = 13 if args.quick else 49
    setups = {
        2: Setup(2, 0.01, (0.01, 0.05), 3.0, np.linspace(0.5, 8.0, rows), np.linspace(-0.06, 0.06, cols)),
        3: Setup(3, 0.10, (0.02, 0.15, 0.15), 20.0, np.linspace(1.0, 10.0, rows), np.linspace(-0.3, 0.3, cols)),
    }
    font = ImageFont.load_default(size=14)
    print(f"Monte Carlo: {args.samples} samples per distance; prior N_p = {DEFAULT_PRIOR}; {os.cpu_count()} cores")
    for dim, setup in setups.items():
        counts = sorted({setup.count, 3.0, 30.0, 300.0})
        methods = [("analytic", False)] + ([("Eq. 5 alone", True)] if dim == 2 else [])
        panels = []
        for tilt, geometry in ((0.0, "aligned"), (45.0, "oblique")):
            errors = error_maps(setup, covariance(setup, tilt), args.samples, methods, counts)
            for name in [n for n, _ in methods] + ["MC noise"]:
                peaks = ", ".join(f"N pi = {c:g}: {errors[name, c].max():.4f}" for c in counts)
                print(f"{dim}D {100 * setup.cell:g} cm cell, {geometry:8s} {name:12s} peak |p error| {peaks}")
            noise = errors["MC noise", setup.count].max()
            panels += [
                panel(errors[name, setup.count], noise, setup, f"{dim}D {geometry}, {name}", 0.05, font)
                for name, _ in methods
            ]
        caption = [
            "|p - p_MC| for one component seen from the origin; rows: mean distance d",
            f"{args.samples:g} MC samples, N pi = {setup.count:g}, N_p = {DEFAULT_PRIOR}, "
            f"cell {100 * setup.cell:g} cm, sigma = {setup.sigmas} m",
        ]
        path = args.out / f"analytic_error_{dim}d.png"
        figure(panels, 0.05, caption, font, len(methods)).save(path)
        print(f"  wrote {path}")
    pair_costs()
    if DATA.is_dir():
        intel_numbers()


def pair_costs() -> None:
    """Microseconds per (cell, component) pair on one thread: near the component (exact paths) and
    well in front of it (Eq. 5 in 2D, Eq. 9 in 3D), component_evidence on 20000 cells per call."""
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    for dim in (2, 3):
        sigmas = [0.01] + [0.1] * (dim - 1)
        mean = np.zeros(dim)
        mean[0] = 5.0
        cov = np.diag(np.square(sigmas))
        component_evidence(mean, cov, np.zeros(dim), np.zeros((1, dim)), 0.1)  # compile
        for where, depth in (("at", (4.95, 5.05)), ("in front of", (0.5, 4.0))):
            centers = np.zeros((20000, dim))
            centers[:, 0] = np.linspace(*depth, len(centers))
            centers[:, 1] = np.linspace(-0.2, 0.2, len(centers))
            start = time.perf_counter()
            component_evidence(mean, cov, np.zeros(dim), centers, 0.1)
            us = 1e6 * (time.perf_counter() - start) / len(centers)
            print(f"{dim}D, 10 cm cells {where} a component at 5 m: {us:.2f} us per (cell, component), 1 thread")
    numba.set_num_threads(threads)


if __name__ == "__main__":
    main()
