"""The fleet map: served maps equal offline reconstruction, re-posing, caches, the node index."""

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from gmm_core import Grid, Pose, fit_scan
from gmm_core.occupancy import map_estimate
from gmm_core.reconstruct import reconstruct
from gmm_core.sampling import scan_seed
from protocol import PoseGraphUpdate, ScanMessage
from services.map_server import nodes, tile_set, tile_updates, tiles
from services.map_server.fleet_map import FleetMap
from services.map_server.tiles import TileCache
from services.map_server.tracers import TracerPool

GRID = Grid.from_bbox([-8.0, -12.0], [8.0, 4.0], 0.1)


@pytest.fixture(scope="module")
def fitted(intel_scans):
    scans = intel_scans[:120]
    return scans, [fit_scan(s.hits, s.no_return) for s in scans]


def drifted(pose: Pose, i: int) -> Pose:
    """An odometry-like estimate: the true pose with a drift that grows along the run."""
    x, y, theta = pose.as_xytheta()
    return Pose.from_xytheta(x + 0.004 * i, y - 0.003 * i, theta + 0.0005 * i)


def offline(scans, models, robot, poses=None):
    poses = poses or [s.pose for s in scans]
    items = [(m, p, scan_seed(robot, s.index)) for m, p, s in zip(models, poses, scans)]
    return map_estimate(*reconstruct(GRID, items, samples_per_cell=4.0))


def test_served_map_equals_offline_reconstruction(fitted):
    scans, models = fitted
    fleet = FleetMap("f")
    for s, m in zip(scans, models):
        assert fleet.add_scan(ScanMessage("f", "r1", s.index, s.stamp, m, s.pose))
    assert np.array_equal(fleet.occupancy(GRID), offline(scans, models, "r1"))


@pytest.mark.parametrize("repose_cells", [0.0, tile_updates.REPOSE_CELLS])
def test_pose_update_reposes_without_refitting(fitted, monkeypatch, repose_cells):
    """A cached tile traces a moved node again only once it moved by more than REPOSE_CELLS of a
    cell at its reach (0: every move); it then equals the offline map of the poses it counts."""
    monkeypatch.setattr(tile_updates, "REPOSE_CELLS", repose_cells)
    scans, models = fitted
    fleet = FleetMap("f")
    estimates = [drifted(s.pose, i) for i, s in enumerate(scans)]
    for s, m, estimate in zip(scans, models, estimates):
        fleet.add_scan(ScanMessage("f", "r1", s.index, s.stamp, m, estimate))
    before = fleet.occupancy(GRID)
    assert np.array_equal(before, offline(scans, models, "r1", estimates))
    assert fleet.apply_poses(PoseGraphUpdate("f", "r1", 1, tuple((s.index, s.pose) for s in scans)))
    after = fleet.occupancy(GRID)
    held = fleet._nodes.robots["r1"].nodes
    counted = [
        s.pose if estimate.displacement(s.pose, held[s.index].reach) > repose_cells * GRID.resolution else estimate
        for s, estimate in zip(scans, estimates)
    ]
    assert np.array_equal(after, offline(scans, models, "r1", counted))
    moved = [c is s.pose for c, s in zip(counted, scans)]
    assert all(moved[1:]) == (repose_cells == 0) and any(moved)  # node 0 has no drift
    assert not np.array_equal(before, after)
    assert not fleet.apply_poses(PoseGraphUpdate("f", "r1", 0, ((0, scans[0].pose),)))  # revision 1 set node 0
    assert fleet.robots()[0]["pose_revision"] == 1


def test_anchor_moves_the_whole_robot(fitted):
    scans, models = fitted
    fleet = FleetMap("f")
    for s, m in zip(scans[:20], models[:20]):
        fleet.add_scan(ScanMessage("f", "r1", s.index, s.stamp, m, s.pose))
    start = fleet.trajectory("r1")
    fleet.apply_poses(PoseGraphUpdate("f", "r1", 1, (), anchor=Pose.from_xytheta(2.0, -1.0, 0.0)))
    assert np.allclose(fleet.trajectory("r1"), start + [2.0, -1.0])


def test_duplicates_and_robot_filter(fitted):
    scans, models = fitted
    fleet = FleetMap("f")
    for k, (s, m) in enumerate(zip(scans[:40], models[:40])):
        fleet.add_scan(ScanMessage("f", "a" if k % 2 else "b", s.index, s.stamp, m, s.pose), size_bytes=100)
    s, m = scans[1], models[1]
    assert not fleet.add_scan(ScanMessage("f", "a", s.index, s.stamp, m, s.pose), size_bytes=100)
    rows = {r["robot"]: r for r in fleet.robots()}
    assert rows["a"]["nodes"] == 20 and rows["b"]["nodes"] == 20 and rows["a"]["bytes_received"] == 2100
    only_a = fleet.occupancy(GRID, robots=["a"])
    both = fleet.occupancy(GRID)
    assert not np.array_equal(only_a, both)
    assert np.all(fleet.occupancy(GRID, robots=["nobody"]) == 0.5)


