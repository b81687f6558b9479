"""SIGTERM to a map server under load: it stops within seconds, and what it acknowledged is stored;
SIGKILL: no tracer process outlives it."""

from __future__ import annotations

import os
import signal
import threading
import time
import urllib.request

import pytest

from gmm_core import fit_scan
from gmm_core.scan import FitConfig
from protocol import ScanMessage, encode, scan_key
from services.host import child_pids
from support.net import free_port, wait_for
from support.processes import stored_nodes


@pytest.mark.parametrize(
    ("tracing", "signum"),
    [((), signal.SIGTERM), (("--trace-processes",), signal.SIGTERM), (("--trace-processes",), signal.SIGKILL)],
    ids=["threads-SIGTERM", "processes-SIGTERM", "processes-SIGKILL"],
)
def test_a_signal_under_ingest_and_tile_load_ends_the_server_within_five_seconds(
    procs, session_to, intel_scans, tmp_path, tracing, signum
):
    """SIGTERM: a clean exit in under 5 s with what was acknowledged stored; SIGKILL: its tracer
    processes (--trace-processes) end with it."""
    if not sys_is_linux():
        pytest.skip("/proc and PR_SET_PDEATHSIG are Linux's")
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    server = procs.server("server", data, zport, hport, extra=tracing)
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
        if tracing:  # a tracer thread starts its process at its first part, which may wait behind ingest
            wait_for(lambda: child_pids(server.pid), 60, "a tracer process")
        tracers = child_pids(server.pid)
        started = time.monotonic()
        server.send_signal(signum)
        code = server.wait(30)
        took = time.monotonic() - started
        gone = wait_gone(tracers, 5.0)
    finally:
        stop.set()
        for worker in workers:
            worker.join()
    assert bool(tracers) == bool(tracing), tracers  # a process per tracer thread that traced
    assert gone, f"tracer processes {tracers} outlived the server"
    if signum == signal.SIGTERM:
        assert code == 0 and took < 5, (code, took, procs.log(server)[-2000:])
        assert stored_nodes(data, "a")  # it stored some before it stopped


def test_a_signal_during_the_kernel_warm_up_ends_the_server_within_five_seconds(procs, tmp_path):
    """On an empty numba cache the start's warm-up compiles for about a minute (a fresh install):
    a stop meanwhile ends the server at once, with nothing opened, not after the compiler."""
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    server = procs.start(
        "server",
        *(
            "server",
            "--zenoh-listen",
            f"tcp/127.0.0.1:{zport}",
            "--http",
            f"127.0.0.1:{hport}",
            "--data-dir",
            str(data),
        ),
        env={"NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")},  # empty: every kernel compiles
    )
    procs.wait_ready("server", "gmmap server config")  # printed just before the warm-up
    time.sleep(1.0)  # compiling by now
    started = time.monotonic()
    server.send_signal(signal.SIGTERM)
    code = server.wait(30)
    took = time.monotonic() - started
    log = procs.log(server)
    assert code == 0 and took < 5, (code, took, log[-2000:])
    assert "stopped while loading its kernels" in log and not data.exists(), log[-2000:]


def sys_is_linux() -> bool:
    return os.uname().sysname == "Linux"


def wait_gone(pids: list[int], timeout: float) -> bool:
    """Whether every process of `pids` ended (or became a zombie: killed, not yet reaped) in `timeout` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all(_ended(pid) for pid in pids):
            return True
        time.sleep(0.05)
    return False


def _ended(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] in "ZX"
    except OSError:
        return True


_DECODED = {}


def _model_and_pose(raw: bytes):
    from protocol import decode

    if raw not in _DECODED:
        message = decode(raw, expect=ScanMessage)
        _DECODED[raw] = (message.model, message.pose)
    return _DECODED[raw]
