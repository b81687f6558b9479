"""The `gmmap` command line."""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from services.cli_flags import (
    Parser,
    config_flag,
    fit_flags,
    http_client_flags,
    keyframe_flags,
    reconstruction_flags,
    resolve_config,
    ros2_flags,
    server_http_flags,
    server_tls_token_flags,
    setting,
    source_flags,
    source_options,
)
from services.config import GmmapConfig
from services.sim.world_names import WORLD_NAMES
from services.zenoh_config import DEFAULT_ENDPOINT


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value >= 0:  # NaN too
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return value


def _progress_bars():
    from tqdm import tqdm

    bars = []

    def start(stage: str, total: int):
        bar = tqdm(total=total, desc=stage, unit="scan", file=sys.stderr, leave=False)
        bars.append(bar)
        return bar.update

    return start, bars


def _read_source(args, config: GmmapConfig, keep_fraction: float = 1.0, seed: int = 0, **options) -> tuple[list, int]:
    """The scans of the source that the keyframe policy keeps, and how many were read."""
    from tqdm import tqdm

    from services.datasets import count_scans, read_scans
    from services.datasets.keyframes import keyframes

    options |= source_options(args)
    total = count_scans(args.log, args.format, **options)
    scans = read_scans(args.log, args.format, keep_fraction=keep_fraction, seed=seed, **options)
    with tqdm(scans, total=total, desc="read", unit="scan", file=sys.stderr, leave=False) as bar:
        kept = list(keyframes(bar, config.keyframe, lambda s: (s.pose, s.stamp)))
        return kept, bar.n


def cmd_replay(args) -> int:
    from services.render import occupancy_png
    from services.replay import DEFAULT_RESOLUTION, MAX_REPLAY_CELLS, replay, replay_grid

    t0 = time.perf_counter()
    config = resolve_config(args)
    options = {} if args.origin is None else {"origin": tuple(args.origin)}
    scans, read = _read_source(args, config, args.keep_fraction, args.seed, **options)
    fit = config.fit.for_dimension(scans[0].pose.dim if scans else 2)
    resolution = args.resolution
    if scans and resolution is None:  # said before the work: an outdoor lidar's extent is coarsened
        resolution = replay_grid(scans, fit.max_range, None, args.bbox).resolution
        if resolution != DEFAULT_RESOLUTION:
            print(
                f"gmmap replay: mapping at {resolution:g} m, the finest of {DEFAULT_RESOLUTION:g} m doubled that keeps "
                f"the grid within {MAX_REPLAY_CELLS:,} cells (--resolution and --bbox choose)",
                file=sys.stderr,
            )
    start, bars = _progress_bars()
    result = replay(
        scans,
        resolution=resolution,
        bbox=args.bbox,
        method=args.method,
        config=fit,
        seed=args.seed,
        reconstruction=config.reconstruction,
        encoding=args.encoding,
        progress=start,
    )
    for bar in bars:
        bar.close()
    g = result.grid
    if args.out:
        np.savez_compressed(
            args.out,
            prob=result.prob,
            hits=result.hits,
            misses=result.misses,
            origin=g.origin,
            resolution=np.float64(g.resolution),
        )
    if args.png:
        with open(args.png, "wb") as f:
            f.write(occupancy_png(result.prob, config.reconstruction.variance))
    view = " (top-down projection)" if g.dim == 3 else ""
    print(
        f"{result.scans} scans (keyframes of {read} read), {result.components} components, "
        f"grid {'x'.join(map(str, g.shape))} "
        f"at {g.resolution} m from {np.round(g.origin, 3).tolist()}, {time.perf_counter() - t0:.1f} s"
        + (f"; wrote {args.out}" if args.out else "")
        + (f"; wrote {args.png}{view}" if args.png else "")
    )
    return 0


