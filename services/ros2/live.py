"""`gmmap agent --source ros2`: a robot's live ROS 2 topics over Zenoh, fitted and sent as nodes.

Subscribes (in the layout of `ros2.mapping`, names.py) to the scan topic (sensor_msgs/LaserScan
or PointCloud2), the poses (tf and tf_static, under `ros2.namespace` as multi-robot set-ups remap
them, or `ros2.odom_topic`) and optionally a SLAM back
end's nav_msgs/Path (`ros2.path_topic`). Samples are queued by Zenoh's threads and handled in
order by one thread, which:
- converts a scan as the rosbag reader does (ros_messages: REP 117 for LaserScan) and holds it
  until its pose at the scan's stamp is known (poses.LivePoses); at most `ros2.hold_scans` wait,
  and one still unposable once the poses reach `ros2.hold_s` past its stamp is dropped, counted;
- passes a posed scan to Agent.add_scan: the keyframe policy, the fit, the outbox and delivery are
  those of every other source;
- matches a Path's poses to the nodes by stamp (within `ros2.match_s`), composes each with the
  node's body-to-sensor mount, and sends what moved as one pose-graph update (Agent.correct).
A sample that cannot be read (bad CDR, a wrong type, a malformed rmw attachment) is logged with
its topic and counted; nothing else changes. In rmw_zenoh's layout the agent is a ROS node in
the graph: liveliness tokens for the node and each subscription (the scan's once its type is seen).
Runs until SIGINT or SIGTERM, then waits up to `agent.timeout` s for the outbox to be acknowledged.
"""

from __future__ import annotations

import logging
import queue
import sys
import threading
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np
import zenoh
import zenoh.ext

from gmm_core.pose import Pose
from services.agent.agent import Agent
from services.agent.outcome import run_outcome
from services.config import GmmapConfig, summary
from services.datasets.common import DatasetError, split_points
from services.datasets.ros_messages import (
    LASER_SCAN,
    POSE_TYPES,
    SCAN_TYPES,
    frame_name,
    geometry_pose,
    laser_scan_beams,
    planar_pose,
    point_cloud_xyz,
    stamp_seconds,
)
from services.stopping import StopSignal
from services.zenoh_config import zenoh_config

from . import wire
from .config import Ros2Config
from .names import (
    KEEP_LAST,
    RELIABLE,
    TRANSIENT_LOCAL,
    VOLATILE,
    RosNode,
    TopicKeys,
    node_name,
    qos_chunk,
    session_id,
)
from .poses import LivePoses

log = logging.getLogger("gmmap.ros2")

TF = "tf2_msgs/msg/TFMessage"
# the options of file sources, and what a live ROS 2 source has instead
FILE_OPTIONS = {
    "corrections": "a SLAM back end's nav_msgs/Path: --path-topic",
    "poses": "tf or --odom-topic",
    "pose_topic": "--odom-topic",
    "scans": "it runs until SIGINT/SIGTERM",
}
PATH = "nav_msgs/msg/Path"
SUBSCRIPTION_QOS = qos_chunk(RELIABLE, VOLATILE, KEEP_LAST, 10)
STATIC_QOS = qos_chunk(RELIABLE, TRANSIENT_LOCAL, KEEP_LAST, 1)  # as tf2's static listener


@dataclass
class HeldScan:
    stamp: float
    frame: str
    planar: bool  # a LaserScan: posed in the plane
    hits: np.ndarray
    no_return: np.ndarray


@dataclass(frozen=True)
class NodeRecord:
    stamp: float
    mount: Pose  # the scan frame in the body frame (3D)
    planar: bool


