"""Node-frame samples of the scan models, drawn once per (node, resolution) and kept across queries.

Samples stay in the node frame: a pose-graph update moves them at trace time (Eq. 2) and never
redraws them. They are deterministic by the node's seed, so an evicted entry drawn again has the
same bytes.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import NamedTuple

import numpy as np

from gmm_core import ScanModel
from gmm_core.sampling import scan_rays

from .nodes import Node, NodeKey

SAMPLE_CACHE_RAYS = 8_000_000  # node-frame samples kept across queries (about 300 MB)
# Decoded scan models kept for drawing a node's samples at the next resolution: a new node is asked
# for at every resolution the viewer's tiles use, within moments (a node holds only its wire bytes).
MODEL_CACHE_NODES = 512


class NodeRays(NamedTuple):
    """The rays of one scan model at one resolution (gmm_core.sampling.scan_rays)."""

    ends: np.ndarray  # (n, d) float64 ray end points in the node frame, metres
    weights: np.ndarray  # (n,) float64 quantised weights: sums of them are exact in float64
    is_hit: np.ndarray  # (n,) bool: ends in a hit (occupied mixture), else only adds misses (free mixture)


class SampleCache:
    """Thread-safe LRU of NodeRays, bounded by SAMPLE_CACHE_RAYS rays in all."""

    def __init__(self, samples_per_cell: float):
        self.samples_per_cell = samples_per_cell
        self.rays_held = 0
        self._lock = threading.Lock()
        self._rays: OrderedDict[tuple[NodeKey, float], NodeRays] = OrderedDict()
        self._models: OrderedDict[NodeKey, ScanModel] = OrderedDict()

    def rays(self, node: Node, resolution: float) -> NodeRays:
        key = (node.key, resolution)
        with self._lock:
            rays = self._rays.get(key)
            if rays is not None:
                self._rays.move_to_end(key)
                return rays
        # Drawn outside the lock; a thread that draws the same key meanwhile draws the same rays.
        rays = NodeRays(*scan_rays(self._model(node), resolution, node.seed, self.samples_per_cell))
        with self._lock:
            if key not in self._rays:
                self._rays[key] = rays
                self.rays_held += len(rays.ends)
            while self.rays_held > SAMPLE_CACHE_RAYS and len(self._rays) > 1:
                _, old = self._rays.popitem(last=False)
                self.rays_held -= len(old.ends)
        return rays

    def _model(self, node: Node) -> ScanModel:
        """The node's scan model, decoded once for all the resolutions asked within moments."""
        with self._lock:
            model = self._models.get(node.key)
            if model is not None:
                self._models.move_to_end(node.key)
                return model
        model = node.model
        with self._lock:
            self._models[node.key] = model
            if len(self._models) > MODEL_CACHE_NODES:
                self._models.popitem(last=False)
        return model
