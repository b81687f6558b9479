"""Tile latency of a real `gmmap server` under 32 concurrent HTTP clients (issue 5).

A server process is filled by a real agent replaying the Intel log (910 scans), then N client
threads in this process (services.sim.run.TileClients) fetch 256 x 256 PNG tiles of the viewer's
tiling (0.05, 0.1 and 0.2 m) at random for a fixed time. Phase "cold" starts with an empty tile
cache; phase "warm" repeats.

    .venv/bin/python bench/http_load.py [--clients 32] [--seconds 15]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

from gmm_core import Grid
from services.http_client import HttpClient
from services.sim.processes import free_port
from services.sim.run import TileClients, tile_urls

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT.parent / "shared" / "data" / "carmen" / "intel-corrected.log.gz"
GMMAP = [sys.executable, "-m", "services.cli"]


def wait_http(url: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            urllib.request.urlopen(url, timeout=1).read()
            return
        except OSError:
            time.sleep(0.2)
    raise RuntimeError(f"{url} did not answer")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--clients", type=int, default=32)
    parser.add_argument("--seconds", type=float, default=15.0)
    args = parser.parse_args()
    zport, hport = free_port(), free_port()
    base = f"http://127.0.0.1:{hport}"
    with tempfile.TemporaryDirectory() as data:
        server = subprocess.Popen(
            GMMAP
            + [
                "server",
                "--zenoh-listen",
                f"tcp/127.0.0.1:{zport}",
                "--http",
                f"127.0.0.1:{hport}",
                "--data-dir",
                data,
            ],
            cwd=ROOT,
        )
        try:
            wait_http(base + "/healthz")
            subprocess.run(
                GMMAP
                + [
                    "agent",
                    "--robot",
                    "intel",
                    "--zenoh-connect",
                    f"tcp/127.0.0.1:{zport}",
                    "--source",
                    f"carmen:{LOG}",
                    "--outbox",
                    f"{data}/outbox.db",
                ],
                cwd=ROOT,
                check=True,
                stderr=subprocess.DEVNULL,
            )
            # The viewer's tiling over the Intel map (0.05, 0.1 and 0.2 m), as `gmmap sim` fetches it.
            urls = tile_urls(Grid.from_bbox([-21.0, -31.0], [26.0, 14.0], 0.05))
            print(f"{len(urls)} distinct tiles, {args.clients} clients, {args.seconds:.0f} s per phase")
            print("| phase | requests | errors | req/s | p50 ms | p90 ms | p99 ms |\n|---|---|---|---|---|---|---|")
            for phase in ("cold", "warm"):
                clients = TileClients(HttpClient(base), urls, args.clients)
                time.sleep(args.seconds)
                lat, errors = clients.stop()
                ms = 1000 * np.percentile(lat, [50, 90, 99])
                print(
                    f"| {phase} | {len(lat)} | {sum(errors.values())} | {len(lat) / args.seconds:.0f} | "
                    f"{ms[0]:.1f} | {ms[1]:.1f} | {ms[2]:.1f} |"
                )
        finally:
            server.terminate()
            server.wait(10)


if __name__ == "__main__":
    main()
