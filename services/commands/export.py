"""`gmmap export`: a map as a ROS map_server PGM + YAML, an OctoMap .bt or a PLY cloud, from a server or
an npz."""

from __future__ import annotations

from services.cli_flags import config_flag, floats, http_client_flags, resolve_config, setting


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


def add_export(sub) -> None:
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
        type=floats,
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
