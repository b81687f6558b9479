"""What to sample of each node at each resolution, kept across queries.

A node's samples are traced as they are drawn (gmm_core.scan_trace) and never held: what is kept
is the node's model ready to sample, once for every resolution (gmm_core.sampling.ScanSampler:
means, Cholesky factors, principal deviations, expected points per component, about 70 bytes a
component in 2D), and per resolution (and samples per cell) asked the counts, offsets and weights
(24 bytes a component), so a query neither decodes the node's message (held by the node, or read from the
store when the node holds none) nor repeats its linear algebra. In the node frame: a pose-graph
update moves the samples at trace time (Eq. 2) and never redraws them. Deterministic by the
node's seed, so an evicted entry made again draws the same samples. For the analytic evidence of
point queries (services/api/points.py) an entry also keeps the node's components with their
covariances decomposed (gmm_core.analytic.components.NodeComponents, about 130 bytes a component in
3D), made the first time a point query reaches the node.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

from gmm_core import ScanModel
from gmm_core.analytic.components import NodeComponents
from gmm_core.sampling import ScanSampler, ScanSamples
from protocol import ScanMessage, decode

from .nodes import Node, NodeKey

SAMPLE_CACHE_BYTES = 256 << 20  # nodes ready to sample, with their per-resolution counts


@dataclass
class _Entry:
    sampler: ScanSampler | None = None  # None until the node is first traced
    at: dict[tuple[float, float], ScanSamples] = field(default_factory=dict)  # by (resolution, samples per cell)
    components: NodeComponents | None = None  # None until a point query first reaches the node
    nbytes: int = 0


class SampleCache:
    """Thread-safe LRU of nodes ready to sample, bounded by SAMPLE_CACHE_BYTES in all."""

    def __init__(self, samples_per_cell: float, stored_bytes: Callable[[NodeKey], bytes] | None = None):
        self.samples_per_cell = samples_per_cell
        self._stored_bytes = stored_bytes  # a node's message as stored, for nodes that hold neither model nor bytes
        self.bytes_held = 0
        self._lock = threading.Lock()
        self._entries: OrderedDict[NodeKey, _Entry] = OrderedDict()

    def samples(self, node: Node, resolution: float, samples_per_cell: float | None = None) -> ScanSamples:
        """The node's samples at `resolution`, `samples_per_cell` (default: the cache's)."""
        at = (resolution, self.samples_per_cell if samples_per_cell is None else samples_per_cell)
        with self._lock:
            entry = self._entries.get(node.key)
            sampler = None if entry is None else entry.sampler
            if entry is not None:
                self._entries.move_to_end(node.key)
                samples = entry.at.get(at)
                if samples is not None:
                    return samples
        # Made outside the lock; a thread that makes the same entry meanwhile makes the same samples.
        if sampler is None:
            sampler = ScanSampler.of(self.model(node), node.seed, self.samples_per_cell)
        samples = sampler.at(*at)
        with self._lock:
            held = self._held(node.key)
            if held.sampler is None:
                held.sampler = sampler
                self._count(held, sampler.nbytes)
            if at not in held.at:
                held.at[at] = samples
                self._count(held, _nbytes(samples))
            self._evict()
        return samples

    def components(self, node: Node) -> NodeComponents:
        """The node's components in its node frame, decomposed (for the analytic evidence)."""
        with self._lock:
            entry = self._entries.get(node.key)
            if entry is not None:
                self._entries.move_to_end(node.key)
                if entry.components is not None:
                    return entry.components
        made = NodeComponents.of(self.model(node))  # outside the lock, as samples
        with self._lock:
            held = self._held(node.key)
            if held.components is None:
                held.components = made
                self._count(held, made.nbytes)
            self._evict()
            return held.components

    def _held(self, key: NodeKey) -> _Entry:
        """The entry of `key`, a new one if there is none (evicted meanwhile); under the lock."""
        held = self._entries.get(key)
        if held is None:
            held = self._entries[key] = _Entry()
        return held

    def _count(self, entry: _Entry, nbytes: int) -> None:
        entry.nbytes += nbytes
        self.bytes_held += nbytes

    def prime(self, key: NodeKey, seed: int, model: ScanModel) -> None:
        """Make node `key` ready to sample from its model at hand (ingest decoded it to check it), so
        the first tile to trace it neither reads nor decodes it again."""
        sampler = ScanSampler.of(model, seed, self.samples_per_cell)
        entry = _Entry(sampler, nbytes=sampler.nbytes)
        with self._lock:
            if key in self._entries:
                return
            self._entries[key] = entry
            self.bytes_held += entry.nbytes
            self._evict()

    def _evict(self) -> None:
        """Drop the least recently used nodes over SAMPLE_CACHE_BYTES (under the lock)."""
        while self.bytes_held > SAMPLE_CACHE_BYTES and len(self._entries) > 1:
            _, old = self._entries.popitem(last=False)
            self.bytes_held -= old.nbytes

    def model(self, node: Node) -> ScanModel:
        """The node's scan model in its node frame, never refitted: held, or decoded from its bytes
        (held, or read from the store)."""
        if node.held_model is not None:
            return node.held_model
        if node.raw is None and self._stored_bytes is None:
            raise LookupError(f"scan {node.key}: the node holds no model and there is no store to read it from")
        return decode(node.raw if node.raw is not None else self._stored_bytes(node.key), expect=ScanMessage).model


def _nbytes(samples: ScanSamples) -> int:
    return sum(m.counts.nbytes + m.offsets.nbytes + m.weights.nbytes for m in (samples.occupied, samples.free))
