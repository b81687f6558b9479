"""`gmmap router`: a Zenoh router (Python library), for setups without zenohd."""

from __future__ import annotations

from services.commands.common import log_to_stderr
from services.zenoh_config import DEFAULT_ENDPOINT


def cmd_router(args) -> int:
    from services.router import run_router

    log_to_stderr(args.verbose)
    return run_router(args.listen or [DEFAULT_ENDPOINT], args.connect or [], args.zenoh_config)


def add_router(sub) -> None:
    p = sub.add_parser("router", help="a Zenoh router (Python library), for setups without zenohd")
    p.add_argument("--listen", action="append", metavar="EP", help=f"default {DEFAULT_ENDPOINT} (repeatable)")
    p.add_argument("--connect", action="append", metavar="EP", help="other routers (repeatable)")
    p.add_argument("--zenoh-config", metavar="FILE.json5")
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(run=cmd_router)
