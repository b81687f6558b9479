"""What the Zenoh side and the HTTP app of one server process share."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .metrics import ServerMetrics

if TYPE_CHECKING:  # imported lazily: the API helper may import state before the others exist
    from .fleet_map import FleetMap
    from .store import Store


@dataclass
class ServerState:
    """One fleet served by one process.

    fleet_map: in-memory map layer (thread-safe); store: durable SQLite store (may be None in
    unit tests of the HTTP app); metrics: Prometheus counters of this server.
    """

    fleet: str
    fleet_map: FleetMap
    store: Store | None = None
    metrics: ServerMetrics = field(default_factory=ServerMetrics)
