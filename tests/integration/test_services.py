"""The map server and robot agents as processes: real Zenoh on 127.0.0.1 (scouting off), real
uvicorn, SQLite in tmp_path, the real Intel logs. Every subprocess is killed in a finally."""

from __future__ import annotations

import io
import json
import signal

import numpy as np
import pytest

from gmm_core import FitConfig, Grid, Pose, fit_scan
from gmm_core.metrics import grid_auroc
from gmm_core.occupancy import map_estimate
from gmm_core.reconstruct import count_beams, reconstruct
from gmm_core.sampling import scan_seed
from protocol import (
    Ack,
    MapQuery,
    MapReply,
    PointQuery,
    ScanMessage,
    ack_key,
    decode,
    encode,
    occupancy_key,
    points_key,
    poses_key,
    scan_key,
)
from services.agent.map_client import MapQueryError, query_bytes, query_points
from services.map_server.store import read_graph
from services.replay import data_extent
from support.net import free_port, get, http_get, metric, wait_for
from support.processes import EVERY_SCAN, HALVES, acked_nodes, store_db, stored_nodes

RESOLUTION = 0.1


@pytest.fixture(scope="module")
def intel(data_dir):
    """Matched (raw, corrected) Intel scans, the 10 cm grid over them and the truth grid."""
    from services.datasets import match_by_timestamp, read_scans

    pairs = match_by_timestamp(
        read_scans(data_dir / "radish" / "intel.clf.bz2"), read_scans(data_dir / "carmen" / "intel-corrected.log.gz")
    )
    assert len(pairs) == 910
    corrected = [fixed for _, fixed in pairs]
    lo, hi = data_extent(corrected, 10.0)
    grid = Grid.from_bbox(np.floor(lo), np.ceil(hi), RESOLUTION)
    truth = count_beams(grid, [(s.hits, s.no_return, s.pose) for s in corrected], 10.0)
    return pairs, grid, truth


def map_query(grid: Grid, robots: tuple[str, ...] | None = None) -> bytes:
    return encode(MapQuery("default", grid.origin, grid.upper, grid.resolution, robots))


def served_map(session, grid: Grid, robots: tuple[str, ...] | None = None) -> tuple[bytes, np.ndarray]:
    raw = query_bytes(session, "default", map_query(grid, robots), timeout=30)
    reply = decode(raw, expect=MapReply, max_bytes=len(raw))
    assert reply.probabilities.shape == grid.array_shape
    return raw, reply.probabilities


