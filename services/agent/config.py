"""The `agent` section of the configuration: one robot's agent (its fit is the `fit` section)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from gmm_core.validation import require_count, require_number
from protocol import ENCODINGS, check_id
from services.zenoh_config import DEFAULT_ENDPOINT, check_endpoints


@dataclass(frozen=True)
class AgentConfig:
    robot: str | None = None  # required to run: the robot's id, in its keys gmmap/<fleet>/<robot>/...
    source: str | None = (
        None  # required to run: FORMAT:PATH (a format of services.datasets.FORMATS) | sim:WORLD:INDEX:ROBOTS[:SEED]
    )
    fleet: str = "default"
    zenoh_connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)  # the router or server the agent (a client) reaches
    zenoh_config: str | None = None  # a Zenoh JSON5 file
    corrections: str | None = None  # corrected CARMEN log: odometry poses first, these as pose-graph updates
    poses: str | None = None  # point-cloud source: poses file (KITTI or TUM layout); None: the source's own
    scan_topic: str | None = None  # rosbag source: the LaserScan or PointCloud2 topic; None: the only one
    pose_topic: str | None = None  # rosbag source: Odometry / PoseStamped topic; None: poses from /tf
    scans: str | None = None  # "A:B" slice of the (matched) scans; node ids stay global
    rate: float = 0.0  # scans per second; 0: as fast as they are fitted
    outbox: str | None = None  # durable outbox; None: ./gmmap-data/outbox-<robot>.db
    encoding: str = "q"  # wire encoding of scans, one of protocol.ENCODINGS
    update_every: int | None = None  # scans between pose-graph updates (0: at the end); None: the source's
    odometry_only: bool = False  # with corrections: the matched scans, but no pose-graph updates
    window: int = 128  # messages published and not yet answered, at most; the outbox holds the rest
    resend_s: float = 1.0  # s, least time before resending what is unacknowledged (grows with the Ack RTT)
    timeout: float = 120.0  # s without an Ack, once everything is published, before giving up
    # MiB of acknowledged messages the outbox keeps, oldest forgotten first, so that a server that
    # lost them (a fresh data directory, a restored backup) gets them again; 0: forget at once.
    keep_acked_mb: float = 256.0
    # m: a node's corrected pose goes out only once some beam end of its scan would move by more than
    # this from the pose the server holds (|dt| + reach * |dR|; services/agent/sent_poses.py). 1 cm is
    # a fifth of the finest 5 cm map cell; over an hour of the office sim (beams reach 21 m) it sends
    # 4.2 poses per scan where 1 mm / 1 mrad sent 5.5: with protocol v3, 6.4 % of the scan payload
    # against 17.6 % (bench/pose_budget.py, docs/BENCHMARKS.md). 0: every change goes out.
    pose_tolerance: float = 0.01

    def __post_init__(self):
        if self.robot is not None:
            check_id(self.robot, "agent.robot")
        check_id(self.fleet, "agent.fleet")
        if self.encoding not in ENCODINGS:
            raise ValueError(f"agent.encoding: must be one of {', '.join(ENCODINGS)}, got {self.encoding!r}")
        require_number("agent.rate", self.rate, positive=False)
        require_number("agent.resend_s", self.resend_s, positive=True)
        require_count("agent.window", self.window, minimum=1)
        require_number("agent.timeout", self.timeout, positive=False)
        require_number("agent.keep_acked_mb", self.keep_acked_mb, positive=False)
        require_number("agent.pose_tolerance", self.pose_tolerance, positive=False)
        if self.update_every is not None:
            require_count("agent.update_every", self.update_every, minimum=0)
        if not self.zenoh_connect:
            raise ValueError("agent.zenoh_connect: an agent needs an endpoint to connect to")
        check_endpoints("agent.zenoh_connect", self.zenoh_connect)

    def reader_options(self) -> dict[str, str]:
        """The source options given, as services.datasets.read_scans takes them."""
        return {k: v for k in ("poses", "scan_topic", "pose_topic") if (v := getattr(self, k)) is not None}

    @property
    def keep_acked_bytes(self) -> int:
        return int(self.keep_acked_mb * 2**20)

    @property
    def outbox_path(self) -> Path:
        return Path(self.outbox) if self.outbox else Path("gmmap-data") / f"outbox-{self.robot}.db"

    def check_runnable(self, needs_source: bool = True) -> None:
        """A ValueError naming what an agent cannot run without."""
        for name in ("robot", "source") if needs_source else ("robot",):
            if getattr(self, name) is None:
                raise ValueError(f"agent.{name}: required (--{name}, or `{name}` in the [agent] section of --config)")
