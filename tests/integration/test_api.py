"""The HTTP API and the web viewer, against a real uvicorn server on 127.0.0.1 and real Intel scans."""

from __future__ import annotations

import io
import json
import re
import shutil
import socket
import threading
import time
from urllib.parse import quote

import numpy as np
import pytest
from PIL import Image

from gmm_core import Grid, fit_scan
from gmm_core.analytic.cells import occupancy_at_cells
from gmm_core.occupancy import DEFAULT_VARIANCE
from protocol import MapReply, ScanMessage, decode, encode
from services.api import create_app
from services.map_server.fleet_map import FleetMap
from services.map_server.metrics import ServerMetrics
from services.map_server.state import ServerState
from services.map_server.store import Store
from services.map_server.tracers import TracerLoad, TracersSaturated
from services.render import occupancy_png, probability_png
from support.browser import CENTRE, FREE_GREY, clicked, headless_chromium, screenshot
from support.ingest import ingested, scan_of, stored_bytes
from support.net import get, post, post_bytes
from support.uvicorn_thread import Server

BBOX = "-10,-20,10,5"  # around the start of the Intel run


@pytest.fixture(scope="module")
def fleet_map(intel_scans):
    fleet = FleetMap("test")
    for s in intel_scans[:400:4]:  # 100 scans spread over the first part of the run
        msg = ScanMessage("test", "r1", node=s.index, stamp=s.stamp, model=fit_scan(s.hits, s.no_return), pose=s.pose)
        assert fleet.add_scan(msg, size_bytes=1000)
    return fleet


@pytest.fixture(scope="module")
def server(fleet_map):
    state = ServerState(fleet="test", fleet_map=fleet_map, store=None, metrics=ServerMetrics())
    with Server(create_app(state)) as running:
        running.state = state
        yield running


@pytest.fixture(scope="module")
def empty_server():
    state = ServerState(fleet="empty", fleet_map=FleetMap("empty"), store=None, metrics=ServerMetrics())
    with Server(create_app(state)) as running:
        yield running


def test_npy_round_trip(server, fleet_map):
    status, headers, body = get(f"{server.url}/v1/occupancy?bbox={BBOX}&resolution=0.1&format=npy")
    assert status == 200
    prob = np.load(io.BytesIO(body))
    grid = Grid.from_bbox([-10, -20], [10, 5], 0.1)
    assert prob.dtype == np.float32 and prob.shape == (250, 200) == grid.array_shape
    assert headers["X-Grid-Shape"] == "250,200"
    assert [float(v) for v in headers["X-Grid-Origin"].split(",")] == [-10.0, -20.0]
    assert float(headers["X-Grid-Resolution"]) == 0.1
    assert np.array_equal(prob, fleet_map.occupancy(grid))
    assert (prob > 0.7).sum() > 200 and (prob < 0.3).sum() > 3000  # walls and free space
    assert ((prob >= 0) & (prob <= 1)).all()


def test_png_and_msgpack(server):
    status, headers, body = get(f"{server.url}/v1/occupancy?bbox={BBOX}&resolution=0.1&format=png")
    assert status == 200 and headers["Content-Type"] == "image/png"
    image = Image.open(io.BytesIO(body))
    assert image.size == (200, 250) and image.mode == "L"
    status, headers, body = get(f"{server.url}/v1/occupancy?bbox={BBOX}&resolution=0.1&format=msgpack")
    assert status == 200
    reply = decode(body, expect=MapReply, max_bytes=len(body))
    assert reply.fleet == "test" and reply.resolution == 0.1
    assert np.array_equal(reply.origin, [-10, -20]) and reply.probabilities.shape == (250, 200)
    _, _, npy = get(f"{server.url}/v1/occupancy?bbox={BBOX}&resolution=0.1")  # npy is the default
    assert np.array_equal(np.load(io.BytesIO(npy)), reply.probabilities)


