"""The `server` section of the configuration: one map server process."""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass

from gmm_core.validation import require_count, require_number
from protocol import check_id
from services.zenoh_config import DEFAULT_ENDPOINT, check_endpoints

SYNCHRONOUS = ("normal", "full")  # SQLite fsync policies: crash of the process / also power loss
HTTP_SECURITY_FLAGS = "--http-tls-cert CERT.pem --http-tls-key KEY.pem --http-tokens FILE"
HTTP_RISK = {  # what a non-loopback HTTP API without it risks
    "TLS and tokens": "anyone who reaches it reads the whole map (the facility's layout)",
    "tokens": "anyone who reaches it reads the whole map (the facility's layout)",
    "TLS": "the tokens and the map cross the network in the clear",
}


def split_address(address: str, field: str = "server.http") -> tuple[str, int]:
    """HOST:PORT -> (host, port): an empty host is 127.0.0.1, an IPv6 host is written [::1]:PORT."""
    host, colon, port = address.rpartition(":")
    if not colon or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{field}: must be HOST:PORT (port 0 to 65535; [::1]:PORT for IPv6), got {address!r}")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        raise ValueError(f"{field}: an IPv6 host is written in brackets, [{host}]:{port}, got {address!r}")
    return host or "127.0.0.1", int(port)


def is_loopback(host: str) -> bool:
    """Whether only this machine can reach `host`: 127.0.0.0/8, ::1 (also IPv4-mapped) and localhost.

    Other names are not resolved here (their address may change): they count as reachable from elsewhere.
    """
    if host.lower().rstrip(".") == "localhost":
        return True
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return False
    mapped = getattr(address, "ipv4_mapped", None)
    return (mapped or address).is_loopback


@dataclass(frozen=True)
class ServerConfig:
    fleet: str = "default"  # the fleet this server holds; its keys are gmmap/<fleet>/...
    zenoh_listen: tuple[str, ...] | None = None  # endpoints to listen on; None: DEFAULT_ENDPOINT unless connecting
    zenoh_connect: tuple[str, ...] = ()  # routers or peers to connect to
    zenoh_config: str | None = None  # a Zenoh JSON5 file; scouting stays off unless it says so
    http: str = "127.0.0.1:8000"  # host:port of the HTTP API; '' for none
    http_tls_cert: str | None = None  # PEM certificate (chain) of the HTTPS server; with http_tls_key
    http_tls_key: str | None = None  # its PEM private key
    http_tokens: str | None = None  # bearer-token file (docs/RELIABILITY.md, "Who may read"); None: no tokens
    http_insecure: bool = False  # serve a non-loopback address without TLS or tokens anyway
    data_dir: str = "./gmmap-data"  # the SQLite store
    synchronous: str = "normal"  # one of SYNCHRONOUS
    robot_quota_mb: float = 512.0  # MiB of stored scan bytes per robot; 0: no quota
    trace_threads: int | None = None  # tracer threads of the fleet map; None: one per core
    # Trace in a process per tracer thread (trace_workers.py) instead of in the server's threads, which
    # share its interpreter lock with ingest and HTTP: for a server with more cores than that lock lets
    # one process use (about 1.2 measured); each process costs about 300 MiB with its own sample cache.
    trace_processes: bool = False
    # Monte-Carlo samples per cell of the nodes a tile update begun while any tracer has work traces
    # (tile_updates.py), refined once the tracers are idle: a fraction of the cost, with more noise; None:
    # tile_updates.BUSY_SAMPLES_PER_CELL by the map's dimension (1 in 2D, 0.3 in 3D, against the default
    # 4); 0: every update with the reconstruction's samples per cell.
    busy_samples_per_cell: float | None = None

    def __post_init__(self):
        check_id(self.fleet, "server.fleet")
        if self.http:
            split_address(self.http)
        if self.synchronous.lower() not in SYNCHRONOUS:
            raise ValueError(f"server.synchronous: must be one of {', '.join(SYNCHRONOUS)}, got {self.synchronous!r}")
        require_number("server.robot_quota_mb", self.robot_quota_mb, positive=False)
        if self.trace_threads is not None:
            require_count("server.trace_threads", self.trace_threads)
        if self.busy_samples_per_cell is not None:
            require_number("server.busy_samples_per_cell", self.busy_samples_per_cell, positive=False)
        check_endpoints("server.zenoh_listen", self.zenoh_listen or ())
        check_endpoints("server.zenoh_connect", self.zenoh_connect)
        if not self.listen and not self.zenoh_connect:
            raise ValueError("server.zenoh_listen: a server needs an endpoint to listen on or to connect to")

    @property
    def listen(self) -> tuple[str, ...]:
        """The endpoints to listen on: a server that connects to a router need not listen."""
        if self.zenoh_listen is not None:
            return self.zenoh_listen
        return () if self.zenoh_connect else (DEFAULT_ENDPOINT,)

    @property
    def http_tls(self) -> bool:
        return bool(self.http_tls_cert)

    def check_http(self) -> None:
        """Refuse HTTP settings that are valid one by one but not together, before the server starts.

        Not in __post_init__: a config file and the flags are applied one after the other, and the file
        alone may lack what a flag adds (a key beside its certificate, --http-insecure beside 0.0.0.0).
        """
        if bool(self.http_tls_cert) != bool(self.http_tls_key):
            raise ValueError("server.http_tls_cert, server.http_tls_key: give both --http-tls-cert and --http-tls-key")
        if not self.http:
            if self.http_tls or self.http_tokens:
                raise ValueError("server.http: TLS or tokens are set but the HTTP API is off (--http '')")
            return
        host, _ = split_address(self.http)
        missing = self._http_missing()
        if missing and not is_loopback(host) and not self.http_insecure:
            raise ValueError(
                f"server.http: refusing to serve {self.http} without {missing}: it is not a loopback address, so "
                f"{HTTP_RISK[missing]}. Give {HTTP_SECURITY_FLAGS} (tokens from `gmmap token NAME`), or "
                "--http-insecure to serve it so anyway (a trusted network, or an authenticating proxy in front), "
                "or bind 127.0.0.1"
            )

    def _http_missing(self) -> str:
        """'TLS and tokens', 'TLS', 'tokens' or '': what the HTTP API lacks."""
        return " and ".join(w for w, given in (("TLS", self.http_tls), ("tokens", self.http_tokens)) if not given)

    def http_exposure(self) -> str | None:
        """A warning for a server that --http-insecure lets serve beyond loopback without TLS or tokens."""
        missing = self._http_missing() if self.http else ""
        if not missing or is_loopback(split_address(self.http)[0]):
            return None
        return f"--http-insecure: serving {self.http} without {missing}: {HTTP_RISK[missing]}"