def test_two_agents_replay_intel_with_pose_correction(procs, session_to, intel, data_dir, tmp_path):
    pairs, grid, (truth_h, truth_m) = intel
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    procs.server("server", data, zport, hport)
    session = session_to(zport)

    # Phase 1: robots without a SLAM back end publish their halves at odometry poses.
    agents = [procs.agent(r, zport, data_dir, "--odometry-only", "--timeout", "60") for r in HALVES]
    for a in agents:
        assert procs.finish(a, 90) == 0, procs.log(a)
    # Both robots by name: a tile of its own, so the corrected map below is traced from its poses
    # (a cached tile counts a node that moved under a quarter cell at its old pose: tile_updates.REPOSE_CELLS).
    _, odometry_map = served_map(session, grid, tuple(HALVES))

    # Phase 2: the same robots again, now with their back end: every scan is a resend (stored
    # once), then the corrected poses every 100 scans and at the end. New outboxes: with its old
    # one, an agent would resume and skip the scans already acknowledged.
    agents = [
        procs.agent(r, zport, data_dir, "--timeout", "60", "--outbox", str(tmp_path / f"outbox-{r}-2.db"))
        for r in HALVES
    ]
    for a in agents:
        assert procs.finish(a, 90) == 0, procs.log(a)
    raw_reply, corrected_map = served_map(session, grid)

    assert stored_nodes(data, "a") == set(range(455)) and stored_nodes(data, "b") == set(range(455, 910))
    robots = {r["robot"]: r for r in json.loads(http_get(hport, "/v1/robots"))}
    assert {r: (v["nodes"], v["pose_revision"]) for r, v in robots.items()} == {"a": (455, 5), "b": (455, 5)}

    # The agent's bytes are the offline fit of the same scan through the same encoding.
    with store_db(data) as db:
        stored = dict(((r, n), raw) for r, n, raw in db.execute("SELECT robot, node, raw FROM scans"))
    for robot, node in (("a", 0), ("b", 455)):
        raw_scan = pairs[node][0]
        model = fit_scan(raw_scan.hits, raw_scan.no_return, FitConfig())
        expected = ScanMessage("default", robot, node, raw_scan.stamp, model, raw_scan.odom_pose)
        assert encode(expected, "q") == stored[(robot, node)]

    # Served map == offline reconstruction of the stored models at the poses the store holds (the
    # corrections in 0.1 mm codes, protocol v3; a node the corrections move by under the agent's
    # pose_tolerance keeps its scan's pose), with the FleetMap's seeds, in its (robot, node) order.
    messages = {key: decode(raw, expect=ScanMessage) for key, raw in stored.items()}
    with store_db(data) as db:
        graphs = {r: read_graph(db, "default", r) for r in HALVES}
    poses = {(r, n): graphs[r].pose(n) or m.pose for (r, n), m in messages.items()}
    corrected = sum(graphs[r].pose(n) is not None for r, n in messages)
    assert corrected >= 0.9 * len(messages), corrected
    for (_, n), pose in poses.items():
        assert np.abs(pose.t - pairs[n][1].pose.t).max() <= 0.011  # within the tolerance of the truth
    offline_h, offline_m = reconstruct(
        grid, [(messages[k].model, poses[k], scan_seed(*k)) for k in sorted(messages)], samples_per_cell=4.0
    )
    offline = map_estimate(offline_h, offline_m, 0.2)
    assert np.array_equal(corrected_map, offline)

    # HTTP serves the same array.
    bbox = ",".join(repr(float(v)) for v in (*grid.origin, *grid.upper))
    npy = http_get(hport, f"/v1/occupancy?bbox={bbox}&resolution={RESOLUTION}&format=npy")
    assert np.array_equal(np.load(io.BytesIO(npy)), corrected_map)

    after, before = grid_auroc(corrected_map, truth_h, truth_m), grid_auroc(odometry_map, truth_h, truth_m)
    print(f"AUROC vs corrected raw grid: odometry {before:.4f}, corrected {after:.4f}")
    assert after >= 0.99
    assert before < after - 0.05

    text = http_get(hport, "/metrics").decode()
    assert metric(text, "gmmap_messages_accepted_total", kind="scan") >= 2 * 910
    assert metric(text, "gmmap_messages_accepted_total", kind="poses") >= 10  # resends count too
    assert metric(text, "gmmap_bytes_received_total", robot="a") > 0


def test_kill_9_during_ingest_loses_no_acknowledged_scan(procs, session_to, intel, data_dir, tmp_path):
    _, grid, _ = intel
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    server = procs.server("server-1", data, zport, hport)
    agents = [procs.agent(r, zport, data_dir, "--rate", "150", "--resend", "0.5", "--timeout", "60") for r in HALVES]
    # Of each robot (one may start seconds after the other, its outbox not yet there to read), and
    # an Ack to each: a batch is committed before its Acks go out, so stored scans alone may have none.
    wait_for(
        lambda: (
            min(len(stored_nodes(data, r)) for r in HALVES) >= 100
            and all(acked_nodes(tmp_path / f"outbox-{r}.db") for r in HALVES)
        ),
        60,
        "100 stored scans of each robot and an Ack to each",
        interval=0.02,
    )
    server.send_signal(signal.SIGKILL)
    server.wait()
    for robot, agent in zip(HALVES, agents):
        acked = acked_nodes(tmp_path / f"outbox-{robot}.db")
        assert acked, f"{robot}: nothing acknowledged before the kill"
        assert acked <= stored_nodes(data, robot), f"{robot}: acknowledged scans missing from the store"
        if len(acked) < 455:  # else it may have been through before the other started
            assert agent.poll() is None, f"agent {robot} finished without the server"

    server = procs.server("server-2", data, zport, hport)
    for a in agents:
        assert procs.finish(a, 90) == 0, procs.log(a)
    assert stored_nodes(data, "a") == set(range(455)) and stored_nodes(data, "b") == set(range(455, 910))

    first, _ = served_map(session_to(zport), grid)
    server.send_signal(signal.SIGTERM)
    assert server.wait(15) == 0, procs.log(server)
    assert "gmmap server: stopping" in procs.log(server)
    procs.server("server-3", data, zport, hport)
    second, _ = served_map(session_to(zport), grid)
    assert first == second


