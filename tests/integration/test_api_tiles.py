"""Tiles over HTTP under load: X-Map-Age on every occupancy answer, 503 + Retry-After when the
tracers are saturated, and what /metrics says of both. Real uvicorn on 127.0.0.1, Intel scans."""

from __future__ import annotations

import json
import logging
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor

import pytest

from gmm_core import Grid, fit_scan
from protocol import ScanMessage
from services.api import create_app
from services.map_server.fleet_map import FleetMap
from services.map_server.metrics import ServerMetrics
from services.map_server.state import ServerState
from services.map_server.tiles import MAX_STALE_S
from services.map_server.warmup import warm_kernels
from support.net import get, post, wait_for
from support.saturation import held_traces, saturated_tracers
from support.uvicorn_thread import Server

ORIGIN = "http://viewer.example"
KINDS = ("fresh", "updated", "stale", "coalesced", "shed")  # of gmmap_tile_answers_total
STOPPING = {"detail": "the map server is stopping", "field": None, "reason": "server_stopping", "retry_after": 1}


@pytest.fixture(scope="module")
def messages(intel_scans):
    return [
        ScanMessage("test", "r1", s.index, s.stamp, fit_scan(s.hits, s.no_return), s.pose) for s in intel_scans[:21]
    ]


@pytest.fixture(scope="module", autouse=True)
def kernels_loaded():
    """As a server loads them before it serves: an update compiling its kernels on a cold numba
    cache, beside another test's, outlasted a request's patience (PATIENCE_S) in a fresh-clone run."""
    warm_kernels()


@pytest.fixture
def server(messages):
    fleet = FleetMap("test", trace_threads=1)
    for msg in messages[:20]:
        fleet.add_scan(msg)
    state = ServerState(fleet="test", fleet_map=fleet, store=None, metrics=ServerMetrics())
    with Server(create_app(state, cors_origins=[ORIGIN])) as running:
        running.fleet_map = fleet
        yield running


def metric(server, line_start: str) -> float:
    text = get(f"{server.url}/metrics")[2].decode()
    return float(next(line.split()[-1] for line in text.splitlines() if line.startswith(line_start)))


def test_every_occupancy_answer_says_how_old_its_state_is(server, messages):
    url = f"{server.url}/v1/occupancy?bbox=-8,-12,8,4&resolution=0.1&format=png"
    for _ in range(2):  # traced, then from the cache
        status, headers, _ = get(url)
        assert status == 200 and headers["X-Map-Age"] == "0.000000"
    server.fleet_map.add_scan(messages[20])
    (tile,) = server.fleet_map._tiles.values()
    with tile.lock:  # as if another request were updating it now: its previous state is served
        status, headers, _ = get(url)
    assert status == 200 and 0 < float(headers["X-Map-Age"]) <= MAX_STALE_S
    # Brought up to date: the next request starts the update and waits for it for PATIENCE_S; on a
    # loaded host (a fresh-clone run beside other tests) the update can take longer, and that
    # request is served the previous state while it runs. Asked again until up to date.
    ages = [float(get(url)[1]["X-Map-Age"])]
    while ages[-1] > 0 and len(ages) < 200:
        time.sleep(0.05)
        ages.append(float(get(url)[1]["X-Map-Age"]))
    assert ages[-1] == 0 and all(0 < age <= MAX_STALE_S for age in ages[:-1]), ages
    waits = len(ages) - 1
    answers = {kind: metric(server, f'gmmap_tile_answers_total{{kind="{kind}"}}') for kind in KINDS}
    # Up to date: updated (the first trace, and the request that waited for the update) or fresh
    # (the cached state, and the update done before the request came).
    assert answers["fresh"] + answers["updated"] == 3 and answers["fresh"] >= 1 and answers["updated"] >= 1, answers
    assert (answers["stale"], answers["coalesced"], answers["shed"]) == (1 + waits, 0, 0), answers
    assert metric(server, "gmmap_tile_age_seconds_count") == 4 + waits
    assert metric(server, 'gmmap_tile_age_seconds_bucket{le="0.0"}') == 3


def test_max_age_zero_is_served_every_change_and_a_max_age_out_of_range_is_refused(server, messages):
    url = f"{server.url}/v1/occupancy?bbox=-8,-12,8,4&resolution=0.1&format=npy"
    assert get(url)[1]["X-Map-Age"] == "0.000000"
    server.fleet_map.add_scan(messages[20])
    (tile,) = server.fleet_map._tiles.values()
    tile.refreshing = True  # as if an update were queued in the background: max_age=0 does not take its state
    status, headers, _ = get(url + "&max_age=0")
    assert status == 200 and headers["X-Map-Age"] == "0.000000"
    for bad in ("5", "-1", "nan"):
        status, _, body = get(url + f"&max_age={bad}")
        assert status in (400, 422) and json.loads(body)["field"] == "max_age", body