def test_png_shows_eq12_classes_at_a_variance(server, fleet_map):
    url = f"{server.url}/v1/occupancy?bbox={BBOX}&resolution=0.1&format=png"
    prob = fleet_map.occupancy(Grid.from_bbox([-10, -20], [10, 5], 0.1))
    default = get(url)[2]
    assert default == get(url + f"&shade=classes&variance={DEFAULT_VARIANCE}")[2] == occupancy_png(prob)
    assert set(np.unique(np.asarray(Image.open(io.BytesIO(default)))).tolist()) == {0, 128, 255}
    wide_open = get(url + "&variance=0.25")[2]
    assert wide_open == occupancy_png(prob, 0.25) != default
    black = [(np.asarray(Image.open(io.BytesIO(png))) == 0).sum() for png in (default, wide_open)]
    assert 0 < black[0] < black[1]  # a larger sigma^2 narrows the dead band: more cells are called occupied
    assert get(url + "&shade=probability")[2] == probability_png(prob)
    assert get(url + "&shade=probability&variance=0.2")[2] == probability_png(prob)  # variance: classes only
    npy = f"{server.url}/v1/occupancy?bbox={BBOX}&resolution=0.1"
    assert get(npy + "&variance=0.25")[2] == get(npy)[2]  # arrays stay probabilities


def test_same_query_same_bytes(server):
    url = f"{server.url}/v1/occupancy?bbox=-3.3,-7.1,4.05,1.2&resolution=0.07&format=npy"
    assert get(url)[2] == get(url)[2]


@pytest.mark.parametrize(
    "query, field, words",
    [
        ("bbox=0,0,1,1&resolution=0.001", "resolution", "0.005"),
        ("bbox=0,0,1,1&resolution=11", "resolution", "10"),
        ("bbox=0,0,1,1&resolution=nan", "resolution", "between"),
        ("bbox=0,0,1,1&resolution=abc", "resolution", ""),
        ("bbox=-1000,-1000,1000,1000&resolution=0.05", "bbox", "16,000,000"),
        ("bbox=-1e300,-1e300,1e300,1e300&resolution=0.05", "bbox", "16,000,000"),
        ("bbox=-1.7e308,0,1.7e308,1&resolution=0.05", "bbox", "16,000,000"),
        ("bbox=0,0,1&resolution=0.1", "bbox", "4 numbers"),
        ("bbox=0,0,nan,1&resolution=0.1", "bbox", "finite"),
        ("bbox=0,0,inf,1&resolution=0.1", "bbox", "finite"),
        ("bbox=0,a,1,1&resolution=0.1", "bbox", "numbers"),
        ("bbox=1,0,0,1&resolution=0.1", "bbox", "exceed"),
        ("bbox=0,0,0,1,1,1&resolution=0.1", "bbox", "2D"),
        ("bbox=0,0,1,1&resolution=0.1&format=tiff", "format", "npy"),
        ("bbox=0,0,1,1&resolution=0.1&robots=bad%20name", "robots", "A-Za-z0-9"),
        ("bbox=0,0,1,1&resolution=0.1&format=png&variance=0.26", "variance", "between 0.0 and 0.25"),
        ("bbox=0,0,1,1&resolution=0.1&format=png&variance=-0.01", "variance", "between 0.0 and 0.25"),
        ("bbox=0,0,1,1&resolution=0.1&format=png&variance=nan", "variance", "between 0.0 and 0.25"),
        ("bbox=0,0,1,1&resolution=0.1&format=png&variance=abc", "variance", ""),
        ("bbox=0,0,1,1&resolution=0.1&format=png&shade=colour", "shade", "classes"),
        ("resolution=0.1", "bbox", ""),
    ],
)
def test_bad_requests_are_422_json(server, fleet_map, query, field, words):
    before = fleet_map.cache_stats()
    status, headers, body = get(f"{server.url}/v1/occupancy?{query}")
    assert status == 422, body
    assert headers["Content-Type"] == "application/json"
    reply = json.loads(body)
    assert reply["field"] == field and words in reply["detail"], reply
    assert fleet_map.cache_stats() == before  # rejected before any work: no tile, no samples


