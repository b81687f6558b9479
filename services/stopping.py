"""SIGTERM and SIGINT as a flag that the process's threads read (`StopSignal`).

A signal handler runs in the main thread between two bytecodes, also inside another handler. One
that takes a lock, as `threading.Event.set` does, deadlocks the process when a second signal
arrives while the first handler holds it: a map server sent SIGTERM twice (its parent's death and
a stop) never stopped. So the handler only assigns a flag, and waiting polls it.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

POLL_S = 0.1  # s between looks at the flag while waiting


class StopSignal:
    """Set by SIGTERM or SIGINT from construction on (construct it in the main thread); read like a
    threading.Event (`is_set`, `wait`)."""

    def __init__(self, signums=(signal.SIGTERM, signal.SIGINT)):
        self._requested = False
        for signum in signums:
            signal.signal(signum, self._request)

    def _request(self, *_) -> None:
        self._requested = True  # no lock, no allocation of note: safe inside a nested handler

    def is_set(self) -> bool:
        return self._requested

    def wait(self, timeout: float | None = None) -> bool:
        """Whether a stop was asked for within `timeout` s (None: until one is)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._requested:
            left = POLL_S if deadline is None else min(POLL_S, deadline - time.monotonic())
            if left <= 0:
                break
            time.sleep(left)
        return self._requested

    def exit_if_stuck(self, seconds: float, name: str) -> None:
        """From now on: once a stop is asked for, end the process `seconds` later if it is still
        running (a stop that hangs, or a signal in the middle of a slow start)."""

        def watch() -> None:
            self.wait()
            time.sleep(seconds)
            print(f"{name}: not stopped {seconds:g} s after the signal; exiting", file=sys.stderr, flush=True)
            os._exit(1)

        threading.Thread(target=watch, name="gmmap-stop-watchdog", daemon=True).start()