def test_garbage_on_scan_and_pose_keys_is_counted_and_dropped(procs, session_to, tmp_path):
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    procs.server("server", data, zport, hport)
    session = session_to(zport)
    wait_for(
        lambda: session.declare_publisher(scan_key("default", "fuzz", 0)).matching_status.matching,
        10,
        "the server's subscribers",
    )
    rng = np.random.default_rng(5)
    garbage = [rng.bytes(int(n)) for n in rng.integers(0, 400, 100)]
    for i, payload in enumerate(garbage):
        session.put(scan_key("default", "fuzz", i), payload)
        session.put(poses_key("default", "fuzz"), payload)
    # Well-formed messages that still do not belong: wrong type on the key, robot not the key's.
    model = fit_scan(rng.normal(size=(30, 2)) + [3, 0], np.zeros((0, 2)))
    good = ScanMessage("default", "ok", 7, 1.0, model, Pose.identity(2))
    session.put(scan_key("default", "fuzz", 1000), encode(Ack("default", "fuzz", "s", "scan", (1,))))
    session.put(scan_key("default", "fuzz", 7), encode(good))
    expected_rejections = 2 * len(garbage) + 2

    acks = []
    sub = session.declare_subscriber(ack_key("default", "ok"), lambda s: acks.append(decode(s.payload.to_bytes())))
    try:
        wait_for(
            lambda: (session.put(scan_key("default", "ok", 7), encode(good)), acks)[1],
            10,
            "the Ack of a good scan",
            interval=0.2,
        )
    finally:
        sub.undeclare()
    assert acks[0].ids == (7,) and acks[0].kind == "scan"

    text = wait_for(
        lambda: (
            (t := http_get(hport, "/metrics").decode())
            and metric(t, "gmmap_messages_rejected_total") >= expected_rejections
            and t
        ),
        10,
        "rejections",
    )
    assert metric(text, "gmmap_messages_rejected_total") == expected_rejections
    assert metric(text, "gmmap_messages_rejected_total", kind="scan", reason="key.robot") == 1
    assert metric(text, "gmmap_messages_rejected_total", kind="scan", reason="type") == 1
    with store_db(data) as db:
        assert db.execute("SELECT robot, node FROM scans").fetchall() == [("ok", 7)]
        assert db.execute("SELECT COUNT(*) FROM poses").fetchone() == (0,)
    # Still serving: over Zenoh (bad queries get an error reply naming the field) and over HTTP.
    with pytest.raises(MapQueryError, match="message"):
        query_bytes(session, "default", b"not a query")
    with pytest.raises(MapQueryError, match="resolution"):
        query_bytes(session, "default", encode(MapQuery("default", [0, 0], [1, 1], 0.001)))
    _, prob = served_map(session, Grid.from_bbox([0, -2], [6, 2], 0.1))
    assert prob.max() > 0.5
    assert json.loads(http_get(hport, "/healthz"))["status"] == "ok"
    text = http_get(hport, "/metrics").decode()  # the refused queries counted, by the field at fault
    assert metric(text, "gmmap_messages_rejected_total", kind="occupancy", reason="message") == 1
    assert metric(text, "gmmap_messages_rejected_total", kind="occupancy", reason="resolution") == 1


