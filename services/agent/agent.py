"""`gmmap agent`: fit a robot's scans, publish them and its pose-graph updates until acknowledged.

Every message goes to the outbox (committed) before it is published; a resender thread
republishes what has gone unanswered, so after a server restart or a reconnect everything gets
through. The resend timeout follows the measured Ack round trip (TCP's estimator, RFC 6298,
never below `resend_s`) and doubles with every further sending of a message: a server that is
slow but alive is not buried in copies of what it is still storing. The Zenoh session (client
mode) opens in the background: a robot out of reach keeps fitting and filling its outbox. A
finite source ends when the outbox is empty.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

import numpy as np
import zenoh

from gmm_core import FitConfig, Pose, fit_scan
from protocol import (
    Ack,
    PoseGraphUpdate,
    ProtocolError,
    Rejection,
    ScanMessage,
    StoreInventory,
    ack_key,
    decode,
    encode,
    inventory_key,
    poses_key,
    scan_key,
)
from services.config import GmmapConfig, summary
from services.datasets.keyframes import KeyframeConfig, KeyframeFilter
from services.sim.trajectory import ClosureSchedule
from services.zenoh_config import zenoh_config

from .config import AgentConfig
from .outbox import Outbox
from .sent_poses import SentPoses, beam_reach
from .sources import (
    FixedCorrections,
    Node,
    RelaxingCorrections,
    SimulatedNodes,
    default_update_every,
    is_simulated,
    load_nodes,
)

log = logging.getLogger("gmmap.agent")

# s without any answer while messages are in flight before they count as lost (a server that is
# slow but answering is never resent to; one that restarted is seen at once by its subscription)
SILENCE_S = 10.0
# Refusals that every later scan would get too: the robot's quota is used up; the map has the other
# dimension (for good).
REFUSES_EVERY_SCAN = ("quota", "dimension")


class Agent:
    def __init__(
        self,
        options: AgentConfig,
        outbox: Outbox,
        config: zenoh.Config,
        fit: FitConfig = FitConfig(),
        keyframe: KeyframeConfig = KeyframeConfig(),
    ):
        self.options = options
        self.fit = fit
        self.outbox = outbox
        self._owns_outbox = False  # Agent.open made it, so close closes it
        self._keyframes = KeyframeFilter(keyframe)
        self.session: zenoh.Session | None = None  # set once connected
        self._ack_subscriber = None
        self._send_lock = threading.Lock()  # one publisher at a time keeps scans before updates
        self._session_lock = threading.Lock()  # exactly one of _connect and close closes the session
        self._changed = threading.Condition()
        self.refused: Rejection | None = None  # the server's last refusal for good, if any
        self.unsent = 0  # scans not published because of a refusal
        self.kept = 0  # nodes of publish_all's source that the keyframe policy kept
        self.resumed = 0  # of those, the ones a previous run of this outbox got through (or held): not fitted again
        self._sent_poses = SentPoses()  # what the server holds of each node's pose, and the node's reach
        self.store: str | None = None  # the store this agent reports to, from its inventory
        # {store that had acknowledged them: messages sent again}, because the store reported to lacked them
        self.requeued: dict[str, int] = {}
        self.lost: set[int] = set()  # acknowledged nodes the store lacks and whose bytes are gone: refit
        self.refitted = 0  # of those, fitted again from the source
        self._reconciled = threading.Event()  # set once the store's inventory was compared with the outbox
        self._store_changed = threading.Event()  # an Ack named another store: compare again
        self._srtt: float | None = None  # smoothed Ack round trip and its mean deviation, s
        self._rttvar = 0.0
        self._stop = threading.Event()
        self._room = threading.Event()  # set by Acks: the resender refills the window
        self._last_heard = 0.0  # time.time() of the server's last answer
        self._probe = None  # a publisher on our scan keys, for the server's presence
        self._server_gone = False
        self._acked_sent = 0.0  # when the latest-sent acknowledged message was sent
        self._connector = threading.Thread(target=self._connect, args=(config,), name="gmmap-connect", daemon=True)
        self._resender = threading.Thread(target=self._resend_loop, name="gmmap-resend", daemon=True)
        self._connector.start()
        self._resender.start()

    # -- connection ----------------------------------------------------------------------------
    def _connect(self, config: zenoh.Config) -> None:
        session = zenoh.open(config)  # blocks until a server or router answers
        o = self.options
        self._ack_subscriber = session.declare_subscriber(ack_key(o.fleet, o.robot), self._on_ack)
        if not self._wait_for_server(session, max(o.resend_s, 2.0)):
            log.warning("connected, but no map server of fleet %s seen yet; the outbox resends", o.fleet)
        with self._session_lock:
            self.session = session
            closed = self._stop.is_set()  # close() ran while we were connecting
        if closed:
            self._close_session()
        else:
            self._store_changed.set()  # the resender asks the store for its inventory

    def reconcile(self) -> bool:
        """Ask the store for what it holds of this robot and put back into the outbox what it lacks;
        False if no store answered. Run at connection and whenever an Ack names another store."""
        o = self.options
        session = self.session
        if session is None:
            return False
        inventory = None
        for reply in session.get(inventory_key(o.fleet, o.robot), timeout=max(o.resend_s, 2.0)):
            if reply.ok is None:
                continue
            try:
                inventory = decode(reply.ok.payload.to_bytes(), expect=StoreInventory, max_bytes=1 << 24)
            except ProtocolError as error:
                log.warning("ignored a malformed inventory: %s", error)
        if inventory is None:
            return False
        requeued, lost = self.outbox.requeue_missing(inventory, inventory.revision)
        if requeued or lost:
            log.warning(
                "store %s lacks %d acknowledged messages: sending them again; %d more are no longer kept",
                inventory.store,
                sum(requeued.values()) + len(lost),
                len(lost),
            )
        for store, count in requeued.items():
            self.requeued[store] = self.requeued.get(store, 0) + count
        self.lost |= lost
        self.store = inventory.store
        self._reconciled.set()
        with self._changed:
            self._changed.notify_all()
        return True

    def wait_reconciled(self, timeout: float) -> bool:
        return self._reconciled.wait(timeout)

    def _wait_for_server(self, session: zenoh.Session, timeout: float) -> bool:
        """Wait until a subscriber of our scans is known, at most `timeout` s.

        Puts before that are dropped by Zenoh, and so are Acks sent before our Ack subscriber
        reached the server; either would wait a resend period. The probe stays: its matching
        status tells the resender when the server went away and came back.
        """
        self._probe = session.declare_publisher(scan_key(self.options.fleet, self.options.robot, 0))
        deadline = time.monotonic() + timeout
        while not self._probe.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        self._last_heard = time.time()  # silence is counted from here
        return self._probe.matching_status.matching

    def _server_returned(self) -> bool:
        """True once after the server's subscriber vanished and came back (a restart, a lost link):
        what was in flight to it may have died in its queue."""
        matched = self._probe is not None and self._probe.matching_status.matching
        returned = matched and self._server_gone
        self._server_gone = not matched
        return returned

    # -- sending -------------------------------------------------------------------------------
    def send(self, kind: str, ident: int, key: str, raw: bytes) -> None:
        """Keep the message (committed first: a crash from here on resends it) and publish what the
        window allows; the rest waits in the outbox for Acks to make room."""
        self.outbox.add(kind, ident, key, raw)
        self._fill_window()

    def _fill_window(self) -> None:
        """Publish unsent messages while fewer than `window` are unanswered (flow control: a server
        that falls behind gets no more than it can queue, and the outbox holds the rest)."""
        with self._send_lock:
            room = self.options.window - self.outbox.in_flight()
            if room > 0:
                self._publish(self.outbox.unsent(room))

    def _publish(self, items) -> None:
        """Put `items` on the wire (caller holds the send lock)."""
        session = self.session
        if session is None or not items:
            return  # offline: sent once connected
        for _, _, key, raw in items:
            # BLOCK: wait for room in the link's queue rather than drop a scan.
            session.put(key, raw, congestion_control=zenoh.CongestionControl.BLOCK)
        self.outbox.mark_sent([(kind, ident) for kind, ident, _, _ in items])

    def _resend_loop(self) -> None:
        while not self._stop.is_set():
            self._room.wait(self.options.resend_s / 2)  # an Ack made room, or time to look again
            self._room.clear()
            if self.session is None:
                continue
            if self._store_changed.is_set():
                self._store_changed.clear()
                if not self.reconcile():
                    self._store_changed.set()  # no store answered yet: ask again next round
            now, timeout = time.time(), self.resend_timeout()
            returned = self._server_returned()
            silent = returned or now - self._last_heard >= max(timeout, SILENCE_S)
            with self._send_lock:
                due = self.outbox.due(now, 0.0 if returned else timeout, silent, self._acked_sent)
                if due:
                    log.info("sending %d unacknowledged messages again", len(due))
                    self._publish(due)
            self._fill_window()

    def resend_timeout(self) -> float:
        """Seconds an unanswered message waits before its second sending."""
        if self._srtt is None:
            return self.options.resend_s
        return max(self.options.resend_s, self._srtt + 4 * self._rttvar)

    def _measured(self, round_trip: float) -> None:
        if self._srtt is None:
            self._srtt, self._rttvar = round_trip, round_trip / 2
        else:
            self._rttvar = 0.75 * self._rttvar + 0.25 * abs(self._srtt - round_trip)
            self._srtt = 0.875 * self._srtt + 0.125 * round_trip

    def _on_ack(self, sample: zenoh.Sample) -> None:
        try:
            answer = decode(sample.payload.to_bytes())
            if not isinstance(answer, (Ack, Rejection)):
                raise ProtocolError("type", f"expected Ack or Rejection, got {type(answer).__name__}")
        except ProtocolError as error:
            log.warning("ignored a malformed ack: %s", error)
            return
        if answer.robot != self.options.robot or answer.fleet != self.options.fleet:
            return
        self._last_heard = time.time()
        if isinstance(answer, Rejection):  # refused for good: stop resending, report at the end
            if self.outbox.reject(answer.kind, answer.ids, answer.reason, answer.detail):
                log.error(
                    "the server refused %d message(s) of kind %s: %s: %s",
                    len(answer.ids),
                    answer.kind,
                    answer.reason,
                    answer.detail,
                )
            self.refused = answer
        else:
            if answer.store != self.store:  # a restarted server on a new data dir, or another server
                self._store_changed.set()
            round_trips, latest = self.outbox.acknowledge(answer.kind, answer.ids, answer.store)
            for round_trip in round_trips:
                self._measured(round_trip)
            self._acked_sent = max(self._acked_sent, latest)
            if answer.queued:  # received and queued by a busy server: not lost, wait for it
                self.outbox.mark_sent([(answer.kind, i) for i in answer.queued], again=False)
        self._room.set()
        with self._changed:
            self._changed.notify_all()

    # -- the embeddable API -------------------------------------------------------------------
    @classmethod
    def open(cls, config: GmmapConfig | AgentConfig) -> Agent:
        """An agent for a robot process that has its own scans and poses (see examples/).

        `config` is a whole configuration (its agent, fit and keyframe sections) or just the
        agent section (default fit and keyframe policy); `robot` must be set. The outbox is
        `config.outbox` (default ./gmmap-data/outbox-<robot>.db); a robot process that restarts
        with the same outbox resends what was not acknowledged and numbers its nodes on.
        """
        if isinstance(config, AgentConfig):
            config = GmmapConfig(agent=config)
        o = config.agent
        o.check_runnable(needs_source=False)
        outbox = Outbox(o.outbox_path, o.fleet, o.robot, o.keep_acked_bytes)
        zenoh_settings = zenoh_config("client", connect=o.zenoh_connect, config_file=o.zenoh_config)
        agent = cls(o, outbox, zenoh_settings, config.fit, config.keyframe)
        agent._owns_outbox = True
        return agent

    def __enter__(self) -> Agent:
        return self

    def __exit__(self, *exc) -> None:
        self.close()  # what is not acknowledged stays in the outbox for the next run

    def add_scan(
        self, points: np.ndarray, no_return: np.ndarray | None, pose: Pose, stamp: float, node: int | None = None
    ) -> int | None:
        """Fit one scan and send it; its node id, or None if the keyframe policy skipped it (or the
        server refused this robot's scans for its quota or their dimension: see `refused`).

        points: (n, d) returned end points in the sensor frame, metres; no_return: (m, d) directions
        of beams without a return (or None); pose: the sensor's pose in the robot's map frame, as the
        robot knows it now (odometry or on-line SLAM); stamp: seconds. `node` defaults to one more
        than the last node this outbox has seen.
        """
        if not isinstance(pose, Pose):
            raise TypeError(f"pose: expected gmm_core.Pose, got {type(pose).__name__}")
        self._sent_poses.check_dim(pose)  # a robot's nodes share one dimension
        points = _points("points", points, pose.dim)
        no_return = _points("no_return", np.empty((0, pose.dim)) if no_return is None else no_return, pose.dim)
        if not self._keyframes.keep(pose, stamp):
            return None
        if node is None:
            last = self.outbox.last_id("scan")
            node = 0 if last is None else last + 1
        return node if self._send_scan(node, points, no_return, pose, stamp) else None

    def correct(self, poses: Mapping[int, Pose], anchor: Pose | None = None) -> int | None:
        """Send a pose-graph update: corrected sensor poses of earlier nodes (and where the robot's
        map frame sits in the fleet's world, if known); returns its revision, or None when no
        node's scan would move by more than `pose_tolerance` and there is no anchor.

        A node goes out only when some beam end of its scan would move by more than `pose_tolerance`
        metres from where the server has it (the scan's own pose, or the correction last sent):
        protocol v2 and later apply updates node by node, so the cost of a correction follows what
        it changes in the map, not the length of the mission. A node whose scan this agent did not
        send (a previous run's) has no known reach and goes out whenever it is corrected.
        """
        o = self.options
        moved = self._sent_poses.moved(poses, o.pose_tolerance)
        if not moved and anchor is None:
            return None
        update = PoseGraphUpdate(o.fleet, o.robot, 0, tuple(moved.items()), anchor)  # checked before numbering
        revision = self.outbox.next_revision()  # increasing across runs of this outbox
        self.send("poses", revision, poses_key(o.fleet, o.robot), encode(replace(update, revision=revision)))
        self._sent_poses.corrections_sent(moved)
        return revision

    def flush(self, timeout: float) -> int:
        """Wait until everything sent is acknowledged, at most `timeout` s; returns what is still held
        (0: all stored by the server). What is held stays in the outbox and is resent."""
        return self.wait_acknowledged(timeout)

    def _send_scan(
        self,
        node: int,
        points: np.ndarray,
        no_return: np.ndarray,
        pose: Pose,
        stamp: float,
        raw: bytes | None = None,
        reach: float | None = None,
    ) -> bool:
        """Send a scan: fitted from its beams, or `raw` (fitted ahead, with its beams' `reach`)."""
        if self.refused is not None and self.refused.reason in REFUSES_EVERY_SCAN:  # nothing more would be taken
            self.unsent += 1
            return False
        if node in self.lost:
            self.lost.discard(node)
            self.refitted += 1
        o = self.options
        raw = raw or self._encoded(node, points, no_return, pose, stamp)
        # noted first: a scan of another dimension than this robot's earlier ones is refused unsent
        self._sent_poses.scan_sent(node, pose, self._reach(points, no_return, pose.dim) if reach is None else reach)
        self.send("scan", node, scan_key(o.fleet, o.robot, node), raw)
        return True

    def _reach(self, points: np.ndarray, no_return: np.ndarray, dim: int) -> float:
        return beam_reach(points, no_return, self.fit.for_dimension(dim).max_range)

    def _encoded(self, node: int, points: np.ndarray, no_return: np.ndarray, pose: Pose, stamp: float) -> bytes:
        """The node's ScanMessage: the scan fitted (Sec. III-A/B) and encoded."""
        o = self.options
        model = fit_scan(points, no_return, self.fit.for_dimension(pose.dim))
        return encode(ScanMessage(o.fleet, o.robot, node, stamp, model, pose), o.encoding)

    def _send_node(self, node: Node) -> bool:
        scan = node.scan
        return self._send_scan(
            node.node, scan.hits, scan.no_return, node.estimate, scan.stamp, node.message, node.reach
        )

    def prepare(self, nodes: Sequence[Node] | SimulatedNodes, progress=None) -> list[Node]:
        """Every node fitted and encoded ahead, its beams dropped: a simulated robot that prepares its
        run, so that a timed (or time-compressed) run measures the server and the link, not the fit."""
        prepared = []
        for node in nodes:
            scan = node.scan
            raw = self._encoded(node.node, scan.hits, scan.no_return, node.estimate, scan.stamp)
            reach = self._reach(scan.hits, scan.no_return, node.estimate.dim)
            beamless = replace(scan, hits=scan.hits[:0], no_return=scan.no_return[:0])
            prepared.append(replace(node, scan=beamless, message=raw, reach=reach))
            if progress is not None:
                progress(1)
        return prepared

    # -- a whole source ------------------------------------------------------------------------
    def publish_all(
        self, nodes: Sequence[Node] | SimulatedNodes, progress=None, closures: ClosureSchedule | None = None
    ) -> int:
        """Fit and send every node the keyframe policy keeps, with pose-graph updates after the
        scans `closures` says (default: a simulated robot's own, else every update_every); returns
        the updates sent. `kept` counts the nodes, `resumed` those a previous run got through."""
        o = self.options
        corrected: dict[int, Node] = {}  # the nodes a back end corrects
        back_end = RelaxingCorrections() if is_simulated(o.source) else FixedCorrections()
        if closures is None:
            closures = closure_schedule(nodes, o.update_every)
        updates = 0
        # A restarted agent resumes: acknowledged scans are through, held ones go out with the resender;
        # those the store lacks and the outbox no longer keeps are fitted again.
        done = self.outbox.known("scan") - self.lost
        self.resumed = self.kept = 0
        sent = 0
        started = time.monotonic()
        for count, node in enumerate(nodes, 1):
            if progress is not None:
                progress(1)
            # the same decisions on every run of a source, so a resumed run skips the same scans
            if self._keyframes.keep(node.estimate, node.scan.stamp):
                self.kept += 1
                if node.node in done:
                    self.resumed += 1
                    delivered = True
                else:
                    if o.rate > 0:
                        time.sleep(max(0.0, started + sent / o.rate - time.monotonic()))
                    sent += 1
                    delivered = self._send_node(node)
                if delivered and node.corrected is not None:
                    corrected[node.node] = node
            if corrected and closures.closes_after(count) and count < len(nodes):
                updates += self.correct(back_end.closure(corrected, final=False)) is not None
        if corrected:  # and once at the end, as a back end closing its graph would
            updates += self.correct(back_end.closure(corrected, final=True)) is not None
        return updates

    def refit(self, nodes: Sequence[Node] | SimulatedNodes) -> int:
        """Fit and send again the nodes the store lacks whose bytes the outbox no longer keeps
        (found after publish_all passed them); returns how many."""
        if not self.lost:
            return 0
        held = self.outbox.held("scan")
        again = [n for n in nodes if n.node in self.lost and n.node not in held]
        for node in again:
            self._send_node(node)
        return len(again)

    def wait_acknowledged(self, timeout: float) -> int:
        """Block until a store's inventory was compared with the outbox and the outbox is empty, or
        `timeout` s pass without an acknowledgement (a slow server that is working through a robot's
        backlog keeps it waiting); returns what is still pending (at least 1 while no store answered)."""
        deadline = time.monotonic() + timeout
        last = None
        with self._changed:
            while (pending := self._unconfirmed()) and time.monotonic() < deadline:
                if last is not None and pending < last:
                    deadline = time.monotonic() + timeout  # progress: the server is alive
                last = pending
                self._changed.wait(min(0.5, max(0.0, deadline - time.monotonic())))
        return pending

    def _unconfirmed(self) -> int:
        pending = self.outbox.pending()
        return pending if self._reconciled.is_set() and not self._store_changed.is_set() else max(pending, 1)

    def close(self) -> None:
        self._stop.set()
        self._room.set()
        self._resender.join()
        with self._session_lock:
            connected = self.session is not None
        if connected:
            self._close_session()
        # else: the connector is still blocked in zenoh.open (nothing reachable); it is a daemon
        if self._owns_outbox:
            self.outbox.close()

    def _close_session(self) -> None:
        if self._probe is not None:
            self._probe.undeclare()
            self._probe = None
        if self._ack_subscriber is not None:
            self._ack_subscriber.undeclare()  # callback subscribers outlive their Python reference
            self._ack_subscriber = None
        self.session.close()


def _points(name: str, a, dim: int) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{name}: expected an (n, {dim}) array for a {dim}D pose, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: {int((~np.isfinite(a)).any(axis=1).sum())} rows are not finite")
    return np.ascontiguousarray(a)


def _requeued(agent: Agent) -> str:
    """What the store lacked of what earlier stores acknowledged, for the summary line."""
    parts = [f"sent again {n} acknowledged by store {s or '(unnamed, protocol v1)'}" for s, n in agent.requeued.items()]
    if agent.refitted:
        parts.append(f"{agent.refitted} scans no longer kept were fitted again")
    if agent.lost:
        parts.append(f"{len(agent.lost)} scans no longer kept are lost")
    if not parts:
        return ""
    lacked = sum(agent.requeued.values()) + agent.refitted + len(agent.lost)
    return f" (the store lacked {lacked} acknowledged messages: {'; '.join(parts)})"


def closure_schedule(nodes: Sequence[Node] | SimulatedNodes, update_every: int) -> ClosureSchedule:
    """When a source's back end closes loops: a simulated robot's own schedule, else every `update_every` scans."""
    return nodes.closures if isinstance(nodes, SimulatedNodes) else ClosureSchedule(update_every)


def run_agent(
    o: AgentConfig,
    fit: FitConfig,
    keyframe: KeyframeConfig,
    nodes: Sequence[Node] | SimulatedNodes | None = None,
    ready: Callable[[], None] | None = None,
) -> int:
    """Run one agent until its source is published and acknowledged; the process exit code.

    `nodes`: the source's nodes when the caller built them (else read from `o.source`); `ready`:
    with it, every node is fitted ahead (Agent.prepare) and `ready()` is called, which returns when
    publishing may start (a simulated fleet starts its timed run once every robot is prepared).
    """
    o.check_runnable()
    started = time.perf_counter()
    print(f"gmmap agent {o.robot} config: {summary(agent=o, fit=fit, keyframe=keyframe)}", file=sys.stderr, flush=True)
    if o.update_every is None:
        o = replace(o, update_every=default_update_every(o.source, o.rate))
    if nodes is None:
        nodes = load_nodes(
            o.source, o.corrections, o.scans, rate=o.rate, update_every=o.update_every, **o.reader_options()
        )
    if o.odometry_only:  # a robot without a SLAM back end: same nodes, odometry stays final
        nodes = [replace(n, corrected=None) for n in nodes]
    outbox = Outbox(o.outbox_path, o.fleet, o.robot, o.keep_acked_bytes)
    agent = Agent(o, outbox, zenoh_config("client", connect=o.zenoh_connect, config_file=o.zenoh_config), fit, keyframe)
    try:
        from tqdm import tqdm

        closures = closure_schedule(nodes, o.update_every)  # of the source: prepared nodes are a list
        if ready is not None:
            with tqdm(total=len(nodes), desc=f"{o.robot} prepare", unit="scan", file=sys.stderr, leave=False) as bar:
                nodes = agent.prepare(nodes, bar.update)
            ready()
            started = time.perf_counter()
        # Against the store's inventory first, when it answers soon: what it lacks is sent again.
        agent.wait_reconciled(min(o.timeout, 5.0))
        with tqdm(total=len(nodes), desc=f"{o.robot} publish", unit="scan", file=sys.stderr, leave=False) as bar:
            updates = agent.publish_all(nodes, bar.update, closures)
        reconciled = agent.wait_reconciled(o.timeout)
        if reconciled:  # a store that answered late may lack what is no longer kept
            agent.refit(nodes)
        published = time.perf_counter()
        # no store answered within the timeout: say so now rather than wait a second one
        pending = agent.wait_acknowledged(o.timeout if reconciled else 0.0)
        if pending:
            print(
                f"gmmap agent {o.robot}: {pending} messages not acknowledged after {o.timeout:.0f} s; "
                f"they stay in {outbox.path} and are resent by the next run "
                f"(is a server for fleet {o.fleet!r} reachable at {','.join(o.zenoh_connect)}?)",
                file=sys.stderr,
                flush=True,
            )
            return 1
        refused = outbox.rejected()
        if refused:
            print(
                f"gmmap agent {o.robot}: the server refused {len(refused)} messages for good "
                f"({refused[-1][2]}: {refused[-1][3]}); they are not stored and not resent "
                f"(listed in table `rejected` of {outbox.path}); {agent.unsent} scans were not published",
                file=sys.stderr,
                flush=True,
            )
            return 3
        resumed = f" ({agent.resumed} of them from a previous run: resumed)" if agent.resumed else ""
        skipped = f" (keyframes of {len(nodes)} read)" if agent.kept < len(nodes) else ""
        print(
            f"gmmap agent {o.robot}: {agent.kept} scans{skipped}{resumed} and {updates} pose-graph updates "
            f"acknowledged by store {agent.store}{_requeued(agent)}; "
            f"published after {published - started:.1f} s, all acknowledged after "
            f"{time.perf_counter() - started:.1f} s",
            file=sys.stderr,
            flush=True,
        )
        return 0
    finally:
        agent.close()
        outbox.close()
