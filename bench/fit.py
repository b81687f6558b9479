"""Fit time per scan: our EM vs scikit-learn's GaussianMixture, one core, same data and K.

    .venv/bin/python bench/fit.py

Both fit full covariances with reg_covar = 1e-4, tol = 1e-3 on the change of the mean
log-likelihood, at most 100 iterations, k-means initialisation (ours: EM to tol on a subset of
40 points per component, then at most 15 passes over all points, `fit_mixture`'s defaults).
2D: every Intel scan, K = FitConfig().n_components(hits) (about 3 points per component); ours on
all 910 scans, scikit-learn on every 10th. 3D: the three Kurt3D scans and the OctoMap scan,
each subsampled (seeded) to 20,000 points, K = 100; times at seed 0, ours with its default (in
3D) two k-means starts and with one. The log-likelihood of one scan moves by about 0.03 nats/point from
one seed to another, for either EM, so the 3D comparison averages over seeds: 40 for ours,
`--sklearn-seeds` (default 10, about 7 s each) for scikit-learn. Numba compile is timed
separately, from an empty numba cache, and excluded from the fit times.
"""

import atexit
import os
import shutil
import tempfile

for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"  # one core for both: numba, and scikit-learn's BLAS / OpenMP
os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp()  # so the first call shows a cold compile
atexit.register(shutil.rmtree, os.environ["NUMBA_CACHE_DIR"], ignore_errors=True)

import argparse
import time
import warnings

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.mixture import GaussianMixture
from tqdm import tqdm

from gmm_core import FitConfig, fit_scan
from gmm_core.em import fit_mixture
from services.datasets import read_scans

DATA = "../shared/data"
REG = 1e-4
SKLEARN_EVERY = 10
N_3D, K_3D, RUNS_3D, OURS_SEEDS = 20_000, 100, 5, 40


def machine_line() -> str:
    cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return f"{cpu}, {os.cpu_count()} cores, load average {load}; {time.strftime('%Y-%m-%d')}"


def timed(f, *args, **kwargs):
    start = time.perf_counter()
    out = f(*args, **kwargs)
    return out, time.perf_counter() - start


