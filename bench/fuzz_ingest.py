"""Fuzz the Zenoh ingest of a real `gmmap server` process with random and mutated messages.

One Zenoh peer on 127.0.0.1 puts N messages (tests/support/fuzz.py keyed_message: seeds of every type,
mutated 9 times in 10, on the keys they name, wrong robots and nodes now and then) as fast as
the server takes them. The same validation runs here as an oracle, in the same order, to know
how many must be rejected and why. Then:

  * the server is alive and still answers (health, a map query over HTTP, a clean SIGTERM exit);
  * every message is accounted for: accepted + rejected in /metrics == N, and the rejections
    by (kind, reason) equal the oracle's;
  * nothing invalid is stored: every row of the store decodes, validates and matches its key
    columns, and PRAGMA integrity_check says ok.

Prints a report (JSON with --json) and exits 1 when a check fails. Usage:

    .venv/bin/python bench/fuzz_ingest.py [--messages 100000] [--seed 0] [--max-seconds 900] [--json]
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections import Counter
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # the repository, and tests/support

from protocol import scan_key  # noqa: E402
from services.map_server.check import check_store  # noqa: E402
from services.map_server.fleet_map import FleetMap  # noqa: E402
from services.map_server.ingest import Ingest  # noqa: E402
from services.map_server.state import ServerState  # noqa: E402
from services.sim.processes import free_port  # noqa: E402
from services.zenoh_config import zenoh_config  # noqa: E402
from support.fuzz import keyed_message, seed_messages  # noqa: E402

FLEET = "fleet-a"  # the fleet of support.fuzz's seed messages


def http(port: int, path: str) -> bytes:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=60) as reply:
        return reply.read()


def counts(metrics: str, name: str) -> Counter:
    """(kind, reason) -> value of a Prometheus counter with those labels ("" where absent)."""
    out = Counter()
    for line in metrics.splitlines():
        if line.startswith(name + "{"):
            series, value = line.rsplit(" ", 1)
            labels = dict(part.split("=", 1) for part in series[len(name) + 1 : -1].split(","))
            out[labels.get("kind", '""').strip('"'), labels.get("reason", '""').strip('"')] += float(value)
    return out


def start_server(data: Path, zport: int, hport: int, log: Path) -> subprocess.Popen:
    command = [
        sys.executable,
        "-m",
        "services.cli",
        "server",
        "--fleet",
        FLEET,
        "--zenoh-listen",
        f"tcp/127.0.0.1:{zport}",
        "--http",
        f"127.0.0.1:{hport}",
        "--data-dir",
        str(data),
    ]
    proc = subprocess.Popen(command, cwd=ROOT, stdout=log.open("wb"), stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 60
    while "gmmap server ready" not in log.read_text(errors="replace"):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f"server did not start:\n{log.read_text(errors='replace')[-3000:]}")
        time.sleep(0.05)
    return proc


def fuzz(messages: int, seed: int, max_seconds: float, work: Path) -> dict:
    zport, hport, data = free_port(), free_port(), work / "data"
    server = start_server(data, zport, hport, work / "server.log")
    session = zenoh.open(zenoh_config("peer", connect=[f"tcp/127.0.0.1:{zport}"]))
    report: dict = {"messages": messages, "seed": seed}
    try:
        probe = session.declare_publisher(scan_key(FLEET, "probe", 0))
        deadline = time.monotonic() + 10
        while not probe.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        probe.undeclare()

        rng = np.random.default_rng(seed)
        seeds = seed_messages(rng)
        oracle = ServerState(FLEET, FleetMap(FLEET))
        check = Ingest(oracle, lambda *_: None)._validate  # the server's own boundary, in the same order
        started = time.monotonic()
        sent = 0
        from tqdm import tqdm

        for _ in tqdm(range(messages), desc="fuzz ingest", unit="msg", mininterval=1, file=sys.stderr):
            if time.monotonic() - started > max_seconds:
                break
            key, payload = keyed_message(rng, seeds, FLEET)
            check(key, payload)
            session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
            sent += 1
        report["sent"] = sent
        report["put_seconds"] = round(time.monotonic() - started, 1)

        expected = counts(oracle.metrics.render().decode(), "gmmap_messages_rejected_total")
        deadline = time.monotonic() + max(60.0, sent / 500)
        while True:  # until the server has answered for every message (or the deadline)
            text = http(hport, "/metrics").decode()
            accepted = counts(text, "gmmap_messages_accepted_total")
            rejected = counts(text, "gmmap_messages_rejected_total")
            done = sum(accepted.values()) + sum(rejected.values())
            if done >= sent or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        report["ingest_seconds"] = round(time.monotonic() - started, 1)
        report["accepted"] = int(sum(accepted.values()))
        report["accepted_by_kind"] = {kind: int(v) for (kind, _), v in sorted(accepted.items())}
        report["rejected"] = int(sum(rejected.values()))
        report["rejected_by_reason"] = {f"{kind}/{reason}": int(v) for (kind, reason), v in sorted(rejected.items())}
        report["oracle_rejected"] = int(sum(expected.values()))
        report["rejections_match_oracle"] = rejected == expected

        health = json.loads(http(hport, "/healthz"))
        extent = json.loads(http(hport, "/v1/map/extent"))
        if extent is not None:  # the map the fuzzed-but-valid scans make still reconstructs
            dim = extent["dim"]
            bbox = ",".join(str(v) for v in [-40.0] * dim + [40.0] * dim)
            started_query = time.monotonic()
            npy = http(hport, f"/v1/occupancy?bbox={bbox}&resolution={0.2 if dim == 2 else 1.0}")
            report["map_query"] = {"dim": dim, "bytes": len(npy), "seconds": round(time.monotonic() - started_query, 2)}
        report["alive"] = health["status"] == "ok" and server.poll() is None
    finally:
        session.close()
        if server.poll() is None:
            server.send_signal(signal.SIGTERM)
            try:
                report["exit_code"] = server.wait(30)
            except subprocess.TimeoutExpired:
                server.kill()
                report["exit_code"] = "killed after 30 s"
        else:
            report["exit_code"] = server.returncode
    store = check_store(data)
    report["store"] = {
        "integrity": store.integrity,
        "scans": store.scans,
        "poses": store.poses,
        "bad_rows": len(store.bad),
        "first_bad": store.bad[:3],
    }
    report["log_tracebacks"] = (work / "server.log").read_text(errors="replace").count("Traceback")
    report["ok"] = bool(
        report.get("alive")
        and report["exit_code"] == 0
        and store.ok
        and report.get("rejections_match_oracle")
        and report.get("accepted", 0) + report.get("rejected", 0) == report.get("sent")
        and report["log_tracebacks"] == 0
    )
    return report


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-seconds", type=float, default=900, help="stop putting after this long")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="gmmap-fuzz-") as tmp:
        report = fuzz(args.messages, args.seed, args.max_seconds, Path(tmp))
    if args.json:
        print(json.dumps(report))
    else:
        for key, value in report.items():
            print(f"{key:>24}: {value}")
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
