"""`gmmap demo`: a map server and three simulated robots in the office; the viewer shows the map grow."""

from __future__ import annotations

import json
import math
import sys
import tempfile
from pathlib import Path

from gmm_core import FitConfig
from services.agent.config import AgentConfig
from services.http_client import HttpClient
from services.map_server.config import ServerConfig
from services.sim.config import SimConfig
from services.sim.fleet import SimSource, robot_name
from services.sim.processes import Processes, free_port, http_security_args
from services.sim.warmup import warm_fleet_kernels
from services.stopping import StopSignal

ROBOTS = 3
RATE = 5.0  # scans per second per robot
FOREVER_S = 3600.0  # --duration 0: the robots drive for an hour, the server runs until Ctrl-C


def stored_scans(http: HttpClient) -> int:
    try:
        return sum(r["nodes"] for r in json.loads(http.get("/v1/robots", timeout=5)))
    except OSError:
        return 0


def run_demo(server: ServerConfig, clients: SimConfig, duration: float) -> int:
    """The demo's server serves `server.http` with its TLS, tokens or --http-insecure; the progress
    bar reads it with `clients`' --http-token and --http-ca."""
    from tqdm import tqdm

    server.check_http()  # refused here, before any process starts
    http = HttpClient.for_server(server, clients.http_token, clients.http_ca)
    # Its processes run with the defaults: their kernels, compiled once here (numba caches them).
    print(
        "gmmap demo: loading numba's kernels (compiled at the first run on a machine, about a minute) ...",
        file=sys.stderr,
        flush=True,
    )
    warm_s = warm_fleet_kernels("office", FitConfig(), AgentConfig().encoding)
    print(f"gmmap demo: kernels ready in {warm_s:.1f} s", file=sys.stderr, flush=True)
    scheme = "https" if server.http_tls else "http"
    where = f"{scheme}://{server.http}/"
    print(f"gmmap demo: the viewer is at {where} ({ROBOTS} robots in the office; Ctrl-C stops)", flush=True)
    stop = StopSignal()
    names = [robot_name(i) for i in range(ROBOTS)]
    scans = math.ceil((duration or FOREVER_S) * RATE)
    with tempfile.TemporaryDirectory(prefix="gmmap-demo-") as tmp:
        procs = Processes(Path(tmp))
        try:
            zenoh_port = free_port()
            procs.server(zenoh_port, server.http, Path(tmp) / "data", "default", *http_security_args(server))
            for i, name in enumerate(names):
                procs.agent(name, str(SimSource("office", i, ROBOTS)), zenoh_port, RATE, scans)
            with tqdm(total=ROBOTS * scans, desc="scans in the map", unit="scan", file=sys.stderr) as bar:
                while not stop.wait(1.0):
                    if procs.reap("server") is not None:
                        print(f"gmmap demo: the server stopped:\n{procs.log_tail('server')}", file=sys.stderr)
                        return 1
                    bar.n = stored_scans(http)
                    bar.refresh()
                    if duration and all(procs.reap(f"agent-{n}") is not None for n in names):
                        break  # the robots have driven for --duration and everything is stored
        finally:
            for name in names:
                procs.stop(f"agent-{name}", timeout=5)
            procs.stop("server")
            procs.close()
    return 0
