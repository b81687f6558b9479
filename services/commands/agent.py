"""`gmmap agent`: a robot agent: fit scans, publish them and pose-graph updates until acknowledged."""

from __future__ import annotations

from services.cli_flags import (
    config_flag,
    fit_flags,
    fleet_id,
    keyframe_flags,
    resolve_config,
    ros2_flags,
    setting,
)
from services.commands.common import log_to_stderr
from services.zenoh_config import DEFAULT_ENDPOINT


def cmd_agent(args) -> int:
    from services.agent.run import run_agent

    log_to_stderr(args.verbose)
    config = resolve_config(args)
    if config.agent.source == "ros2":
        from services.ros2.live import run_ros2_agent

        return run_ros2_agent(config)
    return run_agent(config.agent, config.fit, config.keyframe)


def add_agent(sub) -> None:
    p = sub.add_parser("agent", help="robot agent: fit scans, publish them and pose-graph updates until acknowledged")
    setting(p, "--robot", "agent.robot", type=fleet_id, help="required, here or in --config")
    setting(p, "--fleet", "agent.fleet", type=fleet_id)
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
