"""The `ros2` section of the configuration: how gmmap meets ROS 2 over Zenoh (agent and server).

Both sides name topics the ROS way (`/scan`, relative names under `namespace`) and reach them in
one of two key layouts (`mapping`, services/ros2/names.py): `rmw_zenoh` (ROS 2 Jazzy and later
with the Zenoh middleware) or `bridge` (zenoh-bridge-ros2dds in front of a DDS robot).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gmm_core.validation import require_count, require_number

MAPPINGS = ("rmw_zenoh", "bridge")
# ROS 2 distributions with RIHS01 type hashes (REP 2016, from Iron on); rmw_zenoh ships from Jazzy
DISTROS = ("iron", "jazzy", "kilted", "lyrical")


def check_topic(field: str, name: str) -> str:
    """A ROS topic name: '/'-separated tokens of letters, digits and '_' (relative names allowed)."""
    tokens = name.strip("/").split("/")
    if not name or any(not t or not (t.replace("_", "a").isalnum() and t.isascii()) or t[0].isdigit() for t in tokens):
        raise ValueError(f"{field}: not a ROS topic name (letters, digits, '_' between '/'), got {name!r}")
    return name


@dataclass(frozen=True)
class Ros2Config:
    mapping: str = "rmw_zenoh"  # key layout, one of MAPPINGS
    domain: int = 0  # ROS_DOMAIN_ID, the first chunk of every rmw_zenoh key
    # ROS namespace of relative topic names (and of gmmap's nodes), '' for none; in the bridge layout the
    # bridge's, before every name, absolute ones too (names.py)
    namespace: str = ""
    distro: str = "jazzy"  # whose RIHS01 type hashes gmmap publishes with, one of DISTROS
    # agent, `--source ros2` (its scan topic is agent.scan_topic)
    odom_topic: str | None = None  # nav_msgs/Odometry of the robot body; None: poses from /tf and /tf_static
    path_topic: str | None = None  # nav_msgs/Path of a SLAM back end's optimised poses; None: no corrections
    hold_scans: int = 100  # scans waiting for their pose, at most; the oldest beyond are dropped (counted)
    hold_s: float = 5.0  # s of pose data past a scan's stamp after which a scan that cannot be posed is dropped
    match_s: float = 0.005  # s: a path pose corrects the node whose stamp is this close
    # server, `--ros-map`
    map_topic: str | None = None  # nav_msgs/OccupancyGrid topic; None: no map published
    map_resolution: float = 0.1  # m per cell of the published grid
    map_period: float = 2.0  # s between publications, at least (only when the map changed)
    map_z: str | None = None  # "zmin,zmax", m: the height band of a 3D map's 2D projection; None: all heights
    map_cells: int = 4_000_000  # cells of the published grid, at most: a larger extent is cut around its centre

    def __post_init__(self):
        if self.mapping not in MAPPINGS:
            raise ValueError(f"ros2.mapping: must be one of {', '.join(MAPPINGS)}, got {self.mapping!r}")
        require_count("ros2.domain", self.domain, minimum=0)
        if self.domain > 232:  # ROS 2's own limit (the DDS port formula)
            raise ValueError(f"ros2.domain: must be 0 to 232, got {self.domain}")
        if self.namespace:
            check_topic("ros2.namespace", self.namespace)
        if self.distro not in DISTROS:
            raise ValueError(f"ros2.distro: must be one of {', '.join(DISTROS)}, got {self.distro!r}")
        for name in ("odom_topic", "path_topic", "map_topic"):
            if getattr(self, name) is not None:
                check_topic(f"ros2.{name}", getattr(self, name))
        require_count("ros2.hold_scans", self.hold_scans, minimum=1)
        require_number("ros2.hold_s", self.hold_s, positive=True)
        require_number("ros2.match_s", self.match_s, positive=False)
        require_number("ros2.map_resolution", self.map_resolution, positive=True)
        require_number("ros2.map_period", self.map_period, positive=True)
        require_count("ros2.map_cells", self.map_cells, minimum=1)
        if self.map_z is not None:
            self.z_band  # noqa: B018 - checks it

    @property
    def z_band(self) -> tuple[float, float] | None:
        """map_z as (zmin, zmax), m."""
        if self.map_z is None:
            return None
        try:
            lo, hi = (float(v) for v in self.map_z.split(","))
        except ValueError:
            lo = hi = math.nan
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"ros2.map_z: must be zmin,zmax with finite zmin < zmax, got {self.map_z!r}")
        return lo, hi
