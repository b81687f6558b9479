"""`gmmap router`: a Zenoh router from the Python library, for setups without `zenohd`."""

from __future__ import annotations

import sys

import zenoh

from services.stopping import StopSignal
from services.zenoh_config import zenoh_config


def run_router(listen: list[str], connect: list[str] = (), config_file: str | None = None) -> int:
    config = zenoh_config("router", listen=listen, connect=connect, config_file=config_file)  # refused first
    stop = StopSignal()
    try:
        session = zenoh.open(config)
    except zenoh.ZError as error:  # an endpoint in use or a TLS listener without its key: refused, exit 2
        raise OSError(f"cannot open the Zenoh session: {error}") from None
    print(f"gmmap router ready: {session.zid()} listening on {','.join(listen)}", file=sys.stderr, flush=True)
    stop.wait()
    session.close()
    return 0
