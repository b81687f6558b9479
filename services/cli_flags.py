"""The command line's shared flags: each sets a field of the configuration (`section.field`).

A flag's default is SUPPRESS, so that only the flags given override `--config FILE`, which
overrides the sections' own defaults (shown in the help).
"""

from __future__ import annotations

import argparse
import sys

from services.config import GmmapConfig, load_config

DEFAULTS = GmmapConfig()


class Parser(argparse.ArgumentParser):
    """argparse's parser, which also takes a flag's comma-separated numbers that begin with a negative
    one as a separate argument (`--bbox -5,-5,5,5`, `--ros-map-z -1,2`), as it takes `--bbox=-5,-5,5,5`."""

    def parse_known_args(self, args=None, namespace=None):
        argv = sys.argv[1:] if args is None else list(args)
        return super().parse_known_args(joined_number_lists(argv), namespace)


def joined_number_lists(argv: list[str]) -> list[str]:
    """`--flag -1,2` as `--flag=-1,2`. argparse takes an argument that begins with '-' and is not one
    plain negative number for a flag of its own, and refuses it: a comma-separated list of numbers is
    never a flag, so joining it to the flag before it only turns that refusal into the value meant."""
    joined: list[str] = []
    for k, arg in enumerate(argv):
        if arg == "--":  # positionals from here on
            return joined + argv[k:]
        previous = joined[-1] if joined else ""
        if previous.startswith("--") and "=" not in previous and _negative_number_list(arg):
            joined[-1] = f"{previous}={arg}"
        else:
            joined.append(arg)
    return joined


def _negative_number_list(text: str) -> bool:
    if not (text.startswith("-") and "," in text):
        return False
    try:
        [float(v) for v in text.split(",")]
    except ValueError:
        return False
    return True


def floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def fleet_id(text: str) -> str:
    from protocol import ProtocolError, check_id

    try:
        return check_id(text, "id")
    except ProtocolError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def setting(p: argparse.ArgumentParser, flag: str, key: str, **kwargs) -> None:
    """A flag that sets field `key` ("section.field") of the configuration; its default is the
    section's own, shown in the help, and applies only when neither the flag nor --config sets it."""
    section, name = key.split(".")
    default = getattr(getattr(DEFAULTS, section), name)
    if kwargs.get("action") != "store_true":
        kwargs.setdefault("metavar", None if "choices" in kwargs else flag.lstrip("-").upper().replace("-", "_"))
        if kwargs.get("action") != "append" and default is not None:
            kwargs["help"] = f"{kwargs.get('help', '')} (default {default})".strip()
    p.add_argument(flag, dest=key, default=argparse.SUPPRESS, **kwargs)


def config_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        metavar="FILE",
        default=None,
        help="a TOML or YAML file of [fit], [reconstruction], [server], [agent], [sim], [ros2] settings; "
        "flags given here win over it",
    )


def fit_flags(p: argparse.ArgumentParser) -> None:
    setting(p, "--max-range", "fit.max_range", type=float, help="where no-return beams end, m")
    setting(
        p,
        "--points-per-component",
        "fit.points_per_component",
        type=float,
        metavar="N",
        help="at least this many points a component, on average (default: 3 in 2D, 30 in 3D)",
    )
    setting(
        p,
        "--component-size",
        "fit.component_size",
        type=float,
        metavar="M",
        help="at most one component per occupied cell of this size, m (default: none in 2D, 1.0 in 3D)",
    )
    setting(p, "--max-components", "fit.max_components", type=int, metavar="K", help="per mixture")


def resolve_config(args) -> GmmapConfig:
    """--config, then the flags that were given, over the defaults."""
    overrides: dict[str, dict] = {}
    for key, value in vars(args).items():
        if "." in key:
            section, name = key.split(".")
            overrides.setdefault(section, {})[name] = value
    return load_config(args.config, overrides)


def reconstruction_flags(p: argparse.ArgumentParser) -> None:
    setting(
        p,
        "--samples-per-cell",
        "reconstruction.samples_per_cell",
        type=float,
        help="Monte-Carlo samples per cell of the queried resolution",
    )
    setting(p, "--prior", "reconstruction.prior", type=float, help="N_p of Eq. 11")
    setting(
        p,
        "--variance",
        "reconstruction.variance",
        type=float,
        help="sigma^2 of Eq. 12: PNGs show free / occupied / unknown by its dead band",
    )


