"""`gmmap server --ros-map TOPIC`: the fleet map as nav_msgs/OccupancyGrid, and each robot's
trajectory as nav_msgs/Path on `/<robot>/trajectory`, for RViz, Nav2 and any ROS 2 subscriber.

Every `map_period` s at most, and only when the map changed (a scan stored or a pose graph
applied: the robots' node counts and revisions differ), the grid is asked of the FleetMap exactly
as an HTTP tile is (`FleetMap.occupancy_answer`, the tile cache's incremental update), over the
whole extent of the map (`FleetMap.extent`), cut around its centre to `map_cells` cells. A state
served older than the map (busy tracers, tile_serving.py) is published and asked for again a period later.
- Frame `map`; the grid's min corner is the map origin, cells of `map_resolution`, rows along y.
- data: round(100 p) from the MAP estimate (Eq. 11); -1 where p is exactly 0.5, the value of a
  cell no ray reached (Eq. 12's dead band is left to the consumer, e.g. map_server's thresholds).
- A 3D map is traced over the height band `map_z` (default: the map's own) and projected: a
  column takes its most occupied seen cell, -1 when it has none.
Each sample carries rmw_zenoh's attachment. The grid's publisher keeps its last sample in a Zenoh
advanced-publisher cache (transient local, as rmw_zenoh does it: late joiners that query, e.g. an
AdvancedSubscriber with history, get it), which needs the session's timestamping on
(`timestamped`). In rmw_zenoh's layout the server is a ROS node with a publisher token per topic.
"""

from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np
import zenoh
import zenoh.ext

from gmm_core import Grid, Pose
from services.api import params
from services.map_server.fleet_map import FleetMap

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
    typestore,
)

log = logging.getLogger("gmmap.ros2")

OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
PATH = "nav_msgs/msg/Path"
FRAME = "map"
GRID_QOS = qos_chunk(RELIABLE, TRANSIENT_LOCAL, KEEP_LAST, 1)  # as nav2's map_server publishes /map
PATH_QOS = qos_chunk(RELIABLE, VOLATILE, KEEP_LAST, 1)
POLL_S = 0.05  # s between looks for a change (a publication waits for the period, not for this)


def timestamped(config: zenoh.Config) -> zenoh.Config:
    """The session config with timestamping on, which an advanced publisher's cache needs."""
    config.insert_json5("timestamping/enabled", "true")
    return config


def map_grid(lo: np.ndarray, hi: np.ndarray, resolution: float, cells: int, z_band=None) -> Grid:
    """The grid over [lo, hi] aligned to whole cells from the world origin, cut around its centre to
    at most `cells` cells; a 3D box takes the z band (zmin, zmax) when given."""
    lo, hi = np.array(lo, dtype=np.float64), np.array(hi, dtype=np.float64)
    if z_band is not None and len(lo) == 3:
        lo[2], hi[2] = z_band
    lo, hi = np.floor(lo / resolution) * resolution, np.ceil(hi / resolution) * resolution
    spans = np.maximum(np.round((hi - lo) / resolution), 1)
    if spans.prod() > cells:
        keep = np.floor(spans * (cells / spans.prod()) ** (1 / len(spans)))
        lo = lo + np.floor((spans - np.maximum(keep, 1)) / 2) * resolution
        spans = np.maximum(keep, 1)
    return params.grid(lo, lo + spans * resolution, resolution)


def grid_cells(prob: np.ndarray) -> np.ndarray:
    """OccupancyGrid data (int8, row-major from the min corner) of p(occupied) [iy, ix] or [iz, iy, ix]."""
    seen = prob != 0.5
    percent = np.rint(prob * 100).astype(np.int8)
    if prob.ndim == 3:  # the most occupied seen cell of each column
        percent = np.where(seen, percent, -1).max(axis=0)
        return percent.ravel()
    return np.where(seen, percent, -1).astype(np.int8).ravel()


def _stamp(store, seconds: float):
    sec, nanosec = divmod(round(seconds * 1e9), 10**9)
    return store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _pose(store, pose: Pose):
    g = "geometry_msgs/msg/"
    if pose.dim == 2:
        x, y, theta = pose.as_xytheta()
        position, (w, qx, qy, qz) = (x, y, 0.0), (math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2))
    else:
        position, (w, qx, qy, qz) = tuple(pose.t), tuple(pose.as_quaternion())
    return store.types[g + "Pose"](
        position=store.types[g + "Point"](*(float(v) for v in position)),
        orientation=store.types[g + "Quaternion"](x=float(qx), y=float(qy), z=float(qz), w=float(w)),
    )