def test_saturated_tracers_shed_with_503_and_retry_after_then_serve_again(server, monkeypatch):
    cold_grids = [Grid.from_bbox([-8.0, -12.0], [0.0, -4.0], r) for r in (0.2, 0.25, 0.3)]
    url = f"{server.url}/v1/occupancy?bbox=-6,-10,2,-2&resolution=0.15"
    with saturated_tracers(monkeypatch, server.fleet_map, cold_grids):
        status, headers, body = get(url)
        assert status == 503 and headers["Content-Type"] == "application/json"
        assert int(headers["Retry-After"]) >= 1
        reply = json.loads(body)
        assert reply["reason"] == "tracers_saturated" and reply["field"] is None
        assert reply["detail"].startswith("tracers saturated: 2 traces queued for 1 tracer thread (no part timed")
        assert reply["retry_after"] == int(headers["Retry-After"])
        assert "X-Map-Age" not in headers
        assert metric(server, "gmmap_tracer_queue_depth") == 2
    status, headers, _ = get(url)
    assert status == 200 and headers["X-Map-Age"] == "0.000000"
    assert metric(server, 'gmmap_tile_answers_total{kind="shed"}') == 1
    assert metric(server, 'gmmap_tile_answers_total{kind="updated"}') == 1
    assert metric(server, "gmmap_tracer_queue_depth") == 0
    assert metric(server, "gmmap_cache_misses_total") == 4  # the three queued tiles, and this one


def test_requests_whose_traces_a_stop_cuts_off_are_503_with_retry_after_and_log_no_traceback(
    server, monkeypatch, caplog
):
    """A stopping server closes its map before its HTTP server (server.py): a request tracing then,
    one queued behind it and one that comes after are answered 503, not 500 with a traceback."""
    uvicorn_log = logging.getLogger("uvicorn.error")  # uvicorn's logger: it does not propagate to caplog's
    uvicorn_log.addHandler(caplog.handler)
    tile = f"{server.url}/v1/occupancy?bbox=-6,-10,2,-2&resolution=0.15"
    points = {"points": [[0.0, 0.0], [1.0, 1.0]], "resolution": 0.1, "method": "mc"}
    try:
        with ThreadPoolExecutor(2) as requests:
            with held_traces(monkeypatch) as held:
                tracing = requests.submit(get, tile)
                wait_for(lambda: held, 20, "the tile's trace")
                queued = requests.submit(post, f"{server.url}/v1/occupancy/points", points)
                wait_for(lambda: server.fleet_map.cache_stats()["trace_queued"] == 1, 20, "the points' trace")
                server.fleet_map.close()
            tile_answers = [tracing.result(), get(tile.replace("0.15", "0.2"))]
            points_answer = queued.result()
    finally:
        uvicorn_log.removeHandler(caplog.handler)
    for status, headers, body in tile_answers:
        assert (status, headers["Retry-After"], json.loads(body)) == (503, "1", STOPPING)
    assert (points_answer[0], json.loads(points_answer[1])) == (503, STOPPING)
    assert not caplog.records, [r.getMessage() for r in caplog.records]


def test_a_tile_out_of_date_when_the_server_stops_is_503_with_retry_after_and_logs_no_traceback(
    server, messages, caplog
):
    """A cached tile that a scan made out of date, asked for after the stop closed the map: its update
    would run in the background, which the closed map refuses (503), not 500 "cannot schedule new
    futures after shutdown" with a traceback."""
    uvicorn_log = logging.getLogger("uvicorn.error")  # uvicorn's logger: it does not propagate to caplog's
    uvicorn_log.addHandler(caplog.handler)
    tile = f"{server.url}/v1/occupancy?bbox=-6,-10,2,-2&resolution=0.1"
    try:
        assert get(tile)[0] == 200
        server.fleet_map.add_scan(messages[20])
        server.fleet_map.close()
        status, headers, body = get(tile)
    finally:
        uvicorn_log.removeHandler(caplog.handler)
    assert (status, headers["Retry-After"], json.loads(body)) == (503, "1", STOPPING)
    assert not caplog.records, [r.getMessage() for r in caplog.records]


def test_the_age_and_retry_headers_are_exposed_to_a_viewer_on_another_origin(server):
    url = f"{server.url}/v1/occupancy?bbox=0,0,1,1&resolution=0.5"
    with urllib.request.urlopen(urllib.request.Request(url, headers={"Origin": ORIGIN}), timeout=60) as reply:
        assert reply.status == 200
        exposed = {h.strip() for h in reply.headers["Access-Control-Expose-Headers"].split(",")}
    assert {"X-Map-Age", "Retry-After", "X-Grid-Shape"} <= exposed
