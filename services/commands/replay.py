"""`gmmap replay`: fit and reconstruct a log offline; write the map as npz and PNG."""

from __future__ import annotations

import sys
import time

import numpy as np

from services.cli_flags import (
    config_flag,
    fit_flags,
    floats,
    keyframe_flags,
    reconstruction_flags,
    resolve_config,
    source_flags,
)
from services.commands.common import progress_bars, read_source


def cmd_replay(args) -> int:
    from services.render import occupancy_png
    from services.replay import DEFAULT_RESOLUTION, MAX_REPLAY_CELLS, replay, replay_grid

    t0 = time.perf_counter()
    config = resolve_config(args)
    options = {} if args.origin is None else {"origin": tuple(args.origin)}
    scans, read = read_source(args, config, args.keep_fraction, args.seed, **options)
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
    start, bars = progress_bars()
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


def add_replay(sub) -> None:
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
        type=floats,
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
    p.add_argument("--origin", type=floats, default=None, help="sensor origin x,y,z of an xyz file")
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