class LiveSource:
    """The subscriptions of one robot's topics and the thread-side handling of their samples."""

    def __init__(self, agent: Agent, ros: Ros2Config, scan_topic: str, session: zenoh.Session, robot: str):
        self.agent = agent
        self.ros = ros
        self.session = session
        self.counts: Counter[str] = Counter()  # received, nodes, updates, bad, dropped_unposed, dropped_behind
        self.poses = LivePoses(odometry=ros.odom_topic is not None)
        self._held: deque[HeldScan] = deque()
        self._nodes: dict[int, NodeRecord] = {}
        self._inbox: queue.SimpleQueue = queue.SimpleQueue()
        self._scans_queued = 0
        self._lock = threading.Lock()
        # tf and tf_static are relative, as multi-robot set-ups remap them (Nav2: /tf:=tf): /tf without a
        # namespace. With odometry, tf_static alone mounts the sensor on the odometry's child frame.
        topics = {"scan": (scan_topic, SCAN_TYPES), "tf_static": ("tf_static", (TF,))}
        if ros.odom_topic is None:
            topics["tf"] = ("tf", (TF,))
        else:
            topics["odom"] = (ros.odom_topic, POSE_TYPES)
        if ros.path_topic is not None:
            topics["path"] = (ros.path_topic, (PATH,))
        self.topics = {role: (TopicKeys.of(topic, ros), types) for role, (topic, types) in topics.items()}
        self._graph = RosNode(ros.domain, session_id(session.zid()), node_name("gmmap_agent", robot), ros.namespace)
        self._tokens = []
        self._entity = 0
        if ros.mapping == "rmw_zenoh":
            self._tokens.append(session.liveliness().declare_token(self._graph.token))
            for role, (keys, types) in self.topics.items():
                if role != "scan":
                    self._declare_subscription(
                        keys.name, types[0], STATIC_QOS if role == "tf_static" else SUBSCRIPTION_QOS
                    )
        self._scan_type: str | None = None
        self._subscribers = [self._subscribe(role, keys) for role, (keys, _) in self.topics.items()]

    def _subscribe(self, role: str, keys: TopicKeys):
        """A subscriber of the topic; tf_static's, transient local as tf2's, also asks the publishers'
        caches for what they sent before it came (rmw_zenoh keeps transient-local samples in a Zenoh
        advanced publisher's cache), so a robot's mounts published at its start reach a later agent."""
        callback = lambda sample: self._on_sample(role, sample)  # noqa: E731
        if role != "tf_static":
            return self.session.declare_subscriber(keys.subscription, callback)
        history = zenoh.ext.HistoryConfig(detect_late_publishers=True)
        return zenoh.ext.declare_advanced_subscriber(self.session, keys.subscription, callback, history=history)

    def _declare_subscription(self, topic: str, msgtype: str, qos: str) -> None:
        self._entity += 1
        token = self._graph.entity_token(self._entity, "MS", topic, msgtype, self.ros.distro, qos)
        self._tokens.append(self.session.liveliness().declare_token(token))

    def describe(self) -> str:
        return ", ".join(f"{role} {keys.subscription}" for role, (keys, _) in self.topics.items())

    # -- Zenoh's threads: queue and return -------------------------------------------------
    def _on_sample(self, role: str, sample: zenoh.Sample) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        if role == "scan":
            with self._lock:
                if self._scans_queued >= self.ros.hold_scans:  # the fit is behind: newest dropped
                    self.counts["dropped_behind"] += 1
                    return
                self._scans_queued += 1
        self._inbox.put((role, str(sample.key_expr), sample.payload.to_bytes(), attachment))

    # -- the handling thread ---------------------------------------------------------------
    def run(self, stop: StopSignal) -> None:
        while not stop.is_set():
            try:
                item = self._inbox.get(timeout=0.1)
            except queue.Empty:
                continue
            self.handle(*item)

    def handle(self, role: str, key: str, payload: bytes, attachment: bytes | None) -> None:
        if role == "scan":
            with self._lock:
                self._scans_queued -= 1
        self.counts["received"] += 1
        self.counts[f"received_{role}"] += 1
        keys, types = self.topics[role]
        try:
            if attachment is not None and self.ros.mapping == "rmw_zenoh":
                wire.Attachment.decode(attachment)
            msgtype, msg = self._decode(keys, types, key, payload)
            if role == "scan":
                self._scan(msgtype, msg)
            elif role in ("tf", "tf_static"):
                self.poses.add_tf(msg, static=role == "tf_static")
            elif role == "odom":
                self.poses.add_odometry(msg, msgtype)
            else:
                self._correct(msg)
            self._pose_held()
        except (wire.RosWireError, DatasetError, ValueError) as error:
            self._count("bad", "ignored a sample on %s (%s): %s", keys.name, key, error)

    def _count(self, what: str, message: str, *args) -> None:
        """Count one more `what`; log it the 1st, 10th, 100th... time (a misconfigured robot repeats)."""
        self.counts[what] += 1
        n = self.counts[what]
        if n == 10 ** (len(str(n)) - 1):
            log.warning(f"{message} [{what} {n}]", *args)

    def _decode(self, keys: TopicKeys, types: tuple[str, ...], key: str, payload: bytes):
        """(type, message): the type the key names (rmw_zenoh), else the first of `types` that the
        bytes decode as (the bridge's keys name no type; CDR refuses a wrong type's lengths)."""
        named = keys.message_type(key)
        if keys.mapping == "rmw_zenoh":
            if named not in types:
                raise wire.RosWireError(f"key: type {named or key!r}, expected one of {', '.join(types)}")
            return named, wire.decode(payload, named)
        error = None
        for msgtype in types:
            try:
                return msgtype, wire.decode(payload, msgtype)
            except wire.RosWireError as e:
                error = e
        raise error

    def _scan(self, msgtype: str, msg) -> None:
        if self._scan_type is None and self.ros.mapping == "rmw_zenoh":
            self._declare_subscription(self.topics["scan"][0].name, msgtype, SUBSCRIPTION_QOS)
        self._scan_type = msgtype
        stamp, frame = stamp_seconds(msg.header), frame_name(msg.header.frame_id)
        if msgtype == LASER_SCAN:
            hits, no_return = laser_scan_beams(msg)
        else:
            hits, no_return = split_points(point_cloud_xyz(msg), 0.0, None)
        self._held.append(HeldScan(stamp, frame, msgtype == LASER_SCAN, hits, no_return))
        while len(self._held) > self.ros.hold_scans:
            self._held.popleft()
            self.counts["dropped_unposed"] += 1

    def _pose_held(self) -> None:
        """Send the held scans whose poses are known, in order of arrival."""
        while self._held:
            scan = self._held[0]
            try:
                pose = self.poses.sensor_pose(scan.frame, scan.stamp)
                mount = self.poses.mount(scan.frame, scan.stamp)
            except DatasetError as error:  # Extrapolation, or a frame not announced yet
                if self.poses.newest - scan.stamp <= self.ros.hold_s:
                    return  # its pose may still come; the scans behind it wait too
                self._held.popleft()
                self._count("dropped_unposed", "dropped a scan at %.3f s that cannot be posed: %s", scan.stamp, error)
                continue
            self._held.popleft()
            if scan.planar:
                pose = planar_pose(pose)
            node = self.agent.add_scan(scan.hits, scan.no_return, pose, scan.stamp)
            if node is not None:
                self._nodes[node] = NodeRecord(scan.stamp, mount, scan.planar)
                self.counts["nodes"] += 1

    def _correct(self, msg) -> None:
        """A SLAM back end's Path: the nodes whose stamps it has, re-posed (only what moved is sent)."""
        if not msg.poses or not self._nodes:
            return
        stamps = np.array([stamp_seconds(p.header) for p in msg.poses])
        order = np.argsort(stamps, kind="stable")
        stamps = stamps[order]
        nodes = np.fromiter(self._nodes, dtype=np.int64, count=len(self._nodes))
        node_stamps = np.array([self._nodes[n].stamp for n in nodes])
        j = np.clip(np.searchsorted(stamps, node_stamps), 1, max(len(stamps) - 1, 1))
        nearest = np.where(np.abs(stamps[j - 1] - node_stamps) <= np.abs(stamps[j] - node_stamps), j - 1, j)
        nearest = np.minimum(nearest, len(stamps) - 1)
        close = np.abs(stamps[nearest] - node_stamps) <= self.ros.match_s
        corrected = {}
        for node, k in zip(nodes[close], nearest[close]):
            record = self._nodes[int(node)]
            body = geometry_pose(msg.poses[order[k]].pose, f"path pose {order[k]}")
            sensor = body.compose(record.mount)
            corrected[int(node)] = planar_pose(sensor) if record.planar else sensor
        if corrected and self.agent.correct(corrected) is not None:
            self.counts["updates"] += 1

    def close(self) -> None:
        self.counts["dropped_unposed"] += len(self._held)  # held at the end: never posed
        self._held.clear()
        for subscriber in self._subscribers:
            subscriber.undeclare()
        for token in self._tokens:
            token.undeclare()
        self._subscribers, self._tokens = [], []