def test_tile_cache_hits_and_invalidation_only_where_nodes_moved(fitted):
    scans, models = fitted
    fleet = FleetMap("f")
    for s, m in zip(scans[:30], models[:30]):
        fleet.add_scan(ScanMessage("f", "r1", s.index, s.stamp, m, s.pose))
    far = Grid.from_bbox([500.0, 500.0], [501.0, 501.0], 0.1)
    first = fleet.occupancy(GRID)
    fleet.occupancy(far)
    assert fleet.occupancy(GRID) is first and fleet.cache_stats()["hits"] == 1
    s = scans[0]
    x, y, t = s.pose.as_xytheta()
    fleet.apply_poses(PoseGraphUpdate("f", "r1", 1, ((s.index, Pose.from_xytheta(x + 0.5, y, t)),)))
    assert fleet.occupancy(far) is not None and fleet.cache_stats()["hits"] == 2  # far tile kept
    assert fleet.occupancy(GRID) is not first  # the moved node reaches GRID: recomputed


def test_a_stale_tile_brought_up_to_date_has_the_bytes_of_a_fresh_one(fitted, monkeypatch):
    """Scans arriving, partial corrections and an anchor change between queries: each updated tile
    (only the difference traced) equals the tile a new FleetMap traces from scratch. (Every move is
    traced here; sub-cell moves left out: test_pose_update_reposes_without_refitting.)"""
    monkeypatch.setattr(tile_updates, "REPOSE_CELLS", 0.0)
    scans, models = fitted
    served = FleetMap("f")
    messages = [
        ScanMessage("f", "r1", s.index, s.stamp, m, drifted(s.pose, i)) for i, (s, m) in enumerate(zip(scans, models))
    ]

    def fresh():
        fleet = FleetMap("f")
        for msg in messages[:added]:
            fleet.add_scan(msg)
        for update in updates:
            fleet.apply_poses(update)
        return fleet.occupancy(GRID)

    added, updates = 0, []
    for step, upto in enumerate((30, 60, 90, 120)):
        for msg in messages[added:upto]:
            served.add_scan(msg)
        added = upto
        if step == 1:  # correct every other node received so far
            updates.append(PoseGraphUpdate("f", "r1", 1, tuple((s.index, s.pose) for s in scans[:upto:2])))
        if step == 2:
            updates.append(PoseGraphUpdate("f", "r1", 2, (), anchor=Pose.from_xytheta(0.3, -0.2, 0.05)))
        for update in updates[-1:] if step in (1, 2) else []:
            served.apply_poses(update)
        assert np.array_equal(served.occupancy(GRID), fresh()), f"step {step}"
    assert served.cache_stats()["misses"] == 1 and served.cache_stats()["updates"] == 3


def test_the_change_log_stays_bounded_while_tiles_still_update_exactly(fitted, monkeypatch):
    """Entries every cached tile has read are dropped; a tile left alone holds the log back only up
    to CHANGE_LOG_LIMIT, and is traced afresh once the log no longer covers it. Every tile, updated
    or retraced, has the bytes of a fresh one."""
    monkeypatch.setattr(nodes, "CHANGE_LOG_LIMIT", 64)  # halved when full: 32, still over one step
    monkeypatch.setattr(tile_set, "LAYER_MAX_CELLS", 0)  # GRID and corner are tiles of their own
    afresh, trace_afresh = [], TileCache._trace_afresh

    def traced_afresh(cache, tile, *args):
        afresh.append((cache, tile.grid))
        trace_afresh(cache, tile, *args)

    monkeypatch.setattr(TileCache, "_trace_afresh", traced_afresh)
    scans, models = fitted
    messages = [
        ScanMessage("f", "r1", s.index, s.stamp, m, drifted(s.pose, i)) for i, (s, m) in enumerate(zip(scans, models))
    ]
    corner = Grid.from_bbox([-8.0, -12.0], [0.0, -4.0], 0.1)

    def fresh(grid):
        fleet = FleetMap("f")
        for msg in messages[:added]:
            fleet.add_scan(msg)
        for update in updates:
            fleet.apply_poses(update)
        return fleet.occupancy(grid)

    served, added, updates = FleetMap("f"), 0, []
    for step, upto in enumerate(range(20, 121, 20)):  # 20 scans and 10 corrections a step: 30 entries
        for msg in messages[added:upto]:
            served.add_scan(msg)
        added = upto
        updates.append(
            PoseGraphUpdate("f", "r1", step + 1, tuple((s.index, s.pose) for s in scans[upto - 20 : upto : 2]))
        )
        served.apply_poses(updates[-1])
        assert served.cache_stats()["change_log"] <= 64
        assert np.array_equal(served.occupancy(GRID), fresh(GRID)), f"step {step}"
        if step == 0:
            assert served.cache_stats()["change_log"] == 0  # the only tile read every entry
            served.occupancy(corner)  # cached, then left alone: it holds the log back
    assert served.cache_stats()["change_log"] > 0
    assert np.array_equal(served.occupancy(corner), fresh(corner))
    # GRID: traced afresh once, then updated by difference; corner: afresh when new and when left behind.
    assert [grid is GRID for cache, grid in afresh if cache is served._tiles] == [True, False, False]


