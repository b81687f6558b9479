"""ROS 2 over Zenoh without ROS: the Intel log played as a robot's ROS 2 topics (rosbags CDR, real
Zenoh keys of rmw_zenoh or zenoh-bridge-ros2dds) through a `gmmap router` into `gmmap agent
--source ros2`, stored by a map server; its map against `gmmap replay` of the same messages."""

from __future__ import annotations

import io
import json
import shutil
import signal

import numpy as np
import pytest
import zenoh

from gmm_core import Grid, Pose
from gmm_core.occupancy import classify, map_estimate
from gmm_core.reconstruct import reconstruct
from gmm_core.sampling import scan_seed
from protocol import ScanMessage, decode
from services.agent.agent import Agent
from services.agent.config import AgentConfig
from services.cli import main
from services.config import GmmapConfig
from services.datasets.keyframes import KeyframeConfig
from services.map_server.store import read_graph
from services.zenoh_config import zenoh_config
from support.net import free_port, get, http_get, wait_for
from support.paths import ROOT
from support.processes import EVERY_SCAN, rejected_nodes, store_db, stored_nodes, written_nodes
from support.ros2_robot import MOUNT, OCCUPANCY_GRID, PATH, MapSubscriber, RosRobot, intel_topics, laser_3d
from support.rosbags_written import ODOMETRY, POINT_CLOUD2, TF, RosMessages, write_bag

SCANS = 60
RESOLUTION = 0.1
CLASS_AGREEMENT = 0.97  # of cells, served against an offline replay with other Monte-Carlo seeds


@pytest.fixture(scope="module")
def intel(data_dir):
    return intel_topics(data_dir, SCANS)


def grid_of(intel) -> Grid:
    """The 10 cm grid over every laser position, odometry or corrected, and 10 m (the fit's max range) around."""
    positions = np.concatenate([intel.odometry[:, :2], intel.corrected[:, :2]])
    return Grid.from_bbox(np.floor(positions.min(axis=0) - 10.5), np.ceil(positions.max(axis=0) + 10.5), RESOLUTION)


def served(hport: int, grid: Grid) -> np.ndarray:
    """The HTTP tile with every change and every sample (max_age 0: the /map publisher may keep the
    tracers busy, and an update then thins its samples), once up to date (X-Map-Age 0)."""
    bbox = ",".join(repr(float(v)) for v in (*grid.origin, *grid.upper))
    url = f"http://127.0.0.1:{hport}/v1/occupancy?bbox={bbox}&resolution={RESOLUTION}&format=npy&max_age=0"

    def current():
        status, headers, body = get(url)
        return body if status == 200 and float(headers["X-Map-Age"]) == 0 else None

    return np.load(io.BytesIO(wait_for(current, 60, "an up-to-date tile", interval=0.2)))


def stored_map(data, grid: Grid, poses: dict[int, Pose] | None = None) -> np.ndarray:
    """The offline reconstruction of the stored models, at their stored (or `poses`) poses, with the
    server's seeds: what the server must serve, bit for bit."""
    with store_db(data) as db:
        messages = {n: decode(raw, expect=ScanMessage) for n, raw in db.execute("SELECT node, raw FROM scans")}
    items = [(m.model, (poses or {}).get(n, m.pose), scan_seed("ros", n)) for n, m in sorted(messages.items())]
    hits, misses = reconstruct(grid, items, samples_per_cell=4.0)
    return map_estimate(hits, misses, 0.2)


def replayed(tmp_path, name: str, intel, poses: np.ndarray, grid: Grid) -> np.ndarray:
    """`gmmap replay` of a ROS 2 bag of the same scans and /tf_static with odometry at `poses`."""
    m = RosMessages("sqlite3")
    messages = [intel.static]
    for (_, scan), (x, y, theta), stamp in zip(intel.steps, poses, intel.stamps):
        body = laser_3d(x, y, theta).compose(MOUNT.inverse())
        messages += [("/odom", ODOMETRY, stamp, m.odometry(float(stamp), "odom", "base_link", body)), scan]
    bag = write_bag(tmp_path / name, "sqlite3", sorted(messages, key=lambda msg: msg[2]))
    out = tmp_path / f"{name}.npz"
    bbox = ",".join(repr(float(v)) for v in (*grid.origin, *grid.upper))
    args = [str(bag), "--scan-topic", "/scan", "--pose-topic", "/odom", "--bbox=" + bbox, "--resolution"]
    assert main(["replay", *args, str(RESOLUTION), *EVERY_SCAN, "--out", str(out)]) == 0
    return np.load(out)["prob"]


