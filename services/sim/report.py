"""The figures of one `gmmap sim` run, typed. `SimReport.to_json()` is report.json: its keys, their
order and their meaning are a contract read by scripts outside the repository, so fields are only
ever added at the end (as `config` was), never renamed, reordered or dropped.
How each figure is measured: render.MEASUREMENT_NOTES."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field


@dataclass
class RobotReport:
    """One robot's traffic, as `per_robot[name]` of report.json."""

    scans_published: int
    scans_stored: int
    bytes_on_wire: int  # robot to server, TCP bytes counted by its relay
    bytes_on_wire_down: int  # server to robot
    payload_bytes: dict[str, int]  # by kind: "scan", "poses", "ack"
    messages: dict[str, int]  # by kind, as payload_bytes
    scans_resent: int  # unacknowledged after 1 s and sent again
    framing_bytes_per_message: float | None  # (wire - payload) / messages, robot to server
    raw_scan_bytes: int
    grid_delta_bytes: int
    octomap_delta_bytes: int | None  # None without octomap-python
    components: int  # Gaussian components the server holds for the robot
    ingest_lag_p99_s: float | None
    agent_exit: int | None  # the robots process's exit code


@dataclass
class AurocPoint:
    """One map snapshot, as a row of `auroc_over_time`: AUROC at 0.1 m of the three maps."""

    t_s: float  # since the first scan on the wire
    scans: int  # stored by then
    served: float | None  # None: the observed cells are all of one class
    published_estimates: float | None
    odometry: float | None


@dataclass
class MissionWindow:
    """One window of `over_mission_time` (a run cut into MISSION_WINDOWS): what must flatten, not
    climb, over a long mission."""

    mission_s: float  # simulated seconds since the robots started, at the window's end
    server_rss_mb: float | None  # the server's resident memory at the window's end
    tile_requests: int  # answered in the window
    tile_latency_p99_s: float | None
    scan_payload_bytes: int  # on the wire in the window
    pose_payload_bytes: int


@dataclass
class SimReport:
    """report.json, one field a key, in its order."""

    # what was run
    world: str
    dimension: int
    robots: int
    duration_s: float
    rate_hz: float
    time_scale: float  # simulated seconds per wall second
    seed: int
    http_clients: int
    component_size: float | None
    wall_s: float
    restart_s: float | None  # the server restarted on the run's data directory: seconds until it served every node
    # traffic, all robots
    scans_published: int
    scans_stored: int
    scans_resent: int
    bytes_on_wire: int
    bytes_on_wire_down: int
    payload_bytes: dict[str, int]
    scan_payload_bytes: int  # payload_bytes["scan"], flat for scripts
    pose_payload_bytes: int  # payload_bytes["poses"]
    framing_bytes_per_message: float | None
    raw_scan_bytes: int
    grid_delta_bytes: int
    octomap_delta_bytes: int | None
    components: int
    # the final maps
    auroc: float | None  # served
    auroc_before_correction: float | None  # odometry only
    auroc_published_estimates: float | None
    auroc_resolution_m: float
    auroc_cells: int
    # latencies
    ingest_lag_p50_s: float | None
    ingest_lag_p99_s: float | None
    ingest_lag_max_s: float | None
    tile_requests: int
    tile_errors: int
    tile_error_kinds: dict[str, int]
    tile_latency_p50_s: float | None
    tile_latency_p99_s: float | None
    tile_shed: int  # answered 503 (the tracers saturated), of tile_errors
    tile_shed_fraction: float  # of all tile requests
    tile_age_p99_s: float | None  # X-Map-Age of the answers: how stale the tiles served were
    tile_age_max_s: float | None
    # processor time
    cpu_s: dict[str, float]  # "server", "agents", "harness"
    # The machine's CPU time while the robots drove, as fractions "busy", "idle", "steal" (Linux; absent
    # elsewhere): on a shared VM, the share stolen by other guests says how many cores the run had;
    # "loop_rate_before": millions of iterations per second of a bare Python loop just before the drive
    # (services.host.loop_rate), which also falls when other guests slow the host without stealing.
    host_cpu: dict[str, float] | None
    realtime_factor: float
    schedule_slip_s: float | None
    # the server's memory
    server_rss_start_mb: float | None
    server_rss_end_mb: float | None
    server_rss_max_mb: float | None
    server_rss_growth_mb: float | None
    server_rss_over_time: list[tuple[float, float]]  # (s since the robots started, MiB)
    over_mission_time: list[MissionWindow]
    per_robot: dict[str, RobotReport]
    auroc_over_time: list[AurocPoint]
    config: dict = field(default_factory=dict)  # the resolved configuration the run was given (GmmapConfig.to_dict())

    def to_json(self) -> dict:
        """report.json's object: nested reports as objects, keys in field order."""
        return asdict(self)
