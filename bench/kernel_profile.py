"""Where a numba kernel's time goes, stretch by stretch of its machine code.

    .venv/bin/python bench/kernel_profile.py region|merge [--frequency 2000] [--top 20]

py-spy sees a numba kernel as one opaque call, and `perf` sees its code without symbols. This runs
the workload under `perf record` (needs `perf` and binutils' `objdump`), has it write out the
kernel's machine code (the mapping numba loaded the kernel into, from the address numba gives),
disassembles that, and prints the share of the kernel's samples in each 64-byte stretch with the
stretch's instructions: enough to tell a vector loop (`vcvttpd2dq`, `vroundpd`) from a scatter
(`vaddsd` to memory, then `vmovsd`) or a call to libm. A sample lands on the instruction after
the one that stalls (a load's cost shows at the store that follows it). How the numbers were read
for the tracer and the merge: docs/BENCHMARKS.md, twenty-eighth session.

Workloads (one core, warm JIT):
- region: `GridCounts.add_many` of the 150 nodes that reach bench/query3d.py's region (the mine
  map, 1 sample per cell), six times; kernel `scan_trace._trace_blocks`;
- merge: `voxel_merge._merge` on BALM scan #3 (bench/lidar_stages.py's inputs), 300 times.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")  # one core, as the targets are measured

import argparse
import collections
import ctypes
import json
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

WINDOW = 64  # bytes of machine code a row of the table covers


def region_workload() -> tuple[object, Callable[[], None]]:
    import mine_map
    from query3d import REGION_CELLS, RESOLUTION, fleet

    from gmm_core import Grid, scan_trace

    messages, updates, position = mine_map.load()
    region = Grid(position - np.array(REGION_CELLS) * RESOLUTION / 2, RESOLUTION, REGION_CELLS)
    scans = []
    add_many = scan_trace.GridCounts.add_many

    def keep(counts, batch):  # the scans the region's trace adds, kept to trace them again
        scans.extend(batch)
        add_many(counts, batch)

    scan_trace.GridCounts.add_many = keep
    fleet(messages, updates, 1.0).counts(region)
    scan_trace.GridCounts.add_many = add_many

    def run() -> None:
        for _ in range(6):
            scan_trace.GridCounts(region).add_many(scans)

    return scan_trace._trace_blocks, run


def merge_workload() -> tuple[object, Callable[[], None]]:
    from lidar import read

    from gmm_core import rings, voxel_merge, voxels
    from services.config import load_config

    config = load_config().fit.for_dimension(3)
    points = np.ascontiguousarray(read("balm")[3].hits)
    shift = points[0].copy()
    finest, tiers, _ = voxels.voxel_tiers(config.voxel_size, config.voxel_fine_range, config.voxel_near_range)
    sums, keys = voxels._voxel_statistics(points, finest, shift, tiers)
    k = min(
        config.n_components_of_count(len(points), 3),
        voxels._count_cells(keys, 3, round(config.component_size / finest)),
    )
    costed = rings.with_footprint(sums, -shift, rings.ring_spacing(points))
    eu, ev = voxel_merge._voxel_edges(keys, finest, tiers)
    inputs = [(costed.copy(), eu.copy(), ev.copy()) for _ in range(301)]  # _merge changes its inputs
    voxel_merge._merge(*inputs.pop(), k, config.reg_covar)  # compiled or loaded: dump_kernel reads its code

    def run() -> None:
        for c, u, v in inputs:
            voxel_merge._merge(c, u, v, k, config.reg_covar)

    return voxel_merge._merge, run


WORKLOADS = {"region": region_workload, "merge": merge_workload}


def dump_kernel(dispatcher, folder: Path) -> None:
    """The mapping that holds the dispatcher's one compiled kernel, as code.bin, and where it lies (kernel.json)."""
    overload = next(iter(dispatcher.overloads.values()))
    start = overload.library.get_pointer_to_function(overload.fndesc.llvm_func_name)
    for line in open("/proc/self/maps"):
        lo, hi = (int(a, 16) for a in line.split()[0].split("-"))
        if lo <= start < hi:
            (folder / "code.bin").write_bytes(ctypes.string_at(lo, hi - lo))
            (folder / "kernel.json").write_text(json.dumps({"start": start, "lo": lo, "hi": hi}))
            return
    raise RuntimeError(f"no mapping holds the kernel at {start:#x}")


