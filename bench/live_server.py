"""A real `gmmap server` for the benches that fill one: started and waited for until ready, and
scan messages put to it over Zenoh until it acknowledges each (an Ack comes after the SQLite
commit: stored durably)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh

from protocol import Ack, ack_key, decode, scan_key

ROOT = Path(__file__).resolve().parents[1]
BLOCK = zenoh.CongestionControl.BLOCK  # as an agent puts: never dropped under load


def start_server(flags: Sequence[str], one_core: bool = False) -> subprocess.Popen:
    """`gmmap server` with `flags`, once it says it is ready (its configuration first, then "ready");
    pinned to core 0 with taskset where `one_core` and taskset exists. Its log is read on meanwhile,
    so a full pipe never blocks it."""
    pin = ["taskset", "-c", "0"] if one_core and shutil.which("taskset") else []
    command = [*pin, sys.executable, "-m", "services.cli", "server", *flags]
    server = subprocess.Popen(command, cwd=ROOT, stderr=subprocess.PIPE, text=True)
    for line in server.stderr:
        if "ready" in line:
            break
    else:
        raise SystemExit("the server did not start")
    threading.Thread(target=server.stderr.read, daemon=True).start()
    return server


class AckedScans:
    """Listens to the Acks of `robots` of `fleet` on `session`; ready once the server hears it."""

    def __init__(self, session: zenoh.Session, fleet: str, robots: Sequence[str]):
        self.session = session
        self.acked: set[tuple[str, int]] = set()
        self.last_ack = 0.0  # time.perf_counter() of the newest
        self._expected = None
        self._done, self._lock = threading.Event(), threading.Lock()
        self._subscribers = [session.declare_subscriber(ack_key(fleet, r), self._on_ack) for r in robots]
        probe = session.declare_publisher(scan_key(fleet, robots[0], 0))
        while not probe.matching_status.matching:
            time.sleep(0.01)
        probe.undeclare()
        time.sleep(0.2)  # the Ack subscribers reach the server

    def _on_ack(self, sample) -> None:
        ack = decode(sample.payload.to_bytes(), expect=Ack)
        with self._lock:
            self.acked.update((ack.robot, i) for i in ack.ids)
            self.last_ack = time.perf_counter()
            if len(self.acked) == self._expected:
                self._done.set()

    def put(self, messages: Sequence[tuple[str, bytes]]) -> None:
        """Put every (key, scan message bytes), each a new node."""
        with self._lock:
            self._expected = len(messages)
        for key, raw in messages:
            self.session.put(key, raw, congestion_control=BLOCK)

    def wait(self, timeout_s: float) -> bool:
        """Whether every message put was acknowledged within `timeout_s`."""
        return self._done.wait(timeout_s)

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
