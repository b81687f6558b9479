"""A Zenoh client on the map server that notes every scan, pose-graph update and Ack of a fleet."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import zenoh

from protocol import Ack, ProtocolError, decode, parse_key
from services.zenoh_config import zenoh_config


@dataclass(frozen=True)
class WireEvent:
    t: float  # epoch seconds when the tap saw it (at the server: publish + loopback)
    robot: str
    kind: str  # "scan", "poses" or "ack"
    size: int  # payload bytes
    ids: tuple[int, ...] = ()  # scan: (node,); ack: the acknowledged ids
    acked: str | None = None  # ack: what it acknowledges, "scan" or "poses"


class WireTap:
    def __init__(self, fleet: str, zenoh_port: int):
        self.events: list[WireEvent] = []
        self._lock = threading.Lock()
        self._published: set[tuple[str, int]] = set()
        self._stored: set[tuple[str, int]] = set()
        self._session = zenoh.open(zenoh_config("client", connect=[f"tcp/127.0.0.1:{zenoh_port}"]))
        self._subscriber = self._session.declare_subscriber(f"gmmap/{fleet}/**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        t = time.time()
        payload = sample.payload.to_bytes()
        try:
            _, robot, kind, node = parse_key(str(sample.key_expr))
            ack = decode(payload, expect=Ack) if kind == "ack" else None
        except ProtocolError:
            return
        if kind == "scan":
            event = WireEvent(t, robot, kind, len(payload), (node,))
        elif ack is not None:
            event = WireEvent(t, robot, kind, len(payload), ack.ids, ack.kind)
        else:
            event = WireEvent(t, robot, kind, len(payload))
        with self._lock:
            self.events.append(event)
            if kind == "scan":
                self._published.add((robot, node))
            elif ack is not None and ack.kind == "scan":
                self._stored.update((robot, i) for i in ack.ids)

    def counts(self) -> tuple[int, int]:
        """Distinct scans seen published, and acknowledged (stored)."""
        with self._lock:
            return len(self._published), len(self._stored)

    def stored_per_robot(self) -> dict[str, int]:
        with self._lock:
            out: dict[str, int] = {}
            for robot, _ in self._stored:
                out[robot] = out.get(robot, 0) + 1
            return out

    def close(self) -> None:
        self._subscriber.undeclare()  # callback subscribers outlive their Python reference
        self._session.close()