def perf_report(perf_data: Path, sort: str) -> str:
    command = ["perf", "report", "-i", str(perf_data), "--no-children", "--sort", sort, "-g", "none"]
    return subprocess.run(command, capture_output=True, text=True, check=True).stdout


def sampled_addresses(perf_data: Path) -> tuple[collections.Counter, float]:
    """Percent of all samples at each address perf could not name (JIT code), and their total."""
    at: collections.Counter = collections.Counter()
    for line in perf_report(perf_data, "sym").splitlines():
        found = re.match(r"\s*([0-9.]+)%\s+\[\.\]\s+0x([0-9a-f]+)\s*$", line)
        if found:
            at[int(found.group(2), 16)] += float(found.group(1))
    return at, sum(at.values())


def mnemonics(folder: Path, lo: int) -> dict[int, str]:
    """The first mnemonic of each instruction of code.bin, by address (in address order, as objdump lists them)."""
    listing = subprocess.run(
        ["objdump", "-D", "-b", "binary", "-m", "i386:x86-64", f"--adjust-vma={lo}", str(folder / "code.bin")],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    out = {}
    for line in listing.splitlines():
        parts = line.split("\t")
        address = re.match(r"\s*([0-9a-f]+):", parts[0])
        if address and len(parts) >= 3 and parts[2].strip():
            out[int(address.group(1), 16)] = parts[2].split()[0]
    return out


def report(folder: Path, top: int) -> None:
    kernel = json.loads((folder / "kernel.json").read_text())
    at, unnamed = sampled_addresses(folder / "perf.data")
    inside = {a: p for a, p in at.items() if kernel["lo"] <= a < kernel["hi"]}
    total = sum(inside.values())
    if total == 0:
        sys.exit("no samples fell in the kernel's code")
    windows: collections.Counter = collections.Counter()
    for a, p in inside.items():
        windows[(a - kernel["start"]) // WINDOW * WINDOW] += p
    ops = mnemonics(folder, kernel["lo"])
    print(f"{total:.1f} % of all samples in the kernel's mapping ({unnamed - total:.1f} % in other unnamed code)")
    shares = [line.strip() for line in perf_report(folder / "perf.data", "dso").splitlines() if "%" in line]
    print("by object (libm: calls the kernel makes):", "; ".join(" ".join(row.split()[:2]) for row in shares[:5]))
    print("\n| share of the kernel's samples | offset from the kernel's entry | instructions |\n|---|---|---|")
    for offset, p in windows.most_common(top):
        first = kernel["start"] + offset
        names = [name for a, name in ops.items() if first <= a < first + WINDOW]
        print(f"| {100 * p / total:.1f} % | {offset:+#x} | {' '.join(names)} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("workload", choices=list(WORKLOADS))
    parser.add_argument("--frequency", type=int, default=2000, help="perf's samples a second")
    parser.add_argument("--top", type=int, default=20, help="rows: the stretches with the most samples")
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)  # the run under perf writes here
    args = parser.parse_args()
    if args.child:
        kernel, run = WORKLOADS[args.workload]()
        dump_kernel(kernel, args.child)
        run()
        return
    missing = [tool for tool in ("perf", "objdump") if shutil.which(tool) is None]
    if missing:
        sys.exit(f"kernel_profile needs {' and '.join(missing)} (linux-perf, binutils)")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        command = [sys.executable, __file__, args.workload, "--child", str(folder)]
        record = ["perf", "record", "-q", "-F", str(args.frequency), "-o", str(folder / "perf.data"), "--"]
        subprocess.run(record + command, check=True)
        report(folder, args.top)


if __name__ == "__main__":
    main()
