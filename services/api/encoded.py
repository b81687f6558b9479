"""Reply bodies of cached tiles, encoded once."""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np


class EncodedTiles:
    """Reply bodies of recent tiles: a cached tile is the same read-only array until it changes,
    so its PNG (the costliest part of a cached reply) is encoded once. One body per request (format,
    and a PNG's shade and variance; grid; robots), for the array it was made from; at most `max_bytes`
    in all."""

    def __init__(self, max_bytes: int = 64 << 20):
        self._max_bytes = max_bytes
        self._bytes = 0
        self._bodies: OrderedDict[tuple, tuple[np.ndarray, bytes]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: tuple, prob: np.ndarray) -> bytes | None:
        with self._lock:
            hit = self._bodies.get(key)
            if hit is None or hit[0] is not prob:
                return None
            self._bodies.move_to_end(key)
            return hit[1]

    def put(self, key: tuple, prob: np.ndarray, body: bytes) -> None:
        size = prob.nbytes + len(body)
        if size > self._max_bytes // 8:  # a large region: not worth holding
            return
        with self._lock:
            old = self._bodies.pop(key, None)
            if old is not None:
                self._bytes -= old[0].nbytes + len(old[1])
            self._bodies[key] = (prob, body)
            self._bytes += size
            while self._bytes > self._max_bytes:
                _, (p, b) = self._bodies.popitem(last=False)
                self._bytes -= p.nbytes + len(b)
