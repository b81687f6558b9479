"""The `gmmap` command line."""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np


SIM_WORLDS = ["mine", "office", "warehouse"]  # services.sim.worlds.WORLDS, without importing numba here


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


def _fit_config(args, dim: int):
    from gmm_core import FitConfig

    component_size = args.component_size
    if component_size is None and dim == 3:
        component_size = 1.0  # dense 3D scans: about one component per square metre of surface
    return FitConfig(max_range=args.max_range, points_per_component=args.points_per_component,
                     component_size=component_size)


def cmd_replay(args) -> int:
    from services.datasets import count_scans, read_scans
    from services.render import occupancy_png
    from services.replay import replay

    t0 = time.perf_counter()
    options = {}
    if args.origin is not None:
        options["origin"] = tuple(args.origin)
    from tqdm import tqdm
    total = count_scans(args.log, args.format)
    scans = list(tqdm(read_scans(args.log, args.format, keep_fraction=args.keep_fraction, seed=args.seed, **options),
                      total=total, desc="read", unit="scan", file=sys.stderr, leave=False))
    start, bars = _progress_bars()
    config = _fit_config(args, scans[0].pose.dim if scans else 2)
    result = replay(scans, resolution=args.resolution, bbox=args.bbox, method=args.method, config=config,
                    seed=args.seed, samples_per_cell=args.samples_per_cell, prior=args.prior,
                    encoding=args.encoding, progress=start)
    for bar in bars:
        bar.close()
    g = result.grid
    if args.out:
        np.savez_compressed(args.out, prob=result.prob, hits=result.hits, misses=result.misses,
                            origin=g.origin, resolution=np.float64(g.resolution))
    if args.png:
        with open(args.png, "wb") as f:
            f.write(occupancy_png(result.prob))
    view = " (top-down projection)" if g.dim == 3 else ""
    print(f"{result.scans} scans, {result.components} components, grid {'x'.join(map(str, g.shape))} "
          f"at {g.resolution} m from {np.round(g.origin, 3).tolist()}, {time.perf_counter() - t0:.1f} s"
          + (f"; wrote {args.out}" if args.out else "") + (f"; wrote {args.png}{view}" if args.png else ""))
    return 0


def cmd_inspect(args) -> int:
    import json

    from protocol import encode
    from services.datasets import read_scans
    from services.replay import fit_scans, scan_message

    scans = list(read_scans(args.log, args.format))
    dim = scans[0].pose.dim if scans else 2
    config = _fit_config(args, dim)
    start, bars = _progress_bars()
    models = fit_scans(scans, config, start("fit", len(scans)))
    for bar in bars:
        bar.close()
    sizes = [len(encode(scan_message(m, s), args.encoding)) for m, s in zip(models, scans)]
    # Raw: float32 per beam in 2D (ranges), float32 x, y, z per point in 3D.
    raw = [4 * (len(s.hits) + len(s.no_return)) * (1 if dim == 2 else 3) for s in scans]
    components = sum(m.n_components for m in models)
    report = {
        "scans": len(scans), "dimension": dim, "encoding": args.encoding, "components": components,
        "bytes": sum(sizes), "raw_bytes": sum(raw),
        "bytes_per_component": sum(sizes) / max(components, 1), "bytes_per_scan": sum(sizes) / max(len(scans), 1),
        "raw_bytes_per_scan": sum(raw) / max(len(scans), 1), "ratio_to_raw": sum(sizes) / max(sum(raw), 1),
    }
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        for key, value in report.items():
            print(f"{key:>20}: {value:.2f}" if isinstance(value, float) else f"{key:>20}: {value}")
    return 0


def _logging(verbose: bool) -> None:
    import logging

    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")


def cmd_server(args) -> int:
    from services.map_server.server import ServerOptions, run_server

    _logging(args.verbose)
    return run_server(ServerOptions(
        fleet=args.fleet, zenoh_listen=tuple(e for e in args.zenoh_listen or () if e), zenoh_connect=tuple(args.zenoh_connect or ()),
        zenoh_config=args.zenoh_config, http=args.http or None, data_dir=args.data_dir,
        synchronous=args.synchronous, robot_quota_mb=args.robot_quota_mb, trace_threads=args.trace_threads))


def cmd_router(args) -> int:
    from services.router import run_router

    _logging(args.verbose)
    return run_router(args.listen, args.connect or [], args.zenoh_config)


