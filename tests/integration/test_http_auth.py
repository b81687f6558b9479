"""Who may read the map over HTTP: TLS and bearer tokens against real uvicorn servers (the app in a
thread, and `gmmap server`, `sim` and `demo` processes), real TLS clients, the API fuzzer with and
without a token, and the viewer in headless Chromium. Two robots of real Intel scans."""

from __future__ import annotations

import http.client
import io
import json
import os
import shutil
import ssl
import subprocess
import sys
import urllib.error
import urllib.request

import numpy as np
import pytest

from gmm_core import fit_scan
from protocol import ScanMessage
from services.api import create_app
from services.map_server.fleet_map import FleetMap
from services.map_server.state import ServerState
from services.map_server.tokens import TokenFile
from support.browser import CENTRE, FREE_GREY, headless_chromium, screenshot
from support.http_auth import make_certs, write_tokens
from support.net import free_port, metric, wait_for
from support.paths import ROOT
from support.uvicorn_thread import Server

GMMAP = [sys.executable, "-m", "services.cli"]
ENV = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
SCHEMATHESIS = sys.executable.rsplit("/", 1)[0] + "/schemathesis"
BBOX = "-10,-20,10,5"
TILE = f"/v1/occupancy?bbox={BBOX}&resolution=0.1&format=npy"
CHROMIUM = pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian chromium is not on PATH")


@pytest.fixture(scope="module")
def secrets(tmp_path_factory):
    """Trial certificates for 127.0.0.1, and a token file: ops reads the fleet, dock robot a only."""
    folder = tmp_path_factory.mktemp("secrets")
    certs = make_certs(folder / "certs")
    tokens = write_tokens(folder / "tokens.txt", {"ops": None, "dock": ["a"]})
    return certs, folder / "tokens.txt", tokens


@pytest.fixture(scope="module")
def fleet_map(intel_scans):
    """Robot a at the start of the Intel run, robot b later in it: their maps differ."""
    fleet = FleetMap("test")
    for robot, scans in (("a", intel_scans[:200:4]), ("b", intel_scans[400:600:4])):
        for s in scans:
            fleet.add_scan(ScanMessage("test", robot, s.index, s.stamp, fit_scan(s.hits, s.no_return), s.pose), 1000)
    return fleet


@pytest.fixture(scope="module")
def server(fleet_map, secrets):
    """The API over TLS with the token file."""
    certs, token_file, tokens = secrets
    with Server(create_app(ServerState("test", fleet_map), tokens=TokenFile(token_file)), certs.cert, certs.key) as s:
        s.tokens, s.token_file = tokens, token_file
        s.context = ssl.create_default_context(cafile=str(certs.ca))
        yield s


def call(server, path: str, token: str | None = None, *, authorization: str | None = None, body=None, context=None):
    """(status, headers, body) of a request to `server`, 4xx included; `authorization` as sent when given."""
    headers = {"Authorization": authorization or f"Bearer {token}"} if (token or authorization) else {}
    if body is not None:
        headers["Content-Type"] = "application/json"
    request = urllib.request.Request(server.url + path, body, headers)
    try:
        with urllib.request.urlopen(request, timeout=60, context=context or server.context) as reply:
            return reply.status, reply.headers, reply.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers, e.read()


def refused(server) -> dict[str, float]:
    text = call(server, "/metrics", server.tokens["ops"])[2].decode()
    return {reason: metric(text, "gmmap_http_refused_total", reason=reason) for reason in ("missing", "invalid")}


PROTECTED = [
    ("/v1/robots", None),
    ("/v1/map/extent", None),
    (TILE, None),
    ("/v1/occupancy?bbox=1,2,3", None),  # malformed: still 401, not 422 (nothing is learnt without a token)
    ("/v1/occupancy/points?xy=0,0&resolution=0.1", None),
    ("/v1/occupancy/points", b"{not json"),  # refused before its body is read
    ("/v1/robots/a/trajectory", None),
    ("/metrics", None),
    ("/nowhere", None),
]


