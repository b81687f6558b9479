"""StopSignal: SIGTERM / SIGINT as a flag (a handler that takes a lock deadlocks on a second signal),
and the watchdog that ends a process whose stop hangs. In subprocesses: handlers are the process's."""

import subprocess
import sys
import time

from support.paths import ROOT

PROGRAM = """
import os, signal, sys, time
sys.path.insert(0, {root!r})
from services.stopping import StopSignal
stop = StopSignal()
stop.exit_if_stuck(0.5, "test process")
for _ in range(50):  # signals in quick succession, handlers running inside each other's bytecodes
    os.kill(os.getpid(), signal.SIGTERM)
assert stop.wait(5) and stop.is_set()
print("stop seen", flush=True)
time.sleep(30)  # a stop that hangs: the watchdog ends the process
"""


def test_repeated_signals_set_the_flag_and_a_hanging_stop_is_ended_by_the_watchdog():
    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", PROGRAM.format(root=str(ROOT))], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 1, done.stderr
    assert done.stdout == "stop seen\n"
    assert "test process: not stopped 0.5 s after the signal; exiting" in done.stderr
    assert time.monotonic() - start < 20  # not the 30 s the program would sleep


def test_wait_returns_false_when_no_stop_comes_within_the_timeout():
    program = (
        f"import sys, time; sys.path.insert(0, {str(ROOT)!r}); from services.stopping import StopSignal; "
        "s = StopSignal(); t = time.monotonic(); r = s.wait(0.3); print(r, round(time.monotonic() - t, 1))"
    )
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=60)
    assert done.stdout.split()[0] == "False" and float(done.stdout.split()[1]) >= 0.3
