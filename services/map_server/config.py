"""The `server` section of the configuration: one map server process."""

from __future__ import annotations

from dataclasses import dataclass

from gmm_core.validation import require_count, require_number
from protocol import check_id
from services.zenoh_config import DEFAULT_ENDPOINT

SYNCHRONOUS = ("normal", "full")  # SQLite fsync policies: crash of the process / also power loss


@dataclass(frozen=True)
class ServerConfig:
    fleet: str = "default"  # the fleet this server holds; its keys are gmmap/<fleet>/...
    zenoh_listen: tuple[str, ...] | None = None  # endpoints to listen on; None: DEFAULT_ENDPOINT unless connecting
    zenoh_connect: tuple[str, ...] = ()  # routers or peers to connect to
    zenoh_config: str | None = None  # a Zenoh JSON5 file; scouting stays off unless it says so
    http: str = "127.0.0.1:8000"  # host:port of the HTTP API; '' for none
    data_dir: str = "./gmmap-data"  # the SQLite store
    synchronous: str = "normal"  # one of SYNCHRONOUS
    robot_quota_mb: float = 512.0  # MiB of stored scan bytes per robot; 0: no quota
    trace_threads: int | None = None  # tracer threads of the fleet map; None: one per core

    def __post_init__(self):
        check_id(self.fleet, "server.fleet")
        if self.synchronous.lower() not in SYNCHRONOUS:
            raise ValueError(f"server.synchronous: must be one of {', '.join(SYNCHRONOUS)}, got {self.synchronous!r}")
        require_number("server.robot_quota_mb", self.robot_quota_mb, positive=False)
        if self.trace_threads is not None:
            require_count("server.trace_threads", self.trace_threads)
        if not self.listen and not self.zenoh_connect:
            raise ValueError("server.zenoh_listen: a server needs an endpoint to listen on or to connect to")

    @property
    def listen(self) -> tuple[str, ...]:
        """The endpoints to listen on: a server that connects to a router need not listen."""
        if self.zenoh_listen is not None:
            return self.zenoh_listen
        return () if self.zenoh_connect else (DEFAULT_ENDPOINT,)
