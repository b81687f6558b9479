"""Wire encodings against map quality and size (issue 4), and the time to decode and encode a
scan message (issue 16).

AUROC of `q` and `f32` against the unencoded models (Intel at 10 cm and 1 cm, Kurt3D at 10 cm;
ground truth: the raw counting grid of every beam), and bytes per scan against raw scans and
OctoMap's binary `.bt` of the same scan at 0.1 m (when octomap-python is installed).

`speed`: microseconds per `q` scan message of simulated office (2D) and mine (3D) scans, this
checkout beside git revision REV (default: the commit before the numba decode), each in its own
process, alternately; and whether both decode every message to the same bits and encode it to
the same bytes.

    .venv/bin/python bench/encoding.py
    .venv/bin/python bench/encoding.py speed [--before REV] [--rounds N]
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import subprocess
import sys
import tempfile
import time
import timeit
from pathlib import Path

import msgpack
import numpy as np

from gmm_core import FitConfig, Grid
from gmm_core.metrics import grid_auroc
from gmm_core.occupancy import map_estimate
from gmm_core.reconstruct import count_beams, reconstruct
from gmm_core.sampling import scan_seed
from protocol import decode, encode
from services.datasets import read_scans
from services.replay import data_extent, fit_scans, scan_message, through_wire

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
MAX_RANGE = 10.0
BEFORE_NUMBA_DECODE = "07afa99"


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


def quality_and_size() -> None:
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


# --- speed: each version of the code in its own process, so both can be imported as `protocol`


def simulated_messages(world: str, scans: int) -> list[bytes]:
    from services.sim.fleet import SimulatedFleet

    recorded = list(itertools.islice(SimulatedFleet(world, 1, scans).scans(0, 0), scans))
    models = fit_scans(recorded, FitConfig().for_dimension(recorded[0].pose.dim))
    return [encode(scan_message(model, scan), "q") for model, scan in zip(models, recorded)]


def time_codec(path: str) -> None:
    """In a worker: per message set, the best mean time to decode and to encode one message, and a
    digest of every decoded array and re-encoded byte; printed as JSON."""
    import protocol

    result = {"protocol": protocol.__file__}
    for name, blobs in msgpack.unpackb(Path(path).read_bytes()).items():
        messages = [decode(blob) for blob in blobs]
        digest = hashlib.sha256()
        for message in messages:
            for mixture in (message.model.occupied, message.model.free):
                for array in (mixture.weights, mixture.means, mixture.covariances):
                    digest.update(array.tobytes())
            digest.update(encode(message, "q"))
        result[name] = {
            "decode_us": per_item_us(decode, blobs),
            "encode_us": per_item_us(lambda message: encode(message, "q"), messages),
            "digest": digest.hexdigest(),
        }
    print(json.dumps(result))


def per_item_us(function, items: list, repeats: int = 7, seconds: float = 0.2) -> float:
    """The best of `repeats` mean times of `function` over `items`, each run about `seconds` long."""

    def run():
        for item in items:
            function(item)

    # CPU time of this process, not wall time: the machine may be shared, and waiting is not work
    number = max(1, int(seconds / timeit.timeit(run, number=1, timer=time.process_time)))
    best = min(timeit.repeat(run, number=number, repeat=repeats, timer=time.process_time))
    return best / (number * len(items)) * 1e6


def run_worker(root: Path, path: Path) -> dict:
    """time_codec in a fresh process that imports `protocol` (and the rest) from `root`."""
    paths = [str(root), str(ROOT / "bench")]
    code = f"import sys; sys.path[:0] = {paths!r}; import encoding; encoding.time_codec({str(path)!r})"
    done = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    return json.loads(done.stdout)


def speed(before: str, rounds: int) -> None:
    sets = {"office 2D": simulated_messages("office", 40), "mine 3D": simulated_messages("mine", 5)}
    components = {name: [decode(blob).model.n_components for blob in blobs] for name, blobs in sets.items()}
    with tempfile.TemporaryDirectory() as folder:
        old = Path(folder) / "before"
        old.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", before], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(old)], input=archive, check=True)
        path = Path(folder) / "messages.msgpack"
        path.write_bytes(msgpack.packb(sets))
        results: dict[str, list[dict]] = {"before": [], "after": []}
        for _ in range(rounds):  # alternately, so a change of load on the machine hits both
            results["before"].append(run_worker(old, path))
            results["after"].append(run_worker(ROOT, path))
    print(f"before: {before} ({results['before'][0]['protocol']}), after: {results['after'][0]['protocol']}")
    print(
        "\n| messages | components | bytes | decode before us | after us | speed-up "
        "| encode before us | after us | speed-up | same bits |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, blobs in sets.items():
        best = {
            version: {op: min(run[name][op] for run in runs) for op in ("decode_us", "encode_us")}
            for version, runs in results.items()
        }
        same = len({run[name]["digest"] for runs in results.values() for run in runs}) == 1
        b, a = best["before"], best["after"]
        print(
            f"| {name}, {len(blobs)} scans | {np.mean(components[name]):.0f} | {np.mean([len(x) for x in blobs]):.0f} "
            f"| {b['decode_us']:.0f} | {a['decode_us']:.0f} | {b['decode_us'] / a['decode_us']:.1f}x "
            f"| {b['encode_us']:.0f} | {a['encode_us']:.0f} | {b['encode_us'] / a['encode_us']:.1f}x "
            f"| {'yes' if same else 'NO'} |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", nargs="?", choices=["quality", "speed"], default="quality")
    parser.add_argument("--before", default=BEFORE_NUMBA_DECODE, help="git revision to time beside this checkout")
    parser.add_argument("--rounds", type=int, default=3, help="processes per version, alternately")
    args = parser.parse_args()
    if args.what == "speed":
        speed(args.before, args.rounds)
    else:
        quality_and_size()


if __name__ == "__main__":
    main()