def test_robot_selection(server, fleet_map):
    url = f"{server.url}/v1/occupancy?bbox=-2,-2,2,2&resolution=0.1"
    mine = np.load(io.BytesIO(get(url + "&robots=r1")[2]))
    assert np.array_equal(mine, np.load(io.BytesIO(get(url)[2])))


def test_naming_a_robot_the_fleet_lacks_is_404_and_an_empty_name_422_not_a_blank_map(server, fleet_map):
    tile = f"{server.url}/v1/occupancy?bbox=-2,-2,2,2&resolution=0.1&robots="
    points = f"{server.url}/v1/occupancy/points?xy=0,0&resolution=0.1&robots="
    before = fleet_map.cache_stats()
    for robots, unknown in (("nobody", "nobody"), ("r1,other,nobody", "nobody, other")):
        missing = {"detail": f"robots: no robot {unknown} in fleet 'test'", "field": "robots"}
        for status, body in (get(tile + robots)[::2], get(points + robots)[::2]):
            assert (status, json.loads(body)) == (404, missing)
        asked = {"points": [[0.0, 0.0]], "resolution": 0.1, "robots": robots.split(",")}
        status, body = post(f"{server.url}/v1/occupancy/points", asked)
        assert (status, json.loads(body)) == (404, missing)
    for robots in ("", "r1,,r1", "r1,"):
        for status, body in (get(tile + robots)[::2], get(points + robots)[::2]):
            assert status == 422 and json.loads(body)["field"] == "robots", (robots, body)
    status, body = post(f"{server.url}/v1/occupancy/points", {"points": [[0.0, 0.0]], "resolution": 0.1, "robots": []})
    assert status == 422 and json.loads(body)["field"] == "robots", body
    assert fleet_map.cache_stats() == before  # refused before any work


def test_empty_map_is_unknown(empty_server):
    for bbox in ("0,0,1,1", "0,0,0,1,1,1"):
        status, headers, body = get(f"{empty_server.url}/v1/occupancy?bbox={bbox}&resolution=0.25")
        assert status == 200 and (np.load(io.BytesIO(body)) == 0.5).all()
    assert json.loads(get(f"{empty_server.url}/v1/map/extent")[2]) is None
    assert json.loads(get(f"{empty_server.url}/v1/robots")[2]) == []


@pytest.mark.parametrize("bbox, format, scanned", [("-20,-20,20,20", "png", 3), ("-5,-5,-5,5,5,5", "bt", 2)])
def test_a_tile_asked_for_before_the_first_scan_leaves_ingest_working(tmp_path, bbox, format, scanned):
    """A viewer (or an export) on a fresh server, then the first robot's scans, of the other dimension:
    they are acknowledged and counted toward the robot's quota."""
    state = ServerState(fleet="default", fleet_map=FleetMap("default"), store=Store(tmp_path))
    with Server(create_app(state)) as running:
        assert get(f"{running.url}/v1/occupancy?bbox={bbox}&resolution=0.2&format={format}")[0] == 200
        messages = [scan_of(scanned, node) for node in (0, 1)]
        answers = ingested(state, messages, quota_bytes=1 << 20)
        assert [(type(a).__name__, a.ids) for a in answers] == [("Ack", (0, 1))]
        assert stored_bytes(state, "r") == sum(len(encode(m)) for m in messages)
        assert json.loads(get(f"{running.url}/v1/map/extent")[2])["dim"] == scanned


