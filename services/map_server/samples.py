"""What to sample of each node at each resolution, kept across queries.

A node's samples are traced as they are drawn (gmm_core.scan_trace) and never held: what is kept
is the node's model ready to sample (means, Cholesky factors, counts and weights per component,
gmm_core.sampling.ScanSamples), a few tens of bytes per component, so a query does not decode
the node's message again (held by the node, or read from the store when the node holds none).
In the node frame: a pose-graph update moves the samples at trace time (Eq. 2) and never redraws
them. Deterministic by the node's seed, so an evicted entry made again
draws the same samples.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable

from gmm_core import ScanModel
from gmm_core.sampling import ScanSamples, scan_samples
from protocol import ScanMessage, decode

from .nodes import Node, NodeKey

SAMPLE_CACHE_COMPONENTS = 2_000_000  # components kept ready to sample (about 150 MB in 2D, 240 MB in 3D)
# Decoded scan models kept for preparing a node's samples at the next resolution: a new node is asked
# for at every resolution the viewer's tiles use, within moments (a node holds only its wire bytes).
MODEL_CACHE_NODES = 512


class SampleCache:
    """Thread-safe LRU of ScanSamples, bounded by SAMPLE_CACHE_COMPONENTS components in all."""

    def __init__(self, samples_per_cell: float, stored_bytes: Callable[[NodeKey], bytes] | None = None):
        self.samples_per_cell = samples_per_cell
        self._stored_bytes = stored_bytes  # a node's message as stored, for nodes that hold neither model nor bytes
        self.components_held = 0
        self._lock = threading.Lock()
        self._samples: OrderedDict[tuple[NodeKey, float], ScanSamples] = OrderedDict()
        self._models: OrderedDict[NodeKey, ScanModel] = OrderedDict()

    def samples(self, node: Node, resolution: float) -> ScanSamples:
        key = (node.key, resolution)
        with self._lock:
            samples = self._samples.get(key)
            if samples is not None:
                self._samples.move_to_end(key)
                return samples
        # Made outside the lock; a thread that makes the same key meanwhile makes the same samples.
        samples = scan_samples(self.model(node), resolution, node.seed, self.samples_per_cell)
        with self._lock:
            if key not in self._samples:
                self._samples[key] = samples
                self.components_held += _components(samples)
            while self.components_held > SAMPLE_CACHE_COMPONENTS and len(self._samples) > 1:
                _, old = self._samples.popitem(last=False)
                self.components_held -= _components(old)
        return samples

    def model(self, node: Node) -> ScanModel:
        """The node's scan model in its node frame, never refitted: held, or decoded from its bytes
        (held or read from the store) once for all the resolutions asked within moments."""
        if node.held_model is not None:
            return node.held_model
        with self._lock:
            model = self._models.get(node.key)
            if model is not None:
                self._models.move_to_end(node.key)
                return model
        if node.raw is None and self._stored_bytes is None:
            raise LookupError(f"scan {node.key}: the node holds no model and there is no store to read it from")
        model = decode(node.raw if node.raw is not None else self._stored_bytes(node.key), expect=ScanMessage).model
        with self._lock:
            self._models[node.key] = model
            if len(self._models) > MODEL_CACHE_NODES:
                self._models.popitem(last=False)
        return model


def _components(samples: ScanSamples) -> int:
    return len(samples.occupied.counts) + len(samples.free.counts)
