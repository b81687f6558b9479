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
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import zenoh

from gmm_core import FitConfig, fit_scan
from protocol import (
    Ack,
    PoseGraphUpdate,
    ProtocolError,
    Rejection,
    ScanMessage,
    ack_key,
    decode,
    encode,
    poses_key,
    scan_key,
)
from services.config import summary
from services.zenoh_config import zenoh_config

from .config import AgentConfig
from .outbox import Outbox
from .sources import Node, SimulatedNodes, default_update_every, load_nodes

log = logging.getLogger("gmmap.agent")


class Agent:
    def __init__(self, options: AgentConfig, outbox: Outbox, config: zenoh.Config, fit: FitConfig = FitConfig()):
        self.options = options
        self.fit = fit
        self.outbox = outbox
        self.session: zenoh.Session | None = None  # set once connected
        self._ack_subscriber = None
        self._send_lock = threading.Lock()  # one publisher at a time keeps scans before updates
        self._session_lock = threading.Lock()  # exactly one of _connect and close closes the session
        self._changed = threading.Condition()
        self.refused: Rejection | None = None  # the server's last refusal for good, if any
        self.unsent = 0  # scans not published because of a refusal
        self.resumed = 0  # scans a previous run of this outbox got through (or left held): not fitted again
        self._srtt: float | None = None  # smoothed Ack round trip and its mean deviation, s
        self._rttvar = 0.0
        self._stop = threading.Event()
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

    def _wait_for_server(self, session: zenoh.Session, timeout: float) -> bool:
        """Wait until a subscriber of our scans is known, at most `timeout` s.

        Puts before that are dropped by Zenoh, and so are Acks sent before our Ack subscriber
        reached the server; either would wait a resend period.
        """
        probe = session.declare_publisher(scan_key(self.options.fleet, self.options.robot, 0))
        try:
            deadline = time.monotonic() + timeout
            while not probe.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.01)
            return probe.matching_status.matching
        finally:
            probe.undeclare()

    # -- sending -------------------------------------------------------------------------------
    def send(self, kind: str, ident: int, key: str, raw: bytes) -> None:
        self.outbox.add(kind, ident, key, raw)  # committed first: a crash from here on resends it
        self._publish([(kind, ident, key, raw)])

    def _publish(self, items) -> None:
        session = self.session
        if session is None:
            return  # offline: the resender sends it once connected
        with self._send_lock:
            for _, _, key, raw in items:
                # BLOCK: wait for room in the link's queue rather than drop a scan.
                session.put(key, raw, congestion_control=zenoh.CongestionControl.BLOCK)
            self.outbox.mark_sent([(kind, ident) for kind, ident, _, _ in items])

    def _resend_loop(self) -> None:
        while not self._stop.wait(self.options.resend_s / 2):
            if self.session is None:
                continue
            due = self.outbox.due(time.time(), self.resend_timeout())
            if due:
                log.info("sending %d unacknowledged messages again", len(due))
                self._publish(due)

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
            for round_trip in self.outbox.acknowledge(answer.kind, answer.ids):
                self._measured(round_trip)
        with self._changed:
            self._changed.notify_all()

    # -- the run -------------------------------------------------------------------------------
    def publish_all(self, nodes: Sequence[Node] | SimulatedNodes, progress=None) -> int:
        """Fit and send every node, with pose-graph updates; returns the updates sent."""
        o = self.options
        config = None  # the fit as it applies to this source's dimension, from its first scan
        corrected = []
        updates = 0
        # A restarted agent resumes: acknowledged scans are through, held ones go out with the resender.
        done = self.outbox.acked("scan") | self.outbox.held("scan")
        self.resumed = 0
        sent = 0
        started = time.monotonic()
        for count, node in enumerate(nodes, 1):
            if self.refused is not None and self.refused.reason == "quota":  # nothing more would be taken
                self.unsent += 1
                continue
            if node.node in done:
                self.resumed += 1
                if node.corrected is not None:
                    corrected.append((node.node, node.corrected))
                if progress is not None:
                    progress(1)
                continue
            if o.rate > 0:
                time.sleep(max(0.0, started + sent / o.rate - time.monotonic()))
            sent += 1
            config = config or self.fit.for_dimension(node.scan.pose.dim)
            model = fit_scan(node.scan.hits, node.scan.no_return, config)
            message = ScanMessage(o.fleet, o.robot, node.node, node.scan.stamp, model, node.estimate)
            self.send("scan", node.node, scan_key(o.fleet, o.robot, node.node), encode(message, o.encoding))
            if node.corrected is not None:
                corrected.append((node.node, node.corrected))
                if o.update_every > 0 and count % o.update_every == 0 and count < len(nodes):
                    updates += self._send_update(corrected)
            if progress is not None:
                progress(1)
        if corrected:  # and once at the end, as a back end closing its graph would
            updates += self._send_update(corrected)
        return updates

    def _send_update(self, corrected) -> int:
        o = self.options
        revision = self.outbox.next_revision()  # increasing across runs of this outbox
        update = PoseGraphUpdate(o.fleet, o.robot, revision, tuple(corrected))
        self.send("poses", revision, poses_key(o.fleet, o.robot), encode(update))
        return 1

    def wait_acknowledged(self, timeout: float) -> int:
        """Block until the outbox is empty or `timeout` s pass; returns what is still pending."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while (pending := self.outbox.pending()) and time.monotonic() < deadline:
                self._changed.wait(min(0.5, max(0.0, deadline - time.monotonic())))
        return pending

    def close(self) -> None:
        self._stop.set()
        self._resender.join()
        with self._session_lock:
            connected = self.session is not None
        if connected:
            self._close_session()
        # else: the connector is still blocked in zenoh.open (nothing reachable); it is a daemon

    def _close_session(self) -> None:
        if self._ack_subscriber is not None:
            self._ack_subscriber.undeclare()  # callback subscribers outlive their Python reference
            self._ack_subscriber = None
        self.session.close()


def run_agent(o: AgentConfig, fit: FitConfig = FitConfig()) -> int:
    """Run one agent until its source is published and acknowledged; the process exit code."""
    o.check_runnable()
    started = time.perf_counter()
    print(f"gmmap agent {o.robot} config: {summary(agent=o, fit=fit)}", file=sys.stderr, flush=True)
    if o.update_every is None:
        o = replace(o, update_every=default_update_every(o.source, o.rate))
    nodes = load_nodes(o.source, o.corrections, o.scans, rate=o.rate, update_every=o.update_every, poses=o.poses)
    if o.odometry_only:  # a robot without a SLAM back end: same nodes, odometry stays final
        nodes = [replace(n, corrected=None) for n in nodes]
    outbox = Outbox(o.outbox or Path("gmmap-data") / f"outbox-{o.robot}.db", o.fleet, o.robot)
    agent = Agent(o, outbox, zenoh_config("client", connect=o.zenoh_connect, config_file=o.zenoh_config), fit)
    try:
        from tqdm import tqdm

        with tqdm(total=len(nodes), desc=f"{o.robot} publish", unit="scan", file=sys.stderr, leave=False) as bar:
            updates = agent.publish_all(nodes, bar.update)
        published = time.perf_counter()
        pending = agent.wait_acknowledged(o.timeout)
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
        print(
            f"gmmap agent {o.robot}: {len(nodes)} scans{resumed} and {updates} pose-graph updates acknowledged; "
            f"published after {published - started:.1f} s, all acknowledged after "
            f"{time.perf_counter() - started:.1f} s",
            file=sys.stderr,
            flush=True,
        )
        return 0
    finally:
        agent.close()
        outbox.close()
