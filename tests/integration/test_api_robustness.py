"""The HTTP API under hostile input: an API fuzzer against its own OpenAPI, request size limits,
work refused before it starts, CORS off. Real uvicorn on 127.0.0.1, a small Intel map."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import zenoh

from gmm_core import fit_scan
from protocol import MapQuery, ScanMessage, encode
from services.agent.map_client import MapQueryError, query_bytes
from services.api import create_app
from services.map_server.fleet_map import FleetMap
from services.map_server.state import ServerState
from services.zenoh_config import zenoh_config
from support.net import free_port, get
from support.net import post as post_json
from support.uvicorn_thread import Server

SCHEMATHESIS = Path(sys.executable).with_name("schemathesis")


@pytest.fixture(scope="module")
def server(intel_scans):
    fleet = FleetMap("test")
    for s in intel_scans[:200:4]:  # 50 scans: a map small enough that the fuzzer's queries stay cheap
        fleet.add_scan(ScanMessage("test", "r1", s.index, s.stamp, fit_scan(s.hits, s.no_return), s.pose), 1000)
    with Server(create_app(ServerState("test", fleet))) as running:
        running.fleet_map = fleet
        yield running


@pytest.mark.skipif(not SCHEMATHESIS.exists(), reason="schemathesis is not installed (pip install -e '.[dev]')")
def test_schemathesis_finds_no_server_error_and_no_schema_violation(server, tmp_path):
    """Every check but positive_data_acceptance: the API rejects schema-valid requests that break
    rules OpenAPI cannot state (lo < hi, the cell limit, one dimension per map), by design."""
    command = [
        str(SCHEMATHESIS),
        "run",
        f"{server.url}/openapi.json",
        "--checks",
        "all",
        "--exclude-checks",
        "positive_data_acceptance",
        "--max-examples",
        "25",
        "--seed",
        "7",
        "--request-timeout",
        "20",
        "--workers",
        "1",
    ]
    run = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=170)
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-2000:]
    assert "passed" in run.stdout


def test_errors_are_json_with_the_documented_schema(server):
    for method, path, code in (
        ("TRACE", "/healthz", 405),
        ("OPTIONS", "/v1/occupancy/points", 405),
        ("GET", "/nowhere", 404),
        ("GET", "/v1/occupancy?bbox=1,2,3", 422),
    ):
        request = urllib.request.Request(f"{server.url}{path}", method=method)
        try:
            urllib.request.urlopen(request, timeout=10)
            raise AssertionError(f"{method} {path} succeeded")
        except urllib.error.HTTPError as e:
            assert e.code == code and e.headers["Content-Type"] == "application/json", (method, path)
            assert set(json.loads(e.read())) == {"detail", "field"}
            if code == 405:  # every method of the path, GET and POST sharing one included
                expected = "GET, POST" if path.endswith("points") else "GET"
                assert e.headers["Allow"] == expected
    status, body = post_json(f"{server.url}/v1/occupancy/points", {"points": [[False, 0]], "resolution": 0.1})
    assert status == 422 and json.loads(body)["field"] == "points.0.0"  # no bool taken for a number


def test_oversized_requests_are_refused_before_any_work(server):
    queries = [
        "bbox=-1e6,-1e6,1e6,1e6&resolution=0.005",  # 1.6e17 cells
        "bbox=-1e300,-1e300,1e300,1e300&resolution=0.005",
        "bbox=0,0,429496729.6,429496729.6&resolution=0.1",
    ]  # 2^64 cells: int64 would wrap to 0
    for query in queries:
        before = server.fleet_map.cache_stats()
        status, _, body = get(f"{server.url}/v1/occupancy?{query}")
        assert status == 422 and json.loads(body)["field"] == "bbox", body
        assert server.fleet_map.cache_stats() == before, query  # no tile, no samples: counted before any work


def test_cors_is_off_by_default(server):
    request = urllib.request.Request(f"{server.url}/v1/robots", headers={"Origin": "http://evil.example"})
    with urllib.request.urlopen(request, timeout=10) as reply:
        assert reply.status == 200 and "Access-Control-Allow-Origin" not in reply.headers
    preflight = urllib.request.Request(
        f"{server.url}/v1/occupancy/points",
        method="OPTIONS",
        headers={"Origin": "http://evil.example", "Access-Control-Request-Method": "POST"},
    )
    try:
        urllib.request.urlopen(preflight, timeout=10)
        raise AssertionError("a CORS preflight was answered")
    except urllib.error.HTTPError as e:
        assert e.code == 405 and "Access-Control-Allow-Origin" not in e.headers


def raw_http(port: int, head: bytes, body_chunks=()) -> bytes:
    """Send a request byte for byte (chunked bodies too); the server's reply, up to 64 KiB."""
    with socket.create_connection(("127.0.0.1", port), timeout=20) as s:
        try:
            s.sendall(head)
            for chunk in body_chunks:
                s.sendall(b"%x\r\n%s\r\n" % (len(chunk), chunk))
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server may answer and close before taking the whole body
        reply = b""
        while not reply.endswith(b"}") and len(reply) < 65536:
            data = s.recv(65536)
            if not data:
                break
            reply += data
    return reply


