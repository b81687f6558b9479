"""ROS 2 latencies (issue 14): a `/scan` publication to its node being served, and a `/slam/path`
to the re-posed map on `/map`.

Real processes on 127.0.0.1: `gmmap router`, `gmmap server --ros-map /map` (connected to the
router) and `gmmap agent --source ros2` (every scan a node); this process is the ROS 2 robot
(tests/support/ros2_robot.py: rosbags CDR on rmw_zenoh or bridge keys) and a /map subscriber.

- scan: the Intel log's first `--scans` scans as LaserScan + Odometry at `--rate` Hz (the log's
  own is about 3 Hz); a thread polls GET /v1/robots every 5 ms, and a scan's latency runs from its
  put to the first answer that counts its node (stored, in the FleetMap, on the HTTP API). The
  first `--warmup` scans are not timed (the agent connects, loads its kernels and reaches the
  server meanwhile); the first one's latency is reported as the cold start.
- path: `--paths` times, a nav_msgs/Path alternately of the corrected and the odometry poses of
  every node; its latency runs from the put to the first /map sample received after it (the grid
  published once the server applied the update: at most one per `--map-period`).

    .venv/bin/python bench/ros2_latency.py [--mapping rmw_zenoh] [--scans 200] [--rate 10]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # the repository, and tests/support

from services.sim.processes import EVERY_SCAN, Processes, free_port  # noqa: E402
from services.zenoh_config import zenoh_config  # noqa: E402
from support.ros2_robot import MOUNT, OCCUPANCY_GRID, MapSubscriber, RosRobot, intel_topics, laser_3d  # noqa: E402
from support.rosbags_written import PATH, RosMessages  # noqa: E402

DATA = ROOT.parent / "shared" / "data"


def nodes_served(hport: int) -> int:
    with urllib.request.urlopen(f"http://127.0.0.1:{hport}/v1/robots", timeout=10) as reply:
        return sum(r["nodes"] for r in json.loads(reply.read()))


def percentiles(values) -> str:
    v = np.array(values) * 1000
    return f"p50 {np.percentile(v, 50):.0f} ms, p95 {np.percentile(v, 95):.0f} ms, max {v.max():.0f} ms (n={len(v)})"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--mapping", default="rmw_zenoh", choices=["rmw_zenoh", "bridge"])
    parser.add_argument("--scans", type=int, default=200)
    parser.add_argument("--rate", type=float, default=10.0)
    parser.add_argument("--warmup", type=int, default=20, help="scans before the timed ones")
    parser.add_argument("--paths", type=int, default=6)
    parser.add_argument("--map-period", type=float, default=2.0)
    args = parser.parse_args()
    intel = intel_topics(DATA, args.scans)
    with tempfile.TemporaryDirectory() as tmp:
        procs = Processes(Path(tmp))
        try:
            rport, hport = free_port(), free_port()
            router = f"tcp/127.0.0.1:{rport}"
            procs.start("router", "router", "--listen", router)
            procs.wait_ready("router", "gmmap router ready")
            ros = ["--ros-mapping", args.mapping]
            procs.server(
                None,
                f"127.0.0.1:{hport}",
                Path(tmp) / "data",
                "default",
                "--zenoh-connect",
                router,
                *ros,
                "--ros-map",
                "/map",
                "--ros-map-period",
                str(args.map_period),
            )
            procs.start(
                "agent",
                "agent",
                "--robot",
                "ros",
                "--zenoh-connect",
                router,
                "--source",
                "ros2",
                "--scan-topic",
                "/scan",
                "--odom-topic",
                "/odom",
                "--path-topic",
                "/slam/path",
                *ros,
                "--outbox",
                str(Path(tmp) / "outbox.db"),
                *EVERY_SCAN,
            )
            procs.wait_ready("agent", "ros2 ready")
            session = zenoh.open(zenoh_config("client", connect=[router]))
            robot = RosRobot(session, args.mapping)
            grids = MapSubscriber(session, args.mapping, "/map", OCCUPANCY_GRID)
            served: dict[int, float] = {}
            done = threading.Event()

            def poll():
                while not done.is_set():
                    count, now = nodes_served(hport), time.time()
                    for k in range(len(served), count):
                        served[k] = now
                    time.sleep(0.005)

            robot.publish(*intel.static[:2], intel.static[3])
            poller = threading.Thread(target=poll, daemon=True)
            poller.start()
            sent = []
            start = time.monotonic()
            for k, step in enumerate(intel.steps):
                if k == args.warmup:  # the agent's outbox reached the server, its fit and the tiles are warm
                    while len(served) < k:
                        time.sleep(0.05)
                    start = time.monotonic() - k / args.rate
                time.sleep(max(0.0, start + k / args.rate - time.monotonic()))
                for topic, msgtype, _, message in step:
                    put = robot.publish(topic, msgtype, message)
                sent.append(put)
            deadline = time.time() + 60
            while len(served) < args.scans and time.time() < deadline:
                time.sleep(0.05)
            done.set()
            scan_latency = [served[k] - sent[k] for k in range(args.warmup, args.scans) if k in served]
            cold = served[0] - sent[0]
            time.sleep(args.map_period + 1)  # the map of the last scans is out
            m = RosMessages("sqlite3")
            path_latency = []
            for round_ in range(args.paths):
                poses = intel.corrected if round_ % 2 == 0 else intel.odometry
                bodies = [(float(s), laser_3d(*p).compose(MOUNT.inverse())) for s, p in zip(intel.stamps, poses)]
                before = len(grids.received)
                put = robot.publish("/slam/path", PATH, m.path(float(intel.stamps[-1]), "map", bodies))
                while len(grids.received) == before and time.time() < put + 30:
                    time.sleep(0.002)
                if len(grids.received) > before:
                    path_latency.append(grids.received[before][0] - put)
                time.sleep(args.map_period + 0.5)
            robot.close()
            session.close()
            print(f"mapping {args.mapping}, {args.scans} scans at {args.rate:g} Hz, map period {args.map_period:g} s")
            print(f"/scan -> node served: {percentiles(scan_latency)}")
            print(f"first scan after the agent started (cold): {cold * 1000:.0f} ms; then {args.warmup} scans untimed")
            print(f"/slam/path -> re-posed /map: {percentiles(path_latency)}")
        finally:
            procs.close()


if __name__ == "__main__":
    main()
