"""Zenoh session configuration shared by the server, the router and the agents.

The library's defaults listen on every interface and scout by multicast; here nothing is
discovered implicitly: endpoints come from the command line or a config file, and scouting
stays off unless that file turns it on (docs/ARCHITECTURE.md, "Zenoh").
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence

import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"  # where a server or router listens, and agents connect, by default
RECONNECT_MS = 500  # peers retry lost links every 0.5 s (library default backs off to 4 s)
# The unicast transports the eclipse-zenoh wheel carries, by how an endpoint addresses them.
HOST_PORT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
PATH_PROTOCOLS = ("unixsock-stream",)
ENDPOINT_FORM = (
    f"PROTO/HOST:PORT (PROTO one of {', '.join(HOST_PORT_PROTOCOLS)}; [::1]:PORT for IPv6) "
    f"or {PATH_PROTOCOLS[0]}/PATH, e.g. {DEFAULT_ENDPOINT}"
)
_HOST_PORT = re.compile(r"(\[[^\]\s/]+\]|[^\s:/\[\]]+):(\d{1,5})")  # [IPv6]:PORT or HOST:PORT


def check_endpoints(field: str, endpoints: Sequence[str]) -> None:
    """A ValueError naming `field` for the first of `endpoints` that is not ENDPOINT_FORM.

    Checked before Zenoh sees them: its parser lets `tcp/localhost` or an unknown protocol
    through, and a client then retries such an endpoint forever without a word. Host names are
    not resolved (a router's name may resolve only once it is up).
    """
    for endpoint in endpoints:
        if not _is_endpoint(endpoint):
            raise ValueError(f"{field}: must be {ENDPOINT_FORM}, got {endpoint!r}")


def _is_endpoint(endpoint: str) -> bool:
    protocol, _, rest = endpoint.partition("/")
    address = re.split("[?#]", rest, maxsplit=1)[0]  # before the ?metadata and #config
    if protocol in HOST_PORT_PROTOCOLS:
        host_port = _HOST_PORT.fullmatch(address)
        if host_port is None or int(host_port[2]) > 65535:
            return False
    elif protocol not in PATH_PROTOCOLS or not address:
        return False
    try:  # the ?metadata and #config parts have Zenoh's own grammar
        zenoh.Config().insert_json5("listen/endpoints", json.dumps([endpoint]))
    except zenoh.ZError:
        return False
    return True


def _config_file(path: str) -> zenoh.Config:
    try:
        return zenoh.Config.from_file(path)
    except zenoh.ZError as error:  # drop the Rust source location Zenoh appends
        reason = re.sub(r"\s+at \S+\.rs:\d+\.?$", "", str(error))
        raise ValueError(f"--zenoh-config: cannot use {path}: {reason}") from None


def zenoh_config(
    mode: str, *, listen: Sequence[str] = (), connect: Sequence[str] = (), config_file: str | None = None
) -> zenoh.Config:
    """A Config in `mode` ("peer", "router" or "client") with explicit endpoints.

    Robot agents are clients: a leaf that reaches the fleet through one server or router. (Peers
    that meet only through a router are not bridged by it when gossip scouting is off, so an
    agent in peer mode behind `gmmap router` would never reach the server.)

    Values from `config_file` (JSON5) win over the defaults set here, except endpoints given
    on the command line, which are always applied. A bad endpoint or file is a ValueError.
    """
    check_endpoints("Zenoh listen endpoint", listen)
    check_endpoints("Zenoh connect endpoint", connect)
    config = _config_file(config_file) if config_file else zenoh.Config()
    library = zenoh.Config()

    def unset(key: str) -> bool:  # the file left the library's default in place
        return config.get_json(key) == library.get_json(key)

    def default(key: str, value) -> None:
        if unset(key):
            config.insert_json5(key, json.dumps(value))

    default("mode", mode)
    default("scouting/multicast/enabled", False)
    default("scouting/gossip/enabled", False)
    if mode == "client":  # keep trying until the router or server is up, and after losing it
        default("connect/timeout_ms", -1)
        default("connect/exit_on_failure", False)
    for side in ("connect", "listen"):
        default(
            f"{side}/retry",
            {"period_init_ms": RECONNECT_MS, "period_max_ms": RECONNECT_MS, "period_increase_factor": 1.0},
        )
    if listen:
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    elif unset("listen/endpoints"):
        config.insert_json5("listen/endpoints", "[]")  # never the library's "all interfaces"
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return config