def cmd_agent(args) -> int:
    from services.agent.agent import AgentOptions, run_agent

    _logging(args.verbose)
    return run_agent(AgentOptions(
        robot=args.robot, source=args.source, fleet=args.fleet, zenoh_connect=tuple(args.zenoh_connect),
        zenoh_config=args.zenoh_config, corrections=args.corrections, scans=args.scans, rate=args.rate,
        outbox=args.outbox, encoding=args.encoding, update_every=args.update_every,
        odometry_only=args.odometry_only, max_range=args.max_range, component_size=args.component_size,
        resend_s=args.resend, timeout=args.timeout))


def cmd_sim(args) -> int:
    from services.sim.run import SimOptions, run_sim

    return run_sim(SimOptions(robots=args.robots, world=args.world, duration=args.duration, rate=args.rate,
                              seed=args.seed, http_clients=args.http_clients, report=args.report,
                              component_size=args.component_size))


def cmd_demo(args) -> int:
    from services.sim.demo import run_demo

    return run_demo(args.http, args.duration)


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
    p.add_argument("--format", choices=["carmen", "kurt3d", "xyz"], default=None)
    p.add_argument("--resolution", type=float, default=0.05, help="cell size, m")
    p.add_argument("--bbox", type=_floats, default=None,
                   help="xmin,ymin,xmax,ymax or xmin,ymin,zmin,xmax,ymax,zmax (use --bbox=...)")
    p.add_argument("--keep-fraction", type=float, default=1.0, help="keep this seeded fraction of the beams")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--method", choices=["mc", "analytic", "raw"], default="mc",
                   help="mc: Monte Carlo (Eq. 11); analytic: per-cell evidence, Eq. 5/10 (2D); raw: counting grid")
    p.add_argument("--max-range", type=float, default=10.0, help="where no-return beams end, m")
    p.add_argument("--points-per-component", type=float, default=3.0)
    p.add_argument("--component-size", type=float, default=None,
                   help="at most one component per occupied cell of this size, m (default: none in 2D, 1.0 in 3D)")
    p.add_argument("--samples-per-cell", type=float, default=4.0)
    p.add_argument("--prior", type=float, default=0.2, help="N_p of Eq. 11")
    p.add_argument("--origin", type=_floats, default=None, help="sensor origin x,y,z of an xyz file")
    p.add_argument("--encoding", choices=["q", "f32", "none"], default="q",
                   help="pass every scan model through this wire encoding first (default q)")
    p.add_argument("--out", default=None, help="map.npz")
    p.add_argument("--png", default=None, help="map.png")
    p.set_defaults(run=cmd_replay)

    p = sub.add_parser("inspect", help="fit a log and report encoded bytes against the raw scans")
    p.add_argument("log")
    p.add_argument("--format", choices=["carmen", "kurt3d", "xyz"], default=None)
    p.add_argument("--encoding", choices=["q", "f32"], default="q")
    p.add_argument("--max-range", type=float, default=10.0)
    p.add_argument("--points-per-component", type=float, default=3.0)
    p.add_argument("--component-size", type=float, default=None)
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=cmd_inspect)

    p = sub.add_parser("server", help="map server: Zenoh ingest and queryable, SQLite store, HTTP API")
    p.add_argument("--fleet", type=_fleet_id, default="default")
    p.add_argument("--zenoh-listen", action="append", metavar="EP",
                   help="endpoint to listen on (repeatable; default tcp/127.0.0.1:7447)")
    p.add_argument("--zenoh-connect", action="append", metavar="EP", help="router or peer to connect to (repeatable)")
    p.add_argument("--zenoh-config", metavar="FILE.json5", help="Zenoh config file (scouting stays off unless it says so)")
    p.add_argument("--http", default="127.0.0.1:8000", metavar="HOST:PORT", help="HTTP address; '' for none")
    p.add_argument("--data-dir", default="./gmmap-data")
    p.add_argument("--synchronous", choices=["normal", "full"], default="normal",
                   help="SQLite fsync policy: normal survives a crash of the process, full also power loss")
    p.add_argument("--robot-quota-mb", type=float, default=512.0, metavar="MIB",
                   help="stored scan bytes per robot; scans beyond are refused with a Rejection (0: no quota)")
    p.add_argument("--trace-threads", type=int, metavar="N",
                   help="tracer threads that sample and trace tiles; a large update is split among them "
                        "(default: one per core)")
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(run=cmd_server)

    p = sub.add_parser("router", help="a Zenoh router (Python library), for setups without zenohd")
    p.add_argument("--listen", action="append", metavar="EP", help="default tcp/127.0.0.1:7447 (repeatable)")
    p.add_argument("--connect", action="append", metavar="EP", help="other routers (repeatable)")
    p.add_argument("--zenoh-config", metavar="FILE.json5")
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(run=cmd_router)

    p = sub.add_parser("agent", help="robot agent: fit scans, publish them and pose-graph updates until acknowledged")
    p.add_argument("--robot", type=_fleet_id, required=True)
    p.add_argument("--fleet", type=_fleet_id, default="default")
    p.add_argument("--zenoh-connect", action="append", metavar="EP", help="default tcp/127.0.0.1:7447 (repeatable)")
    p.add_argument("--zenoh-config", metavar="FILE.json5")
    p.add_argument("--source", required=True, metavar="carmen:PATH|kurt3d:DIR|xyz:PATH|sim:WORLD:INDEX:ROBOTS[:SEED]",
                   help="a log, or robot INDEX of a simulated fleet (needs --scans A:B)")
    p.add_argument("--corrections", metavar="PATH",
                   help="corrected CARMEN log: publish odometry poses, then these as pose-graph updates")
    p.add_argument("--scans", metavar="A:B", help="slice of the (matched) scans; node ids stay global")
    p.add_argument("--rate", type=float, default=0.0, help="scans per second (default: as fast as fitted)")
    p.add_argument("--outbox", metavar="PATH", help="durable outbox (default ./gmmap-data/outbox-<robot>.db)")
    p.add_argument("--encoding", choices=["q", "f32"], default="q")
    p.add_argument("--update-every", type=int, default=None, metavar="N",
                   help="scans between pose-graph updates (0: only at the end; default 100, "
                        "or a sim source's loop-closure period of 10 s)")
    p.add_argument("--odometry-only", action="store_true",
                   help="with --corrections: publish the matched scans but no pose-graph updates")
    p.add_argument("--max-range", type=float, default=10.0)
    p.add_argument("--component-size", type=float, default=None, metavar="M",
                   help="at most one component per occupied cell of this size (default: none in 2D, 1.0 m in 3D)")
    p.add_argument("--resend", type=float, default=1.0, metavar="S",
                   help="resend what is unacknowledged after at least S s (longer when Acks come slowly, "
                        "doubling with each resend)")
    p.add_argument("--timeout", type=float, default=120.0, metavar="S",
                   help="after publishing, wait at most S s for the acknowledgements (exit 1 otherwise)")
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(run=cmd_agent)

    p = sub.add_parser("sim", help="a simulated fleet over real Zenoh: bytes, map AUROC vs ground truth, latencies")
    p.add_argument("--robots", type=int, default=3, help="one agent process each")
    p.add_argument("--world", choices=SIM_WORLDS, default="office",
                   help="office, warehouse: 2D laser; mine: 3D 16-beam lidar")
    p.add_argument("--duration", type=float, default=60.0, help="seconds each robot drives and publishes")
    p.add_argument("--rate", type=float, default=5.0, help="scans per second per robot")
    p.add_argument("--seed", type=int, default=0, help="world, paths, odometry and sensor noise")
    p.add_argument("--http-clients", type=int, default=0, metavar="N",
                   help="concurrent HTTP clients fetching map tiles meanwhile")
    p.add_argument("--report", metavar="DIR", help="write DIR/report.json, DIR/report.md and its PNG plots")
    p.add_argument("--component-size", type=float, default=None, metavar="M",
                   help="the agents' fit: at most one component per occupied cell of this size "
                        "(default: none in 2D, 1.0 m in 3D)")
    p.set_defaults(run=cmd_sim)

    p = sub.add_parser("demo", help="a map server and three simulated robots in the office; the viewer shows the map grow")
    p.add_argument("--duration", type=float, default=0.0,
                   help="seconds the robots drive, then everything stops; 0: until Ctrl-C")
    p.add_argument("--http", default="127.0.0.1:8000", metavar="HOST:PORT", help="where the viewer is served")
    p.set_defaults(run=cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # append-actions cannot have a replaceable default; a server that connects need not listen
    if args.command == "server" and args.zenoh_listen is None and args.zenoh_connect is None:
        args.zenoh_listen = ["tcp/127.0.0.1:7447"]
    if args.command == "router" and args.listen is None:
        args.listen = ["tcp/127.0.0.1:7447"]
    if args.command == "agent" and args.zenoh_connect is None:
        args.zenoh_connect = ["tcp/127.0.0.1:7447"]
    try:
        return args.run(args)
    except (ValueError, OSError) as exc:  # DatasetError and ProtocolError are ValueErrors
        print(f"gmmap {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