def test_without_a_valid_token_every_map_request_gets_401_json(server):
    before = refused(server)
    ops = server.tokens["ops"]
    wrong = {
        "wrong token": f"Bearer {ops}x",
        "the hash, not the token": f"Bearer {TokenFile(server.token_file).clients[0].digest.hex()}",
    }
    for path, body in PROTECTED:
        for authorization in (None, f"Basic {ops}", "Bearer ", *wrong.values()):
            status, headers, reply = call(server, path, authorization=authorization, body=body)
            assert status == 401, (path, authorization, status, reply[:200])
            assert headers["Content-Type"] == "application/json" and set(json.loads(reply)) == {"detail", "field"}
            challenge = headers["WWW-Authenticate"]
            assert challenge.startswith('Bearer realm="gmmap"')
            assert ('error="invalid_token"' in challenge) == (authorization in wrong.values())
        assert call(server, path, ops, body=body)[0] != 401  # the same request with the token passes
    after = refused(server)
    assert after["missing"] - before["missing"] == 3 * len(PROTECTED)  # none, Basic, empty Bearer
    assert after["invalid"] - before["invalid"] == 2 * len(PROTECTED)


def test_what_holds_no_map_stays_open(server):
    for path, holds in (("/healthz", b'"fleet"'), ("/", b"<canvas"), ("/docs", b"swagger"), ("/openapi.json", b"")):
        status, _, body = call(server, path)
        assert status == 200 and holds in body, path
    schema = json.loads(call(server, "/openapi.json")[2])
    assert schema["components"]["securitySchemes"]["bearer"] == {
        "type": "http",
        "scheme": "bearer",
        "description": "a token of the server's --http-tokens",
    }
    secured = {path for path, ops in schema["paths"].items() for op in ops.values() if op.get("security")}
    assert secured == set(schema["paths"]) - {"/healthz"}


def test_tls_is_verified_against_the_fleet_ca(server):
    port = server.port
    with pytest.raises(urllib.error.URLError) as error:  # the system's CAs do not know the trial CA
        call(server, "/healthz", context=ssl.create_default_context())
    assert isinstance(error.value.reason, ssl.SSLCertVerificationError)
    with pytest.raises((OSError, http.client.HTTPException)):  # plain HTTP to the TLS port
        urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=10).read()
    ops = {"Authorization": f"Bearer {server.tokens['ops']}"}
    localhost = urllib.request.Request(f"https://localhost:{port}/v1/robots", headers=ops)
    with urllib.request.urlopen(localhost, timeout=10, context=server.context) as reply:  # the name is checked too
        assert [r["robot"] for r in json.loads(reply.read())] == ["a", "b"]