def test_points(server, fleet_map):
    grid = Grid.from_bbox([-4.0, -6.0], [-1.0, -4.0], 0.1)
    centres = grid.cell_centers()
    expected = fleet_map.occupancy(grid).ravel()
    xy = ",".join(repr(float(v)) for v in centres[::7].ravel())
    status, _, body = get(f"{server.url}/v1/occupancy/points?xy={xy}&resolution=0.1")
    assert status == 200
    reply = json.loads(body)
    assert np.allclose(reply["probabilities"], expected[::7], atol=1e-6)
    status, body = post(f"{server.url}/v1/occupancy/points", {"points": centres.tolist(), "resolution": 0.1})
    assert status == 200 and np.allclose(json.loads(body)["probabilities"], expected, atol=1e-6)
    assert json.loads(body)["method"] == "mc"  # auto: a lattice of cell centres is one grid
    # Scattered points: each its own cell, evaluated like a one-cell grid (mc) or analytically.
    points = np.array([[0.013, -1.27], [-3.21, -5.55], [100.0, 100.0]])
    asked = {"points": points.tolist(), "resolution": 0.2}
    status, body = post(f"{server.url}/v1/occupancy/points", {**asked, "method": "mc"})
    one_cell = [fleet_map.occupancy(Grid(p - 0.1, 0.2, (1, 1)))[0, 0] for p in points]
    assert status == 200 and np.allclose(json.loads(body)["probabilities"], one_cell, atol=1e-6)
    assert json.loads(body)["probabilities"][2] == 0.5
    box = Grid.from_bbox(points.min(0) - 0.1, points.max(0) + 0.1, 0.2)  # the points' cells
    analytic = occupancy_at_cells(fleet_map.posed_components(box), points, 0.2)
    xy = ",".join(map(repr, points.ravel().tolist()))
    by_get = get(f"{server.url}/v1/occupancy/points?xy={xy}&resolution=0.2&method=analytic")[2]
    for reply in (post(f"{server.url}/v1/occupancy/points", asked)[1], by_get):
        assert json.loads(reply)["method"] == "analytic"  # asked, or auto's choice for three scattered points
        assert np.allclose(json.loads(reply)["probabilities"], analytic, atol=1e-6)


@pytest.mark.parametrize(
    "query, field",
    [
        ("xy=" + ",".join(["1"] * 20_002) + "&resolution=0.1", "xy"),
        ("xy=1,2,3&resolution=0.1", "xy"),
        ("xy=1,nan&resolution=0.1", "xy"),
        ("xy=1e300,0&resolution=0.1", "xy"),
        ("xy=1,2&resolution=0.1&method=exact", "method"),
        ("xyz=1,2,3&resolution=0.1", "xyz"),
        ("resolution=0.1", "xy"),
        ("xy=1,2&resolution=0", "resolution"),
    ],
)
def test_bad_points(server, query, field):
    status, _, body = get(f"{server.url}/v1/occupancy/points?{query}")
    assert status == 422 and json.loads(body)["field"] == field, body


def test_a_long_get_in_two_pieces_is_answered_as_in_one(server):
    # h11 parses a request head only once it is whole: one over its default limit (16 KiB) that
    # the network splits got a plain 400; the API's own limits must answer it, with a 422.
    head = "GET /v1/occupancy/points?xy=" + ",".join(["1"] * 20_002) + "&resolution=0.1 HTTP/1.1\r\n"
    request = (head + "Host: 127.0.0.1\r\nConnection: close\r\n\r\n").encode()
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as connection:
        connection.sendall(request[:20_000])
        time.sleep(0.2)  # the first piece is received (and incomplete) before the rest is sent
        connection.sendall(request[20_000:])
        reply = b""
        while chunk := connection.recv(65536):
            reply += chunk
    status_line, _, body = reply.partition(b"\r\n\r\n")
    assert status_line.split()[1] == b"422" and json.loads(body)["field"] == "xy", reply[:300]


