"""SIGTERM to a map server under load: it stops within seconds, and what it acknowledged is stored."""

from __future__ import annotations

import signal
import threading
import time
import urllib.request

from gmm_core import fit_scan
from gmm_core.scan import FitConfig
from protocol import ScanMessage, encode, scan_key
from support.net import free_port
from support.processes import stored_nodes


def test_sigterm_under_ingest_and_tile_load_exits_within_five_seconds(procs, session_to, intel_scans, tmp_path):
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    server = procs.server("server", data, zport, hport)
    session = session_to(zport)
    payloads = []
    for scan in intel_scans[:50]:
        model = fit_scan(scan.hits, scan.no_return, FitConfig())
        payloads.append(encode(ScanMessage("default", "a", 0, scan.stamp, model, scan.pose)))
    stop = threading.Event()

    def flood() -> None:  # far more scans than the server stores in the seconds it has
        node = 0
        while not stop.is_set() and node < 200_000:
            raw = payloads[node % len(payloads)]
            message = ScanMessage("default", "a", node, 0.0, *_model_and_pose(raw))
            session.put(scan_key("default", "a", node), encode(message))
            node += 1

    def tiles() -> None:
        while not stop.is_set():
            try:
                url = f"http://127.0.0.1:{hport}/v1/occupancy?bbox=-30,-30,30,30&resolution=0.02&format=png"
                urllib.request.urlopen(url, timeout=30).read()
            except OSError:
                pass

    workers = [threading.Thread(target=flood), *(threading.Thread(target=tiles) for _ in range(4))]
    for worker in workers:
        worker.start()
    try:
        time.sleep(4)
        started = time.monotonic()
        server.send_signal(signal.SIGTERM)
        code = server.wait(30)
        took = time.monotonic() - started
    finally:
        stop.set()
        for worker in workers:
            worker.join()
    assert code == 0 and took < 5, (code, took, procs.log(server)[-2000:])
    assert stored_nodes(data, "a")  # it stored some before it stopped


_DECODED = {}


def _model_and_pose(raw: bytes):
    from protocol import decode

    if raw not in _DECODED:
        message = decode(raw, expect=ScanMessage)
        _DECODED[raw] = (message.model, message.pose)
    return _DECODED[raw]
