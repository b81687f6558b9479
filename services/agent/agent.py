"""A robot's agent: fit its scans and send them and its pose-graph updates to the map server until
acknowledged (delivery.py). A robot process embeds one (Agent.open, add_scan, correct: see
examples/); `gmmap agent` runs one over a whole source (run.py).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
import zenoh

from gmm_core import FitConfig, Pose, fit_scan
from protocol import PoseGraphUpdate, ScanMessage, encode, poses_key, scan_key
from services.config import GmmapConfig
from services.datasets.keyframes import KeyframeConfig, KeyframeFilter
from services.sim.trajectory import ClosureSchedule
from services.zenoh_config import zenoh_config

from .config import AgentConfig
from .delivery import Delivery
from .outbox import Outbox
from .sent_poses import SentPoses, beam_reach
from .sources import FixedCorrections, Node, RelaxingCorrections, SimulatedNodes, is_simulated

# Refusals that every later scan would get too: the robot's quota is used up; the map has the other
# dimension (for good).
REFUSES_EVERY_SCAN = ("quota", "dimension")


class Agent(Delivery):
    def __init__(
        self,
        options: AgentConfig,
        outbox: Outbox,
        config: zenoh.Config,
        fit: FitConfig = FitConfig(),
        keyframe: KeyframeConfig = KeyframeConfig(),
    ):
        self.fit = fit
        self._keyframes = KeyframeFilter(keyframe)
        self.unsent = 0  # scans not published because of a refusal
        self.kept = 0  # nodes of publish_all's source that the keyframe policy kept
        self.resumed = 0  # of those, the ones a previous run of this outbox got through (or held): not fitted again
        self._sent_poses = SentPoses()  # what the server holds of each node's pose, and the node's reach
        self.refitted = 0  # of the acknowledged nodes the store lacks and whose bytes are gone, fitted again
        super().__init__(options, outbox, config)  # last: it starts the connector and the resender

    # -- the embeddable API -------------------------------------------------------------------
    @classmethod
    def open(cls, config: GmmapConfig | AgentConfig) -> Agent:
        """An agent for a robot process that has its own scans and poses (see examples/).

        `config` is a whole configuration (its agent, fit and keyframe sections) or just the
        agent section (default fit and keyframe policy); `robot` must be set. The outbox is
        `config.outbox` (default ./gmmap-data/outbox-<robot>.db); a robot process that restarts
        with the same outbox resends what was not acknowledged and numbers its nodes on.
        """
        if isinstance(config, AgentConfig):
            config = GmmapConfig(agent=config)
        o = config.agent
        o.check_runnable(needs_source=False)
        outbox = Outbox(o.outbox_path, o.fleet, o.robot, o.keep_acked_bytes)
        zenoh_settings = zenoh_config("client", connect=o.zenoh_connect, config_file=o.zenoh_config)
        agent = cls(o, outbox, zenoh_settings, config.fit, config.keyframe)
        agent._owns_outbox = True
        return agent

    def __enter__(self) -> Agent:
        return self

    def __exit__(self, *exc) -> None:
        self.close()  # what is not acknowledged stays in the outbox for the next run

    def add_scan(
        self, points: np.ndarray, no_return: np.ndarray | None, pose: Pose, stamp: float, node: int | None = None
    ) -> int | None:
        """Fit one scan and send it; its node id, or None if the keyframe policy skipped it (or the
        server refused this robot's scans for its quota or their dimension: see `refused`).

        points: (n, d) returned end points in the sensor frame, metres; no_return: (m, d) directions
        of beams without a return (or None); pose: the sensor's pose in the robot's map frame, as the
        robot knows it now (odometry or on-line SLAM); stamp: seconds. `node` defaults to one more
        than the last node this outbox has seen.
        """
        if not isinstance(pose, Pose):
            raise TypeError(f"pose: expected gmm_core.Pose, got {type(pose).__name__}")
        self._sent_poses.check_dim(pose)  # a robot's nodes share one dimension
        points = _points("points", points, pose.dim)
        no_return = _points("no_return", np.empty((0, pose.dim)) if no_return is None else no_return, pose.dim)
        if not self._keyframes.keep(pose, stamp):
            return None
        if node is None:
            last = self.outbox.last_id("scan")
            node = 0 if last is None else last + 1
        return node if self._send_scan(node, points, no_return, pose, stamp) else None

    def correct(self, poses: Mapping[int, Pose], anchor: Pose | None = None) -> int | None:
        """Send a pose-graph update: corrected sensor poses of earlier nodes (and where the robot's
        map frame sits in the fleet's world, if known); returns its revision, or None when no
        node's scan would move by more than `pose_tolerance` and there is no anchor.

        A node goes out only when some beam end of its scan would move by more than `pose_tolerance`
        metres from where the server has it (the scan's own pose, or the correction last sent):
        protocol v2 and later apply updates node by node, so the cost of a correction follows what
        it changes in the map, not the length of the mission. A node whose scan this agent did not
        send (a previous run's) has no known reach and goes out whenever it is corrected.
        """
        o = self.options
        moved = self._sent_poses.moved(poses, o.pose_tolerance)
        if not moved and anchor is None:
            return None
        update = PoseGraphUpdate(o.fleet, o.robot, 0, tuple(moved.items()), anchor)  # checked before numbering
        revision = self.outbox.next_revision()  # increasing across runs of this outbox
        self.send("poses", revision, poses_key(o.fleet, o.robot), encode(replace(update, revision=revision)))
        self._sent_poses.corrections_sent(moved)
        return revision

    def flush(self, timeout: float) -> int:
        """Wait until everything sent is acknowledged, at most `timeout` s; returns what is still held
        (0: all stored by the server). What is held stays in the outbox and is resent."""
        return self.wait_acknowledged(timeout)

    def _send_scan(
        self,
        node: int,
        points: np.ndarray,
        no_return: np.ndarray,
        pose: Pose,
        stamp: float,
        raw: bytes | None = None,
        reach: float | None = None,
    ) -> bool:
        """Send a scan: fitted from its beams, or `raw` (fitted ahead, with its beams' `reach`)."""
        if self.refused is not None and self.refused.reason in REFUSES_EVERY_SCAN:  # nothing more would be taken
            self.unsent += 1
            return False
        if node in self.lost:
            self.lost.discard(node)
            self.refitted += 1
        o = self.options
        raw = raw or self._encoded(node, points, no_return, pose, stamp)
        # noted first: a scan of another dimension than this robot's earlier ones is refused unsent
        self._sent_poses.scan_sent(node, pose, self._reach(points, no_return, pose.dim) if reach is None else reach)
        self.send("scan", node, scan_key(o.fleet, o.robot, node), raw)
        return True

    def _reach(self, points: np.ndarray, no_return: np.ndarray, dim: int) -> float:
        return beam_reach(points, no_return, self.fit.for_dimension(dim).max_range)

    def _encoded(self, node: int, points: np.ndarray, no_return: np.ndarray, pose: Pose, stamp: float) -> bytes:
        """The node's ScanMessage: the scan fitted (Sec. III-A/B) and encoded."""
        o = self.options
        model = fit_scan(points, no_return, self.fit.for_dimension(pose.dim))
        return encode(ScanMessage(o.fleet, o.robot, node, stamp, model, pose), o.encoding)

    def _send_node(self, node: Node) -> bool:
        scan = node.scan
        return self._send_scan(
            node.node, scan.hits, scan.no_return, node.estimate, scan.stamp, node.message, node.reach
        )

    def prepare(self, nodes: Sequence[Node] | SimulatedNodes, progress=None) -> list[Node]:
        """Every node fitted and encoded ahead, its beams dropped: a simulated robot that prepares its
        run, so that a timed (or time-compressed) run measures the server and the link, not the fit."""
        prepared = []
        for node in nodes:
            scan = node.scan
            raw = self._encoded(node.node, scan.hits, scan.no_return, node.estimate, scan.stamp)
            reach = self._reach(scan.hits, scan.no_return, node.estimate.dim)
            beamless = replace(scan, hits=scan.hits[:0], no_return=scan.no_return[:0])
            prepared.append(replace(node, scan=beamless, message=raw, reach=reach))
            if progress is not None:
                progress(1)
        return prepared

    # -- a whole source ------------------------------------------------------------------------
    def publish_all(
        self, nodes: Sequence[Node] | SimulatedNodes, progress=None, closures: ClosureSchedule | None = None
    ) -> int:
        """Fit and send every node the keyframe policy keeps, with pose-graph updates after the
        scans `closures` says (default: a simulated robot's own, else every update_every); returns
        the updates sent. `kept` counts the nodes, `resumed` those a previous run got through."""
        o = self.options
        corrected: dict[int, Node] = {}  # the nodes a back end corrects
        back_end = RelaxingCorrections() if is_simulated(o.source) else FixedCorrections()
        if closures is None:
            closures = closure_schedule(nodes, o.update_every)
        updates = 0
        # A restarted agent resumes: acknowledged scans are through, held ones go out with the resender;
        # those the store lacks and the outbox no longer keeps are fitted again.
        done = self.outbox.known("scan") - self.lost
        self.resumed = self.kept = 0
        sent = 0
        started = time.monotonic()
        for count, node in enumerate(nodes, 1):
            if progress is not None:
                progress(1)
            # the same decisions on every run of a source, so a resumed run skips the same scans
            if self._keyframes.keep(node.estimate, node.scan.stamp):
                self.kept += 1
                if node.node in done:
                    self.resumed += 1
                    delivered = True
                else:
                    if o.rate > 0:
                        time.sleep(max(0.0, started + sent / o.rate - time.monotonic()))
                    sent += 1
                    delivered = self._send_node(node)
                if delivered and node.corrected is not None:
                    corrected[node.node] = node
            if corrected and closures.closes_after(count) and count < len(nodes):
                updates += self.correct(back_end.closure(corrected, final=False)) is not None
        if corrected:  # and once at the end, as a back end closing its graph would
            updates += self.correct(back_end.closure(corrected, final=True)) is not None
        return updates

    def refit(self, nodes: Sequence[Node] | SimulatedNodes) -> int:
        """Fit and send again the nodes the store lacks whose bytes the outbox no longer keeps
        (found after publish_all passed them); returns how many."""
        if not self.lost:
            return 0
        held = self.outbox.held("scan")
        again = [n for n in nodes if n.node in self.lost and n.node not in held]
        for node in again:
            self._send_node(node)
        return len(again)


def _points(name: str, a, dim: int) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{name}: expected an (n, {dim}) array for a {dim}D pose, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: {int((~np.isfinite(a)).any(axis=1).sum())} rows are not finite")
    return np.ascontiguousarray(a)


def closure_schedule(nodes: Sequence[Node] | SimulatedNodes, update_every: int) -> ClosureSchedule:
    """When a source's back end closes loops: a simulated robot's own schedule, else every `update_every` scans."""
    return nodes.closures if isinstance(nodes, SimulatedNodes) else ClosureSchedule(update_every)
