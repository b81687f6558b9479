"""The tracer pool's threads yield the cores to ingest and HTTP (tracers.TRACER_NICE), and its
background traces to the others (tracers.BACKGROUND_MAX_WAIT_S); an interactive trace alone runs on
every thread; a load is saturated, and a shed request told when to ask again, by the queue and its
estimated wait."""

import os
import sys
import threading
import time

import numpy as np
import pytest

from gmm_core import Grid
from services.map_server import tracers
from services.map_server.tracers import TRACER_NICE, TracerLoad, TracerPool, TracersSaturated


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


def _order_of_parts(monkeypatch, max_wait_s: float) -> list[str]:
    """The order in which a one-thread pool traces: a blocking part, then a background and an
    interactive trace queued behind it in that order."""
    monkeypatch.setattr(tracers, "BACKGROUND_MAX_WAIT_S", max_wait_s)
    pool = TracerPool(1, samples=None)
    order, running, release = [], threading.Event(), threading.Event()

    def part(grid, entries):  # stands in for the kernel: the entries are tags
        tag = entries[0][1]
        if tag == "first":
            running.set()
            release.wait(10)
        order.append(tag)
        return np.zeros(1), np.zeros(1)

    monkeypatch.setattr(pool, "_trace_part", part)
    grid = Grid(np.zeros(2), 1.0, (1, 1))
    calls = []
    try:
        for tag, background, queued in (("first", True, 0), ("snapshot", True, 1), ("viewer", False, 2)):
            calls.append(threading.Thread(target=pool.trace, args=(grid, [tag], [], background)))
            calls[-1].start()
            if tag == "first":  # the thread traces it: the next two wait in the queue, not beside it
                assert running.wait(10)
            deadline = time.monotonic() + 10
            while pool.load().queued < queued and time.monotonic() < deadline:  # in this order
                time.sleep(0.001)
        time.sleep(0.01)
        release.set()
        for call in calls:
            call.join(10)
    finally:
        pool.close()
    return order


def test_background_parts_give_way_to_waiting_interactive_ones(monkeypatch):
    """A viewer's update queued after a graded snapshot's part is traced first; a background part
    that waited BACKGROUND_MAX_WAIT_S goes first all the same (it is not starved)."""
    assert _order_of_parts(monkeypatch, 60.0) == ["first", "viewer", "snapshot"]
    assert _order_of_parts(monkeypatch, 0.0) == ["first", "snapshot", "viewer"]


@pytest.mark.parametrize("background, most", [(False, 2), (True, 1)])
def test_a_trace_runs_parts_on_every_thread_a_background_one_on_all_but_one(monkeypatch, background, most):
    pool = TracerPool(2, samples=None)
    lock, running, seen = threading.Lock(), [0], []

    def part(grid, entries):  # stands in for the kernel, long enough for the parts to overlap
        with lock:
            running[0] += 1
            seen.append(running[0])
        # Until two parts met (or 0.5 s passed): a niced tracer thread on a busy machine may take a
        # while to start its part, and the test is of what the pool allows, not of the scheduler.
        deadline = time.monotonic() + 0.5
        while max(seen) < 2 and time.monotonic() < deadline:
            time.sleep(0.005)
        with lock:
            running[0] -= 1
        return np.full(1, float(len(entries))), np.zeros(1)

    monkeypatch.setattr(pool, "_trace_part", part)
    try:
        hits, _ = pool.trace(Grid(np.zeros(2), 1.0, (1, 1)), list(range(4 * tracers.PART_NODES)), [], background)
    finally:
        pool.close()
    assert hits[0] == 4 * tracers.PART_NODES  # every part summed
    assert max(seen) == most


def test_the_wait_of_a_queue_is_unknown_until_a_part_was_timed_then_estimated_from_the_parts_times(monkeypatch):
    """A saturated fresh pool said "about 0.0 s of work": no part had finished, so none was timed."""
    pool = TracerPool(1, samples=None)
    gate = threading.Event()

    def part(grid, entries):  # stands in for the kernel: waits at the gate
        gate.wait(10)
        return np.zeros(1), np.zeros(1)

    def queue_three() -> list[threading.Thread]:
        """One part traced and two queued behind it, each a trace of its own."""
        calls = [threading.Thread(target=pool.trace, args=(grid, [n], [])) for n in range(3)]
        for call in calls:
            call.start()
        deadline = time.monotonic() + 10
        while pool.load().queued < 2 and time.monotonic() < deadline:
            time.sleep(0.001)
        return calls

    monkeypatch.setattr(pool, "_trace_part", part)
    grid = Grid(np.zeros(2), 1.0, (1, 1))
    try:
        for timed in (False, True):
            gate.clear()
            calls = queue_three()
            time.sleep(0.05)  # the traced part takes at least this
            load = pool.load()
            gate.set()
            for call in calls:
                call.join(10)
            refusal = str(TracersSaturated(load))
            assert (load.queued, load.running) == (2, 1)
            if timed:  # queued parts x the running mean of part times (0.05 s and more, 0 s, 0 s) / threads
                assert load.wait_s > 0.05 and f"about {load.wait_s:.1f} s of work" in refusal, refusal
            else:
                assert load.wait_s is None and "no part timed yet" in refusal, refusal
            assert refusal.startswith("tracers saturated: 2 traces queued for 1 tracer thread (")
    finally:
        pool.close()


@pytest.mark.parametrize(
    "load, saturated, retry_after",
    [
        (TracerLoad(2, 15, 2, 0.9), False, 1),
        (TracerLoad(2, 16, 2, 0.0), True, 1),  # the queue bound, its parts timed at no wait
        (TracerLoad(2, 16, 2, None), True, 1),  # the queue bound, with no part timed yet (wait unknown)
        (TracerLoad(2, 3, 2, 1.0), True, 1),  # the wait bound
        (TracerLoad(2, 3, 2, 2.3), True, 3),
    ],
)
def test_saturation_and_retry_after_follow_the_queue_and_its_estimated_wait(load, saturated, retry_after):
    assert load.saturated is saturated and load.busy
    assert TracersSaturated(load).retry_after == retry_after
    assert not TracerLoad(2, 0, 1, 0.0).busy