def test_a_token_limited_to_robot_a_reads_robot_a_alone(server, fleet_map):
    ops, dock = server.tokens["ops"], server.tokens["dock"]
    fleet_tile = np.load(io.BytesIO(call(server, TILE, ops)[2]))  # cached first: dock must not be served it
    a_tile = np.load(io.BytesIO(call(server, TILE + "&robots=a", ops)[2]))
    status, _, body = call(server, TILE, dock)
    assert status == 200
    dock_tile = np.load(io.BytesIO(body))
    assert np.array_equal(dock_tile, a_tile) and not np.array_equal(dock_tile, fleet_tile)
    for fmt in ("png", "msgpack"):  # the encoded replies are cached per robots too
        assert call(server, f"{TILE[:-3]}{fmt}", dock)[2] == call(server, f"{TILE[:-3]}{fmt}&robots=a", ops)[2]
    assert call(server, TILE + "&robots=a", dock)[2] == body

    assert [r["robot"] for r in json.loads(call(server, "/v1/robots", dock)[2])] == ["a"]
    lo, hi = fleet_map.extent(["a"])
    assert json.loads(call(server, "/v1/map/extent", dock)[2]) == {"dim": 2, "lo": lo.tolist(), "hi": hi.tolist()}
    whole = json.loads(call(server, "/v1/map/extent", ops)[2])
    assert [whole["lo"], whole["hi"]] == [v.tolist() for v in fleet_map.extent()] != [lo.tolist(), hi.tolist()]
    points = "/v1/occupancy/points?xy=0,0,1,-2&resolution=0.1"
    assert json.loads(call(server, points, dock)[2]) == json.loads(call(server, points + "&robots=a", ops)[2])
    assert call(server, "/v1/robots/a/trajectory", dock)[0] == 200

    forbidden_before = metric(call(server, "/metrics", ops)[2].decode(), "gmmap_http_refused_total", reason="forbidden")
    for path, body, field in (
        (TILE + "&robots=b", None, "robots"),
        (TILE + "&robots=a,b", None, "robots"),
        (points + "&robots=b", None, "robots"),
        ("/v1/occupancy/points", json.dumps({"points": [[0.0, 0.0]], "resolution": 0.1, "robots": ["b"]}), "robots"),
        ("/v1/robots/b/trajectory", None, "robot"),
        ("/v1/robots/nobody/trajectory", None, "robot"),  # 403, not 404: no robot's existence is told
        ("/metrics", None, "robots"),  # it counts bytes by robot
    ):
        status, headers, reply = call(server, path, dock, body=body and body.encode())
        assert status == 403 and headers["Content-Type"] == "application/json", (path, status, reply[:200])
        assert json.loads(reply)["field"] == field, path
    after = metric(call(server, "/metrics", ops)[2].decode(), "gmmap_http_refused_total", reason="forbidden")
    assert after - forbidden_before == 7


@pytest.mark.skipif(not os.path.exists(SCHEMATHESIS), reason="schemathesis is not installed (pip install -e '.[dev]')")
def test_schemathesis_over_tls_with_a_token_finds_nothing_and_its_probes_without_one_are_refused(
    server, secrets, tmp_path
):
    """Every check but positive_data_acceptance (as in test_api_robustness), ignored_auth included: for
    each operation it repeats a request that passed without the token and with a wrong one, and fails
    unless both are refused."""
    certs, _, tokens = secrets
    before = refused(server)
    command = [
        SCHEMATHESIS,
        "run",
        f"{server.url}/openapi.json",
        "--header",
        f"Authorization: Bearer {tokens['ops']}",
        "--tls-verify",
        str(certs.ca),
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
    run = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=240)
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-2000:]
    assert "passed" in run.stdout
    after = refused(server)
    # Each operation that answered 2xx was probed once without the token and once with a wrong one: all
    # seven but /healthz (open) and the trajectory (a made-up robot's is 404).
    assert after["missing"] - before["missing"] >= 6 and after["invalid"] - before["invalid"] >= 6


# -- gmmap server, sim and demo processes ------------------------------------------------------------


def beyond_loopback(data, hport: int, *extra: str) -> list[str]:
    """`gmmap server` arguments for every address (0.0.0.0) of this machine."""
    zenoh = ("--zenoh-listen", f"tcp/127.0.0.1:{free_port()}")
    return ["server", *zenoh, "--http", f"0.0.0.0:{hport}", "--data-dir", str(data), *extra]