def cmd_inspect(args) -> int:
    import json

    from protocol import encode
    from services.replay import fit_scans, load_fit_kernels, scan_message

    settings = resolve_config(args)
    scans, read = _read_source(args, settings)
    dim = scans[0].pose.dim if scans else 2
    config = settings.fit.for_dimension(dim)
    start, bars = _progress_bars()
    # fit_s: wall seconds of fitting alone (numba threads as NUMBA_NUM_THREADS sets them), with the
    # fit's kernels loaded first, as a running agent has them (kernels_s).
    kernels_s = load_fit_kernels(scans[0], config) if scans else 0.0
    fit_start = time.perf_counter()
    models = fit_scans(scans, config, start("fit", len(scans)))
    fit_s = time.perf_counter() - fit_start
    for bar in bars:
        bar.close()
    sizes = [len(encode(scan_message(m, s), args.encoding)) for m, s in zip(models, scans)]
    # Raw: float32 per beam in 2D (ranges), float32 x, y, z per point in 3D.
    raw = [4 * (len(s.hits) + len(s.no_return)) * (1 if dim == 2 else 3) for s in scans]
    components = sum(m.n_components for m in models)
    report = {
        "scans": len(scans),  # after keyframing
        "scans_read": read,
        "dimension": dim,
        "encoding": args.encoding,
        "components": components,
        "fit_s": fit_s,
        "kernels_s": kernels_s,
        "bytes": sum(sizes),
        "raw_bytes": sum(raw),
        "bytes_per_component": sum(sizes) / max(components, 1),
        "bytes_per_scan": sum(sizes) / max(len(scans), 1),
        "raw_bytes_per_scan": sum(raw) / max(len(scans), 1),
        "ratio_to_raw": sum(sizes) / max(sum(raw), 1),
    }
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        for key, value in report.items():
            print(f"{key:>20}: {value:.2f}" if isinstance(value, float) else f"{key:>20}: {value}")
    return 0


def _logging(verbose: bool) -> None:
    import logging

    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        stream=sys.stderr,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )


def cmd_server(args) -> int:
    from services.map_server.server import run_server

    _logging(args.verbose)
    config = resolve_config(args)
    code = run_server(config.server, config.reconstruction, config.ros2)
    # The store is closed and every Ack sent: a worker thread still rendering a large PNG for a
    # client that will get no answer must not keep the process from exiting (SIGTERM within seconds).
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def cmd_router(args) -> int:
    from services.router import run_router

    _logging(args.verbose)
    return run_router(args.listen or [DEFAULT_ENDPOINT], args.connect or [], args.zenoh_config)


def cmd_agent(args) -> int:
    from services.agent.run import run_agent

    _logging(args.verbose)
    config = resolve_config(args)
    if config.agent.source == "ros2":
        from services.ros2.live import run_ros2_agent

        return run_ros2_agent(config)
    return run_agent(config.agent, config.fit, config.keyframe)


def cmd_sim(args) -> int:
    from services.sim.run import run_sim

    return run_sim(resolve_config(args))


def cmd_demo(args) -> int:
    from services.sim.demo import run_demo

    config = resolve_config(args)
    return run_demo(config.server, config.sim, args.duration)


def cmd_token(args) -> int:
    from services.map_server.tokens import run_token

    return run_token(args.name, args.robots, args.add)


def cmd_export(args) -> int:
    from services.export.command import run_export

    config = resolve_config(args)
    return run_export(
        args.url,
        args.from_npz,
        args.format,
        args.bbox,
        args.resolution,
        config.reconstruction.variance,
        args.out,
        config.sim.http_token,
        config.sim.http_ca,
    )


