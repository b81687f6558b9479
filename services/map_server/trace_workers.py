"""Tracer processes: a server's tiles sampled and traced by interpreters of their own.

A map server under load is bound by its interpreter lock, not by its cores: ingest, the HTTP
handlers and the tracer threads' Python (each node's sampling plan, the kernel's batches) take
turns on one lock while part of the machine idles (docs/RELIABILITY.md, "Fourth session of
2026-12-02"). With `server.trace_processes`, a tracer thread of a server with a store hands each
part it traces to a process of its own (`TraceWorker`), started at the thread's first part: the
thread only waits on a pipe, and the process samples the nodes and runs the kernel with its own
interpreter.

A process needs no node's model from the server: it reads the node's message from the store's
file (read-only, WAL: never waiting for ingest's commits) and keeps the node ready to sample in a
SampleCache of its own. A part goes out as the grid and, per node, its sign, key, seed, world pose
and samples per cell; it comes back as float64 hit and miss counts, the same bits as tracing the
part in the server (tests/unit/services/map_server/test_trace_workers.py).

    python -m services.map_server.trace_workers FD STORE FLEET SAMPLES_PER_CELL PRIORITY PARENT

is how a worker is started (by `TraceWorker`, never by hand).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import NamedTuple

import numpy as np

from gmm_core import Grid, Pose, ScanModel
from gmm_core.scan_trace import GridCounts
from services.host import die_with_parent

from .nodes import NodeKey
from .samples import SampleCache
from .store import scan_reader

# Nodes traced in one call of the kernel: a thread looks for ingest and for a stop between batches.
BATCH_NODES = 32


class Traced(NamedTuple):
    """One node of a part: what a tracer process needs to trace it (the model comes from the store)."""

    sign: float  # +1 counted in, -1 taken out
    key: NodeKey
    seed: int
    pose: Pose  # node frame -> world
    samples_per_cell: float | None  # None: the map's


class _Stored(NamedTuple):
    """A node as SampleCache.model reads it in a tracer process: from the store only."""

    key: NodeKey
    seed: int
    raw: bytes | None = None
    held_model: ScanModel | None = None


def trace_nodes(grid: Grid, nodes: Sequence[tuple], samples: SampleCache, between: Callable[[], None] = lambda: None):
    """(hits, misses) on `grid` of `nodes`, each (sign, node, pose, samples per cell), BATCH_NODES
    per kernel call; `between` runs before each batch (a thread waits there for ingest, or stops)."""
    counts = GridCounts(grid)
    for first in range(0, len(nodes), BATCH_NODES):
        between()
        # Eq. 2: the node-frame samples moved by the node's world pose as they are traced.
        batch = nodes[first : first + BATCH_NODES]
        counts.add_many([(samples.samples(node, grid.resolution, spc), pose, sign) for sign, node, pose, spc in batch])
    return counts.arrays()


class WorkerGone(RuntimeError):
    """A tracer process ended (stopped, or died) before it answered."""


class TraceWorker:
    """One tracer process and the pipe to it; used by one thread at a time."""

    def __init__(self, store: Path, fleet: str, samples_per_cell: float, nice: int):
        """nice: added to the server's nice value (its main thread's) for the process."""
        priority = os.getpriority(os.PRIO_PROCESS, os.getpid()) + nice
        ours, theirs = socket.socketpair()
        command = [sys.executable, "-m", __name__, str(theirs.fileno()), str(store), fleet, repr(samples_per_cell)]
        self._process = subprocess.Popen(
            [*command, str(priority), str(os.getpid())], pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL
        )
        theirs.close()
        self._conn = Connection(ours.detach())

    @property
    def pid(self) -> int:
        return self._process.pid

    def trace(self, grid: Grid, nodes: Sequence[Traced]) -> tuple[np.ndarray, np.ndarray]:
        """(hits, misses) of `nodes` on `grid`, traced by the process."""
        try:
            self._conn.send((grid, list(nodes)))
            reply = self._conn.recv()
        except (EOFError, OSError) as error:
            raise WorkerGone(f"tracer process {self.pid} ended: {error or 'its pipe closed'}") from None
        if reply[0] == "error":
            raise RuntimeError(f"tracer process {self.pid}: {reply[1]}")
        return reply[1], reply[2]

    def close(self) -> None:
        """End the process now: a part it traces is dropped, and its waiting thread gets WorkerGone."""
        self._process.terminate()
        try:
            self._process.wait(1.0)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        self._conn.close()


def serve(conn: Connection, store: Path, fleet: str, samples_per_cell: float) -> None:
    """Answer parts on `conn` until it closes: ("counts", hits, misses) or ("error", message)."""
    samples = SampleCache(samples_per_cell, scan_reader(store, fleet))
    while True:
        try:
            grid, nodes = conn.recv()
        except EOFError:
            return
        try:
            hits, misses = trace_nodes(
                grid, [(n.sign, _Stored(n.key, n.seed), n.pose, n.samples_per_cell) for n in nodes], samples
            )
            reply = ("counts", hits, misses)
        except Exception as error:  # the part fails in the server, with the reason; the process serves on
            reply = ("error", f"{type(error).__name__}: {error}")
        conn.send(reply)


def main(argv: Sequence[str]) -> None:
    fd, store, fleet, samples_per_cell, priority, parent = argv
    die_with_parent(int(parent))  # a killed server leaves no tracer behind
    # Absolute: a child of a tracer thread already has that thread's nice value (tracers.TRACER_NICE).
    os.setpriority(os.PRIO_PROCESS, 0, min(19, int(priority)))
    serve(Connection(int(fd)), Path(store), fleet, float(samples_per_cell))


if __name__ == "__main__":
    main(sys.argv[1:])
