"""Fetch the shared map over Zenoh: what a robot asks the map server's occupancy and point queryables."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import zenoh

from protocol import (
    MapQuery,
    MapReply,
    PointQuery,
    PointReply,
    ProtocolError,
    decode,
    encode,
    occupancy_key,
    points_key,
)


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


def query_points(
    session: zenoh.Session,
    fleet: str,
    points: np.ndarray | Sequence[Sequence[float]],
    resolution: float,
    robots: Sequence[str] | None = None,
    method: str = "auto",
    timeout: float = 10.0,
) -> PointReply:
    """The server's p(occupied) of the cell of size `resolution` centred on each of `points` (n, d),
    evaluated by `method`: analytic (the paper's local evaluation), mc, or auto (the cheaper)."""
    query = PointQuery(fleet, points, resolution, tuple(robots) if robots is not None else None, method)
    raw = _get(session, points_key(fleet), fleet, encode(query), timeout)
    return decode(raw, expect=PointReply, max_bytes=max(len(raw), 1))


def query_bytes(session: zenoh.Session, fleet: str, payload: bytes, timeout: float = 10.0) -> bytes:
    """The raw reply to an encoded MapQuery (for byte-exact comparisons)."""
    return _get(session, occupancy_key(fleet), fleet, payload, timeout)


def _get(session: zenoh.Session, key: str, fleet: str, payload: bytes, timeout: float) -> bytes:
    for reply in session.get(key, payload=payload, timeout=timeout):
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
        raise MapQueryError(reply.err.payload.to_string())
    raise MapQueryError(f"no map server for fleet {fleet!r} answered within {timeout} s")


__all__ = ["MapQueryError", "ProtocolError", "query_bytes", "query_occupancy", "query_points"]