@pytest.mark.parametrize(
    "payload, field",
    [
        ({"points": [[0, 0]]}, "resolution"),
        ({"points": [[0, "a"]], "resolution": 0.1}, "points.0.1"),
        ({"points": [[0, 0, 0]], "resolution": 0.1}, "points"),
        ({"points": [], "resolution": 0.1}, "points"),
        ({"points": [[0, 0]], "resolution": 0.1, "robots": ["a,b"]}, "robots"),
        ({"points": [[0, 0]], "resolution": 0.1, "method": "MC"}, "method"),
        ("not an object", None),
    ],
)
def test_bad_points_by_post(server, payload, field):
    status, body = post(f"{server.url}/v1/occupancy/points", payload)
    assert status == 422 and json.loads(body)["field"] == field, body


@pytest.mark.parametrize(
    "body, why",
    [
        (b'{"points":[[0,0', "Expecting ',' delimiter at character 15"),
        (
            b'{"points": [[0, 0]], "resolution": 0.1,}',
            "Expecting property name enclosed in double quotes at character 39",
        ),
        (b"\xff\xfe", "Expecting value at character 0"),  # not UTF-8
    ],
)
def test_a_body_that_is_not_json_is_400_saying_where_it_breaks(server, body, why):
    status, reply = post_bytes(f"{server.url}/v1/occupancy/points", body)
    assert status == 400 and json.loads(reply) == {"detail": f"the body is not valid JSON: {why}", "field": None}


def test_an_empty_body_is_422_saying_the_body_is_empty(server):
    status, reply = post_bytes(f"{server.url}/v1/occupancy/points", b"")
    assert status == 422 and json.loads(reply)["detail"].startswith("the body is empty"), reply


def test_too_many_points_by_post(server, fleet_map):
    status, body = post(f"{server.url}/v1/occupancy/points", {"points": [[0, 0]] * 10_001, "resolution": 0.1})
    assert status == 422 and "10,000" in json.loads(body)["detail"]
    scattered = np.random.default_rng(1).uniform(-10, 10, (1500, 2))  # each point its own cell lattice
    before = fleet_map.cache_stats()
    status, body = post(f"{server.url}/v1/occupancy/points", {"points": scattered.tolist(), "resolution": 0.1})
    assert status == 422 and "at most 1,000" in json.loads(body)["detail"]
    assert fleet_map.cache_stats() == before  # refused before any work
    lattice = (np.round(np.random.default_rng(2).uniform(-10, 10, (10_000, 2)) / 0.1) + 0.5) * 0.1
    status, body = post(f"{server.url}/v1/occupancy/points", {"points": lattice.tolist(), "resolution": 0.1})
    assert status == 200 and len(json.loads(body)["probabilities"]) == 10_000


def test_robots_trajectory_extent(server, fleet_map, intel_scans):
    robots = json.loads(get(f"{server.url}/v1/robots")[2])
    assert len(robots) == 1 and robots[0]["robot"] == "r1" and robots[0]["nodes"] == 100
    assert robots[0]["bytes_received"] == 100_000 and robots[0]["components"] > 100
    assert "last_seen" in robots[0] and robots[0]["pose_revision"] is None  # no pose graph: null
    path = json.loads(get(f"{server.url}/v1/robots/r1/trajectory")[2])
    assert len(path) == 100 and np.allclose(path, fleet_map.trajectory("r1"))
    assert np.allclose(path[0], intel_scans[0].pose.t, atol=0.5)  # the sensor sits on the robot
    assert get(f"{server.url}/v1/robots/nobody/trajectory")[0] == 404
    assert get(f"{server.url}/v1/robots/{quote('bad name')}/trajectory")[0] == 422
    extent = json.loads(get(f"{server.url}/v1/map/extent")[2])
    lo, hi = fleet_map.extent()
    assert extent == {"dim": 2, "lo": lo.tolist(), "hi": hi.tolist()}