def _fleet_id(text: str) -> str:
    from protocol import ProtocolError, check_id

    try:
        return check_id(text, "id")
    except ProtocolError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _robot_ids(text: str) -> list[str]:
    return [_fleet_id(robot) for robot in text.split(",")]


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="gmmap", description="Gaussian-mixture occupancy maps for robot fleets")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("replay", help="fit and reconstruct a log offline; write the map as npz and PNG")
    source_flags(p)
    keyframe_flags(p)
    p.add_argument(
        "--resolution",
        type=float,
        default=None,
        help="cell size, m (default 0.05, doubled while the grid would hold over 64 M cells)",
    )
    p.add_argument(
        "--bbox",
        type=_floats,
        default=None,
        help="xmin,ymin,xmax,ymax or xmin,ymin,zmin,xmax,ymax,zmax; default the data's extent",
    )
    p.add_argument("--keep-fraction", type=float, default=1.0, help="keep this seeded fraction of the beams")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--method",
        choices=["mc", "analytic", "raw"],
        default="mc",
        help="mc: Monte Carlo (Eq. 11); analytic: per-cell evidence, Eq. 5/10 (2D); raw: counting grid",
    )
    fit_flags(p)
    reconstruction_flags(p)
    p.add_argument("--origin", type=_floats, default=None, help="sensor origin x,y,z of an xyz file")
    p.add_argument(
        "--encoding",
        choices=["q", "f32", "none"],
        default="q",
        help="pass every scan model through this wire encoding first (default q)",
    )
    p.add_argument("--out", default=None, help="map.npz")
    p.add_argument("--png", default=None, help="map.png")
    config_flag(p)
    p.set_defaults(run=cmd_replay)

    p = sub.add_parser("inspect", help="fit a log and report encoded bytes against the raw scans")
    source_flags(p)
    keyframe_flags(p)
    p.add_argument("--encoding", choices=["q", "f32"], default="q")
    fit_flags(p)
    p.add_argument("--json", action="store_true")
    config_flag(p)
    p.set_defaults(run=cmd_inspect)

    p = sub.add_parser("server", help="map server: Zenoh ingest and queryable, SQLite store, HTTP API")
    setting(p, "--fleet", "server.fleet", type=_fleet_id)
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

    p = sub.add_parser("router", help="a Zenoh router (Python library), for setups without zenohd")
    p.add_argument("--listen", action="append", metavar="EP", help=f"default {DEFAULT_ENDPOINT} (repeatable)")
    p.add_argument("--connect", action="append", metavar="EP", help="other routers (repeatable)")
    p.add_argument("--zenoh-config", metavar="FILE.json5")
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(run=cmd_router)

    p = sub.add_parser("agent", help="robot agent: fit scans, publish them and pose-graph updates until acknowledged")
    setting(p, "--robot", "agent.robot", type=_fleet_id, help="required, here or in --config")
    setting(p, "--fleet", "agent.fleet", type=_fleet_id)
    setting(
        p,
        "--zenoh-connect",
        "agent.zenoh_connect",
        action="append",
        metavar="EP",
        help=f"default {DEFAULT_ENDPOINT} (repeatable)",
    )
    setting(p, "--zenoh-config", "agent.zenoh_config", metavar="FILE.json5")
    setting(
        p,
        "--source",
        "agent.source",
        metavar="FORMAT:PATH|sim:WORLD:INDEX:ROBOTS[:SEED]",
        help="a log (FORMAT: carmen, kurt3d, xyz, pcd, ply, kitti or rosbag; guessed when left out), robot INDEX "
        "of a simulated fleet (needs --scans A:B), or ros2: live ROS 2 topics over Zenoh until SIGINT/SIGTERM "
        "(--scan-topic, --odom-topic, --path-topic, --ros-*); required, here or in --config",
    )
    setting(
        p,
        "--corrections",
        "agent.corrections",
        metavar="PATH",
        help="corrected CARMEN log: publish odometry poses, then these as pose-graph updates",
    )
    setting(p, "--poses", "agent.poses", metavar="FILE", help="pcd, ply, kitti source: poses file, KITTI or TUM layout")
    setting(
        p, "--scan-topic", "agent.scan_topic", metavar="T", help="rosbag or ros2 source: LaserScan or PointCloud2 topic"
    )
    setting(p, "--pose-topic", "agent.pose_topic", metavar="T", help="rosbag source: Odometry or PoseStamped topic")
    setting(
        p,
        "--odom-topic",
        "ros2.odom_topic",
        metavar="T",
        help="ros2 source: nav_msgs/Odometry of the robot body (default: poses from /tf and /tf_static)",
    )
    setting(
        p,
        "--path-topic",
        "ros2.path_topic",
        metavar="T",
        help="ros2 source: nav_msgs/Path of a SLAM back end's optimised poses, sent as pose-graph updates",
    )
    ros2_flags(p)
    keyframe_flags(p)
    setting(p, "--scans", "agent.scans", metavar="A:B", help="slice of the (matched) scans; node ids stay global")
    setting(p, "--rate", "agent.rate", type=float, help="scans per second (0: as fast as fitted)")
    setting(
        p, "--outbox", "agent.outbox", metavar="PATH", help="durable outbox (default ./gmmap-data/outbox-<robot>.db)"
    )
    setting(p, "--encoding", "agent.encoding", choices=["q", "f32"])
    setting(
        p,
        "--update-every",
        "agent.update_every",
        type=int,
        metavar="N",
        help="scans between pose-graph updates (0: only at the end; default 100, "
        "or a sim source's loop-closure period of 10 s)",
    )
    setting(
        p,
        "--odometry-only",
        "agent.odometry_only",
        action="store_true",
        help="with --corrections: publish the matched scans but no pose-graph updates",
    )
    fit_flags(p)
    setting(
        p,
        "--resend",
        "agent.resend_s",
        type=float,
        metavar="S",
        help="resend what is unacknowledged after at least S s (longer when Acks come slowly, "
        "doubling with each resend)",
    )
    setting(
        p,
        "--timeout",
        "agent.timeout",
        type=float,
        metavar="S",
        help="after publishing, give up (exit 1) once S s pass without an acknowledgement",
    )
    setting(
        p,
        "--keep-acked-mb",
        "agent.keep_acked_mb",
        type=float,
        metavar="MIB",
        help="acknowledged messages the outbox keeps, so a server that lost them gets them again",
    )
    config_flag(p)
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(run=cmd_agent)

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

    p = sub.add_parser(
        "export", help="a map as a ROS map_server PGM + YAML, an OctoMap .bt or a PLY cloud, from a server or an npz"
    )
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--url", metavar="http://HOST:PORT", help="a map server's HTTP API")
    source.add_argument("--from", dest="from_npz", metavar="MAP.npz", help="a map written by `gmmap replay --out`")
    p.add_argument(
        "--format",
        choices=["pgm", "bt", "ot", "ply"],
        required=True,
        help="pgm: PATH.pgm + PATH.yaml for ROS map_server and Nav2 (3D: seen from above); bt: OctoMap binary tree "
        "(3D maps, classes); ot: OctoMap full tree (3D maps, the MAP log-odds); ply: occupied cell centres with "
        "their probability",
    )
    p.add_argument(
        "--bbox",
        type=_floats,
        default=None,
        help="xmin,ymin,xmax,ymax or xmin,ymin,zmin,xmax,ymax,zmax; default the whole map",
    )
    p.add_argument(
        "--resolution",
        type=float,
        default=None,
        help="cell size, m: --url default 0.1 (bt, ot: on OctoMap's voxels); --from: the npz's, which is not resampled",
    )
    setting(
        p,
        "--variance",
        "reconstruction.variance",
        type=float,
        help="sigma^2 of Eq. 12: cells are free, occupied or unknown by its dead band",
    )
    p.add_argument("--out", required=True, metavar="PATH", help="PATH.pgm and PATH.yaml, PATH.bt, PATH.ot or PATH.ply")
    http_client_flags(p)  # --url with TLS and tokens
    config_flag(p)
    p.set_defaults(run=cmd_export)

    p = sub.add_parser("token", help="a new bearer token for the HTTP API (stdout), and its line for --http-tokens")
    p.add_argument("name", type=_fleet_id, help="who the token is for, unique in the token file")
    p.add_argument("--robots", type=_robot_ids, metavar="ID,ID", help="read only these robots' map (default: all)")
    p.add_argument("--add", metavar="FILE", help="append the line to this token file (created mode 600)")
    p.set_defaults(run=cmd_token)
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