@pytest.mark.parametrize(
    "given, says",
    [
        ((), "refusing to serve 0.0.0.0:PORT without TLS and tokens: it is not a loopback address"),
        (("tokens",), "without TLS: it is not a loopback address, so the tokens and the map cross the network"),
        (("cert", "key"), "without tokens: it is not a loopback address, so anyone who reaches it reads"),
        (("cert", "ca-as-key", "tokens"), "--http-tls-cert CERT --http-tls-key CA: not a PEM certificate and its key"),
        (("cert", "key", "cert-as-tokens"), "CERT line 1: the second word must be sha256:"),
    ],
)
def test_gmmap_server_beyond_loopback_refuses_to_start_without_tls_and_tokens(secrets, tmp_path, given, says):
    certs, token_file, _ = secrets
    hport = free_port()
    flags = {
        "cert": ("--http-tls-cert", certs.cert),
        "key": ("--http-tls-key", certs.key),
        "ca-as-key": ("--http-tls-key", certs.ca),
        "tokens": ("--http-tokens", token_file),
        "cert-as-tokens": ("--http-tokens", certs.cert),
    }
    args = beyond_loopback(tmp_path / "data", hport, *(str(v) for g in given for v in flags[g]))
    run = subprocess.run(GMMAP + args, cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr[-2000:]
    expected = says.replace("PORT", str(hport)).replace("CERT", str(certs.cert)).replace("CA", str(certs.ca))
    assert expected in run.stderr, run.stderr[-2000:]
    assert "gmmap server ready" not in run.stderr and not (tmp_path / "data").exists()  # nothing was opened
    if not given:
        for flag in ("--http-tls-cert", "--http-tls-key", "--http-tokens", "--http-insecure", "127.0.0.1"):
            assert flag in run.stderr


def test_gmmap_server_beyond_loopback_with_tls_and_tokens_or_said_insecure(procs, secrets, tmp_path):
    certs, token_file, tokens = secrets
    hport = free_port()
    secure = ("--http-tls-cert", str(certs.cert), "--http-tls-key", str(certs.key), "--http-tokens", str(token_file))
    proc = procs.ready(procs.start("server", *beyond_loopback(tmp_path / "a", hport, *secure)), "gmmap server ready")
    assert f"http https://0.0.0.0:{hport} (2 token clients)" in procs.log(proc)
    url = f"https://127.0.0.1:{hport}/v1/robots"
    context = ssl.create_default_context(cafile=str(certs.ca))
    with urllib.request.urlopen(
        urllib.request.Request(url, headers={"Authorization": f"Bearer {tokens['ops']}"}), timeout=10, context=context
    ) as reply:
        assert json.loads(reply.read()) == []
    with pytest.raises(urllib.error.HTTPError) as error:
        urllib.request.urlopen(url, timeout=10, context=context)
    assert error.value.code == 401 and json.loads(error.value.read())["field"] is None
    assert procs.stop("server") == 0

    hport = free_port()
    proc = procs.ready(
        procs.start("server", *beyond_loopback(tmp_path / "b", hport, "--http-insecure")), "gmmap server ready"
    )
    assert f"WARNING --http-insecure: serving 0.0.0.0:{hport} without TLS and tokens" in procs.log(proc)
    with urllib.request.urlopen(f"http://127.0.0.1:{hport}/v1/robots", timeout=10) as reply:
        assert json.loads(reply.read()) == []


def test_sim_against_its_server_with_tls_and_tokens(secrets, tmp_path):
    """`gmmap sim`'s snapshots and tile clients over HTTPS with a token: every request answered."""
    certs, token_file, tokens = secrets
    (tmp_path / "ops.token").write_text(tokens["ops"] + "\n")
    server = ["--http-tls-cert", str(certs.cert), "--http-tls-key", str(certs.key), "--http-tokens", str(token_file)]
    client = ["--http-token", "ops.token", "--http-ca", str(certs.ca)]  # relative: the sim's own folder
    sim = ["sim", "--robots", "1", "--duration", "4", "--http-clients", "1", "--report", "out", *server, *client]
    run = subprocess.run(GMMAP + sim, cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["scans_published"] == report["scans_stored"] == 20
    assert report["tile_requests"] > 0 and report["tile_errors"] == 0, report
    assert report["auroc"] > 0.8  # the snapshots were read


def test_demo_with_tls_and_tokens_and_its_refusal_beyond_loopback(secrets, tmp_path):
    certs, token_file, tokens = secrets
    (tmp_path / "ops.token").write_text(tokens["ops"])
    port = free_port()
    refused_run = subprocess.run(
        GMMAP + ["demo", "--duration", "3", "--http", f"0.0.0.0:{port}"],
        cwd=tmp_path,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert refused_run.returncode == 2 and "refusing to serve 0.0.0.0" in refused_run.stderr
    assert "viewer is at" not in refused_run.stdout  # said before anything started
    secure = ["--http-tls-cert", str(certs.cert), "--http-tls-key", str(certs.key), "--http-tokens", str(token_file)]
    client = ["--http-token", "ops.token", "--http-ca", str(certs.ca)]
    demo = subprocess.Popen(
        GMMAP + ["demo", "--duration", "3", "--http", f"127.0.0.1:{port}", *secure, *client],
        cwd=tmp_path,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert demo.stdout.readline().startswith(f"gmmap demo: the viewer is at https://127.0.0.1:{port}/")
        context = ssl.create_default_context(cafile=str(certs.ca))

        def robots(client: str) -> list[dict]:
            headers = {"Authorization": f"Bearer {tokens[client]}"}
            request = urllib.request.Request(f"https://127.0.0.1:{port}/v1/robots", headers=headers)
            with urllib.request.urlopen(request, timeout=5, context=context) as reply:
                return json.loads(reply.read())

        def nodes() -> int:  # 0 until the server answers
            try:
                return sum(r["nodes"] for r in robots("ops"))
            except OSError:
                return 0

        # On a cold numba cache the robots' first fits compile while other tests do: give it time.
        wait_for(nodes, 120, "the demo's first nodes", interval=0.3)
        assert robots("dock") == []  # the demo's robots are r0, r1, r2: none is dock's robot a
        assert demo.wait(60) == 0
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()


# -- the viewer --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def plain_server(fleet_map, secrets):
    """The API with tokens on loopback without TLS (allowed there), for Chromium."""
    _, token_file, tokens = secrets
    with Server(create_app(ServerState("test", fleet_map), tokens=TokenFile(token_file))) as s:
        s.tokens = tokens
        yield s


def robot_pixels(image: np.ndarray) -> tuple[int, int]:
    """Pixels of the first robot's colour (#e6194b) and of the second's (#0082c8)."""
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    first = (r > 180) & (g < 80) & (b < 120)
    second = (r < 60) & (g > 100) & (g < 160) & (b > 170)
    return int(first.sum()), int(second.sum())


@CHROMIUM
@pytest.mark.parametrize("client, robots", [("ops", 2), ("dock", 1)])
def test_viewer_with_a_token_in_the_address_draws_its_robots_map(plain_server, tmp_path, client, robots):
    image = screenshot(tmp_path, f"{plain_server.url}/#token={plain_server.tokens[client]}")
    centre = image.mean(axis=2)[CENTRE]
    assert (centre > FREE_GREY).mean() > 0.05, "the map is not drawn"
    assert (centre < 70).mean() > 0.0003, "no occupied cells drawn"
    first, second = robot_pixels(image)
    assert first > 100, "robot a's trajectory is not drawn"
    assert (second > 100) if robots == 2 else (second == 0), (first, second)


@CHROMIUM
@pytest.mark.parametrize("fragment, why", [("", ""), ("#token=gmmap_wrong", "The server refused this token.")])
def test_viewer_without_a_valid_token_asks_for_one_and_shows_no_map(plain_server, tmp_path, fragment, why):
    dom = headless_chromium(tmp_path, "--dump-dom", f"{plain_server.url}/{fragment}").stdout.decode()
    assert '<form id="login" class="panel">' in dom, dom[-3000:]  # shown: no `hidden` attribute left
    assert "token holders only" in dom and f'<div id="login-why">{why}</div>' in dom
    image = screenshot(tmp_path, f"{plain_server.url}/{fragment}")
    assert np.all(image[360:540, 150:650] == 128) and robot_pixels(image) == (0, 0)  # no tile below the form