def test_health_metrics_docs(server):
    status, _, body = get(f"{server.url}/healthz")
    assert status == 200 and json.loads(body)["status"] == "ok"
    get(f"{server.url}/v1/occupancy?bbox=0,0,1,1&resolution=0.5")
    get(f"{server.url}/v1/occupancy?bbox=0,0,1,1&resolution=0.5")
    status, headers, body = get(f"{server.url}/metrics")
    assert status == 200 and headers["Content-Type"].startswith("text/plain; version=0.0.4")
    text = body.decode()
    for name in (
        "gmmap_query_seconds_bucket",
        "gmmap_query_seconds_count",
        "gmmap_cache_hits_total",
        "gmmap_cache_misses_total",
        "gmmap_messages_accepted",
        "gmmap_bytes_received",
    ):
        assert name in text, name
    hits = float(next(line.split()[1] for line in text.splitlines() if line.startswith("gmmap_cache_hits_total")))
    assert hits >= 1
    status, _, page = get(f"{server.url}/docs")
    assert status == 200
    assets = re.findall(r'(?:src|href)="([^"]+)"', page.decode())
    assert assets and all(a.startswith("/static/swagger-ui/") for a in assets), assets  # no CDN: works offline
    for asset in assets:
        assert get(f"{server.url}{asset}")[0] == 200, asset
    spec = json.loads(get(f"{server.url}/openapi.json")[2])
    assert "/v1/occupancy" in spec["paths"] and "/v1/robots" in spec["paths"]
    assert "DESIGN.md" not in json.dumps(spec) and "docs/ARCHITECTURE.md" in spec["info"]["description"]
    parameters = {p["name"]: p for p in spec["paths"]["/v1/occupancy"]["get"]["parameters"]}
    variance = parameters["variance"]
    assert variance["schema"]["minimum"] == 0 and variance["schema"]["maximum"] == 0.25
    assert variance["schema"]["default"] == DEFAULT_VARIANCE and "Eq. 12" in variance["description"]
    assert parameters["shade"]["schema"]["default"] == "classes"
    assert get(f"{server.url}/nowhere")[0] == 404


def test_queries_do_not_block_the_event_loop(server):
    """A cold 9 M cell reconstruction (about a second) runs in the threadpool: /healthz answers meanwhile."""
    slow = threading.Thread(target=get, args=(f"{server.url}/v1/occupancy?bbox=-30,-30,30,30&resolution=0.02",))
    slow.start()
    time.sleep(0.1)
    assert get(f"{server.url}/healthz")[0] == 200
    still_running = slow.is_alive()  # a blocked event loop would answer only once the query is done
    slow.join()
    assert still_running


# -- the web viewer in headless Chromium ------------------------------------------------------


def test_viewer_is_served(server):
    status, headers, body = get(f"{server.url}/")
    assert status == 200 and headers["Content-Type"].startswith("text/html")
    assert b"<canvas" in body and b"v1/occupancy" in body and b"http" not in body.split(b"<script>")[1]
    assert f"const DEFAULT_VARIANCE = {DEFAULT_VARIANCE!r};".encode() in body  # the server's, written in


@pytest.mark.skipif(
    shutil.which("chromium") is None, reason="Debian chromium is not on PATH (make test installs it when run as root)"
)
def test_api_docs_render_offline(server, tmp_path):
    """Swagger UI's scripts come from the server itself: the page lists the API with no network beyond it."""
    dom = headless_chromium(tmp_path, "--dump-dom", f"{server.url}/docs").stdout.decode()
    assert "/v1/occupancy/points" in dom and "opblock" in dom, dom[-2000:]


