"""`gmmap sim`: a simulated fleet over real Zenoh: bytes, map AUROC vs ground truth, latencies."""

from __future__ import annotations

from services.cli_flags import (
    config_flag,
    fit_flags,
    http_client_flags,
    reconstruction_flags,
    resolve_config,
    server_tls_token_flags,
    setting,
)
from services.sim.world_names import WORLD_NAMES


def cmd_sim(args) -> int:
    from services.sim.run import run_sim

    return run_sim(resolve_config(args))


def add_sim(sub) -> None:
    p = sub.add_parser("sim", help="a simulated fleet over real Zenoh: bytes, map AUROC vs ground truth, latencies")
    setting(p, "--robots", "sim.robots", type=int, help="robots in the fleet, each a full agent")
    setting(p, "--world", "sim.world", choices=WORLD_NAMES, help="office, warehouse: 2D laser; mine: 3D 16-beam lidar")
    setting(p, "--duration", "sim.duration", type=float, help="simulated seconds each robot drives and publishes")
    setting(p, "--rate", "sim.rate", type=float, help="scans per simulated second per robot")
    setting(p, "--time-scale", "sim.time_scale", type=float, metavar="X", help="simulated seconds per wall second")
    setting(p, "--seed", "sim.seed", type=int, help="world, paths, odometry and sensor noise")
    setting(
        p,
        "--http-clients",
        "sim.http_clients",
        type=int,
        metavar="N",
        help="concurrent HTTP clients fetching map tiles meanwhile",
    )
    setting(p, "--report", "sim.report", metavar="DIR", help="write DIR/report.json, DIR/report.md and its PNG plots")
    server_tls_token_flags(p)  # the sim's own server on 127.0.0.1
    http_client_flags(p)  # its snapshot and tile clients
    fit_flags(p)  # the robots' fit
    reconstruction_flags(p)  # the server's
    config_flag(p)
    p.set_defaults(run=cmd_sim)