def traced_then_changed(fitted, trace_threads: int = 1) -> tuple[FleetMap, np.ndarray]:
    """A map of every other of the first 60 scans, its GRID tile traced (returned), then the others added."""
    scans, models = fitted
    fleet = FleetMap("f", trace_threads=trace_threads)
    for s, m in zip(scans[:60:2], models[:60:2]):
        fleet.add_scan(ScanMessage("f", "r1", s.index, s.stamp, m, s.pose))
    before = fleet.occupancy(GRID)
    for s, m in zip(scans[1:60:2], models[1:60:2]):
        fleet.add_scan(ScanMessage("f", "r1", s.index, s.stamp, m, s.pose))
    return fleet, before


def test_a_tile_being_updated_is_served_as_it_was_to_concurrent_requests(fitted):
    scans, models = fitted
    fleet, before = traced_then_changed(fitted)
    (tile,) = fleet._tiles.values()
    with tile.lock:  # as if another request were updating it now
        assert fleet.occupancy(GRID) is before and fleet.cache_stats()["stale"] == 1
    after = fleet.occupancy(GRID)  # the next lone request brings it up to date
    assert not np.array_equal(after, before) and np.array_equal(after, offline(scans[:60], models[:60], "r1"))


def test_a_patient_request_waits_for_a_slow_update_only_so_long_then_gets_the_previous_state(fitted, monkeypatch):
    scans, models = fitted
    fleet, before = traced_then_changed(fitted)
    gate, trace_part = threading.Event(), TracerPool._trace_part
    monkeypatch.setattr(TracerPool, "_trace_part", lambda pool, *a: gate.wait(60) and trace_part(pool, *a))
    # The update (in the background) waits at the gate: after its patience the request gets the previous state.
    start = time.monotonic()
    answer = fleet.occupancy_answer(GRID, patience=0.3)
    assert answer.prob is before and answer.kind == "stale" and 0 < answer.age <= tiles.MAX_STALE_S
    assert 0.3 <= time.monotonic() - start < 5
    gate.set()  # the update goes on; the next patient request waits for it and gets it
    answer = fleet.occupancy_answer(GRID, patience=30.0)
    assert answer.kind == "updated" and answer.age == 0.0
    assert np.array_equal(answer.prob, offline(scans[:60], models[:60], "r1"))
    assert fleet.occupancy_answer(GRID, patience=30.0).kind == "fresh"


def test_max_age_zero_waits_for_every_change_even_with_a_previous_state_and_busy_tracers(fitted, monkeypatch):
    monkeypatch.setattr(tile_set, "LAYER_MAX_CELLS", 0)  # GRID's tile is the one max_age 0 asks (never a layer)
    scans, models = fitted
    fleet, before = traced_then_changed(fitted)
    (tile,) = fleet._tiles.values()
    updated = []
    with tile.lock:  # another request updating it: max_age 0 waits for that one, then updates
        waiting = threading.Thread(target=lambda: updated.append(fleet.occupancy_answer(GRID, max_age=0.0)))
        waiting.start()
        waiting.join(0.5)
        assert waiting.is_alive() and not updated
    waiting.join(60)
    assert updated[0].age == 0.0 and not np.array_equal(updated[0].prob, before)
    assert np.array_equal(updated[0].prob, offline(scans[:60], models[:60], "r1"))


def test_tiles_traced_from_many_threads_at_once_equal_one_at_a_time(fitted):
    """Tiles trace on the requesting threads with no lock around the kernel (trace_threads=1)."""
    scans, models = fitted
    tiles = [
        Grid.from_bbox([x, y], [x + 4.0, y + 4.0], r)
        for x in (-8.0, -4.0, 0.0, 4.0)
        for y in (-12.0, -4.0)
        for r in (0.05, 0.1)
    ]
    fleets = [FleetMap("f"), FleetMap("f")]
    for fleet in fleets:
        for s, m in zip(scans, models):
            fleet.add_scan(ScanMessage("f", "r1", s.index, s.stamp, m, s.pose))
    one_at_a_time = [fleets[0].occupancy(t) for t in tiles]
    with ThreadPoolExecutor(8) as pool:
        at_once = list(pool.map(fleets[1].occupancy, tiles))
    assert all(np.array_equal(a, b) for a, b in zip(one_at_a_time, at_once))


