"""`gmmap agent`: fit a robot's scans, publish them and its pose-graph updates until acknowledged.

Every message goes to the outbox (committed) before it is published; a resender thread
republishes whatever has waited longer than `resend_s` without an Ack, so after a server
restart or a reconnect everything gets through. The Zenoh session (client mode) opens in the
background: a robot out of reach keeps fitting and filling its outbox. A finite source ends
when the outbox is empty.
"""
from __future__ import annotations

import logging
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import zenoh

from gmm_core import fit_scan
from protocol import (Ack, PoseGraphUpdate, ProtocolError, ScanMessage, ack_key, decode, encode, poses_key,
                      scan_key)
from services.zenoh_config import zenoh_config

from .outbox import Outbox
from .sources import Node, fit_config, load_nodes

log = logging.getLogger("gmmap.agent")


@dataclass
class AgentOptions:
    robot: str
    source: str
    fleet: str = "default"
    zenoh_connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    zenoh_config: str | None = None
    corrections: str | None = None
    scans: str | None = None  # "A:B" slice of the (matched) scans
    rate: float = 0.0  # scans per second; 0: as fast as they are fitted
    outbox: str | None = None  # default ./gmmap-data/outbox-<robot>.db
    encoding: str = "q"
    update_every: int = 100  # scans between pose-graph updates (with --corrections)
    odometry_only: bool = False  # corrections select the scans, but no pose-graph updates are sent
    max_range: float = 10.0
    resend_s: float = 1.0
    timeout: float = 120.0  # seconds to wait for the last Acks once everything is published


class Agent:
    def __init__(self, options: AgentOptions, outbox: Outbox, config: zenoh.Config):
        self.options = options
        self.outbox = outbox
        self.session: zenoh.Session | None = None  # set once connected
        self._ack_subscriber = None
        self._send_lock = threading.Lock()  # one publisher at a time keeps scans before updates
        self._session_lock = threading.Lock()  # exactly one of _connect and close closes the session
        self._changed = threading.Condition()
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
            due = self.outbox.due(time.time() - self.options.resend_s)
            if due:
                log.info("sending %d unacknowledged messages again", len(due))
                self._publish(due)

    def _on_ack(self, sample: zenoh.Sample) -> None:
        try:
            ack = decode(sample.payload.to_bytes(), expect=Ack)
        except ProtocolError as error:
            log.warning("ignored a malformed ack: %s", error)
            return
        if ack.robot == self.options.robot and ack.fleet == self.options.fleet:
            self.outbox.acknowledge(ack.kind, ack.ids)
            with self._changed:
                self._changed.notify_all()

    # -- the run -------------------------------------------------------------------------------
    def publish_all(self, nodes: list[Node], progress=None) -> int:
        """Fit and send every node, with pose-graph updates; returns the updates sent."""
        o = self.options
        config = fit_config(nodes[0].scan.pose.dim, o.max_range) if nodes else None
        corrected = []
        updates = 0
        started = time.monotonic()
        for count, node in enumerate(nodes, 1):
            if o.rate > 0:
                time.sleep(max(0.0, started + (count - 1) / o.rate - time.monotonic()))
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


def run_agent(o: AgentOptions) -> int:
    started = time.perf_counter()
    nodes = load_nodes(o.source, o.corrections, o.scans)
    if o.odometry_only:  # a robot without a SLAM back end: same nodes, odometry stays final
        nodes = [replace(n, corrected=None) for n in nodes]
    outbox = Outbox(o.outbox or Path("gmmap-data") / f"outbox-{o.robot}.db", o.fleet, o.robot)
    agent = Agent(o, outbox, zenoh_config("client", connect=o.zenoh_connect, config_file=o.zenoh_config))
    try:
        from tqdm import tqdm

        with tqdm(total=len(nodes), desc=f"{o.robot} publish", unit="scan", file=sys.stderr, leave=False) as bar:
            updates = agent.publish_all(nodes, bar.update)
        published = time.perf_counter()
        pending = agent.wait_acknowledged(o.timeout)
        if pending:
            print(f"gmmap agent {o.robot}: {pending} messages not acknowledged after {o.timeout:.0f} s; "
                  f"they stay in {outbox.path} and are resent by the next run "
                  f"(is a server for fleet {o.fleet!r} reachable at {','.join(o.zenoh_connect)}?)",
                  file=sys.stderr, flush=True)
            return 1
        print(f"gmmap agent {o.robot}: {len(nodes)} scans and {updates} pose-graph updates acknowledged; "
              f"published after {published - started:.1f} s, all acknowledged after "
              f"{time.perf_counter() - started:.1f} s", file=sys.stderr, flush=True)
        return 0
    finally:
        agent.close()
        outbox.close()
