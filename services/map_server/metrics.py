"""Prometheus metrics of one map server, in a registry of its own.

A per-server CollectorRegistry (not the global default) keeps two servers in one test
process from colliding on metric names.
"""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

TILE_ANSWER_KINDS = ("fresh", "updated", "stale", "coalesced", "shed")


class ServerMetrics:
    content_type = CONTENT_TYPE_LATEST

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.accepted = Counter("gmmap_messages_accepted", "Messages stored (or already held)", ["kind"], registry=r)
        self.rejected = Counter(
            "gmmap_messages_rejected",
            "Messages rejected at the boundary",
            ["kind", "reason"],
            registry=r,
        )
        self.bytes_received = Counter("gmmap_bytes_received", "Wire bytes of accepted messages", ["robot"], registry=r)
        self.stored_bytes = Gauge(
            "gmmap_robot_stored_bytes",
            "Wire bytes of the scans stored per robot (what the quota counts)",
            ["robot"],
            registry=r,
        )
        self.query_seconds = Histogram(
            "gmmap_query_seconds",
            "Occupancy query latency (HTTP and Zenoh)",
            registry=r,
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.15, 0.25, 0.5, 1, 2.5, 5),
        )
        self.cache_hits = Counter("gmmap_cache_hits", "Tile cache hits", registry=r)
        self.cache_misses = Counter("gmmap_cache_misses", "Tile cache misses (traced from scratch)", registry=r)
        self.cache_updates = Counter(
            "gmmap_cache_updates", "Stale cached tiles brought up to date (only new or moved scans traced)", registry=r
        )
        self.cache_stale = Counter(
            "gmmap_cache_stale",
            "Requests answered with a tile's previous state while another request updated it",
            registry=r,
        )
        self.cache_thinned = Counter(
            "gmmap_cache_thinned_updates",
            "Tile updates traced with server.busy_samples_per_cell while the tracers had other work",
            registry=r,
        )
        self.tile_answers = Counter(
            "gmmap_tile_answers",
            "HTTP occupancy answers by kind: fresh (cached, up to date), updated (traced for the request), stale "
            "(the previous state, while another request updates the tile or the tracers are saturated), coalesced "
            "(a recent state while every tracer is busy), shed (503: the tracers are saturated)",
            ["kind"],
            registry=r,
        )
        for kind in TILE_ANSWER_KINDS:
            self.tile_answers.labels(kind)
        self.tile_age = Histogram(
            "gmmap_tile_age_seconds",
            "X-Map-Age of HTTP occupancy answers: how long the state served had been out of date (0: up to date)",
            registry=r,
            buckets=(0, 0.05, 0.1, 0.25, 0.5, 1, 1.5, 2, 5),
        )
        self.tracer_queue = Gauge(
            "gmmap_tracer_queue_depth", "Trace parts waiting for a tracer thread (at the scrape)", registry=r
        )
        self.http_refused = Counter(
            "gmmap_http_refused",
            "HTTP requests refused: no bearer token (missing), a wrong one (invalid), a robot the token may not "
            "read (forbidden)",
            ["reason"],
            registry=r,
        )
        for reason in ("missing", "invalid", "forbidden"):
            self.http_refused.labels(reason)  # each series shows from the start, at 0

    def render(self) -> bytes:
        """The registry in Prometheus text exposition format."""
        return generate_latest(self.registry)

    def rejected_total(self) -> float:
        """Sum over all (kind, reason) labels — for tests and logs."""
        return sum(s.value for m in self.rejected.collect() for s in m.samples if s.name.endswith("_total"))
