"""The tracer pool's threads yield the cores to ingest and HTTP (tracers.TRACER_NICE)."""

import os
import sys
import threading

import pytest

from services.map_server.tracers import TRACER_NICE, TracerPool


@pytest.mark.skipif(sys.platform != "linux", reason="per-thread nice values are Linux's")
def test_tracer_threads_run_at_a_lower_priority_than_the_server():
    pool = TracerPool(2, samples=None)
    try:
        tracer = pool._pool.submit(lambda: os.getpriority(os.PRIO_PROCESS, threading.get_native_id())).result()
    finally:
        pool.close()
    caller = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    assert tracer == min(19, caller + TRACER_NICE)
    assert caller == os.getpriority(os.PRIO_PROCESS, 0)  # the rest of the process keeps its priority
