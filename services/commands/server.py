"""`gmmap server`: the map server: Zenoh ingest and queryable, SQLite store, HTTP API."""

from __future__ import annotations

import os
import sys

from services.cli_flags import (
    config_flag,
    fleet_id,
    reconstruction_flags,
    resolve_config,
    ros2_flags,
    server_http_flags,
    setting,
)
from services.commands.common import log_to_stderr
from services.zenoh_config import DEFAULT_ENDPOINT


def cmd_server(args) -> int:
    from services.map_server.server import run_server

    log_to_stderr(args.verbose)
    config = resolve_config(args)
    code = run_server(config.server, config.reconstruction, config.ros2)
    # The store is closed and every Ack sent: a worker thread still rendering a large PNG for a
    # client that will get no answer must not keep the process from exiting (SIGTERM within seconds).
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def add_server(sub) -> None:
    p = sub.add_parser("server", help="map server: Zenoh ingest and queryable, SQLite store, HTTP API")
    setting(p, "--fleet", "server.fleet", type=fleet_id)
    setting(
        p,
        "--zenoh-listen",
        "server.zenoh_listen",
        action="append",
        metavar="EP",
        help=f"endpoint to listen on (repeatable; default {DEFAULT_ENDPOINT}, none with --zenoh-connect)",
    )
    setting(
        p,
        "--zenoh-connect",
        "server.zenoh_connect",
        action="append",
        metavar="EP",
        help="router or peer to connect to (repeatable)",
    )
    setting(
        p,
        "--zenoh-config",
        "server.zenoh_config",
        metavar="FILE.json5",
        help="Zenoh config file (scouting stays off unless it says so)",
    )
    server_http_flags(p)
    setting(p, "--data-dir", "server.data_dir")
    setting(
        p,
        "--synchronous",
        "server.synchronous",
        choices=["normal", "full"],
        help="SQLite fsync policy: normal survives a crash of the process, full also power loss",
    )
    setting(
        p,
        "--robot-quota-mb",
        "server.robot_quota_mb",
        type=float,
        metavar="MIB",
        help="stored scan bytes per robot; scans beyond are refused with a Rejection (0: no quota)",
    )
    setting(
        p,
        "--trace-threads",
        "server.trace_threads",
        type=int,
        metavar="N",
        help="tracer threads that sample and trace tiles; a large update is split among them (default: one per core)",
    )
    setting(
        p,
        "--trace-processes",
        "server.trace_processes",
        action="store_true",
        help="trace tiles in a process per tracer thread, not sharing the server's interpreter lock (for servers "
        "with more than 2 cores; each process takes about 300 MiB with its own sample cache)",
    )
    setting(
        p,
        "--busy-samples-per-cell",
        "server.busy_samples_per_cell",
        type=float,
        metavar="N",
        help="Monte-Carlo samples per cell of tile updates begun while any tracer has work, refined once they are "
        "idle (0: always the reconstruction's; default 1 in 2D, 0.3 in 3D)",
    )
    setting(
        p,
        "--ros-map",
        "ros2.map_topic",
        metavar="TOPIC",
        help="publish the fleet map as nav_msgs/OccupancyGrid on this ROS 2 topic (and each robot's "
        "nav_msgs/Path on /<robot>/trajectory)",
    )
    setting(p, "--ros-map-resolution", "ros2.map_resolution", type=float, metavar="M", help="cell size of --ros-map")
    setting(p, "--ros-map-period", "ros2.map_period", type=float, metavar="S", help="at most one --ros-map per S s")
    setting(p, "--ros-map-z", "ros2.map_z", metavar="ZMIN,ZMAX", help="3D maps: the height band projected to --ros-map")
    ros2_flags(p)
    reconstruction_flags(p)
    config_flag(p)
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(run=cmd_server)