class RosMapPublisher:
    """A thread publishing the map and the trajectories on the server's Zenoh session."""

    def __init__(self, session: zenoh.Session, fleet_map: FleetMap, ros: Ros2Config, fleet: str):
        self.session, self.fleet_map, self.ros = session, fleet_map, ros
        self.store = typestore(ros.distro)
        keys = TopicKeys.of(ros.map_topic, ros)
        self.topic = keys.name
        self._graph = RosNode(ros.domain, session_id(session.zid()), node_name("gmmap_server", fleet), ros.namespace)
        self._tokens: list = []
        self._entities = 0
        self._sequence = 0
        self._trajectories: dict[str, tuple] = {}  # robot -> (publisher, gid, published signature)
        key = keys.publication(OCCUPANCY_GRID, ros.distro)
        self._grid_gid = self._announce(self.topic, OCCUPANCY_GRID, GRID_QOS)
        self._grid_publisher = zenoh.ext.declare_advanced_publisher(
            session, key, cache=zenoh.ext.CacheConfig(1), publisher_detection=True
        )
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="gmmap-ros-map", daemon=True)
        self._thread.start()

    def _announce(self, topic: str, msgtype: str, qos: str) -> bytes:
        """Declare the publisher's liveliness token (rmw_zenoh layout); its GID for attachments."""
        self._entities += 1
        if not self._tokens and self.ros.mapping == "rmw_zenoh":
            self._tokens.append(self.session.liveliness().declare_token(self._graph.token))
        token = self._graph.entity_token(self._entities, "MP", topic, msgtype, self.ros.distro, qos)
        if self.ros.mapping == "rmw_zenoh":
            self._tokens.append(self.session.liveliness().declare_token(token))
        return wire.gid_of(token)

    def _attachment(self, gid: bytes) -> bytes | None:
        if self.ros.mapping != "rmw_zenoh":
            return None
        self._sequence += 1
        return wire.Attachment(self._sequence, time.time_ns(), gid).encode()

    def _signature(self) -> tuple:
        return tuple((r["robot"], r["nodes"], r["pose_revision"]) for r in self.fleet_map.robots())

    def _loop(self) -> None:
        published, last = None, -math.inf
        while not self._stop.wait(POLL_S):
            signature = self._signature()
            if signature == published or time.monotonic() - last < self.ros.map_period:
                continue
            last = time.monotonic()
            try:
                current = self.publish_grid()
                self.publish_trajectories()
                # a state older than the map (the tracers were busy: tile_serving.py) goes out again next period
                published = signature if current else None
            except Exception:  # noqa: BLE001 - a failed publication is logged; the server keeps serving
                log.exception("publishing the map on %s failed", self.topic)

    def publish_grid(self) -> bool:
        """Publish the map; whether the state published was up to date with every sample (else it was a
        previous one, at most tiles.MAX_STALE_S old, or one thinned, served while the tracers were busy)."""
        extent = self.fleet_map.extent()
        if extent is None:
            return True
        ros = self.ros
        grid = map_grid(*extent, ros.map_resolution, ros.map_cells, ros.z_band)
        answer = self.fleet_map.occupancy_answer(grid)
        prob = answer.prob
        now = time.time()
        t = self.store.types
        info = t["nav_msgs/msg/MapMetaData"](
            map_load_time=_stamp(self.store, now),
            resolution=grid.resolution,
            width=grid.shape[0],
            height=grid.shape[1],
            # the min corner; a 3D map's projection lies at the bottom of its band
            origin=_pose(self.store, Pose.from_quaternion([*grid.origin[:2], grid.origin[2:3].sum()], [1, 0, 0, 0])),
        )
        header = t["std_msgs/msg/Header"](stamp=_stamp(self.store, now), frame_id=FRAME)
        message = t[OCCUPANCY_GRID](header=header, info=info, data=grid_cells(prob))
        payload = wire.encode(message, OCCUPANCY_GRID, ros.distro)
        self._grid_publisher.put(payload, attachment=self._attachment(self._grid_gid))
        return answer.age == 0 and answer.samples_per_cell == self.fleet_map.samples_per_cell  # else again, refined

    def publish_trajectories(self) -> None:
        t, now = self.store.types, time.time()
        for row in self.fleet_map.robots():
            robot, signature = row["robot"], (row["nodes"], row["pose_revision"])
            if robot not in self._trajectories:
                keys = TopicKeys.of(f"/{robot.replace('-', '_')}/trajectory", self.ros)
                key = keys.publication(PATH, self.ros.distro)
                gid = self._announce(keys.name, PATH, PATH_QOS)
                self._trajectories[robot] = (self.session.declare_publisher(key), gid, None)
            publisher, gid, sent = self._trajectories[robot]
            if sent == signature:
                continue
            header = t["std_msgs/msg/Header"](stamp=_stamp(self.store, now), frame_id=FRAME)
            poses = [
                t["geometry_msgs/msg/PoseStamped"](header=header, pose=_pose(self.store, pose))
                for _, pose in self.fleet_map.world_poses(robot)
            ]
            payload = wire.encode(t[PATH](header=header, poses=poses), PATH, self.ros.distro)
            publisher.put(payload, attachment=self._attachment(gid))
            self._trajectories[robot] = (publisher, gid, signature)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._grid_publisher.undeclare()
        for publisher, _, _ in self._trajectories.values():
            publisher.undeclare()
        for token in self._tokens:
            token.undeclare()
