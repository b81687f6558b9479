"""From wire bytes to the store and the map: validate, commit, then acknowledge.

Zenoh callbacks only enqueue (key, bytes); one worker thread drains the queue in batches, so
a batch of scans is one SQLite transaction and one Ack per robot (group commit: thousands of
messages per second even with synchronous=FULL). The order per batch is: validate every
message, hold back the scans over their robot's storage quota, commit the others, put them in
the FleetMap, publish the scan Acks; then pose updates one by one (commit, apply, Ack). Nothing
is acknowledged before its commit.

A scan over the quota, and a message of the other dimension than the map's (a map is 2D or 3D
for good), is answered with a Rejection, not left unanswered: the robot would otherwise resend it
forever without knowing why.

Ingest comes first: while a batch is processed whose oldest message waited in the queue over
HOLD_TRACERS_AFTER_S, the map's tracers wait at their next node (FleetMap.ingest_first), so a
flood of tile requests slows the tiles, not the store. A server that keeps up does not hold them:
at 200 scans/s the ingest thread is busy most of the time, and holding the tracers for every batch
left them a few percent of the time to trace (docs/RELIABILITY.md, "Seventh session"). A scan
that waits in the queue longer than QUEUED_ACK_S is announced to its robot in an Ack's `queued`
list every QUEUED_ACK_S: received, not lost, so the robot holds it rather than resends it.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from contextlib import nullcontext
from typing import NamedTuple

from protocol import Ack, PoseGraphUpdate, ProtocolError, Rejection, ScanMessage, ack_key, decode, encode, parse_key

from .nodes import ScanEntry
from .state import ServerState

log = logging.getLogger("gmmap.server")

MAX_BATCH = 512
QUEUED_ACK_S = 2.0  # s between the Acks that list a robot's scans still waiting in the queue
QUEUE_LIMIT = 20_000  # a full queue blocks the Zenoh callback: back-pressure instead of loss
HOLD_TRACERS_AFTER_S = 0.2  # a batch whose oldest message waited this long (s) holds the tracers
_STOP = object()


class Unfit(NamedTuple):
    """A valid message this map can never take, and why (its dimension is not the map's)."""

    message: ScanMessage | PoseGraphUpdate
    error: ProtocolError


class Ingest:
    """Owns the write path of one server. `submit` is safe from any thread."""

    def __init__(self, state: ServerState, publish: Callable[[str, bytes], None], quota_bytes: int | None = None):
        self.state = state
        self.publish = publish  # (key, payload) -> None: sends an Ack or a Rejection
        self.quota = quota_bytes  # stored scan bytes per robot; None: no quota
        self._usage: dict[str, int] = defaultdict(int)  # stored scan bytes per robot (wire size)
        self._queue: queue.Queue = queue.Queue(QUEUE_LIMIT)
        self._thread = threading.Thread(target=self._run, name="gmmap-ingest", daemon=True)
        self._dim: int | None = None  # of the first accepted message: a map is 2D or 3D for good
        self._deadline = math.inf  # set by stop: the worker ends after the batch that passes it
        self._waiting: dict[str, dict[int, float]] = defaultdict(dict)  # robot -> {queued scan: when}
        self._waiting_lock = threading.Lock()
        self._announcer = threading.Thread(target=self._announce_queued, name="gmmap-queued", daemon=True)

    def start(self) -> None:
        self._thread.start()
        self._announcer.start()

    def stop(self, timeout: float = 1.5) -> None:
        """Stop the worker after what it can store within `timeout` s; what is still queued then is
        dropped unacknowledged (its robots hold it and send it again), so a server under load stops
        in seconds rather than after its whole backlog."""
        self._deadline = time.monotonic() + timeout
        try:
            self._queue.put_nowait(_STOP)
        except queue.Full:
            pass  # the worker sees the deadline after its current batch
        self._thread.join(timeout + 1.0)
        while True:  # what is left is dropped, and a Zenoh callback blocked on the full queue is let go
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break

    def submit(self, key: str, payload: bytes) -> None:
        if self._deadline == math.inf:  # once stopping, not acknowledged: the robot sends it again
            self._note_waiting(key)
            self._queue.put((key, payload, time.monotonic()))

    @staticmethod
    def _scan_of(key: str) -> tuple[str, int] | None:
        """(robot, node) of a scan key; None for any other key (a bad one is rejected, and counted,
        when its turn comes)."""
        try:
            _, robot, kind, node = parse_key(key)
        except ProtocolError:
            return None
        return (robot, node) if kind == "scan" else None

    def _note_waiting(self, key: str) -> None:
        scan = self._scan_of(key)
        if scan is not None:
            with self._waiting_lock:
                self._waiting[scan[0]].setdefault(scan[1], time.monotonic())

    def _done_waiting(self, robot: str, nodes: list[int]) -> None:
        with self._waiting_lock:
            waiting = self._waiting.get(robot)
            for node in nodes if waiting else ():
                waiting.pop(node, None)

    def _announce_queued(self) -> None:
        """Every QUEUED_ACK_S, tell each robot which of its scans wait longer than that (Ack.queued)."""
        while self._deadline == math.inf:
            time.sleep(QUEUED_ACK_S)
            due = time.monotonic() - QUEUED_ACK_S
            with self._waiting_lock:
                late = {r: sorted(n for n, t in w.items() if t <= due) for r, w in self._waiting.items()}
            for robot, nodes in late.items():
                if nodes:
                    self._send(robot, Ack(self.state.fleet, robot, self.state.store.identity, "scan", (), tuple(nodes)))

    def replay(self) -> int:
        """Load the store into the FleetMap (before subscribing); returns the scans loaded."""
        fleet_map, scans, usage = self.state.fleet_map, 0, defaultdict(int)
        batch: list[ScanEntry] = []
        for record in self.state.store.load(self.state.fleet):
            message = record.message
            self._dim = self._dim or message.dim
            if isinstance(message, ScanEntry):
                batch.append(message)
                usage[message.robot] += record.size
                if len(batch) == MAX_BATCH:  # in batches, as ingest adds them
                    scans += sum(fleet_map.add_entries(batch))
                    batch = []
            else:
                fleet_map.apply_poses(message)
        scans += sum(fleet_map.add_entries(batch))
        for robot, size in usage.items():  # once per robot, not once per scan
            self._add_usage(robot, size)
        for robot, when in self.state.store.last_received(self.state.fleet).items():
            fleet_map.set_last_seen(robot, when)
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
            now = time.monotonic()
            stop = any(item is _STOP for item in batch) or now > self._deadline
            queued = [item for item in batch if item is not _STOP]  # (key, payload, when queued), oldest first
            items = [(key, payload) for key, payload, _ in queued]
            behind = bool(queued) and now - queued[0][2] > HOLD_TRACERS_AFTER_S
            try:
                with self.state.fleet_map.ingest_first() if behind else nullcontext():
                    self._process(items)
            except Exception:  # the server keeps serving; the agents resend what was not acked
                log.exception("ingest batch of %d failed", len(batch))
                for key, _ in items:  # no longer announced as queued: their robots resend them
                    self._done_waiting_key(key)
            if stop:
                return

    def _process(self, batch: list[tuple[str, bytes]]) -> None:
        scans: list[tuple[ScanMessage, bytes]] = []
        updates: list[tuple[PoseGraphUpdate, bytes]] = []
        for key, payload in batch:
            if time.monotonic() > self._deadline:
                break  # stopping: the rest is not acknowledged, and sent again by its robots
            verdict = self._validate(key, payload)
            if isinstance(verdict, ScanMessage):
                scans.append((verdict, payload))
            elif isinstance(verdict, PoseGraphUpdate):
                updates.append((verdict, payload))
            else:  # rejected and counted: no longer announced as queued
                self._done_waiting_key(key)
                if verdict is not None:
                    self._refuse(verdict)
        if scans:
            self._ingest_scans(scans)
        for update, payload in updates:
            self._ingest_poses(update, payload)

    def _done_waiting_key(self, key: str) -> None:
        scan = self._scan_of(key)
        if scan is not None:
            self._done_waiting(scan[0], [scan[1]])

    def _validate(self, key: str, payload: bytes) -> ScanMessage | PoseGraphUpdate | Unfit | None:
        """The message; or, after counting why it was rejected, None, or Unfit for a valid message
        this map can never take (answered by _process). Touches neither the store nor the map: a
        fuzzer runs it as the server's oracle (bench/fuzz_ingest.py)."""
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
        except ProtocolError as error:
            self._count_rejected(kind, key, error)
            return None
        if self._dim is not None and message.dim != self._dim:
            error = ProtocolError("dimension", f"this map is {self._dim}D, the message is {message.dim}D")
            self._count_rejected(kind, key, error)
            return Unfit(message, error)
        self._dim = message.dim
        return message

    def _count_rejected(self, kind: str, key: str, error: ProtocolError) -> None:
        self.state.metrics.rejected.labels(kind, error.field).inc()
        log.debug("rejected %s on %s: %s", kind, key, error)

    def _refuse(self, unfit: Unfit) -> None:
        """Answer an unfit message with a Rejection naming the field: left unanswered, its robot
        would resend it until its timeout and then blame the network."""
        message, error = unfit
        kind, ident = ("scan", message.node) if isinstance(message, ScanMessage) else ("poses", message.revision)
        log.warning("refused %s %d of %s: %s", kind, ident, message.robot, error)
        refusal = Rejection(
            self.state.fleet, message.robot, self.state.store.identity, kind, (ident,), error.field, error.message
        )
        self._send(message.robot, refusal)

    def _within_quota(self, scans: list[tuple[ScanMessage, bytes]]) -> list[tuple[ScanMessage, bytes]]:
        """The scans that fit their robot's quota; the others are counted and refused.

        A resend of a scan already held always passes (it costs nothing, and its Ack may have
        been lost). Within a batch, every scan counts until the commit says which were new: near
        the quota this may refuse a scan that would just have fitted, never admit one over it.
        """
        if self.quota is None:
            return scans
        kept, refused, batch = [], defaultdict(list), defaultdict(int)
        for message, payload in scans:
            robot = message.robot
            if (
                self._usage[robot] + batch[robot] + len(payload) > self.quota
                and self.state.store.scan_bytes(message.fleet, robot, message.node) is None
            ):
                refused[robot].append(message.node)
                self.state.metrics.rejected.labels("scan", "quota").inc()
            else:
                kept.append((message, payload))
                batch[robot] += len(payload)
        for robot, nodes in refused.items():
            self._done_waiting(robot, nodes)
            detail = (
                f"robot {robot} holds {self._usage[robot] / 2**20:.4g} MiB of scans on this server, "
                f"the quota is {self.quota / 2**20:.4g} MiB (gmmap server --robot-quota-mb)"
            )
            log.warning("refused %d scans of %s: %s", len(nodes), robot, detail)
            refusal = Rejection(
                self.state.fleet, robot, self.state.store.identity, "scan", tuple(nodes), "quota", detail
            )
            self._send(robot, refusal)
        return kept

    def _add_usage(self, robot: str, size: int) -> None:
        self._usage[robot] += size
        self.state.metrics.stored_bytes.labels(robot).set(self._usage[robot])

    def _ingest_scans(self, scans: list[tuple[ScanMessage, bytes]]) -> None:
        state = self.state
        scans = self._within_quota(scans)
        if not scans:
            return
        entries = [ScanEntry.of(m, len(raw), raw) for m, raw in scans]  # what the store and the map keep
        new = state.store.put_scans(scans, entries)  # committed: from here on they may be acknowledged
        # Counted as committed, before anything else can fail: a scan of a failed batch is resent,
        # found held and acknowledged, never counted again.
        for (message, payload), added in zip(scans, new):
            if added:
                self._add_usage(message.robot, len(payload))
        state.fleet_map.add_entries(entries, [m.model for m, _ in scans])  # a held correction applies as it lands
        acks: dict[str, dict[int, None]] = defaultdict(dict)  # per robot, each node once, in order
        for message, payload in scans:
            state.metrics.accepted.labels("scan").inc()
            state.metrics.bytes_received.labels(message.robot).inc(len(payload))
            acks[message.robot][message.node] = None  # resends too: the sender must stop resending
        for robot, nodes in acks.items():
            self._done_waiting(robot, list(nodes))
            self._ack(robot, "scan", list(nodes))

    def _ingest_poses(self, update: PoseGraphUpdate, payload: bytes) -> None:
        state = self.state
        if state.store.put_poses(update):
            state.fleet_map.apply_poses(update)
        state.metrics.accepted.labels("poses").inc()
        state.metrics.bytes_received.labels(update.robot).inc(len(payload))
        # Acked even when it changed nothing (a resend, or every node it lists set by a newer revision):
        # it is held, as far as it will ever be, so the robot must stop resending it.
        self._ack(update.robot, "poses", [update.revision])

    def _ack(self, robot: str, kind: str, ids: list[int]) -> None:
        self._send(robot, Ack(self.state.fleet, robot, self.state.store.identity, kind, tuple(ids)))

    def _send(self, robot: str, answer: Ack | Rejection) -> None:
        try:
            self.publish(ack_key(self.state.fleet, robot), encode(answer))
        except Exception:  # a lost answer only costs a resend, which is answered again
            log.exception("could not publish %s %s for %s", answer.kind, type(answer).__name__, robot)
