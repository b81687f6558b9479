"""What an agent publishes: the scans of a data source as pose-graph nodes.

`--source carmen:PATH --corrections PATH` pairs each raw scan with the same scan in a corrected
log (identical beams, services.datasets.match_by_timestamp): the node id is the position in
that matched sequence, the published pose is the raw log's odometry, and the corrected pose is
what the agent's SLAM back end later sends in pose-graph updates. Without corrections the node
id is the scan's index in the log and the log's pose is final.

`--source sim:WORLD:INDEX:ROBOTS[:SEED] --scans A:B` is robot INDEX of a simulated fleet
(services.sim.fleet): scans A to B of a run of B scans, simulated as they are published, with
the robot's own drifting estimate as the published pose and the true pose as the corrected
one; the agent's pose-graph updates then play the loop closures, every `update_every` scans.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from gmm_core import Pose
from services.datasets import FORMATS, RangeScan, match_by_timestamp, read_scans
from services.sim.fleet import DEFAULT_RATE, SimSource, SimulatedFleet, correction_interval, shared_fleet
from services.sim.trajectory import ClosureSchedule

LOG_UPDATE_EVERY = 100  # scans between pose-graph updates of a log with --corrections


@dataclass(frozen=True)
class Node:
    node: int
    scan: RangeScan  # beams in the sensor frame, stamp
    estimate: Pose  # published with the scan (odometry where corrections follow)
    corrected: Pose | None  # sent in pose-graph updates; None: no back end for this source
    message: bytes | None = (
        None  # the encoded ScanMessage when fitted ahead (Agent.prepare); `scan` then keeps no beams
    )
    reach: float | None = None  # with `message`: the farthest beam end from the sensor, metres


def parse_source(text: str) -> tuple[str | None, str]:
    """ "carmen:PATH" -> ("carmen", PATH); a bare path leaves the format to be guessed (None). A path
    may hold colons, so an unknown prefix is read as part of it; only where no such path exists is the
    prefix named as an unknown kind."""
    fmt, sep, path = text.partition(":")
    if sep and fmt in FORMATS:
        return fmt, path
    if sep and fmt.isidentifier() and not Path(text).exists():
        known = ", ".join((*FORMATS, "sim", "ros2"))
        raise ValueError(f"--source: unknown source kind {fmt!r} (known: {known}) and no file or directory {text!r}")
    return None, text


def parse_slice(text: str | None) -> slice:
    """ "A:B" (either side may be empty) -> slice(A, B)."""
    if not text:
        return slice(None)
    start, sep, stop = text.partition(":")
    try:
        if not sep:
            raise ValueError
        chosen = slice(int(start) if start else None, int(stop) if stop else None)
    except ValueError:
        raise ValueError(f"--scans must be A:B with integers, got {text!r}") from None
    # A and B of one sign count from the same end: B at or before A selects nothing
    if chosen.start is not None and chosen.stop is not None and (chosen.start < 0) == (chosen.stop < 0):
        if chosen.stop <= chosen.start:
            raise ValueError(f"--scans {text!r} selects no scans: B must come after A")
    return chosen


def is_simulated(source: str) -> bool:
    return source.startswith("sim:")


def default_update_every(source: str, rate: float) -> int:
    """Scans between pose-graph updates: the simulated loop-closure period, or 100 for a log."""
    return correction_interval(rate or DEFAULT_RATE) if is_simulated(source) else LOG_UPDATE_EVERY


class FixedCorrections:
    """A log's SLAM back end: every node's corrected pose is final from the start."""

    def closure(self, nodes: Mapping[int, Node], final: bool) -> dict[int, Pose]:
        return {k: n.corrected for k, n in nodes.items() if n.corrected is not None}


class RelaxingCorrections:
    """A simulated robot's pose-graph optimiser: each loop closure moves every node it knows part
    of the way from its estimate to the truth, half of what is left, so the newest nodes move most
    and older ones less and less, as an optimiser spreads a closure's correction; the last closure
    (the mission's end) converges to the truth.

    A node left 2^-HALVINGS of its offset (micrometres) is settled: later closures, but the last,
    leave it out, so a closure costs the nodes of its last HALVINGS closures, not the whole mission."""

    HALVINGS = 20

    def __init__(self) -> None:
        self._joined: dict[int, int] = {}  # node -> the closure that first placed it
        self._closures = 0

    def closure(self, nodes: Mapping[int, Node], final: bool) -> dict[int, Pose]:
        self._closures += 1
        poses = {}
        for k, n in nodes.items():
            if n.corrected is None:
                continue
            halvings = self._closures - self._joined.setdefault(k, self._closures) + 1
            if final or halvings <= self.HALVINGS:
                poses[k] = n.corrected.between(n.estimate, 0.0 if final else 0.5**halvings)
        return poses


@dataclass(frozen=True)
class SimulatedNodes:
    """A simulated robot's nodes, each scan simulated when the agent gets to it."""

    fleet: SimulatedFleet
    index: int
    span: range
    update_every: int  # the robot's estimate restarts from the true pose after each update

    def __len__(self) -> int:
        return len(self.span)

    @property
    def closures(self) -> ClosureSchedule:
        return self.fleet.closures(self.index, self.update_every)

    def __iter__(self) -> Iterator[Node]:
        scans = self.fleet.scans(self.index, self.update_every)
        for scan in itertools.islice(scans, self.span.start, self.span.stop):
            yield Node(scan.index, scan, scan.odom_pose, scan.pose)


def simulated_nodes(source: str, scans: str | None, rate: float, update_every: int) -> SimulatedNodes:
    sim = SimSource.parse(source)
    span = parse_slice(scans)
    if span.stop is None or not 0 <= (span.start or 0) < span.stop:
        raise ValueError(
            "--scans: a sim source needs A:B with 0 <= A < B, the scans of its run to publish (0:300 is 60 s at 5 Hz)"
        )
    span = range(span.start or 0, span.stop)
    fleet = shared_fleet(sim.world, sim.robots, span.stop, rate or DEFAULT_RATE, sim.seed)
    return SimulatedNodes(fleet, sim.index, span, update_every)


def load_nodes(
    source: str,
    corrections: str | None = None,
    scans: str | None = None,
    *,
    rate: float = 0.0,
    update_every: int | None = None,
    **options,
) -> list[Node] | SimulatedNodes:
    """The nodes of a log (a list), or of a simulated robot (simulated as iterated); `options` go to
    the log's reader (services.datasets.read_scans)."""
    if is_simulated(source):
        if corrections is not None:
            raise ValueError("--corrections: a sim source brings its own (the true poses)")
        if options:
            raise ValueError(f"--{next(iter(options)).replace('_', '-')}: a sim source takes no reader options")
        if update_every is None:
            update_every = default_update_every(source, rate)
        return simulated_nodes(source, scans, rate, update_every)
    fmt, path = parse_source(source)
    if corrections is None:
        nodes = [Node(s.index, s, s.pose, None) for s in read_scans(path, fmt, **options)]
    else:
        pairs = match_by_timestamp(read_scans(path, fmt), read_scans(corrections))
        if not pairs:
            raise ValueError(f"--corrections: no scan of {path} is in {corrections}")
        nodes = [Node(i, raw, raw.odom_pose or raw.pose, fixed.pose) for i, (raw, fixed) in enumerate(pairs)]
    return nodes[parse_slice(scans)]
