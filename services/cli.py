"""The `gmmap` command line."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from services.config import GmmapConfig, load_config
from services.sim.world_names import WORLD_NAMES
from services.zenoh_config import DEFAULT_ENDPOINT

DEFAULTS = GmmapConfig()


def _setting(p: argparse.ArgumentParser, flag: str, key: str, **kwargs) -> None:
    """A flag that sets field `key` ("section.field") of the configuration; its default is the
    section's own, shown in the help, and applies only when neither the flag nor --config sets it."""
    section, name = key.split(".")
    default = getattr(getattr(DEFAULTS, section), name)
    if kwargs.get("action") != "store_true":
        kwargs.setdefault("metavar", None if "choices" in kwargs else flag.lstrip("-").upper().replace("-", "_"))
        if kwargs.get("action") != "append" and default is not None:
            kwargs["help"] = f"{kwargs.get('help', '')} (default {default})".strip()
    p.add_argument(flag, dest=key, default=argparse.SUPPRESS, **kwargs)


def _config_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        metavar="FILE",
        default=None,
        help="a TOML or YAML file of [fit], [reconstruction], [server], [agent], [sim] settings; "
        "flags given here win over it",
    )


def _fit_flags(p: argparse.ArgumentParser) -> None:
    _setting(p, "--max-range", "fit.max_range", type=float, help="where no-return beams end, m")
    _setting(
        p, "--points-per-component", "fit.points_per_component", type=float, help="about this many points per component"
    )
    _setting(
        p,
        "--component-size",
        "fit.component_size",
        type=float,
        metavar="M",
        help="at most one component per occupied cell of this size, m (default: none in 2D, 1.0 in 3D)",
    )
    _setting(p, "--max-components", "fit.max_components", type=int, metavar="K", help="per mixture")


def resolve_config(args) -> GmmapConfig:
    """--config, then the flags that were given, over the defaults."""
    overrides: dict[str, dict] = {}
    for key, value in vars(args).items():
        if "." in key:
            section, name = key.split(".")
            overrides.setdefault(section, {})[name] = value
    return load_config(args.config, overrides)


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _progress_bars():
    from tqdm import tqdm

    bars = []

    def start(stage: str, total: int):
        bar = tqdm(total=total, desc=stage, unit="scan", file=sys.stderr, leave=False)
        bars.append(bar)
        return bar.update

    return start, bars


def cmd_replay(args) -> int:
    from services.datasets import count_scans, read_scans
    from services.render import occupancy_png
    from services.replay import replay

    t0 = time.perf_counter()
    options = {}
    if args.origin is not None:
        options["origin"] = tuple(args.origin)
    if args.poses is not None:
        options["poses"] = args.poses
    from tqdm import tqdm

    total = count_scans(args.log, args.format)
    scans = list(
        tqdm(
            read_scans(args.log, args.format, keep_fraction=args.keep_fraction, seed=args.seed, **options),
            total=total,
            desc="read",
            unit="scan",
            file=sys.stderr,
            leave=False,
        )
    )
    start, bars = _progress_bars()
    config = resolve_config(args)
    result = replay(
        scans,
        resolution=args.resolution,
        bbox=args.bbox,
        method=args.method,
        config=config.fit.for_dimension(scans[0].pose.dim if scans else 2),
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
        f"{result.scans} scans, {result.components} components, grid {'x'.join(map(str, g.shape))} "
        f"at {g.resolution} m from {np.round(g.origin, 3).tolist()}, {time.perf_counter() - t0:.1f} s"
        + (f"; wrote {args.out}" if args.out else "")
        + (f"; wrote {args.png}{view}" if args.png else "")
    )
    return 0