@pytest.mark.skipif(
    shutil.which("chromium") is None, reason="Debian chromium is not on PATH (make test installs it when run as root)"
)
def test_a_click_on_the_viewer_shows_the_analytic_probability_of_its_cell(server, tmp_path):
    """The viewer's probe: a click asks /v1/occupancy/points (method analytic) for the clicked point's
    cell at the view's resolution, and the status line shows what the API answers for it."""
    shown = "document.getElementById('status').textContent"
    read = f"{shown}.includes('p(occupied)') ? [document.body.dataset.probe, {shown}] : null"
    answered, status = clicked(tmp_path, f"{server.url}/", (400, 300), read)
    probe = json.loads(answered)
    assert f"p(occupied) {probe['p']:.3f} at ({probe['x']:.2f}, {probe['y']:.2f})" in status, status
    xy = f"{probe['x']},{probe['y']}"
    _, _, body = get(f"{server.url}/v1/occupancy/points?xy={xy}&resolution={probe['resolution']}&method=analytic")
    assert json.loads(body)["probabilities"] == [probe["p"]] and 0.0 <= probe["p"] <= 1.0
    assert 0.005 <= probe["resolution"] <= 10


@pytest.mark.skipif(
    shutil.which("chromium") is None, reason="Debian chromium is not on PATH (make test installs it when run as root)"
)
def test_viewer_asks_a_shed_tile_again_after_its_retry_after(server, tmp_path, monkeypatch):
    """A tile answered 503 (the tracers saturated, as a cold server's first screen may find them) is
    asked again after its Retry-After, not left blank until the map changes."""
    fleet_map, shed, asked = server.state.fleet_map, [], {}
    answer = fleet_map.occupancy_answer

    def saturated_at_first(grid, robots=None, **kwargs):
        asked.setdefault((tuple(grid.origin), grid.resolution), []).append(time.monotonic())
        if len(shed) < 8:
            shed.append(grid)
            raise TracersSaturated(TracerLoad(threads=2, queued=16, running=2, wait_s=0.5))  # Retry-After: 1
        return answer(grid, robots, **kwargs)

    monkeypatch.setattr(fleet_map, "occupancy_answer", saturated_at_first)
    free = (screenshot(tmp_path, f"{server.url}/").mean(axis=2)[CENTRE] > FREE_GREY).mean()
    assert len(shed) == 8 and free > 0.05, f"{len(shed)} shed, {free:.1%} free pixels"
    gaps = [b - a for times in asked.values() for a, b in zip(times, times[1:])]
    assert gaps and min(gaps) >= 0.95, f"a shed tile was asked again {min(gaps):.2f} s after its 503 (Retry-After: 1)"


@pytest.mark.skipif(
    shutil.which("chromium") is None, reason="Debian chromium is not on PATH (make test installs it when run as root)"
)
@pytest.mark.parametrize(
    "query, free_at_least, occupied_at_least",
    # probabilities: only cells with p < 0.08 are near-white (4.4 % of the centre with the samples traced as drawn)
    [("", 0.05, 0.0003), ("?variance=0.25", 0.05, 0.003), ("?shade=probability", 0.03, 0.003)],
)
def test_viewer_draws_the_map(server, tmp_path, query, free_at_least, occupied_at_least):
    """The Eq. 12 classes (the default layer, at the default and at a chosen variance) and the probabilities."""
    image = screenshot(tmp_path, f"{server.url}/{query}")
    assert image.shape[:2] == (600, 800)
    centre = image.mean(axis=2)[CENTRE]
    free = (centre > FREE_GREY).mean()
    occupied = (centre < 70).mean()
    assert free > free_at_least, f"only {free:.1%} free (near-white) map pixels: the map is not drawn"
    assert occupied > occupied_at_least, f"only {occupied:.2%} occupied (dark) map pixels"
    if "probability" not in query:  # classes: white, black or the grey of unknown, nothing between
        plain = (image.max(axis=2) == image.min(axis=2))[CENTRE]
        assert np.isin(centre[plain], [0, 128, 255]).mean() > 0.999
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    trajectory = (r > 180) & (g < 80) & (b < 120)  # the first robot's colour, #e6194b
    assert trajectory.sum() > 100, "the robot's trajectory is not drawn"
