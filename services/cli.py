"""The `gmmap` command line: a subcommand a module (services/commands/), shared flags in cli_flags.py."""

from __future__ import annotations

import argparse
import sys

from services.cli_flags import Parser
from services.commands.agent import add_agent
from services.commands.demo import add_demo
from services.commands.export import add_export
from services.commands.inspect import add_inspect
from services.commands.replay import add_replay
from services.commands.router import add_router
from services.commands.server import add_server
from services.commands.sim import add_sim
from services.commands.token import add_token


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="gmmap", description="Gaussian-mixture occupancy maps for robot fleets")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (add_replay, add_inspect, add_server, add_router, add_agent, add_sim, add_demo, add_export, add_token):
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "server.zenoh_listen", None) is not None:  # `--zenoh-listen ''`: listen on nothing
        setattr(args, "server.zenoh_listen", [e for e in getattr(args, "server.zenoh_listen") if e])
    try:
        return args.run(args)
    except (ValueError, OSError) as exc:  # DatasetError and ProtocolError are ValueErrors
        print(f"gmmap {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
