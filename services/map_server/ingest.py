"""From wire bytes to the store and the map: validate, commit, then acknowledge.

Zenoh callbacks only enqueue (key, bytes); one worker thread drains the queue in batches, so
a batch of scans is one SQLite transaction and one Ack per robot (group commit: thousands of
messages per second even with synchronous=FULL). The order per batch is: validate every
message, commit the scans, put them in the FleetMap, publish the scan Acks; then pose
updates one by one (commit, apply, Ack). Nothing is acknowledged before its commit.
"""
from __future__ import annotations

import logging
import queue
import threading
from collections import defaultdict
from collections.abc import Callable

from protocol import Ack, PoseGraphUpdate, ProtocolError, ScanMessage, ack_key, decode, encode, parse_key

from .state import ServerState

log = logging.getLogger("gmmap.server")

MAX_BATCH = 512
QUEUE_LIMIT = 20_000  # a full queue blocks the Zenoh callback: back-pressure instead of loss
_STOP = object()


class Ingest:
    """Owns the write path of one server. `submit` is safe from any thread."""

    def __init__(self, state: ServerState, publish: Callable[[str, bytes], None]):
        self.state = state
        self.publish = publish  # (key, payload) -> None: sends an Ack
        self._queue: queue.Queue = queue.Queue(QUEUE_LIMIT)
        self._thread = threading.Thread(target=self._run, name="gmmap-ingest", daemon=True)
        self._dim: int | None = None  # of the first accepted message: a map is 2D or 3D for good

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Finish what is queued, then stop the worker."""
        self._queue.put(_STOP)
        self._thread.join(timeout)

    def submit(self, key: str, payload: bytes) -> None:
        self._queue.put((key, payload))

    def replay(self) -> int:
        """Load the store into the FleetMap (before subscribing); returns the scans loaded."""
        scans = 0
        for record in self.state.store.load(self.state.fleet):
            self._dim = self._dim or record.message.dim
            if isinstance(record.message, ScanMessage):
                scans += self.state.fleet_map.add_scan(record.message, record.size)
            else:
                self.state.fleet_map.apply_poses(record.message)
        return scans

    # -- worker --------------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            batch = [self._queue.get()]
            while len(batch) < MAX_BATCH:
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            stop = any(item is _STOP for item in batch)
            try:
                self._process([item for item in batch if item is not _STOP])
            except Exception:  # the server keeps serving; the agents resend what was not acked
                log.exception("ingest batch of %d failed", len(batch))
            if stop:
                return

    def _process(self, batch: list[tuple[str, bytes]]) -> None:
        scans: list[tuple[ScanMessage, bytes]] = []
        updates: list[tuple[PoseGraphUpdate, bytes]] = []
        for key, payload in batch:
            message = self._validate(key, payload)
            if isinstance(message, ScanMessage):
                scans.append((message, payload))
            elif message is not None:
                updates.append((message, payload))
        if scans:
            self._ingest_scans(scans)
        for update, payload in updates:
            self._ingest_poses(update, payload)

    def _validate(self, key: str, payload: bytes) -> ScanMessage | PoseGraphUpdate | None:
        """The message, or None after counting why it was rejected."""
        metrics = self.state.metrics
        kind = "unknown"
        try:
            fleet, robot, kind, node = parse_key(key)
            expected = {"scan": ScanMessage, "poses": PoseGraphUpdate}.get(kind)
            if expected is None or fleet != self.state.fleet:
                raise ProtocolError("key", f"not a scan or pose key of fleet {self.state.fleet}: {key}")
            message = decode(payload, expect=expected)
            if message.fleet != fleet:
                raise ProtocolError("key.fleet", f"key says {fleet}, message says {message.fleet}")
            if message.robot != robot:
                raise ProtocolError("key.robot", f"key says {robot}, message says {message.robot}")
            if kind == "scan" and message.node != node:
                raise ProtocolError("key.node", f"key says {node}, message says {message.node}")
            if self._dim is not None and message.dim != self._dim:
                raise ProtocolError("dimension", f"this map is {self._dim}D, the message is {message.dim}D")
            self._dim = message.dim
            return message
        except ProtocolError as error:
            metrics.rejected.labels(kind, error.field).inc()
            log.debug("rejected %s on %s: %s", kind, key, error)
            return None

    def _ingest_scans(self, scans: list[tuple[ScanMessage, bytes]]) -> None:
        state = self.state
        state.store.put_scans(scans)  # committed: from here on they may be acknowledged
        acks: dict[str, list[int]] = defaultdict(list)
        for message, payload in scans:
            state.fleet_map.add_scan(message, len(payload))  # a held correction applies as it lands
            state.metrics.accepted.labels("scan").inc()
            state.metrics.bytes_received.labels(message.robot).inc(len(payload))
            acks[message.robot].append(message.node)  # duplicates too: the sender must stop resending
        for robot, nodes in acks.items():
            self._ack(robot, "scan", nodes)

    def _ingest_poses(self, update: PoseGraphUpdate, payload: bytes) -> None:
        state = self.state
        if state.store.put_poses(update, payload):
            state.fleet_map.apply_poses(update)
        state.metrics.accepted.labels("poses").inc()
        state.metrics.bytes_received.labels(update.robot).inc(len(payload))
        self._ack(update.robot, "poses", [update.revision])  # an older revision is acked as superseded

    def _ack(self, robot: str, kind: str, ids: list[int]) -> None:
        ack = Ack(self.state.fleet, robot, kind, tuple(ids))
        try:
            self.publish(ack_key(self.state.fleet, robot), encode(ack))
        except Exception:  # a lost Ack only costs a resend, which is acknowledged again
            log.exception("could not publish %s ack for %s", kind, robot)