def sklearn_fit(points: np.ndarray, k: int, seed: int = 0):
    """(mean log-likelihood per point, seconds, iterations) of scikit-learn's fit."""
    gm = GaussianMixture(k, covariance_type="full", reg_covar=REG, random_state=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        _, seconds = timed(gm.fit, points)
    return gm.score(points), seconds, gm.n_iter_


def bench_2d():
    scans = list(read_scans(f"{DATA}/carmen/intel-corrected.log.gz"))
    config = FitConfig()
    first = scans[0].hits
    _, compile_s = timed(fit_mixture, first, config.n_components(first), reg_covar=REG)
    for scan in scans[:20]:  # warm caches and the branch predictor before timing
        fit_scan(scan.hits, scan.no_return)

    ours_ms, scan_ms, ll = [], [], []
    for i, scan in enumerate(tqdm(scans, desc="2D Intel scans")):
        k = config.n_components(scan.hits)
        mixture, seconds = timed(fit_mixture, scan.hits, k, reg_covar=REG)
        ours_ms.append(1e3 * seconds)
        scan_ms.append(1e3 * timed(fit_scan, scan.hits, scan.no_return)[1])
        if i % SKLEARN_EVERY == 0:
            sk_ll, sk_s, _ = sklearn_fit(scan.hits, k)
            ll.append((mixture.log_density(scan.hits).mean(), sk_ll, 1e3 * seconds, 1e3 * sk_s))
    ll = np.array(ll)
    ks = [config.n_components(s.hits) for s in scans]
    return dict(
        n=len(scans),
        k=(min(ks), int(np.median(ks)), max(ks)),
        compile_s=compile_s,
        ours_ms=np.array(ours_ms),
        scan_ms=np.array(scan_ms),
        subset=ll,
    )


def scans_3d():
    for i, scan in enumerate(read_scans(f"{DATA}/3d/kurt3d")):
        yield f"Kurt3D scan {i:03d}", scan.hits
    scan = next(read_scans(f"{DATA}/3d/octomap/scan.dat.bz2", origin=(0, 0, 0.49)))
    yield "OctoMap scan.dat", scan.hits


def mean_and_error(values) -> tuple[float, float]:
    """Mean and its standard error."""
    if len(values) < 2:
        return float(np.mean(values)), float("nan")
    return float(np.mean(values)), float(np.std(values, ddof=1) / np.sqrt(len(values)))


def bench_3d(sklearn_seeds: int):
    rows = []
    for name, hits in tqdm(list(scans_3d()), desc="3D scans"):
        points = hits[np.random.default_rng(0).choice(len(hits), N_3D, replace=False)]
        row = dict(name=name, n=len(hits))
        for n_init in (2, 1):
            row[n_init] = 1e3 * np.median(
                [timed(fit_mixture, points, K_3D, reg_covar=REG, n_init=n_init)[1] for _ in range(RUNS_3D)]
            )
            row[n_init, "ll"] = mean_and_error(
                [
                    fit_mixture(points, K_3D, reg_covar=REG, seed=seed, n_init=n_init).log_density(points).mean()
                    for seed in range(OURS_SEEDS)
                ]
            )
        sk = [sklearn_fit(points, K_3D, seed) for seed in range(sklearn_seeds)]
        row["sk_ms"], row["sk_iter"] = 1e3 * sk[0][1], sk[0][2]
        row["sk_ll"] = mean_and_error([ll for ll, _, _ in sk])
        rows.append(row)
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sklearn-seeds", type=int, default=10)
    args = parser.parse_args()
    two = bench_2d()
    three = bench_3d(args.sklearn_seeds)
    ours_ms, sub = two["ours_ms"], two["subset"]
    ours_ll, sk_ll, ours_sub_ms, sk_ms = sub.T
    print(f"\n{machine_line()}; numba and BLAS limited to 1 thread")
    print(f"numba compile of fit_mixture (empty cache, first call): {two['compile_s']:.1f} s\n")

    print(
        f"2D Intel: {two['n']} scans, K min/median/max = {two['k']}; scikit-learn on every "
        f"{SKLEARN_EVERY}th scan ({len(sub)} scans)\n"
    )
    print("| 2D Intel, per scan | median ms | p90 ms | mean log-lik / point |")
    print("|---|---|---|---|")
    print(
        f"| ours `fit_mixture`, all {two['n']} scans | {np.median(ours_ms):.2f} "
        f"| {np.percentile(ours_ms, 90):.2f} | - |"
    )
    print(
        f"| ours `fit_scan` (occupied + free), all {two['n']} scans | {np.median(two['scan_ms']):.2f} "
        f"| {np.percentile(two['scan_ms'], 90):.2f} | - |"
    )
    print(
        f"| ours `fit_mixture`, subset | {np.median(ours_sub_ms):.2f} | {np.percentile(ours_sub_ms, 90):.2f} "
        f"| {ours_ll.mean():.4f} |"
    )
    print(f"| scikit-learn, subset | {np.median(sk_ms):.2f} | {np.percentile(sk_ms, 90):.2f} | {sk_ll.mean():.4f} |")
    rel = (ours_ll - sk_ll) / np.abs(sk_ll)
    print(
        f"\nsubset: speed-up (median of per-scan ratios) {np.median(sk_ms / ours_sub_ms):.0f}x; "
        f"log-lik ours - sklearn: mean {np.mean(ours_ll - sk_ll):+.4f} nats/point, "
        f"per-scan relative median {100 * np.median(rel):+.2f}%, worst {100 * rel.min():+.2f}%, "
        f"ours >= sklearn on {np.mean(ours_ll >= sk_ll) * 100:.0f}% of scans\n"
    )

    print(
        f"3D: {N_3D:,} points (seeded subsample), K = {K_3D}; times: median of {RUNS_3D} runs (ours), "
        f"1 run (scikit-learn, tol 1e-3, iterations in brackets), seed 0; log-likelihood per point: "
        f"mean +- standard error over seeds 0-{OURS_SEEDS - 1} (ours) and 0-{args.sklearn_seeds - 1} "
        f"(scikit-learn)\n"
    )
    print(
        "| 3D scan (points) | ours ms | ours, 1 start ms | scikit-learn ms (iters) | speed-up "
        "| log-lik: scikit-learn | ours | ours, 1 start | ours - scikit-learn |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in three:
        (sk, sk_se), (ll2, se2), (ll1, se1) = r["sk_ll"], r[2, "ll"], r[1, "ll"]
        print(
            f"| {r['name']} ({r['n']:,}) | {r[2]:.0f} | {r[1]:.0f} | {r['sk_ms']:.0f} ({r['sk_iter']}) "
            f"| {r['sk_ms'] / r[2]:.0f}x | {sk:.4f} +- {sk_se:.4f} | {ll2:.4f} +- {se2:.4f} "
            f"| {ll1:.4f} +- {se1:.4f} | {ll2 - sk:+.4f} ({100 * (ll2 - sk) / abs(sk):+.2f} %) |"
        )


if __name__ == "__main__":
    main()