def occupancy_grid(message) -> tuple[Grid, np.ndarray]:
    """The grid an OccupancyGrid covers (resolution as the server was given it, 0.1 m: the message
    holds it as float32) and its cells [iy, ix]."""
    info = message.info
    assert abs(info.resolution - RESOLUTION) < 1e-7
    origin = np.array([info.origin.position.x, info.origin.position.y])
    grid = Grid.from_bbox(origin, origin + np.array([info.width, info.height]) * RESOLUTION, RESOLUTION)
    return grid, np.asarray(message.data, dtype=np.int8).reshape(info.height, info.width)


def near(xytheta: np.ndarray, expected: np.ndarray, atol: float) -> bool:
    """Same position and heading (angles compared modulo 2 pi)."""
    heading = abs(np.angle(np.exp(1j * (xytheta[2] - expected[2]))))
    return bool(np.all(np.abs(xytheta[:2] - expected[:2]) <= atol) and heading <= atol)


def assert_near(xytheta: np.ndarray, expected: np.ndarray, atol: float) -> None:
    assert near(xytheta, expected, atol), (xytheta, expected)


def agreement(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(classify(a, 0.09) == classify(b, 0.09)))


@pytest.mark.parametrize("mapping", ["rmw_zenoh", "bridge"])
def test_live_ros2_topics_through_a_router_map_as_replay_does(procs, intel, mapping, tmp_path):
    rport, hport, data = free_port(), free_port(), tmp_path / "data"
    router = f"tcp/127.0.0.1:{rport}"
    procs.ready(procs.start("router", "router", "--listen", router), "gmmap router ready")
    ros_map = ["--ros-map", "/map", "--ros-map-period", "0.5", "--ros-mapping", mapping]
    procs.server("server", data, None, hport, "--zenoh-connect", router, *ros_map)
    # a bridge started with namespace bot1 puts it before every key of the DDS robot's topics, absolute or not
    namespace = "bot1" if mapping == "bridge" else ""
    ros_args = ["--scan-topic", "/scan", "--odom-topic", "/odom", "--path-topic", "/slam/path"]
    ros_args += ["--ros-namespace", namespace]
    # the robot is up first: its /tf_static was published before the agent came (transient local)
    robot_config = zenoh_config("client", connect=[router])
    robot_config.insert_json5("timestamping/enabled", "true")  # for the publication cache
    session = zenoh.open(robot_config)
    robot = RosRobot(session, mapping, namespace)
    if mapping == "rmw_zenoh":
        robot.latch(*intel.static[:2], intel.static[3])
    agent = procs.start(
        "agent",
        "agent",
        "--robot",
        "ros",
        "--zenoh-connect",
        router,
        "--source",
        "ros2",
        *ros_args,
        "--ros-mapping",
        mapping,
        "--outbox",
        str(tmp_path / "outbox.db"),
        "--timeout",
        "30",
        *EVERY_SCAN,
    )
    procs.wait_ready("agent", "ros2 ready", 180)  # a loaded machine takes its time
    grids, paths = (
        MapSubscriber(session, mapping, "/map", OCCUPANCY_GRID),
        MapSubscriber(session, mapping, "/ros/trajectory", PATH),
    )
    try:
        if mapping == "bridge":  # the bridge's own caching is the bridge's: published while the agent listens
            robot.publish(*intel.static[:2], intel.static[3])
        for step in intel.steps:
            for topic, msgtype, _, message in step:
                robot.publish(topic, msgtype, message)
        wait_for(lambda: stored_nodes(data, "ros") == set(range(SCANS)), 60, f"{SCANS} stored nodes")
        grid = grid_of(intel)
        odometry_map = served(hport, grid)

        # each node at the laser's odometry pose, through Odometry of base_link and the /tf_static mount
        with store_db(data) as db:
            for node, raw in db.execute("SELECT node, raw FROM scans"):
                pose = decode(raw, expect=ScanMessage).pose.as_xytheta()
                assert_near(pose, intel.odometry[node], 1e-4)
        assert np.array_equal(odometry_map, stored_map(data, grid))
        assert agreement(odometry_map, replayed(tmp_path, "odometry", intel, intel.odometry, grid)) >= CLASS_AGREEMENT

        path_sent = robot.publish(*intel.path[:2], intel.path[3])
        wait_for(
            lambda: (
                {r["robot"]: r["pose_revision"] for r in json.loads(http_get(hport, "/v1/robots"))}.get("ros")
                is not None
            ),
            30,
            "the pose-graph update",
        )
        with store_db(data) as db:
            graph = read_graph(db, "default", "ros")
        # The nodes whose beam ends the Path moves by over agent.pose_tolerance (1 cm), at the corrected
        # pose in 0.1 mm codes (protocol v3); the others keep their scan's own pose.
        corrected_poses = {n: pose for n in range(SCANS) if (pose := graph.pose(n)) is not None}
        print(f"{mapping}: {len(corrected_poses)} of {SCANS} nodes corrected")
        assert len(corrected_poses) >= SCANS // 2
        for node, pose in corrected_poses.items():
            assert_near(pose.as_xytheta(), intel.corrected[node], 1e-4)
        served_poses = [intel.corrected[k] if k in corrected_poses else intel.odometry[k] for k in range(SCANS)]
        corrected_map = served(hport, grid)
        assert np.array_equal(corrected_map, stored_map(data, grid, corrected_poses))

        # /map: a grid the server publishes after the update, decoded by rosbags, as the HTTP tile (it
        # publishes on change, possibly before the update showed in /v1/robots: looked for since the put)
        def as_tile(message) -> bool:
            ros_grid, cells = occupancy_grid(message)
            tile = served(hport, ros_grid)
            return cells.shape == tile.shape and np.array_equal(
                cells, np.where(tile == 0.5, -1, np.rint(tile * 100)).astype(np.int8)
            )

        grid_message = grids.first(after=path_sent, accept=as_tile)
        assert grid_message.header.frame_id == "map"
        ros_grid, cells = occupancy_grid(grid_message)
        assert ros_grid.shape[0] == grid_message.info.width
        assert (cells == -1).mean() < 0.9 and (cells > 65).sum() > 100  # walls and free space, not all unknown

        def as_served(path) -> bool:
            xytheta = [
                (p.position.x, p.position.y, 2 * np.arctan2(p.orientation.z, p.orientation.w))
                for p in (stamped.pose for stamped in path.poses)
            ]
            return len(xytheta) == SCANS and all(
                near(np.array(p), served_poses[k], 1e-4) for k, p in enumerate(xytheta)
            )

        paths.first(after=path_sent, accept=as_served)
        if mapping == "rmw_zenoh":  # the agent and the server in the ROS graph (`ros2 node list`, `ros2 topic info`)
            tokens = {str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/**") if r.ok is not None}
            entities = {tuple(t.split("/")[5:10]) for t in tokens}
            assert ("NN", "%", "%", "gmmap_agent_ros") in {e[:4] for e in entities}, tokens
            for topic, dds in (
                ("%scan", "sensor_msgs::msg::dds_::LaserScan_"),
                ("%slam%path", "nav_msgs::msg::dds_::Path_"),
            ):
                assert ("MS", "%", "%", "gmmap_agent_ros", topic) in entities, tokens
                assert any(f"/{topic}/{dds}/RIHS01_" in t for t in tokens), tokens
            assert ("MP", "%", "%", "gmmap_server_default", "%map") in entities, tokens
        # a late joiner gets the last grid from the publisher's cache (transient local)
        late = MapSubscriber(session, mapping, "/map", OCCUPANCY_GRID)
        assert np.array_equal(occupancy_grid(late.settled(after=0.0))[1], cells)

        corrected_replay = replayed(tmp_path, "corrected", intel, intel.corrected, grid)
        agree, before = agreement(corrected_map, corrected_replay), agreement(odometry_map, corrected_replay)
        print(f"{mapping}: classes as the corrected replay's: {agree:.4f} (before the Path: {before:.4f})")
        assert agree >= CLASS_AGREEMENT
        assert before < agree - 0.01
    finally:
        robot.close()
        session.close()
    agent.send_signal(signal.SIGINT)
    assert procs.finish(agent, 60) == 0, procs.log(agent)
    log = procs.log(agent)
    assert f"{2 * SCANS + 2} samples, {SCANS} nodes, 1 pose-graph updates; 0 scans dropped" in log, log


def test_a_secured_router_passes_each_robots_ros_topics_and_the_map_and_no_forgery(procs, intel, tmp_path):
    """docs/security/router-ros2.json5 as shipped: robot a's ROS topics (namespace /a) reach its agent,
    a's puts on b's topics reach nobody, both robots read /map and see a's agent in the graph."""
    shutil.copytree(ROOT / "docs" / "security", tmp_path / "docs" / "security")
    security = tmp_path / "docs" / "security"
    rport, hport, data = free_port(), free_port(), tmp_path / "data"
    router = f"tcp/127.0.0.1:{rport}"
    config = ["--zenoh-config", "docs/security/router-ros2.json5"]
    procs.ready(procs.start("router", "router", "--listen", router, *config), "gmmap router ready")
    server_config = ("--zenoh-config", "docs/security/server-via-router.json5")
    procs.server("server", data, None, hport, "--zenoh-connect", router, *server_config, "--ros-map", "/map")
    agents = {}
    for robot in ("a", "b"):
        agents[robot] = procs.start(
            f"agent-{robot}",
            "agent",
            "--robot",
            robot,
            "--zenoh-connect",
            router,
            "--zenoh-config",
            f"docs/security/robot-{robot}.json5",
            "--source",
            "ros2",
            "--ros-namespace",
            f"/{robot}",
            "--scan-topic",
            "scan",
            "--odom-topic",
            "odom",
            "--outbox",
            str(tmp_path / f"outbox-{robot}.db"),
            "--timeout",
            "30",
            *EVERY_SCAN,
        )
        procs.wait_ready(f"agent-{robot}", "ros2 ready", 180)
    sessions = {
        r: zenoh.open(zenoh_config("client", connect=[router], config_file=str(security / f"robot-{r}.json5")))
        for r in ("a", "b")
    }
    robot = RosRobot(sessions["a"], "rmw_zenoh")
    grids = MapSubscriber(sessions["b"], "rmw_zenoh", "/map", OCCUPANCY_GRID)
    try:
        robot.publish("/a/tf_static", intel.static[1], intel.static[3])
        for step in intel.steps[:20]:
            for topic, msgtype, _, message in step:
                robot.publish(f"/a{topic}", msgtype, message)
                # the same bytes on robot b's keys: dropped by the router
                forged = bytes(robot.store.serialize_cdr(message, msgtype))
                sessions["a"].put(robot.key(f"/b{topic}", msgtype), forged)
        wait_for(lambda: stored_nodes(data, "a") == set(range(20)), 60, "robot a's 20 nodes")
        grid = grids.settled(after=0.0)
        assert (np.asarray(grid.data) > 65).sum() > 10
        tokens = {str(r.ok.key_expr) for r in sessions["b"].liveliness().get("@ros2_lv/0/**") if r.ok is not None}
        assert any(t.endswith("/NN/%/%a/gmmap_agent_a") for t in tokens), tokens
        assert any("/MP/%/%/gmmap_server_default/%map/" in t for t in tokens), tokens
    finally:
        robot.close()
        for s in sessions.values():
            s.close()
    for agent in agents.values():
        agent.send_signal(signal.SIGINT)
        assert procs.finish(agent, 60) == 0, procs.log(agent)
    assert "ros2 stopped: 41 samples, 20 nodes" in procs.log(agents["a"]), procs.log(agents["a"])
    assert "ros2 stopped: 0 samples, 0 nodes" in procs.log(agents["b"]), procs.log(agents["b"])
    assert "warning: no sample arrived on the scan topic's key" in procs.log(agents["b"])
    assert "no sample arrived" not in procs.log(agents["a"])
    assert stored_nodes(data, "b") == set()


def test_without_a_server_the_agent_stops_with_1_and_what_it_holds(procs, intel, tmp_path):
    router = f"tcp/127.0.0.1:{free_port()}"
    procs.ready(procs.start("router", "router", "--listen", router), "gmmap router ready")
    outbox = tmp_path / "outbox.db"
    agent = procs.start(
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
        "--outbox",
        str(outbox),
        "--timeout",
        "2",
        *EVERY_SCAN,
    )
    procs.wait_ready("agent", "ros2 ready", 180)  # a loaded machine takes its time
    session = zenoh.open(zenoh_config("client", connect=[router]))
    robot = RosRobot(session, "rmw_zenoh")
    try:
        robot.publish(*intel.static[:2], intel.static[3])
        for step in intel.steps[:3]:
            for topic, msgtype, _, message in step:
                robot.publish(topic, msgtype, message)
        wait_for(lambda: len(written_nodes(outbox)) == 3, 30, "3 scans in the outbox")
    finally:
        robot.close()
        session.close()
    agent.send_signal(signal.SIGTERM)
    assert procs.finish(agent, 60) == 1, procs.log(agent)
    assert "3 messages not acknowledged after 2 s" in procs.log(agent), procs.log(agent)


def test_a_3d_robot_in_a_2d_fleet_is_refused_and_the_agent_exits_3_saying_so(procs, tmp_path):
    """The server refuses the robot's PointCloud2 scans for good (its fleet's map is 2D): at its stop
    the agent says so after its counts, in the words of a file source, and exits 3, not 0."""
    router, data = f"tcp/127.0.0.1:{free_port()}", tmp_path / "data"
    procs.ready(procs.start("router", "router", "--listen", router), "gmmap router ready")
    procs.server("server", data, None, free_port(), "--zenoh-connect", router)
    rng = np.random.default_rng(0)
    flat = AgentConfig(robot="flat", zenoh_connect=(router,), outbox=str(tmp_path / "flat.db"))
    with Agent.open(GmmapConfig(agent=flat, keyframe=KeyframeConfig.every_scan())) as agent:  # the map is 2D
        assert agent.add_scan(rng.normal(size=(100, 2)) + [3.0, 0.0], None, Pose.identity(2), 0.0) == 0
        assert agent.flush(60) == 0
    outbox = tmp_path / "outbox.db"
    ros_args = ["--source", "ros2", "--scan-topic", "/scan", "--outbox", str(outbox), "--timeout", "30"]
    agent = procs.start("agent", "agent", "--robot", "solid", "--zenoh-connect", router, *ros_args, *EVERY_SCAN)
    procs.wait_ready("agent", "ros2 ready", 180)  # a loaded machine takes its time
    session = zenoh.open(zenoh_config("client", connect=[router]))
    robot, m = RosRobot(session, "rmw_zenoh"), RosMessages("sqlite3")
    try:
        robot.publish("/tf_static", TF, m.tf([(0.0, "base_link", "laser", MOUNT)]))
        robot.publish("/tf", TF, m.tf([(s, "odom", "base_link", laser_3d(s, 0.0, 0.0)) for s in (1.0, 3.0)]))
        cloud = (rng.normal(size=(400, 3)) + [5.0, 0.0, 0.0]).astype(np.float32)
        xyz = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
        robot.publish("/scan", POINT_CLOUD2, m.point_cloud(2.0, "laser", cloud.tobytes(), xyz, 12, len(cloud)))
        wait_for(lambda: rejected_nodes(outbox) == {0}, 60, "the 3D scan refused")
    finally:
        robot.close()
        session.close()
    agent.send_signal(signal.SIGINT)
    assert procs.finish(agent, 60) == 3, procs.log(agent)
    counts, refused = procs.log(agent).strip().splitlines()[-2:]
    assert "ros2 stopped: 3 samples, 1 nodes, 0 pose-graph updates; 0 scans dropped" in counts, counts
    assert refused == (
        "gmmap agent solid: the server refused 1 messages for good (dimension: this map is 2D, the message is 3D); "
        f"they are not stored and not resent (listed in table `rejected` of {outbox}); 0 scans were not published"
    )
    assert stored_nodes(data, "solid") == set() and stored_nodes(data, "flat") == {0}
