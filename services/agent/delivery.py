"""How an agent's messages reach the map server: every message goes to the outbox (committed)
before it is published; a resender thread republishes what has gone unanswered, so after a server
restart or a reconnect everything gets through. The resend timeout follows the measured Ack round
trip (TCP's estimator, RFC 6298, never below `resend_s`) and doubles with every further sending of a
message: a server that is slow but alive is not buried in copies of what it is still storing. The
Zenoh session (client mode) opens in the background: a robot out of reach keeps fitting and filling
its outbox.
"""

from __future__ import annotations

import logging
import threading
import time

import zenoh

from protocol import Ack, ProtocolError, Rejection, StoreInventory, ack_key, decode, inventory_key, scan_key

from .config import AgentConfig
from .outbox import Outbox

log = logging.getLogger("gmmap.agent")

# s without any answer while messages are in flight before they count as lost (a server that is
# slow but answering is never resent to; one that restarted is seen at once by its subscription)
SILENCE_S = 10.0


class Delivery:
    """The outbox, the Zenoh session and the threads that deliver what the outbox holds (the part of an
    Agent, agent.py, that neither fits nor decides what to send)."""

    def __init__(self, options: AgentConfig, outbox: Outbox, config: zenoh.Config):
        self.options = options
        self.outbox = outbox
        self._owns_outbox = False  # Agent.open made it, so close closes it
        self.session: zenoh.Session | None = None  # set once connected
        self._ack_subscriber = None
        self._send_lock = threading.Lock()  # one publisher at a time keeps scans before updates
        self._session_lock = threading.Lock()  # exactly one of _connect and close closes the session
        self._changed = threading.Condition()
        self.refused: Rejection | None = None  # the server's last refusal for good, if any
        self.store: str | None = None  # the store this agent reports to, from its inventory
        # {store that had acknowledged them: messages sent again}, because the store reported to lacked them
        self.requeued: dict[str, int] = {}
        self.lost: set[int] = set()  # acknowledged nodes the store lacks and whose bytes are gone: refit
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

    # -- waiting and closing -------------------------------------------------------------------
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
