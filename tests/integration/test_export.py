"""`gmmap export --url` against real uvicorn servers on 127.0.0.1 over real scans (Intel in 2D,
Kurt3D in 3D), and the same formats served by /v1/occupancy."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading

import numpy as np
import pytest
from plyfile import PlyData

from gmm_core import FitConfig, Grid, fit_scan
from gmm_core.occupancy import FREE, OCCUPIED, UNKNOWN, classify
from protocol import ScanMessage
from services.api import create_app
from services.cli import main
from services.datasets import read_scans
from services.export.octomap_tree import bt_bytes
from services.export.pgm import pgm_bytes
from services.export.ply import ply_bytes
from services.export.sources import fetch, on_lattice
from services.http_client import HttpClient
from services.map_server.fleet_map import FleetMap
from services.map_server.state import ServerState
from services.map_server.tokens import TokenFile
from services.render import top_down_classes
from support.http_auth import write_tokens
from support.net import get, metric, wait_for
from support.octomap_trees import class_log_odds, nodes_log_odds
from support.paths import ROOT
from support.ros_maps import grid_values, map_server_load
from support.saturation import saturated_tracers
from support.uvicorn_thread import Server

octomap = pytest.importorskip("octomap", reason="octomap-python is in the [bench] and [dev] extras")

BBOX = "-10,-20,10,5"  # around the start of the Intel run


@pytest.fixture(scope="module")
def intel_map(intel_scans):
    fleet = FleetMap("test")
    for s in intel_scans[:400:4]:
        assert fleet.add_scan(ScanMessage("test", "r1", s.index, s.stamp, fit_scan(s.hits, s.no_return), s.pose), 1000)
    return fleet


@pytest.fixture(scope="module")
def kurt3d_map(data_dir):
    fleet = FleetMap("test")
    config = FitConfig().for_dimension(3)
    for s in read_scans(data_dir / "3d" / "kurt3d"):
        model = fit_scan(s.hits, s.no_return, config)
        assert fleet.add_scan(ScanMessage("test", "k", s.index, s.stamp, model, s.pose), 1000)
    return fleet


@pytest.fixture(scope="module")
def server(intel_map):
    with Server(create_app(ServerState("test", intel_map))) as running:
        yield running


@pytest.fixture(scope="module")
def server_3d(kurt3d_map):
    with Server(create_app(ServerState("test", kurt3d_map))) as running:
        yield running


def test_pgm_from_a_server_is_the_served_map(server, intel_map, tmp_path, capsys):
    out = tmp_path / "intel"
    args = ["export", "--url", server.url, "--format", "pgm", f"--bbox={BBOX}", "--resolution", "0.2"]
    assert main([*args, "--variance", "0.06", "--out", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    grid = Grid.from_bbox([-10, -20], [10, 5], 0.2)
    prob = intel_map.occupancy(grid)
    data, meta = map_server_load(tmp_path / "intel.yaml")
    assert meta["origin"] == [-10.0, -20.0, 0.0] and meta["resolution"] == 0.2
    classes = classify(prob, 0.06)
    assert (classes == OCCUPIED).sum() > 20 and (classes == FREE).sum() > 1000
    np.testing.assert_array_equal(data, grid_values(classes))
    status, headers, body = get(f"{server.url}/v1/occupancy?bbox={BBOX}&resolution=0.2&format=pgm&variance=0.06")
    assert status == 200 and headers["Content-Type"] == "image/x-portable-graymap"
    assert body == (tmp_path / "intel.pgm").read_bytes()


def test_whole_map_by_default(server, intel_map, tmp_path):
    assert main(["export", "--url", server.url, "--format", "ply", "--out", str(tmp_path / "all")]) == 0
    extent = json.loads(get(f"{server.url}/v1/map/extent")[2])
    grid = Grid.from_bbox(extent["lo"], extent["hi"], 0.1)  # the default resolution of --url
    prob = intel_map.occupancy(grid)
    assert (tmp_path / "all.ply").read_bytes() == ply_bytes(prob, grid, 0.21)
    vertex = PlyData.read(tmp_path / "all.ply")["vertex"]
    assert vertex.count == (classify(prob, 0.21) == OCCUPIED).sum() > 200
    assert (vertex["z"] == 0).all()


def test_slabs_under_the_cell_limit_join_seamlessly(server):
    client = HttpClient(server.url)
    lo, hi = np.array([-10.0, -20.0]), np.array([10.0, 5.0])
    whole = fetch(client, lo, hi, 0.1)
    slabs = fetch(client, lo, hi, 0.1, max_cells=4_000)  # 20 cells a row: 19 requests of 10 rows
    assert whole.grid == slabs.grid and whole.prob.shape == (250, 200)
    np.testing.assert_array_equal(whole.prob, slabs.prob)


def test_every_format_of_a_3d_server(server_3d, kurt3d_map, tmp_path):
    out = tmp_path / "kurt3d"
    for fmt in ("bt", "ot", "pgm", "ply"):
        assert main(["export", "--url", server_3d.url, "--format", fmt, "--resolution", "0.25", "--out", str(out)]) == 0
    extent = json.loads(get(f"{server_3d.url}/v1/map/extent")[2])
    lo, hi = on_lattice(np.array(extent["lo"]), np.array(extent["hi"]), 0.25)  # bt asks for OctoMap's voxels
    grid = Grid.from_bbox(lo, hi, 0.25)
    prob = kurt3d_map.occupancy(grid)
    classes = classify(prob, 0.21)
    assert (classes == OCCUPIED).sum() > 100 and (classes == FREE).sum() > 1000
    body = (tmp_path / "kurt3d.bt").read_bytes()
    assert body == bt_bytes(prob, grid, 0.21)
    tree = octomap.OcTree(str(tmp_path / "kurt3d.bt").encode())  # OctoMap's readBinary
    expected = class_log_odds(tree, classes.ravel(), OCCUPIED, FREE)
    np.testing.assert_allclose(nodes_log_odds(tree, grid.cell_centers()), expected, rtol=1e-6)  # NaN: NaN
    box = ",".join(repr(float(v)) for v in (*lo, *hi))
    status, headers, served = get(f"{server_3d.url}/v1/occupancy?bbox={box}&resolution=0.25&format=bt")
    assert status == 200 and served == body
    full = octomap.OcTree.read(str(tmp_path / "kurt3d.ot").encode())  # OctoMap's read: the MAP log-odds
    expected = np.where(classes.ravel() == UNKNOWN, np.nan, np.log(prob.ravel() / (1 - prob.ravel())))
    np.testing.assert_allclose(nodes_log_odds(full, grid.cell_centers()), expected, rtol=1e-5)
    status, headers, served = get(f"{server_3d.url}/v1/occupancy?bbox={box}&resolution=0.25&format=ot")
    assert status == 200 and served == (tmp_path / "kurt3d.ot").read_bytes()
    whole = Grid.from_bbox(extent["lo"], extent["hi"], 0.25)  # pgm and ply: the extent as it is
    prob = kurt3d_map.occupancy(whole)
    assert (tmp_path / "kurt3d.pgm").read_bytes() == pgm_bytes(top_down_classes(prob, 0.21))
    assert (tmp_path / "kurt3d.ply").read_bytes() == ply_bytes(prob, whole, 0.21)


def test_refusals(server, server_3d, tmp_path, capsys):
    out = str(tmp_path / "x")
    assert main(["export", "--url", server.url, "--format", "bt", "--out", out]) == 2
    assert "format: bt: OctoMap trees are 3D and this map is 2D" in capsys.readouterr().err
    assert main(["export", "--url", server.url, "--format", "pgm", "--bbox=0,0,0,1,1,1", "--out", out]) == 2
    assert "bbox: this map is 2D: give 4 numbers" in capsys.readouterr().err
    tiny = ["--bbox=0,0,1,1", "--resolution", "0.001"]  # the server's limit, in its own words
    assert main(["export", "--url", server.url, "--format", "pgm", *tiny, "--out", out]) == 2
    assert "/v1/occupancy answered 422: resolution: must be between 0.005 and 10.0 m" in capsys.readouterr().err
    assert main(["export", "--url", server.url, "--format", "pgm", "--resolution", "0.001", "--out", out]) == 2
    assert "cells at 0.001 m; an export holds at most 128,000,000" in capsys.readouterr().err
    with Server(create_app(ServerState("empty", FleetMap("empty")))) as empty:
        assert main(["export", "--url", empty.url, "--format", "pgm", "--out", out]) == 2
        assert f"--url: the map at {empty.url} is empty: nothing to export" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    for fmt in ("bt", "ot"):
        status, _, body = get(f"{server.url}/v1/occupancy?bbox={BBOX}&resolution=0.1&format={fmt}")
        assert status == 422 and json.loads(body) == {
            "detail": f"format: {fmt}: OctoMap trees are 3D and this map is 2D; export it as pgm or ply",
            "field": "format",
        }
    status, _, body = get(f"{server_3d.url}/v1/occupancy?bbox=0,0,0,1,1,10000&resolution=0.3&format=bt")
    assert status == 422 and json.loads(body) == {
        "detail": "bbox: an OctoMap tree at 0.3 m reaches +-9830.4 m from the origin; this map spans z 0 .. 10000.2 m",
        "field": "bbox",
    }


def test_the_command_with_a_token(intel_map, tmp_path):
    """`gmmap export` as a process, against a server that needs a bearer token."""
    tokens = write_tokens(tmp_path / "tokens.txt", {"ops": None})
    (tmp_path / "ops.token").write_text(tokens["ops"] + "\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    with Server(create_app(ServerState("test", intel_map), tokens=TokenFile(tmp_path / "tokens.txt"))) as secured:
        command = [sys.executable, "-m", "services.cli", "export", "--url", secured.url, "--format", "pgm"]
        command += [f"--bbox={BBOX}", "--out", str(tmp_path / "map")]
        refused = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
        assert refused.returncode == 2 and "answered 401" in refused.stderr
        done = subprocess.run(
            [*command, "--http-token", str(tmp_path / "ops.token")],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert done.returncode == 0, done.stderr
    data, meta = map_server_load(tmp_path / "map.yaml")
    np.testing.assert_array_equal(
        data, grid_values(classify(intel_map.occupancy(Grid.from_bbox([-10, -20], [10, 5], 0.1)), 0.21))
    )


def test_a_busy_server_is_waited_for(intel_scans, tmp_path, monkeypatch):
    """A 503 (tracers saturated) is asked again after its Retry-After, not reported as a failure."""
    fleet = FleetMap("test", trace_threads=1)
    for s in intel_scans[:20]:
        fleet.add_scan(ScanMessage("test", "r1", s.index, s.stamp, fit_scan(s.hits, s.no_return), s.pose))
    cold_grids = [Grid.from_bbox([-8.0, -12.0], [0.0, -4.0], r) for r in (0.2, 0.25, 0.3)]
    result = {}
    args = ["export", "--url", "", "--format", "pgm", "--bbox=-8,-12,8,4", "--out", str(tmp_path / "busy")]
    with Server(create_app(ServerState("test", fleet))) as busy:
        args[2] = busy.url
        export = threading.Thread(target=lambda: result.setdefault("rc", main(args)))
        with saturated_tracers(monkeypatch, fleet, cold_grids):
            export.start()
            shed = 'gmmap_tile_answers_total{kind="shed"}'
            wait_for(lambda: metric(get(f"{busy.url}/metrics")[2].decode(), shed) >= 1, 30, "a 503")
        export.join(timeout=60)
    assert result == {"rc": 0}
    data, _ = map_server_load(tmp_path / "busy.yaml")
    prob = fleet.occupancy(Grid.from_bbox([-8, -12], [8, 4], 0.1))
    np.testing.assert_array_equal(data, grid_values(classify(prob, 0.21)))