def _open_session(config: zenoh.Config, stop: StopSignal) -> zenoh.Session | None:
    """Open (a client blocks until a router answers) unless `stop` is set first."""
    box: list[zenoh.Session] = []
    opener = threading.Thread(target=lambda: box.append(zenoh.open(config)), name="gmmap-ros2-open", daemon=True)
    opener.start()
    while opener.is_alive() and not stop.is_set():
        opener.join(0.1)
    return box[0] if box else None


def run_ros2_agent(config: GmmapConfig) -> int:
    """`gmmap agent --source ros2` until SIGINT/SIGTERM; 0 once all is acknowledged, 1 if the
    timeout passes with messages still held in the outbox, 3 if the server refused messages for
    good (a 3D scan in a 2D fleet, a robot over its quota: table `rejected` of the outbox); the
    same outcome as a file source's (services.agent.outcome)."""
    o, ros = config.agent, config.ros2
    if o.scan_topic is None:
        raise ValueError("agent.scan_topic: --source ros2 needs --scan-topic (a LaserScan or PointCloud2 topic)")
    for name, instead in FILE_OPTIONS.items():
        if getattr(o, name) is not None:
            raise ValueError(f"agent.{name}: a ros2 source does not take it ({instead})")
    stop = StopSignal()
    print(
        f"gmmap agent {o.robot} config: {summary(agent=o, fit=config.fit, keyframe=config.keyframe, ros2=ros)}",
        file=sys.stderr,
        flush=True,
    )
    agent = Agent.open(config)
    source = None
    try:
        session = _open_session(zenoh_config("client", connect=o.zenoh_connect, config_file=o.zenoh_config), stop)
        if session is not None:
            source = LiveSource(agent, ros, o.scan_topic, session, o.robot)
            print(
                f"gmmap agent {o.robot}: ros2 ready ({ros.mapping}): {source.describe()}", file=sys.stderr, flush=True
            )
            source.run(stop)
            source.close()
            session.close()
        counts = source.counts if source is not None else Counter()
        # nothing held: nothing to wait for (a store that never answered has nothing of this run)
        pending = agent.flush(o.timeout) if agent.outbox.pending() else 0
        dropped = counts["dropped_unposed"] + counts["dropped_behind"]
        print(
            f"gmmap agent {o.robot}: ros2 stopped: {counts['received']} samples, {counts['nodes']} nodes, "
            f"{counts['updates']} pose-graph updates; {dropped} scans dropped ({counts['dropped_unposed']} without "
            f"a pose, {counts['dropped_behind']} behind the fit), {counts['bad']} unreadable samples",
            file=sys.stderr,
            flush=True,
        )
        if source is not None and not counts["received_scan"]:
            # the likeliest cause is a name: a topic, a mapping or a namespace the robot does not use
            print(
                f"gmmap agent {o.robot}: warning: no sample arrived on the scan topic's key "
                f"{source.topics['scan'][0].subscription}: check --scan-topic, --ros-mapping and --ros-namespace",
                file=sys.stderr,
                flush=True,
            )
        store = f"by store {agent.store}" if agent.store else "(nothing was held)"
        return run_outcome(agent, pending, f"all acknowledged {store}")
    finally:
        agent.close()