def test_query_touches_only_nodes_that_reach_it(fitted):
    scans, models = fitted
    fleet = FleetMap("f")
    for s, m in zip(scans, models):
        fleet.add_scan(ScanMessage("f", "r1", s.index, s.stamp, m, s.pose))
    far = Grid.from_bbox([500.0, 500.0], [501.0, 501.0], 0.1)
    assert np.all(fleet.occupancy(far) == 0.5)
    assert fleet.cache_stats()["sample_bytes"] == 0  # no node was sampled
    lo, hi = fleet.extent()
    assert np.all(lo < GRID.upper) and np.all(hi > GRID.origin)


def test_extent_of_some_robots_is_the_box_of_their_nodes_alone(fitted):
    """What a token limited to some robots is told of the map's extent."""
    scans, models = fitted
    fleet, alone = FleetMap("f"), FleetMap("f")
    for s, m in zip(scans[:60], models[:60]):
        fleet.add_scan(ScanMessage("f", "a", s.index, s.stamp, m, s.pose))
        alone.add_scan(ScanMessage("f", "a", s.index, s.stamp, m, s.pose))
    far = Pose.from_xytheta(300.0, -200.0, 0.0)  # robot b, far from a: it widens the whole map's box
    for s, m in zip(scans[60:], models[60:]):
        fleet.add_scan(ScanMessage("f", "b", s.index, s.stamp, m, far.compose(s.pose)))
    assert [np.array_equal(x, y) for x, y in zip(fleet.extent(["a"]), alone.extent())] == [True, True]
    assert fleet.extent(["a", "b"])[1][0] > 250 and np.array_equal(fleet.extent(["a", "b"])[1], fleet.extent()[1])
    assert fleet.extent(["nobody"]) is None and fleet.extent([]) is None and FleetMap("e").extent(["a"]) is None


def test_dimension_mismatch_is_refused(fitted):
    scans, models = fitted
    fleet = FleetMap("f")
    fleet.add_scan(ScanMessage("f", "r1", 0, 0.0, models[0], scans[0].pose))
    with pytest.raises(ValueError, match="bbox"):
        fleet.occupancy(Grid.from_bbox([0, 0, 0], [1, 1, 1], 0.1))


def test_a_batch_with_a_scan_of_the_other_dimension_changes_nothing(fitted):
    # The whole batch is refused before any of it is held: a scan held from a refused batch would
    # be neither indexed nor logged, and no tile would learn of it.
    scans, models = fitted
    flat = ScanMessage("f", "r1", 0, 0.0, models[0], scans[0].pose)
    points = np.random.default_rng(0).uniform(-2, 2, (500, 3))
    solid = ScanMessage("f", "r2", 0, 0.0, fit_scan(points, np.zeros((0, 3))), Pose.identity(3))
    fleet = FleetMap("f")
    with pytest.raises(ValueError, match="dimension"):
        fleet.add_scans([(flat, 100, None), (solid, 100, None)])
    assert fleet.dim is None and fleet.robots() == [] and fleet.extent() is None
    assert fleet.add_scans([(flat, 100, None)]) == [True] and fleet.dim == 2
    with pytest.raises(ValueError, match="dimension"):
        fleet.add_scans([(ScanMessage("f", "r1", 1, 0.0, models[1], scans[1].pose), 100, None), (solid, 100, None)])
    assert [r["nodes"] for r in fleet.robots()] == [1]


def test_a_correction_that_arrives_before_its_scan_is_held(fitted):
    scans, models = fitted
    s, m = scans[5], models[5]
    fleet = FleetMap("f")
    fleet.apply_poses(PoseGraphUpdate("f", "r1", 3, ((s.index, s.pose),)))
    fleet.add_scan(ScanMessage("f", "r1", s.index, s.stamp, m, drifted(s.pose, 50)))
    assert np.allclose(fleet.trajectory("r1")[0], s.pose.t)


def test_unknown_robots_are_those_the_map_has_had_nothing_from(fitted):
    """What the HTTP API answers 404 for: a scan or a pose graph makes a robot known."""
    scans, models = fitted
    s, m = scans[0], models[0]
    fleet = FleetMap("f")
    fleet.add_scan(ScanMessage("f", "a", s.index, s.stamp, m, s.pose))
    fleet.apply_poses(PoseGraphUpdate("f", "b", 1, ((s.index, s.pose),)))
    assert fleet.unknown_robots(["nobody", "b", "a", "c"]) == ["c", "nobody"]
    assert fleet.unknown_robots([]) == []
