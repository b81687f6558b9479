"""`gmmap demo`: a map server and three simulated robots in the office; the viewer shows the map grow."""

from __future__ import annotations

import argparse

from services.cli_flags import http_client_flags, resolve_config, server_http_flags


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value >= 0:  # NaN too
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return value


def cmd_demo(args) -> int:
    from services.sim.demo import run_demo

    config = resolve_config(args)
    return run_demo(config.server, config.sim, args.duration)


def add_demo(sub) -> None:
    p = sub.add_parser(
        "demo", help="a map server and three simulated robots in the office; the viewer shows the map grow"
    )
    p.add_argument(
        "--duration",
        type=_seconds,
        default=0.0,
        help="seconds the robots drive, then everything stops; 0: until Ctrl-C",
    )
    server_http_flags(p)  # where the viewer is served, and how it is secured
    http_client_flags(p)  # the demo's own progress reads
    p.set_defaults(run=cmd_demo, config=None)