def keyframe_flags(p: argparse.ArgumentParser) -> None:
    """When a scan becomes a node (services.datasets.keyframes); 0 turns a reason off."""
    setting(p, "--keyframe-distance", "keyframe.distance", type=float, metavar="M", help="a node after moving M m")
    setting(p, "--keyframe-angle", "keyframe.angle", type=float, metavar="DEG", help="a node after turning DEG degrees")
    setting(p, "--keyframe-period", "keyframe.period", type=float, metavar="S", help="a node after S s")


def server_tls_token_flags(p: argparse.ArgumentParser) -> None:
    """TLS and bearer tokens of a server's HTTP API (docs/RELIABILITY.md, "Who may read the map")."""
    setting(p, "--http-tls-cert", "server.http_tls_cert", metavar="CERT.pem", help="serve HTTPS with this certificate")
    setting(p, "--http-tls-key", "server.http_tls_key", metavar="KEY.pem", help="the certificate's private key")
    setting(
        p,
        "--http-tokens",
        "server.http_tokens",
        metavar="FILE",
        help="bearer tokens, one client a line: NAME sha256:HEX [robots=ID,...] (made by `gmmap token NAME`)",
    )


def server_http_flags(p: argparse.ArgumentParser) -> None:
    """Where a server's HTTP API listens, and how it is secured."""
    setting(
        p,
        "--http",
        "server.http",
        metavar="HOST:PORT",
        help="HTTP address ([::1]:PORT for IPv6; '' for none); beyond loopback it needs TLS and tokens",
    )
    server_tls_token_flags(p)
    setting(
        p,
        "--http-insecure",
        "server.http_insecure",
        action="store_true",
        help="serve a non-loopback --http without TLS or tokens anyway (a trusted network, or a proxy that "
        "authenticates)",
    )


def http_client_flags(p: argparse.ArgumentParser) -> None:
    """How the command's own HTTP clients reach a server that has TLS and tokens."""
    setting(p, "--http-token", "sim.http_token", metavar="FILE", help="a file holding the bearer token to send")
    setting(p, "--http-ca", "sim.http_ca", metavar="CA.pem", help="the CA that signed the server's TLS certificate")


SOURCE_OPTIONS = ("poses", "scan_topic", "pose_topic")  # read_scans keywords, set only when given


def source_flags(p: argparse.ArgumentParser) -> None:
    """The data source of `replay` and `inspect`: a path, its format, and the format's options."""
    from services.datasets import FORMATS

    p.add_argument("log", help="a log file, scan directory or bag (formats: " + ", ".join(FORMATS) + ")")
    p.add_argument("--format", choices=FORMATS, default=None, help="default: guessed from the path")
    p.add_argument("--poses", default=None, help="pcd, ply, kitti: poses file, KITTI (12 numbers a line) or TUM layout")
    p.add_argument("--scan-topic", default=None, help="rosbag: LaserScan or PointCloud2 topic (default: the only one)")
    p.add_argument("--pose-topic", default=None, help="rosbag: Odometry or PoseStamped topic (default: poses from /tf)")


def source_options(args: argparse.Namespace) -> dict:
    """The reader options given on the command line."""
    return {name: getattr(args, name) for name in SOURCE_OPTIONS if getattr(args, name) is not None}


def ros2_flags(p: argparse.ArgumentParser) -> None:
    """How a process meets ROS 2 over Zenoh (services/ros2): the key layout, domain, namespace, distro."""
    setting(
        p,
        "--ros-mapping",
        "ros2.mapping",
        choices=["rmw_zenoh", "bridge"],
        help="ROS 2 key layout: rmw_zenoh (Jazzy and later) or bridge (zenoh-bridge-ros2dds)",
    )
    setting(p, "--ros-domain", "ros2.domain", type=int, metavar="ID", help="ROS_DOMAIN_ID")
    setting(
        p,
        "--ros-namespace",
        "ros2.namespace",
        metavar="NS",
        help="ROS namespace of relative topic names; with --ros-mapping bridge the bridge's, before every topic",
    )
    setting(p, "--ros-distro", "ros2.distro", choices=["iron", "jazzy", "kilted", "lyrical"], help="type hashes of")
