"""The pool of threads that trace a fleet map's tiles: exact float64 counts of a set of posed nodes.

Not numba's threading layer: a server shares its cores with ingest, HTTP and often robots, and
numba's OpenMP threads spin at every barrier: two of them on a busy 2-core machine traced 6x
slower than one (0.5 vs 3.1-3.7 M rays/s).

Tracer threads run at TRACER_NICE (Linux sets a nice value per thread): on a saturated machine the
kernel's scheduler then gives the ingest and HTTP threads their CPU first, and the tracers the
rest, where ingest pausing them (`ingest_first`) alone left a core idle between the pauses. Nice
+10 was tried before tiles were shed: under a flood of HTTP requests they starved; +5 still gives
a tracer a third of a core beside a busy thread at 0 (docs/RELIABILITY.md).

With `server.trace_processes` (a server with a store) each tracer thread hands its parts to a
process of its own and waits (trace_workers.py), so the tracers' Python no longer takes turns with
ingest and HTTP on one interpreter lock; otherwise the threads trace themselves.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from itertools import islice
from pathlib import Path

import numpy as np

from gmm_core import Grid

from .nodes import Posed
from .samples import SampleCache
from .trace_workers import Traced, TraceWorker, WorkerGone, trace_nodes


class TracingStopped(RuntimeError):
    """A trace cut off, or refused, because its pool was closed: the server is stopping. `retry_after`:
    the seconds a client waits before it asks again (a restarted server answers once it listens)."""

    reason = "server_stopping"
    retry_after = 1

    def __init__(self):
        super().__init__("the map server is stopping")


# A trace is split into parts of at most PART_NODES nodes. A background trace runs its parts on at most
# all threads but one at a time: the graded snapshot (every change, every sample: thousands of nodes)
# otherwise held both threads of a 2-core server for seconds while the viewer's updates waited
# (docs/RELIABILITY.md, "Seventh session"). An interactive trace may run parts on every thread: alone,
# it has the pool to itself (one part at a time left a thread idle while the viewer waited for it).
PART_NODES = 256
SPLIT_MAX_CELLS = 1 << 22  # a trace on a grid this large is one part (each part holds its own counts)
# Saturated: a new trace would wait behind this many queued parts per tracer thread, or about this
# long (queued parts x the recent mean part time / threads). The count also bounds a queue whose
# parts have no measured time yet.
SATURATED_QUEUE_PER_THREAD = 8
SATURATED_WAIT_S = 1.0
PART_SECONDS_WEIGHT = 0.2  # of the latest part in the running mean of part times
# Parts of background traces (those of unbounded tile updates: a request for every change, an
# in-process caller) start only when no other part waits, or once the oldest has waited this long:
# a viewer's update does not queue behind a graded snapshot of thousands of nodes, and the snapshot
# still gets a turn every few seconds under any load.
BACKGROUND_MAX_WAIT_S = 2.0
TRACER_NICE = 5  # added to a tracer thread's nice value (CFS weight 335 against 1024 at nice 0)


def _lower_priority() -> None:
    """Raise the calling thread's nice value by TRACER_NICE (Linux: per thread; elsewhere a no-op)."""
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + TRACER_NICE)
    except (AttributeError, OSError):  # no per-thread priorities here: the tracers run at the server's
        pass


@dataclass(frozen=True)
class TracerLoad:
    """The pool at one moment: parts waiting for a thread, parts being traced, the estimated wait
    (None until a part has been timed: it was 0 then, and the queue's count alone bounds it)."""

    threads: int
    queued: int
    running: int
    wait_s: float | None

    @property
    def idle(self) -> bool:
        """No tracer has work."""
        return self.queued + self.running == 0

    @property
    def busy(self) -> bool:
        """Every tracer thread has work: a new trace would share them or wait."""
        return self.queued + self.running >= self.threads

    @property
    def saturated(self) -> bool:
        waits_long = self.wait_s is not None and self.wait_s >= SATURATED_WAIT_S
        return self.queued >= SATURATED_QUEUE_PER_THREAD * self.threads or waits_long


