"""Ingest throughput of a real `gmmap server` process: scan messages stored and acknowledged per second.

The Intel log is fitted once; its 910 encoded scans are then published as --robots robots (so
every message is new to the server) from one Zenoh peer as fast as the link takes them. The
clock runs from the first put to the last Ack; every Ack comes after the SQLite commit, so
this is the end-to-end rate of durable ingest. With --http-clients N, N clients fetch the
viewer's tiles of the log's map over HTTP meanwhile (as `gmmap sim --http-clients` does): the
server's capacity under tile load, which issue 16 wants at least twice the 200 scans/s of its
20-robot run. Usage:

    .venv/bin/python bench/ingest.py [--robots 6] [--synchronous normal|full] [--http-clients 32] [--trace-processes]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from live_server import AckedScans, start_server  # noqa: E402

from gmm_core import Grid, Pose, fit_scan  # noqa: E402
from protocol import Ack, PoseGraphUpdate, ScanMessage, ack_key, decode, encode, poses_key, scan_key  # noqa: E402
from services.datasets import read_scans  # noqa: E402
from services.http_client import HttpClient  # noqa: E402
from services.sim.processes import free_port  # noqa: E402
from services.sim.run import TileClients, tile_urls  # noqa: E402
from services.zenoh_config import zenoh_config  # noqa: E402

LOG = ROOT.parent / "shared" / "data" / "carmen" / "intel-corrected.log.gz"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=6)
    parser.add_argument("--synchronous", choices=["normal", "full"], default="normal")
    parser.add_argument("--http-clients", type=int, default=0, help="clients fetching tiles meanwhile")
    parser.add_argument("--trace-processes", action="store_true", help="the server traces in tracer processes")
    args = parser.parse_args()

    scans = list(read_scans(LOG))
    models = [fit_scan(s.hits, s.no_return) for s in scans]
    robots = [f"r{i}" for i in range(args.robots)]
    messages = [
        (scan_key("default", r, s.index), encode(ScanMessage("default", r, s.index, s.stamp, m, s.pose)))
        for r in robots
        for s, m in zip(scans, models)
    ]
    total_bytes = sum(len(raw) for _, raw in messages)

    port, http_port = free_port(), free_port()
    lo = np.min([s.pose.t for s in scans], axis=0) - 10.0
    hi = np.max([s.pose.t for s in scans], axis=0) + 10.0
    urls = tile_urls(Grid.from_bbox(lo, hi, 0.1))
    clients = None
    with tempfile.TemporaryDirectory() as data:
        server = start_server(
            [
                "--zenoh-listen",
                f"tcp/127.0.0.1:{port}",
                "--http",
                f"127.0.0.1:{http_port}" if args.http_clients else "",
                "--data-dir",
                data,
                "--synchronous",
                args.synchronous,
                *(["--trace-processes"] if args.trace_processes else []),
            ]
        )
        session = None
        try:
            session = zenoh.open(zenoh_config("peer", connect=[f"tcp/127.0.0.1:{port}"]))
            acks = AckedScans(session, "default", robots)
            if args.http_clients:
                clients = TileClients(HttpClient(f"http://127.0.0.1:{http_port}"), urls, args.http_clients)
                time.sleep(2.0)  # every client has a request in flight
            start = time.perf_counter()
            acks.put(messages)
            published = time.perf_counter()
            if not acks.wait(120):
                raise SystemExit(f"only {len(acks.acked)} of {len(messages)} acknowledged")
            seconds = acks.last_ack - start
            if clients is not None:
                tiles, errors = clients.stop()
                clients = None

            # A correction of every node of one robot: put -> stored, applied and acknowledged.
            latencies = []
            for revision in range(1, 6):
                acked_rev = threading.Event()

                def got(sample, r=revision, acked=acked_rev):
                    return decode(sample.payload.to_bytes(), expect=Ack).ids == (r,) and acked.set()

                sub = session.declare_subscriber(ack_key("default", robots[0]), got)
                update = PoseGraphUpdate(
                    "default",
                    robots[0],
                    revision,
                    tuple((s.index, s.pose.compose(Pose.from_xytheta(0.01 * revision, 0, 0))) for s in scans),
                )
                raw = encode(update)
                t = time.perf_counter()
                session.put(poses_key("default", robots[0]), raw, congestion_control=zenoh.CongestionControl.BLOCK)
                if not acked_rev.wait(10):
                    raise SystemExit("pose update not acknowledged")
                latencies.append(time.perf_counter() - t)
                sub.undeclare()
            acks.close()
        finally:
            if clients is not None:
                clients.stop()
            if session is not None:
                session.close()
            server.terminate()
            server.wait(15)
    n = len(messages)
    print(
        f"{n} scan messages ({total_bytes / n:.0f} B each, {args.robots} robots), synchronous={args.synchronous}: "
        f"published in {published - start:.2f} s, all stored and acknowledged in {seconds:.2f} s "
        f"-> {n / seconds:.0f} messages/s, {total_bytes / seconds / 1e6:.1f} MB/s"
    )
    if args.http_clients:
        latencies_s = sorted(latency for _, latency, _ in tiles)
        p99 = latencies_s[int(0.99 * (len(latencies_s) - 1))] if latencies_s else float("nan")
        print(
            f"meanwhile {args.http_clients} HTTP clients got {len(tiles)} tiles (p99 {p99:.2f} s), "
            f"failures by kind: {errors or 'none'}"
        )
    print(
        f"pose-graph update of all {len(scans)} nodes of one robot ({len(raw)} B), put -> stored, applied, "
        f"acknowledged: median {sorted(latencies)[2] * 1e3:.1f} ms, max {max(latencies) * 1e3:.1f} ms"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
