"""Fuzz the HTTP API of a real `gmmap server` with schemathesis, from the server's own OpenAPI.

A server on 127.0.0.1 gets a small map (the first --scans scans of the corrected Intel log,
published by a `gmmap agent`), then `schemathesis run /openapi.json` runs every phase (examples,
coverage, fuzzing, stateful) with every check except positive_data_acceptance: the API rightly
refuses schema-valid requests that break rules OpenAPI cannot state (lo < hi, the cell and point
limits, a 3D box on a 2D map). Afterwards the server must still be up with no traceback in its
log, and exit 0 on SIGTERM; then the time to refuse oversized requests is measured (median and
maximum of 20 each). Exit status: schemathesis's, or 1 when the server did not hold.

    .venv/bin/python bench/http_fuzz.py [--max-examples 1000] [--seed 0] [--scans 100]
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.sim.processes import free_port  # noqa: E402

LOG = ROOT.parent / "shared" / "data" / "carmen" / "intel-corrected.log.gz"
SCHEMATHESIS = Path(sys.executable).with_name("schemathesis")


def cli(work: Path, name: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", *args],
        cwd=work,
        stdout=(work / f"{name}.log").open("wb"),
        stderr=subprocess.STDOUT,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
    )


OVERSIZED = {  # what a careless or hostile client may ask; each must be refused before any work
    "GET 1.6e17 cells": "/v1/occupancy?bbox=-1e6,-1e6,1e6,1e6&resolution=0.005",
    "GET 2^64 cells (int64 wraps)": "/v1/occupancy?bbox=0,0,429496729.6,429496729.6&resolution=0.1",
    "GET 1e300 m box": "/v1/occupancy?bbox=-1e300,-1e300,1e300,1e300&resolution=0.005",
    "GET 20,001 points": "/v1/occupancy/points?resolution=0.1&xy=" + ",".join(["1"] * 40_002),
    "POST declaring a 2 MB body": None,  # refused on its headers, before the body is read
}
POST_HEAD = (
    b"POST /v1/occupancy/points HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
    b"Content-Length: 2000000\r\n\r\n"
)


def post_head(port: int) -> int:
    """Status of a POST that declares 2 MB and sends none of it (so no unread data makes a reset)."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        s.sendall(POST_HEAD)
        return int(s.recv(65536).split(b" ", 2)[1])


def refusal_times(port: int) -> dict[str, str]:
    """name -> 'status, median / max ms' over 20 requests."""
    out = {}
    for name, path in OVERSIZED.items():
        times, statuses = [], set()
        for _ in range(20):
            started = time.perf_counter()
            if path is None:
                statuses.add(post_head(port))
            else:
                try:
                    urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=30)
                    statuses.add(200)
                except urllib.error.HTTPError as error:
                    statuses.add(error.code)
            times.append((time.perf_counter() - started) * 1000)
        times.sort()
        out[name] = f"{'/'.join(map(str, sorted(statuses)))}, {times[10]:.1f} / {times[-1]:.1f} ms"
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-examples", type=int, default=1000, help="per operation and phase")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scans", type=int, default=100)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="gmmap-http-fuzz-") as tmp:
        work = Path(tmp)
        zport, hport = free_port(), free_port()
        server = cli(
            work,
            "server",
            "server",
            "--zenoh-listen",
            f"tcp/127.0.0.1:{zport}",
            "--http",
            f"127.0.0.1:{hport}",
            "--data-dir",
            str(work / "data"),
        )
        try:
            agent = cli(
                work,
                "agent",
                "agent",
                "--robot",
                "r1",
                "--zenoh-connect",
                f"tcp/127.0.0.1:{zport}",
                "--source",
                f"carmen:{LOG}",
                "--scans",
                f"0:{args.scans}",
                "--outbox",
                str(work / "outbox.db"),
            )
            if agent.wait(300) != 0:
                print((work / "agent.log").read_text(errors="replace")[-2000:], file=sys.stderr)
                return 1
            command = [
                str(SCHEMATHESIS),
                "run",
                f"http://127.0.0.1:{hport}/openapi.json",
                "--checks",
                "all",
                "--exclude-checks",
                "positive_data_acceptance",
                "--max-examples",
                str(args.max_examples),
                "--seed",
                str(args.seed),
                "--request-timeout",
                "30",
                "--workers",
                "1",
                "--no-color",
            ]
            print("$ " + " ".join(command[1:]), flush=True)
            started = time.perf_counter()
            run = subprocess.run(command, cwd=work, capture_output=True, text=True)
            elapsed = time.perf_counter() - started
            print(run.stdout[-8000:])
            cases = re.search(r"(\d+) generated, (.*)", run.stdout)
            with urllib.request.urlopen(f"http://127.0.0.1:{hport}/healthz", timeout=10) as reply:
                healthy = reply.status == 200
            refusals = refusal_times(hport)
        finally:
            server.send_signal(signal.SIGTERM)
            code = server.wait(30)
        tracebacks = (work / "server.log").read_text(errors="replace").count("Traceback")
    print(
        f"schemathesis exit {run.returncode} after {elapsed:.0f} s; test cases: "
        f"{cases.group(0) if cases else '?'}; server healthy after: {healthy}, exit code {code}, "
        f"tracebacks in its log: {tracebacks}"
    )
    for name, result in refusals.items():
        print(f"  refused {name:<30} {result}")
    return run.returncode or int(not healthy or code != 0 or tracebacks > 0)


if __name__ == "__main__":
    sys.exit(main())