def test_request_bodies_over_one_mib_are_refused_with_413(server):
    port = int(server.url.rsplit(":", 1)[1])
    post = b"POST /v1/occupancy/points HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
    # Declared too long: refused on the headers, before a byte of the body is read. (The test sends
    # no body: unread bytes at the close would make the kernel reset the connection. A server that
    # waited for the body would answer nothing before the socket's timeout.)
    reply = raw_http(port, post + b"Content-Length: 2000000\r\n\r\n")
    assert reply.startswith(b"HTTP/1.1 413") and b"1,048,576" in reply, reply[:300]
    # Chunked, without a length: counted as it arrives, refused once past 1 MiB (17 chunks of 64 KiB).
    reply = raw_http(port, post + b"Transfer-Encoding: chunked\r\n\r\n", [b"[" * 65536] * 17)
    assert reply.startswith(b"HTTP/1.1 413") and b'"detail"' in reply, reply[:300]
    # Under the limit, the same endpoint still answers.
    status, body = post_json(f"{server.url}/v1/occupancy/points", {"points": [[0.0, 0.0]], "resolution": 0.1})
    assert status == 200


def not_parsed(reply: bytes) -> dict:
    """The JSON error body of a 400 for a request HTTP's parser refused (h11: the app never saw it)."""
    head, _, body = reply.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 400") and b"content-type: application/json" in head.lower(), reply[:300]
    return json.loads(body)


@pytest.mark.parametrize(
    "head", [b"NOT HTTP AT ALL\r\n\r\n", b"GET /healthz HTTP/1.1\r\nHost: x\r\nno colon here\r\n\r\n"]
)
def test_a_request_that_is_not_http_gets_400_with_the_json_error_body(server, head):
    reply = not_parsed(raw_http(server.port, head))
    assert reply["field"] is None and reply["detail"].startswith("Invalid HTTP request received"), reply


def test_server_limits_request_heads_and_zenoh_map_queries(procs, tmp_path):
    """The real `gmmap server`: heads over 1 MiB get a JSON 400; huge Zenoh queries a named error."""
    zport, hport = free_port(), free_port()
    procs.server("server", tmp_path / "data", zport, hport)
    long_query = b"GET /v1/occupancy/points?resolution=0.1&xy=" + b"1," * (1 << 20) + b"1 HTTP/1.1\r\nHost: x\r\n\r\n"
    reply = not_parsed(raw_http(hport, long_query))
    assert "1,048,576 bytes" in reply["detail"] and reply["field"] is None, reply
    # 10,000 points (the API's maximum) fit under the limit.
    points = ",".join(["12.3456,-7.891"] * 10_000)
    status, _, body = get(f"http://127.0.0.1:{hport}/v1/occupancy/points?resolution=0.1&xy={points}")
    assert status == 200 and len(json.loads(body)["probabilities"]) == 10_000

    session = zenoh.open(zenoh_config("peer", connect=[f"tcp/127.0.0.1:{zport}"]))
    try:
        for lo, hi in (([0, 0], [2**32 * 0.1] * 2), ([-1e300] * 3, [1e300] * 3)):
            with pytest.raises(MapQueryError, match="bbox: .* cells requested"):  # counted, not built
                query_bytes(session, "default", encode(MapQuery("default", np.array(lo), np.array(hi), 0.1)))
    finally:
        session.close()
