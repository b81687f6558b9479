"""Simulated fleets: the `sim:` agent source, the measuring pieces of `gmmap sim`, a short run of it
over real Zenoh with its report, and `gmmap demo`."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest

from gmm_core import Grid
from gmm_core.reconstruct import count_beams
from services.agent.sources import default_update_every, load_nodes
from services.sim.byte_models import GRID_DELTA_CELL_BYTES, grid_state, scan_window
from services.sim.fleet import SimSource, SimulatedFleet
from services.sim.processes import free_port
from services.sim.record import blocks
from services.sim.relay import CountingRelay
from support.net import wait_for
from support.paths import ROOT

GMMAP = [sys.executable, "-m", "services.cli"]
ENV = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
REPORT_KEYS = {
    "robots",
    "duration_s",
    "bytes_on_wire",
    "raw_scan_bytes",
    "grid_delta_bytes",
    "components",
    "auroc",
    "auroc_before_correction",
    "scans_published",
    "scans_stored",
    "ingest_lag_p99_s",
    "tile_latency_p99_s",
    "scan_payload_bytes",
    "pose_payload_bytes",
}


# --- the sim source ------------------------------------------------------------------------------


def test_sim_source_parses_and_names_what_is_wrong():
    assert SimSource.parse("sim:office:1:3") == SimSource("office", 1, 3, 0)
    assert str(SimSource.parse("sim:mine:0:1:7")) == "sim:mine:0:1:7"
    for bad, says in [
        ("sim:office:3:3", "INDEX"),
        ("sim:moon:0:1", "world"),
        ("sim:office:a:3", "sim:WORLD"),
        ("sim:office:0", "sim:WORLD"),
    ]:
        with pytest.raises(ValueError, match=says):
            SimSource.parse(bad)
    with pytest.raises(ValueError, match="--scans"):
        load_nodes("sim:office:0:2")


def test_sim_nodes_publish_the_robots_estimate_and_correct_to_the_truth():
    update_every = default_update_every("sim:office:0:2", 5.0)
    assert update_every == 50  # the loop-closure period, 10 s at 5 Hz
    nodes = load_nodes("sim:office:1:2:3", scans="0:60", rate=5.0)
    assert len(nodes) == 60
    listed = list(nodes)
    assert [n.node for n in listed] == list(range(60))
    # The same robot as the harness builds it: same beams, same true poses.
    fleet = SimulatedFleet("office", 2, 60, 5.0, seed=3)
    for node, scan in zip(listed, fleet.scans(1, update_every)):
        assert np.array_equal(node.scan.hits, scan.hits)
        assert np.allclose(node.corrected.t, scan.pose.t) and np.allclose(node.estimate.t, scan.odom_pose.t)
    drift = [np.linalg.norm(n.estimate.t - n.corrected.t) for n in listed]
    # Robot 1 of 2 closes its loops half an interval before robot 0: after 25 scans, then every 50.
    assert nodes.closures.offset == 25 and load_nodes("sim:office:0:2:3", scans="0:60", rate=5.0).closures.offset == 0
    assert drift[0] == 0 and drift[24] > 0 and drift[25] < drift[24]
    # --scans A:B: scans A to B of a run of B scans (paths are planned for the whole run).
    later = list(load_nodes("sim:office:1:2:3", scans="10:20", rate=5.0))
    assert [n.node for n in later] == list(range(10, 20))
    whole_run = list(load_nodes("sim:office:1:2:3", scans="0:20", rate=5.0))
    assert np.array_equal(later[0].scan.hits, whole_run[10].scan.hits)


# --- measuring pieces ----------------------------------------------------------------------------


def test_relay_counts_both_directions():
    server = socket.create_server(("127.0.0.1", 0))
    relay = CountingRelay(server.getsockname()[1])
    try:
        robot = socket.create_connection(("127.0.0.1", relay.port))
        far, _ = server.accept()
        robot.sendall(b"x" * 5000)
        received = b""
        while len(received) < 5000:
            received += far.recv(65536)
        far.sendall(b"ack")
        assert robot.recv(10) == b"ack"
        assert (relay.up, relay.down) == (5000, 3)
    finally:
        relay.close()
        server.close()


def test_grid_deltas_in_windows_equal_the_whole_grid():
    fleet = SimulatedFleet("office", 1, 8, 5.0, seed=1)
    grid = Grid.from_bbox(fleet.world.raster.origin, fleet.world.raster.upper, 0.1)
    hits, misses = np.zeros(grid.array_shape, np.float32), np.zeros(grid.array_shape, np.float32)
    scans = list(fleet.scans(0, 0))
    for k, scan in enumerate(scans):
        window, sub = scan_window(grid, scan, 10.0)
        before = grid_state(hits[window], misses[window])
        h, m = count_beams(sub, [(scan.hits, scan.no_return, scan.pose)], 10.0)
        hits[window] += h
        misses[window] += m
        changed = np.count_nonzero(grid_state(hits[window], misses[window]) != before)
        whole = [count_beams(grid, [(s.hits, s.no_return, s.pose) for s in scans[:n]], 10.0) for n in (k, k + 1)]
        assert changed == np.count_nonzero(grid_state(*whole[0]) != grid_state(*whole[1]))
    assert np.array_equal(hits, count_beams(grid, [(s.hits, s.no_return, s.pose) for s in scans], 10.0)[0])
    assert GRID_DELTA_CELL_BYTES == 5
    assert scan_window(Grid((100.0, 100.0), 0.1, (5, 5)), scans[0], 1.0) is None


@pytest.mark.parametrize("shape", [(30, 20, 17), (800, 590, 80), (41, 7)])
def test_blocks_cover_the_grid_exactly_once(shape):
    grid = Grid((0.0, 1.0, 2.0)[: len(shape)], 0.1, shape)
    limit = 500_000 if grid.n_cells > 10**6 else 30 * 20 * 4
    pieces = blocks(grid, max_cells=limit)
    covered = np.zeros(grid.array_shape, dtype=int)
    for box, place in pieces:
        assert box.n_cells <= limit and covered[place].shape == box.array_shape
        corner = tuple(s.start for s in place)[::-1]  # (ix, iy[, iz]) of the box's first cell
        assert np.allclose(box.origin, grid.origin + np.array(corner) * grid.resolution)
        covered[place] += 1
    assert np.all(covered == 1)
    if shape == (800, 590, 80):  # the mine's graded box: boxes span its height, not slabs of it
        assert all(box.shape[2] == 80 for box, _ in pieces) and len(pieces) < 100


# --- processes -----------------------------------------------------------------------------------


def test_short_sim_over_zenoh_writes_a_complete_report(tmp_path):
    out = tmp_path / "report"
    result = subprocess.run(
        GMMAP
        + [
            "sim",
            "--robots",
            "2",
            "--world",
            "office",
            "--duration",
            "6",
            "--rate",
            "5",
            "--http-clients",
            "1",
            "--report",
            str(out),
        ],
        cwd=tmp_path,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    assert REPORT_KEYS <= report.keys()
    assert report["robots"] == 2 and report["duration_s"] == 6
    assert report["scans_published"] == report["scans_stored"] == 60
    assert report["bytes_on_wire"] > report["payload_bytes"]["scan"] == report["scan_payload_bytes"] > 0
    assert report["pose_payload_bytes"] == report["payload_bytes"]["poses"] > 0
    assert report["bytes_on_wire"] < report["raw_scan_bytes"] == 60 * 360 * 4
    assert report["grid_delta_bytes"] > 0 and report["components"] > 0
    assert report["auroc"] > 0.8 and report["auroc_before_correction"] > 0.5
    assert 0 <= report["ingest_lag_p99_s"] < 5 and report["tile_requests"] > 0 and report["tile_errors"] == 0
    assert 0 < report["tile_latency_p99_s"] < 5
    assert set(report["per_robot"]) == {"r0", "r1"} and report["realtime_factor"] > 0
    assert 20 < report["server_rss_start_mb"] <= report["server_rss_max_mb"] < 4096  # a Python server's RSS
    windows = report["over_mission_time"]
    assert len(windows) == 30 and sum(w["pose_payload_bytes"] for w in windows) == report["pose_payload_bytes"]
    assert report["time_scale"] == 1 and report["restart_s"] > 0
    markdown = (out / "report.md").read_text()
    for png in ("bytes_over_time.png", "auroc_over_time.png", "map_vs_truth.png", "over_mission_time.png"):
        assert f"]({png})" in markdown
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "auroc" in result.stdout


def test_demo_serves_the_viewer_and_stops_after_its_duration(tmp_path):
    port = free_port()
    with open(tmp_path / "stderr", "w") as stderr:
        demo = subprocess.Popen(
            GMMAP + ["demo", "--duration", "3", "--http", f"127.0.0.1:{port}"],
            cwd=tmp_path,
            env=ENV,
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
        )
    try:
        assert demo.stdout.readline().startswith(f"gmmap demo: the viewer is at http://127.0.0.1:{port}/")
        said = (tmp_path / "stderr").read_text()  # the kernels were compiled (or loaded) before any process started
        assert "gmmap demo: loading numba's kernels" in said and "gmmap demo: kernels ready in" in said, said

        def nodes() -> int:  # 0 until the server answers
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/v1/robots", timeout=5) as response:
                    return sum(r["nodes"] for r in json.loads(response.read()))
            except OSError:
                return 0

        wait_for(nodes, 60, "the demo's first nodes", interval=0.3)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5) as response:
            assert b"gmmap viewer" in response.read()
        assert demo.wait(60) == 0
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()


def children_of(pid: int) -> list[int]:
    """Processes whose parent is `pid` (from /proc)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.append(int(entry))
    return found


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_whose_parent_died_before_it_asked_to_die_with_it_ends_at_once():
    """The window PR_SET_PDEATHSIG leaves open: a parent killed between the fork and the child's
    prctl is never signalled for, so the child compares its parent with the pid that started it."""
    code = "from services.host import die_with_parent; import time; die_with_parent({}); time.sleep(30)"
    gone = subprocess.run([sys.executable, "-c", code.format(1)], env=ENV, timeout=60)  # its parent is not pid 1
    assert gone.returncode == -signal.SIGTERM
    kept = subprocess.Popen([sys.executable, "-c", code.format("__import__('os').getppid()")], env=ENV)
    try:
        with pytest.raises(subprocess.TimeoutExpired):
            kept.wait(timeout=3)  # its parent (this test) lives: it runs on
    finally:
        kept.kill()
        kept.wait()


def command_line(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return "?"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_sim_killed_with_sigkill_leaves_no_process_behind(tmp_path):
    sim = subprocess.Popen(
        [*GMMAP, "sim", "--robots", "2", "--duration", "120", "--rate", "2"],
        cwd=tmp_path,
        env=ENV,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        while len(children := children_of(sim.pid)) < 2:  # the server and the robots' process
            assert time.monotonic() < deadline and sim.poll() is None, "the sim did not start its children"
            time.sleep(0.2)
        sim.kill()
        sim.wait()
        deadline = time.monotonic() + 30  # 15 s ran out once on a loaded 2-core CI machine
        while any(alive(pid) for pid in children):
            assert time.monotonic() < deadline, [(pid, command_line(pid)) for pid in children if alive(pid)]
            time.sleep(0.2)
    finally:
        if sim.poll() is None:
            sim.kill()