def cmd_inspect(args) -> int:
    import json

    from protocol import encode
    from services.datasets import read_scans
    from services.replay import fit_scans, scan_message

    scans = list(read_scans(args.log, args.format, **({"poses": args.poses} if args.poses else {})))
    dim = scans[0].pose.dim if scans else 2
    config = resolve_config(args).fit.for_dimension(dim)
    start, bars = _progress_bars()
    models = fit_scans(scans, config, start("fit", len(scans)))
    for bar in bars:
        bar.close()
    sizes = [len(encode(scan_message(m, s), args.encoding)) for m, s in zip(models, scans)]
    # Raw: float32 per beam in 2D (ranges), float32 x, y, z per point in 3D.
    raw = [4 * (len(s.hits) + len(s.no_return)) * (1 if dim == 2 else 3) for s in scans]
    components = sum(m.n_components for m in models)
    report = {
        "scans": len(scans),
        "dimension": dim,
        "encoding": args.encoding,
        "components": components,
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
    return run_server(config.server, config.reconstruction)


def cmd_router(args) -> int:
    from services.router import run_router

    _logging(args.verbose)
    return run_router(args.listen or [DEFAULT_ENDPOINT], args.connect or [], args.zenoh_config)


def cmd_agent(args) -> int:
    from services.agent.agent import run_agent

    _logging(args.verbose)
    config = resolve_config(args)
    return run_agent(config.agent, config.fit)


def cmd_sim(args) -> int:
    from services.sim.run import run_sim

    return run_sim(resolve_config(args))


def cmd_demo(args) -> int:
    from services.sim.demo import run_demo

    return run_demo(args.http, args.duration)


def _reconstruction_flags(p: argparse.ArgumentParser) -> None:
    _setting(
        p,
        "--samples-per-cell",
        "reconstruction.samples_per_cell",
        type=float,
        help="Monte-Carlo samples per cell of the queried resolution",
    )
    _setting(p, "--prior", "reconstruction.prior", type=float, help="N_p of Eq. 11")
    _setting(
        p,
        "--variance",
        "reconstruction.variance",
        type=float,
        help="sigma^2 of Eq. 12: PNGs show free / occupied / unknown by its dead band",
    )


def _fleet_id(text: str) -> str:
    from protocol import ProtocolError, check_id

    try:
        return check_id(text, "id")
    except ProtocolError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gmmap", description="Gaussian-mixture occupancy maps for robot fleets")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("replay", help="fit and reconstruct a log offline; write the map as npz and PNG")
    p.add_argument("log", help="CARMEN log, Kurt3D directory or xyz file")
    p.add_argument("--format", choices=["carmen", "kurt3d", "xyz", "pcd"], default=None)
    p.add_argument("--poses", default=None, help="pcd: poses file, KITTI (12 numbers a line) or TUM layout")
    p.add_argument("--resolution", type=float, default=0.05, help="cell size, m")
    p.add_argument(
        "--bbox",
        type=_floats,
        default=None,
        help="xmin,ymin,xmax,ymax or xmin,ymin,zmin,xmax,ymax,zmax (use --bbox=...)",
    )
    p.add_argument("--keep-fraction", type=float, default=1.0, help="keep this seeded fraction of the beams")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--method",
        choices=["mc", "analytic", "raw"],
        default="mc",
        help="mc: Monte Carlo (Eq. 11); analytic: per-cell evidence, Eq. 5/10 (2D); raw: counting grid",
    )
    _fit_flags(p)
    _reconstruction_flags(p)
    p.add_argument("--origin", type=_floats, default=None, help="sensor origin x,y,z of an xyz file")
    p.add_argument(
        "--encoding",
        choices=["q", "f32", "none"],
        default="q",
        help="pass every scan model through this wire encoding first (default q)",
    )
    p.add_argument("--out", default=None, help="map.npz")
    p.add_argument("--png", default=None, help="map.png")
    _config_flag(p)
    p.set_defaults(run=cmd_replay)

    p = sub.add_parser("inspect", help="fit a log and report encoded bytes against the raw scans")
    p.add_argument("log")
    p.add_argument("--format", choices=["carmen", "kurt3d", "xyz", "pcd"], default=None)
    p.add_argument("--poses", default=None, help="pcd: poses file, KITTI (12 numbers a line) or TUM layout")
    p.add_argument("--encoding", choices=["q", "f32"], default="q")
    _fit_flags(p)
    p.add_argument("--json", action="store_true")
    _config_flag(p)
    p.set_defaults(run=cmd_inspect)

    p = sub.add_parser("server", help="map server: Zenoh ingest and queryable, SQLite store, HTTP API")
    _setting(p, "--fleet", "server.fleet", type=_fleet_id)
    _setting(
        p,
        "--zenoh-listen",
        "server.zenoh_listen",
        action="append",
        metavar="EP",
        help=f"endpoint to listen on (repeatable; default {DEFAULT_ENDPOINT}, none with --zenoh-connect)",
    )
    _setting(
        p,
        "--zenoh-connect",
        "server.zenoh_connect",
        action="append",
        metavar="EP",
        help="router or peer to connect to (repeatable)",
    )
    _setting(
        p,
        "--zenoh-config",
        "server.zenoh_config",
        metavar="FILE.json5",
        help="Zenoh config file (scouting stays off unless it says so)",
    )
    _setting(p, "--http", "server.http", metavar="HOST:PORT", help="HTTP address; '' for none")
    _setting(p, "--data-dir", "server.data_dir")
    _setting(
        p,
        "--synchronous",
        "server.synchronous",
        choices=["normal", "full"],
        help="SQLite fsync policy: normal survives a crash of the process, full also power loss",
    )
    _setting(
        p,
        "--robot-quota-mb",
        "server.robot_quota_mb",
        type=float,
        metavar="MIB",
        help="stored scan bytes per robot; scans beyond are refused with a Rejection (0: no quota)",
    )
    _setting(
        p,
        "--trace-threads",
        "server.trace_threads",
        type=int,
        metavar="N",
        help="tracer threads that sample and trace tiles; a large update is split among them (default: one per core)",
    )
    _reconstruction_flags(p)
    _config_flag(p)
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(run=cmd_server)

    p = sub.add_parser("router", help="a Zenoh router (Python library), for setups without zenohd")
    p.add_argument("--listen", action="append", metavar="EP", help=f"default {DEFAULT_ENDPOINT} (repeatable)")
    p.add_argument("--connect", action="append", metavar="EP", help="other routers (repeatable)")
    p.add_argument("--zenoh-config", metavar="FILE.json5")
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(run=cmd_router)

    p = sub.add_parser("agent", help="robot agent: fit scans, publish them and pose-graph updates until acknowledged")
    _setting(p, "--robot", "agent.robot", type=_fleet_id, help="required, here or in --config")
    _setting(p, "--fleet", "agent.fleet", type=_fleet_id)
    _setting(
        p,
        "--zenoh-connect",
        "agent.zenoh_connect",
        action="append",
        metavar="EP",
        help=f"default {DEFAULT_ENDPOINT} (repeatable)",
    )
    _setting(p, "--zenoh-config", "agent.zenoh_config", metavar="FILE.json5")
    _setting(
        p,
        "--source",
        "agent.source",
        metavar="carmen:PATH|kurt3d:DIR|xyz:PATH|sim:WORLD:INDEX:ROBOTS[:SEED]",
        help="a log, or robot INDEX of a simulated fleet (needs --scans A:B); required, here or in --config",
    )
    _setting(
        p,
        "--corrections",
        "agent.corrections",
        metavar="PATH",
        help="corrected CARMEN log: publish odometry poses, then these as pose-graph updates",
    )
    _setting(p, "--poses", "agent.poses", metavar="FILE", help="pcd source: poses file, KITTI or TUM layout")
    _setting(p, "--scans", "agent.scans", metavar="A:B", help="slice of the (matched) scans; node ids stay global")
    _setting(p, "--rate", "agent.rate", type=float, help="scans per second (0: as fast as fitted)")
    _setting(
        p, "--outbox", "agent.outbox", metavar="PATH", help="durable outbox (default ./gmmap-data/outbox-<robot>.db)"
    )
    _setting(p, "--encoding", "agent.encoding", choices=["q", "f32"])
    _setting(
        p,
        "--update-every",
        "agent.update_every",
        type=int,
        metavar="N",
        help="scans between pose-graph updates (0: only at the end; default 100, "
        "or a sim source's loop-closure period of 10 s)",
    )
    _setting(
        p,
        "--odometry-only",
        "agent.odometry_only",
        action="store_true",
        help="with --corrections: publish the matched scans but no pose-graph updates",
    )
    _fit_flags(p)
    _setting(
        p,
        "--resend",
        "agent.resend_s",
        type=float,
        metavar="S",
        help="resend what is unacknowledged after at least S s (longer when Acks come slowly, "
        "doubling with each resend)",
    )
    _setting(
        p,
        "--timeout",
        "agent.timeout",
        type=float,
        metavar="S",
        help="after publishing, wait at most S s for the acknowledgements (exit 1 otherwise)",
    )
    _config_flag(p)
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(run=cmd_agent)

    p = sub.add_parser("sim", help="a simulated fleet over real Zenoh: bytes, map AUROC vs ground truth, latencies")
    _setting(p, "--robots", "sim.robots", type=int, help="robots in the fleet, each a full agent")
    _setting(p, "--world", "sim.world", choices=WORLD_NAMES, help="office, warehouse: 2D laser; mine: 3D 16-beam lidar")
    _setting(p, "--duration", "sim.duration", type=float, help="seconds each robot drives and publishes")
    _setting(p, "--rate", "sim.rate", type=float, help="scans per second per robot")
    _setting(p, "--seed", "sim.seed", type=int, help="world, paths, odometry and sensor noise")
    _setting(
        p,
        "--http-clients",
        "sim.http_clients",
        type=int,
        metavar="N",
        help="concurrent HTTP clients fetching map tiles meanwhile",
    )
    _setting(p, "--report", "sim.report", metavar="DIR", help="write DIR/report.json, DIR/report.md and its PNG plots")
    _fit_flags(p)  # the robots' fit
    _reconstruction_flags(p)  # the server's
    _config_flag(p)
    p.set_defaults(run=cmd_sim)

    p = sub.add_parser(
        "demo", help="a map server and three simulated robots in the office; the viewer shows the map grow"
    )
    p.add_argument(
        "--duration", type=float, default=0.0, help="seconds the robots drive, then everything stops; 0: until Ctrl-C"
    )
    p.add_argument("--http", default="127.0.0.1:8000", metavar="HOST:PORT", help="where the viewer is served")
    p.set_defaults(run=cmd_demo)
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
