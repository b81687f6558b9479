"""`gmmap token`: a new bearer token for the HTTP API (stdout), and its line for --http-tokens."""

from __future__ import annotations

from services.cli_flags import fleet_id


def _robot_ids(text: str) -> list[str]:
    return [fleet_id(robot) for robot in text.split(",")]


def cmd_token(args) -> int:
    from services.map_server.tokens import run_token

    return run_token(args.name, args.robots, args.add)


def add_token(sub) -> None:
    p = sub.add_parser("token", help="a new bearer token for the HTTP API (stdout), and its line for --http-tokens")
    p.add_argument("name", type=fleet_id, help="who the token is for, unique in the token file")
    p.add_argument("--robots", type=_robot_ids, metavar="ID,ID", help="read only these robots' map (default: all)")
    p.add_argument("--add", metavar="FILE", help="append the line to this token file (created mode 600)")
    p.set_defaults(run=cmd_token)