class TracersSaturated(RuntimeError):
    """A request refused without queueing work: the tracers' queue is over its bound.
    `retry_after` is the estimated wait in whole seconds, at least 1 (1 while it is unknown)."""

    reason = "tracers_saturated"

    def __init__(self, load: TracerLoad):
        self.load = load
        self.retry_after = max(1, math.ceil(load.wait_s or 0.0))
        work = "no part timed yet" if load.wait_s is None else f"about {load.wait_s:.1f} s of work"
        threads = f"{load.threads} tracer thread{'s' if load.threads != 1 else ''}"
        super().__init__(
            f"tracers saturated: {load.queued} traces queued for {threads} ({work}); retry after {self.retry_after} s"
        )


class TracerPool:
    """All sampling and tracing runs here: at most `threads` at once, so memory stays bounded and
    ingest and HTTP keep a share of the cores however many clients ask for tiles.

    Ingest comes first: while `ingest_first` is held, tracers wait at their next node, so the
    ingest thread has the interpreter to itself but for traces already inside a kernel (which
    run outside the GIL). Under overload the tiles slow down and go stale; the store does not."""

    def __init__(self, threads: int, samples: SampleCache, store: tuple[Path, str] | None = None):
        """store: (the store's file, the fleet) to trace in processes of their own (trace_workers.py),
        one per tracer thread, reading the nodes' models from it; None: in the threads."""
        self.threads = threads
        self.samples = samples
        self._store = store
        self._pool = ThreadPoolExecutor(threads, "gmmap-trace", initializer=_lower_priority)
        self._closed = False
        self._ingest_idle = threading.Event()
        self._ingest_idle.set()
        self._count_lock = threading.Lock()
        # Parts waiting for a thread, (queued at, grid, entries, future): interactive, background.
        self._parts: tuple[deque, deque] = (deque(), deque())
        self._running = 0
        self._part_seconds: float | None = None  # running mean, from the first part that finished
        self._local = threading.local()  # a tracer thread's TraceWorker
        self._workers: list[TraceWorker] = []

    @property
    def worker_pids(self) -> list[int]:
        """Process ids of the tracer processes started so far (none when tracing in threads)."""
        with self._count_lock:
            return [worker.pid for worker in self._workers]

    @contextmanager
    def ingest_first(self):
        """Hold the tracers at their next node while the block runs (one ingest batch)."""
        self._ingest_idle.clear()
        try:
            yield
        finally:
            self._ingest_idle.set()

    @property
    def _queued(self) -> int:
        return len(self._parts[0]) + len(self._parts[1])

    def load(self) -> TracerLoad:
        with self._count_lock:
            queued, running, part_s = self._queued, self._running, self._part_seconds
        return TracerLoad(self.threads, queued, running, None if part_s is None else queued * part_s / self.threads)

    def close(self) -> None:
        """Stop tracing: queued traces are cancelled, running ones end at their next node, so a
        server stops in moments however large the tiles it was asked for (their requests fail)."""
        with self._count_lock:  # as `_submit` checks it: no part is queued after this
            self._closed = True
            self._pool.shutdown(wait=False, cancel_futures=True)
            workers, self._workers = self._workers, []
            waiting = [part for parts in self._parts for part in parts]
            for parts in self._parts:
                parts.clear()
        self._ingest_idle.set()  # a tracer held for ingest sees `_closed` at once
        for _, _, _, future in waiting:  # their traces fail as the running ones do
            future.set_exception(TracingStopped())
        for worker in workers:  # a thread waiting on one gets WorkerGone, raised as TracingStopped
            worker.close()

    def trace(
        self, grid: Grid, plus: list[Posed], minus: list[Posed], background: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Exact float64 hit and miss counts on `grid` of the nodes in `plus` less those in `minus`.

        Traced in parts of at most PART_NODES nodes, each by the one-thread kernel, as many at a time
        as there are threads (a `background` trace: all but one), the next queued as one finishes,
        so other traces' parts run between them (counts are sums of quantised weights, exact in any
        order, so the split changes no bit). A background trace's parts give way to the others'
        (BACKGROUND_MAX_WAIT_S).
        """
        entries = [(1.0, posed) for posed in plus] + [(-1.0, posed) for posed in minus]
        parts = 1 if grid.n_cells > SPLIT_MAX_CELLS else max(1, -(-len(entries) // PART_NODES))
        shares = iter([entries[i::parts] for i in range(parts)])
        in_flight = max(1, self.threads - 1) if background else self.threads
        running = deque(self._submit(grid, share, background) for share in islice(shares, in_flight))
        hits, misses = running.popleft().result()
        while True:
            share = next(shares, None)
            if share is not None:  # the next part is queued only once one has finished
                running.append(self._submit(grid, share, background))
            if not running:
                return hits, misses
            h, m = running.popleft().result()
            hits += h
            misses += m

    def _submit(self, grid: Grid, entries: list[tuple[float, Posed]], background: bool) -> Future:
        """Queue a part; a pool thread takes the next part due when it is free (`_next_part`).
        TracingStopped once the pool is closed."""
        future: Future = Future()
        with self._count_lock:
            if self._closed:
                raise TracingStopped()
            self._parts[1 if background else 0].append((time.monotonic(), grid, entries, future))
            self._pool.submit(self._next_part)
        return future

    def _next_part(self) -> None:
        """Trace the part due (an interactive one, unless a background one waited BACKGROUND_MAX_WAIT_S),
        counted in the pool's load (queued until it starts, then running)."""
        with self._count_lock:
            interactive, background = self._parts
            overdue = background and time.monotonic() - background[0][0] > BACKGROUND_MAX_WAIT_S
            parts = background if overdue or not interactive else interactive
            if not parts:  # the pool was closed: its parts were failed
                return
            _, grid, entries, future = parts.popleft()
            self._running += 1
        start = time.perf_counter()
        try:
            future.set_result(self._trace_part(grid, entries))
        except BaseException as error:  # the trace's caller raises it
            future.set_exception(error)
        finally:
            seconds = time.perf_counter() - start
            with self._count_lock:
                self._running -= 1
                mean = self._part_seconds
                self._part_seconds = seconds if mean is None else mean + PART_SECONDS_WEIGHT * (seconds - mean)

    def _trace_part(self, grid: Grid, entries: list[tuple[float, Posed]]) -> tuple[np.ndarray, np.ndarray]:
        if self._store is None:
            nodes = [(sign, posed.node, posed.pose, posed.samples_per_cell) for sign, posed in entries]
            return trace_nodes(grid, nodes, self.samples, self._wait_for_ingest)
        self._wait_for_ingest()
        nodes = [Traced(sign, p.key, p.node.seed, p.pose, p.samples_per_cell) for sign, p in entries]
        worker = self._worker()
        try:
            return worker.trace(grid, nodes)
        except WorkerGone:
            if self._closed:
                raise TracingStopped() from None
            self._forget(worker)  # it died: this thread starts another for its next part
            raise

    def _wait_for_ingest(self) -> None:
        """Wait while ingest runs a batch; TracingStopped once the pool is closed."""
        self._ingest_idle.wait()
        if self._closed:
            raise TracingStopped()

    def _forget(self, worker: TraceWorker) -> None:
        self._local.worker = None
        with self._count_lock:
            if worker in self._workers:
                self._workers.remove(worker)
        worker.close()  # reaped

    def _worker(self) -> TraceWorker:
        """This tracer thread's process, started at its first part (a server that is never asked for
        a tile starts none). It dies with the thread, which lives as long as the pool."""
        worker = getattr(self._local, "worker", None)
        if worker is None:
            worker = self._local.worker = TraceWorker(*self._store, self.samples.samples_per_cell, TRACER_NICE)
            with self._count_lock:
                self._workers.append(worker)
            if self._closed:  # closed while it started: close() may have missed it
                worker.close()
                raise TracingStopped()
        return worker