@pytest.mark.parametrize("dim", [2, 3])
def test_zenoh_point_query_answers_as_the_http_api(procs, session_to, tmp_path, dim):
    """A robot's point query over Zenoh (gmmap/<fleet>/map/points) gets what GET /v1/occupancy/points
    gives for the same points and method, auto's choice included, in 2D and 3D; a bad one an error
    naming the field, counted."""
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    procs.server("server", data, zport, hport)
    session = session_to(zport)
    rng = np.random.default_rng(11)
    # A wall at x = 3 m (3D: 2 m high) seen from three poses along y: hits on it, free space before it.
    across = np.linspace(-3, 3, 120)
    wall = (
        np.column_stack([np.full(120, 3.0), across])
        if dim == 2
        else np.array([[3.0, y, z] for y in across[::3] for z in np.linspace(-1, 1, 15)])
    )
    acks = []

    def acked(node: int, raw: bytes) -> bool:
        session.put(scan_key("default", "w", node), raw)
        return any(node in a.ids for a in acks)

    sub = session.declare_subscriber(ack_key("default", "w"), lambda s: acks.append(decode(s.payload.to_bytes())))
    try:
        for node, y in enumerate((-1.0, 0.0, 1.0)):
            seen = wall - np.eye(dim)[1] * y + rng.normal(0, 0.01, wall.shape)  # in the sensor's frame
            model = fit_scan(seen, np.zeros((0, dim)))
            pose = Pose(np.eye(dim), np.eye(dim)[1] * y)
            raw = encode(ScanMessage("default", "w", node, float(node), model, pose))
            wait_for(lambda: acked(node, raw), 10, f"the Ack of scan {node}", interval=0.2)  # noqa: B023 - called here
    finally:
        sub.undeclare()

    points = np.array([[3.0, 0.0, 0.0], [1.5, 0.5, 0.0], [-20.0, 20.0, 0.0]])[:, :dim]  # wall, before it, unseen
    xy = ("xy=" if dim == 2 else "xyz=") + ",".join(map(str, points.ravel().tolist()))
    for method in ("auto", "analytic", "mc"):
        reply = query_points(session, "default", points, 0.1, method=method, timeout=30)
        status, _, body = get(f"http://127.0.0.1:{hport}/v1/occupancy/points?{xy}&resolution=0.1&method={method}")
        assert status == 200, body
        served = json.loads(body)
        assert reply.method == served["method"] == ("mc" if method == "mc" else "analytic")  # 3 scattered points
        assert np.array_equal(reply.probabilities, np.array(served["probabilities"], dtype=np.float32))
        assert reply.probabilities[0] > 0.7 and reply.probabilities[1] < 0.3 and reply.probabilities[2] == 0.5
    lattice = (np.stack(np.meshgrid(*[np.arange(16)] * dim), -1).reshape(-1, dim) + 0.5) * 0.1
    assert query_points(session, "default", lattice, 0.1, ("w",), timeout=30).method == "mc"  # one grid for all

    for query, field in (
        (PointQuery("default", points, 0.001), "resolution"),
        (PointQuery("default", np.zeros((2, 5 - dim)), 0.1), "points"),  # a 3D query of a 2D map, or 2D of 3D
        (PointQuery("default", rng.uniform(-50, 50, (1001, dim)), 0.1, None, "analytic"), "points"),
        (PointQuery("other", points, 0.1), "fleet"),  # on this fleet's key
        (PointQuery("default", points, 0.1, ("nosuch",)), "robots"),  # a mistyped robot: not a blank answer
        (PointQuery("default", points, 0.1, ()), "robots"),
    ):
        replies = list(session.get(points_key("default"), payload=encode(query), timeout=30))
        assert len(replies) == 1 and replies[0].err is not None
        assert replies[0].err.payload.to_string().startswith(f"{field}:"), replies[0].err.payload.to_string()
    grid = Grid.from_bbox(np.full(dim, -1.0), np.full(dim, 1.0), 0.1)
    replies = list(session.get(occupancy_key("default"), payload=map_query(grid, ("w", "nosuch")), timeout=30))
    assert replies[0].err.payload.to_string() == "robots: no robot nosuch in fleet 'default'"
    assert query_points(session, "default", points[:1], 0.1, timeout=30).probabilities[0] > 0.7  # still serving
    text = http_get(hport, "/metrics").decode()
    for field, count in (("resolution", 1), ("points", 2), ("fleet", 1), ("robots", 2)):
        assert metric(text, "gmmap_messages_rejected_total", kind="points", reason=field) == count


def test_agent_and_server_meet_through_a_router(procs, data_dir, tmp_path):
    """Agent (client) -> `gmmap router` <- server (peer), the agent started first."""
    rport, data = free_port(), tmp_path / "data"
    router = procs.ready(procs.start("router", "router", "--listen", f"tcp/127.0.0.1:{rport}"), "gmmap router ready")
    agent = procs.start(
        "agent",
        "agent",
        "--robot",
        "solo",
        "--zenoh-connect",
        f"tcp/127.0.0.1:{rport}",
        "--source",
        f"carmen:{data_dir / 'carmen' / 'intel-corrected.log.gz'}",
        "--scans",
        "0:50",
        *EVERY_SCAN,
        "--outbox",
        str(tmp_path / "outbox.db"),
        "--timeout",
        "30",
    )
    procs.server("server", data, 0, free_port(), "--zenoh-connect", f"tcp/127.0.0.1:{rport}")
    assert procs.finish(agent, 60) == 0, procs.log(agent)
    assert stored_nodes(data, "solo") == set(range(50))
    router.send_signal(signal.SIGINT)
    assert router.wait(10) == 0
