"""A map server loads numba's kernels before it serves (services/map_server/warmup.py): after
`warm_kernels`, real scans decoded, added, re-posed and traced into a viewer's tile, and point queries
of both methods, compile nothing more. Run in a fresh interpreter, where nothing else has called the kernels yet."""

import json
import subprocess
import sys

from support.paths import DATA, ROOT

# Both scripts: what numba compiled so far, and the JSON line the tests read.
COMPILED = """
import itertools, json, sys
import numba


def compiled():
    # Every numba kernel of the project's modules and the signatures it holds so far.
    found = {}
    for name, module in list(sys.modules.items()):
        if name.split(".")[0] in ("gmm_core", "protocol", "services"):
            for attr, value in vars(module).items():
                if isinstance(value, numba.core.registry.CPUDispatcher):
                    found[f"{name}.{attr}"] = len(value.signatures)
    return found


def report(before, warmed, after):
    # The kernels the warm-up compiled, and those compiled after it (with how many signatures).
    print(json.dumps({"warmed": sorted(k for k in warmed if warmed[k] > before.get(k, 0)),
                      "new": {k: after[k] - warmed.get(k, 0) for k in after if after[k] > warmed.get(k, 0)}}))
"""

SCRIPT = (
    COMPILED
    + """
import numpy as np
from gmm_core import Grid, Pose, fit_scan
from protocol import PoseGraphUpdate, ScanMessage, decode, encode
from services.datasets import read_scans
from services.map_server.fleet_map import FleetMap
from services.map_server.nodes import ScanEntry
from services.api.points import evaluate


# A robot's side first: real scans fitted and encoded (its kernels are not the server's).
data = sys.argv[1]
sets = {2: read_scans(data + "/carmen/intel-corrected.log.gz"), 3: read_scans(data + "/3d/kurt3d", fmt="kurt3d")}
robots = {}
for dim, scans in sets.items():
    raws = []
    for node, scan in enumerate(itertools.islice(scans, 3)):
        model = fit_scan(scan.hits, scan.no_return)
        raws.append(encode(ScanMessage("f", f"r{dim}", node, scan.stamp, model, scan.pose), "q" if node else "f32"))
    robots[dim] = raws

from services.map_server.warmup import warm_kernels

before = compiled()
warm_kernels()
warmed = compiled()
for dim, raws in robots.items():  # the server's side: ingest, a tile, a correction, the tile again
    fleet_map = FleetMap("f", trace_threads=1)
    messages = [decode(raw, expect=ScanMessage) for raw in raws]
    fleet_map.add_entries([ScanEntry.of(m, len(r), r) for m, r in zip(messages, raws)], [m.model for m in messages])
    grid = Grid(np.full(dim, -3.2), 0.05 if dim == 2 else 0.1, (128,) * dim if dim == 2 else (64, 64, 16))
    fleet_map.occupancy(grid)
    moved = tuple((node, Pose(np.eye(dim), np.full(dim, 0.3))) for node in range(len(raws)))
    fleet_map.apply_poses(PoseGraphUpdate("f", f"r{dim}", 1, moved))
    fleet_map.occupancy(grid)
    points = np.random.default_rng(0).uniform(-3, 3, (5, dim))
    for method in ("analytic", "mc"):  # a point query, as the HTTP API and the Zenoh queryable answer it
        evaluate(fleet_map, points, 0.1, None, method)
    fleet_map.close()
report(before, warmed, compiled())
"""
)


def test_after_warm_up_real_scans_and_tiles_compile_nothing():
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(DATA)], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    # The warm-up reached the server's own kernels (the robot's fit and encoding loaded the shared ones).
    assert {"gmm_core.scan_trace._trace_blocks", "gmm_core.occupancy._map_estimate"} <= set(result["warmed"])
    assert result["new"] == {}, f"kernels the warm-up did not load: {result['new']}"


FLEET_SCRIPT = (
    COMPILED
    + """
from gmm_core import FitConfig, fit_scan
from protocol import ScanMessage, encode
from services.sim.fleet import SimulatedFleet
from services.sim.warmup import warm_fleet_kernels

before = compiled()
warm_fleet_kernels("office", FitConfig(), "q")
warmed = compiled()
fleet = SimulatedFleet("office", 3, 20, 5.0)  # the demo's robots: another robot, later scans, a loop closure
for scan in itertools.islice(fleet.scans(2, correct_every=5), 12):
    model = fit_scan(scan.hits, scan.no_return, FitConfig().for_dimension(2))
    encode(ScanMessage("default", "r2", scan.index, scan.stamp, model, scan.odom_pose), "q")
report(before, warmed, compiled())
"""
)


def test_after_the_fleet_warm_up_a_demo_robot_compiles_nothing():
    """`gmmap demo` compiles once, before its processes start (services/sim/warmup.py): a robot of
    the demo then simulates, fits and encodes its scans with kernels from numba's cache only."""
    run = subprocess.run([sys.executable, "-c", FLEET_SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert "gmm_core.scan_trace._trace_blocks" in result["warmed"]  # the server's too
    assert any(k.startswith("services.sim.") for k in result["warmed"])  # the simulated sensor's
    assert result["new"] == {}, f"kernels the warm-up did not load: {result['new']}"
