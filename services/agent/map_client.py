"""Fetch the shared map over Zenoh: what a robot asks the map server's occupancy queryable."""

from __future__ import annotations

from collections.abc import Sequence

import zenoh

from protocol import MapQuery, MapReply, ProtocolError, decode, encode, occupancy_key


class MapQueryError(RuntimeError):
    """The server answered with an error, or nobody answered in time."""


def query_occupancy(
    session: zenoh.Session,
    fleet: str,
    lo: Sequence[float],
    hi: Sequence[float],
    resolution: float,
    robots: Sequence[str] | None = None,
    timeout: float = 10.0,
) -> MapReply:
    """The server's occupancy grid of the box [lo, hi] at `resolution` (MapReply)."""
    query = MapQuery(fleet, lo, hi, resolution, tuple(robots) if robots is not None else None)
    raw = query_bytes(session, fleet, encode(query), timeout)
    return decode(raw, expect=MapReply, max_bytes=max(len(raw), 1))


def query_bytes(session: zenoh.Session, fleet: str, payload: bytes, timeout: float = 10.0) -> bytes:
    """The raw reply to an encoded MapQuery (for byte-exact comparisons)."""
    for reply in session.get(occupancy_key(fleet), payload=payload, timeout=timeout):
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
        raise MapQueryError(reply.err.payload.to_string())
    raise MapQueryError(f"no map server for fleet {fleet!r} answered within {timeout} s")


__all__ = ["MapQueryError", "ProtocolError", "query_bytes", "query_occupancy"]
