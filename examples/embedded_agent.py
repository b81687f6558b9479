"""A robot process that already has its scans and poses, feeding a gmmap server through the
embeddable agent (services.agent.agent.Agent): the same outbox, keyframes and delivery as
`gmmap agent`, called from your own code.

Here the robot's driver and SLAM back end are played by a real log: each CARMEN scan arrives
with its odometry pose, and at the end the back end's corrected poses go out as one pose-graph
update, those of the nodes whose scan they move by more than `agent.pose_tolerance` (this
corrected log's odometry is already the corrected pose, so none do). Replace the loop with your
sensor callback.

    gmmap server &                                  # a map server on tcp/127.0.0.1:7447
    python examples/embedded_agent.py               # then look at http://127.0.0.1:8000/
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from services.agent.agent import Agent
from services.agent.config import AgentConfig
from services.datasets import read_scans
from services.zenoh_config import DEFAULT_ENDPOINT

INTEL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "carmen" / "intel-corrected.log.gz"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--log", default=str(INTEL), help="a log standing for the robot's driver (default: Intel)")
    p.add_argument("--robot", default="embedded")
    p.add_argument("--connect", default=DEFAULT_ENDPOINT, help="the map server's (or a router's) Zenoh endpoint")
    p.add_argument("--outbox", default=None, help="default ./gmmap-data/outbox-<robot>.db")
    p.add_argument("--timeout", type=float, default=60.0, help="s to wait for the acknowledgements")
    args = p.parse_args(argv)

    config = AgentConfig(robot=args.robot, zenoh_connect=(args.connect,), outbox=args.outbox)
    corrected = {}  # node -> the back end's pose of it
    with Agent.open(config) as agent:
        for scan in read_scans(args.log):  # your sensor callback
            # published at the pose the robot has now (odometry); None: not a keyframe, not sent
            node = agent.add_scan(scan.hits, scan.no_return, scan.odom_pose or scan.pose, scan.stamp)
            if node is not None:
                corrected[node] = scan.pose
        agent.correct(corrected)  # e.g. after a loop closure: only nodes whose pose changed are needed
        held = agent.flush(args.timeout)
    print(f"{len(corrected)} nodes sent, {held} not yet acknowledged (kept in the outbox for the next run)")
    return 0 if held == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
