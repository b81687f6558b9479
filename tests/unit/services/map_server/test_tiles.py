"""Tiles under load: the age of the state served, stale answers bounded in age, updates coalesced,
and requests shed when the tracers are saturated; a map with no scan caches no tile."""

import threading
import time

import numpy as np
import pytest

from gmm_core import Grid, Pose, ScanModel, fit_scan
from gmm_core.occupancy import DEFAULT_PRIOR, map_estimate, monte_carlo_estimate
from protocol import PoseGraphUpdate, ScanMessage
from services.map_server import tile_serving, tile_set, tile_state, tile_updates, tiles
from services.map_server.fleet_map import FleetMap
from services.map_server.tiles import MAX_STALE_S, PATIENCE_S, TileCache
from services.map_server.tracers import TracerLoad, TracerPool, TracersSaturated, TracingStopped
from support.fuzz import scan_like_mixture
from support.ingest import scan_of
from support.net import wait_for
from support.saturation import saturated_tracers

GRID = Grid.from_bbox([-8.0, -12.0], [8.0, 4.0], 0.1)
COLD = [Grid.from_bbox([-8.0, -12.0], [0.0, -4.0], r) for r in (0.2, 0.25, 0.3)]  # tiles not yet cached


@pytest.fixture(scope="module")
def messages(intel_scans):
    return [ScanMessage("f", "r1", s.index, s.stamp, fit_scan(s.hits, s.no_return), s.pose) for s in intel_scans[:40]]


def fleet_of(messages, **kwargs) -> FleetMap:
    fleet = FleetMap("f", **kwargs)
    for msg in messages:
        assert fleet.add_scan(msg)
    return fleet


def test_an_answer_says_how_long_its_state_has_been_out_of_date(messages):
    fleet = fleet_of(messages[:20])
    first = fleet.occupancy_answer(GRID)
    assert (first.kind, first.age) == ("updated", 0.0)
    assert fleet.occupancy_answer(GRID) == tile_state.TileAnswer(first.prob, 0.0, "fresh", fleet.samples_per_cell)
    changed = time.monotonic()  # at most the time the change is stamped with
    fleet.add_scan(messages[20])
    (tile,) = fleet._tiles.values()
    with tile.lock:  # as if another request were updating it now
        time.sleep(0.05)
        stale = fleet.occupancy_answer(GRID)
        assert stale.kind == "stale" and stale.prob is first.prob
        assert 0.05 <= stale.age <= time.monotonic() - changed < MAX_STALE_S
    after = fleet.occupancy_answer(GRID)
    assert (after.kind, after.age) == ("updated", 0.0)
    assert np.array_equal(after.prob, fleet_of(messages[:21]).occupancy(GRID))


def test_a_previous_state_older_than_max_stale_is_not_served(messages, monkeypatch):
    """The request waits for the update under way instead, then updates the tile itself."""
    monkeypatch.setattr(tiles, "MAX_STALE_S", 0.05)
    fleet = fleet_of(messages[:20])
    fleet.occupancy(GRID)
    fleet.add_scan(messages[20])
    (tile,) = fleet._tiles.values()
    time.sleep(0.1)  # the previous state is now too old to serve
    answers = []
    with tile.lock:  # another request updating it
        waiting = threading.Thread(target=lambda: answers.append(fleet.occupancy_answer(GRID)))
        waiting.start()
        waiting.join(0.3)
        assert waiting.is_alive()  # it waits for that update rather than take the old state
    waiting.join(10)
    (answer,) = answers
    assert (answer.kind, answer.age) == ("updated", 0.0)
    assert np.array_equal(answer.prob, fleet_of(messages[:21]).occupancy(GRID))
    assert fleet.cache_stats()["stale"] == 0


def test_changes_during_an_update_wait_and_the_next_update_applies_them_at_once(messages, monkeypatch):
    fleet = fleet_of(messages[:20])
    fleet.occupancy(GRID)
    fleet.add_scan(messages[20])
    updates, trace_changes = [], TileCache._trace_changes

    def traced_changes(cache, tile, changed, *args):
        updates.append(sorted(key[1] for key in changed))
        if len(updates) == 1:  # three scans arrive while the first update traces
            for msg in messages[21:24]:
                fleet.add_scan(msg)
            time.sleep(0.02)
        trace_changes(cache, tile, changed, *args)

    monkeypatch.setattr(TileCache, "_trace_changes", traced_changes)
    during = fleet.occupancy_answer(GRID)
    assert during.kind == "updated" and 0.02 <= during.age < MAX_STALE_S  # it lacks the three scans
    assert np.array_equal(during.prob, fleet_of(messages[:21]).occupancy(GRID))
    after = fleet.occupancy_answer(GRID)
    assert (after.kind, after.age) == ("updated", 0.0)
    assert updates == [[messages[20].node], [m.node for m in messages[21:24]]]  # one update for all three
    assert np.array_equal(after.prob, fleet_of(messages[:24]).occupancy(GRID))


def test_busy_tracers_coalesce_a_recent_state_and_update_an_older_one_in_the_background(messages, monkeypatch):
    """With every tracer busy, a state at most COALESCE_S old with at most COALESCE_CHANGES changes
    since is served as is; otherwise it is served stale while an update starts in the background
    (with idle tracers the request updates it itself: other tests)."""
    monkeypatch.setattr(tile_serving, "COALESCE_CHANGES", 2)
    monkeypatch.setattr(tile_serving, "COALESCE_S", 0.2)
    fleet = fleet_of(messages[:20])
    before = fleet.occupancy(GRID)
    monkeypatch.setattr(TracerPool, "load", lambda pool: TracerLoad(pool.threads, 0, pool.threads, 0.0))
    fleet.add_scan(messages[20])
    fleet.add_scan(messages[21])
    coalesced = fleet.occupancy_answer(GRID)
    assert coalesced.kind == "coalesced" and coalesced.prob is before and 0 < coalesced.age <= 0.2
    for upto, pause in ((23, 0.0), (24, 0.25)):  # a third change; then one older than COALESCE_S
        fleet.add_scan(messages[upto - 1])
        time.sleep(pause)
        stale = fleet.occupancy_answer(GRID)
        assert stale.kind == "stale" and 0 < stale.age <= MAX_STALE_S
        wait_for(lambda: fleet.occupancy_answer(GRID).kind == "fresh", 30, "the background update")
        assert np.array_equal(fleet.occupancy(GRID), fleet_of(messages[:upto]).occupancy(GRID))
    assert fleet.cache_stats()["coalesced"] == 1 and fleet.cache_stats()["updates"] == 2


def test_saturated_tracers_shed_what_would_trace_serve_what_they_can_and_recover(messages, monkeypatch):
    monkeypatch.setattr(tile_set, "LAYER_MAX_CELLS", 0)  # `warm` and `changed` are tiles of their own
    fleet = fleet_of(messages[:20], trace_threads=1)
    warm, changed = GRID, Grid.from_bbox([-4.0, -8.0], [4.0, 0.0], 0.1)
    fleet.occupancy(warm)
    before = fleet.occupancy(changed)
    fleet.add_scan(messages[20])  # reaches both: `changed` is not asked again before the load
    fleet.occupancy(warm)
    cold = Grid.from_bbox([-6.0, -10.0], [2.0, -2.0], 0.15)
    with saturated_tracers(monkeypatch, fleet, COLD):
        tiles_before = fleet.cache_stats()["tiles"]
        with pytest.raises(TracersSaturated, match="tracers saturated: 2 traces queued for 1 tracer") as shed:
            fleet.occupancy_answer(cold, may_shed=True)
        assert shed.value.retry_after >= 1 and shed.value.reason == "tracers_saturated"
        assert fleet.cache_stats()["tiles"] == tiles_before  # shed before any work: no tile made
        assert fleet.occupancy_answer(warm, may_shed=True).kind == "fresh"
        stale = fleet.occupancy_answer(changed, may_shed=True)  # served rather than shed, its update queued
        assert stale.kind == "stale" and stale.prob is before and 0 < stale.age <= MAX_STALE_S
        wait_for(lambda: fleet.cache_stats()["trace_queued"] == 3, 20, "the background update to queue")
        monkeypatch.setattr(tiles, "MAX_STALE_S", 0.0)  # now too old to serve: shed rather than wait
        with pytest.raises(TracersSaturated):
            fleet.occupancy_answer(changed, may_shed=True)
        monkeypatch.setattr(tiles, "MAX_STALE_S", MAX_STALE_S)
        stats = fleet.cache_stats()
        assert (stats["shed"], stats["stale"], stats["trace_queued"]) == (2, 1, 3)
    answer = fleet.occupancy_answer(cold, may_shed=True)
    assert (answer.kind, answer.age) == ("updated", 0.0)
    assert np.array_equal(answer.prob, fleet_of(messages[:21]).occupancy(cold))
    wait_for(lambda: fleet.occupancy_answer(changed).kind == "fresh", 30, "the background update")
    assert np.array_equal(fleet.occupancy(changed), fleet_of(messages[:21]).occupancy(changed))
    assert fleet.cache_stats()["trace_queued"] == 0


def test_an_out_of_date_tile_asked_for_after_close_is_tracing_stopped(messages, monkeypatch):
    """After close (a stopping server) a request whose tile would be updated in the background, with
    idle tracers (patient) or busy ones, raises TracingStopped (503 over HTTP), not the refresher's
    RuntimeError "cannot schedule new futures after shutdown" (500); an up-to-date tile is still served,
    without the refinement idle tracers would start."""
    monkeypatch.setattr(tile_updates, "FULL_UPDATE_NODES", 10)
    fleet = fleet_of(messages[:20], busy_samples_per_cell=1.0)
    fleet.occupancy(GRID)
    fleet.add_scan(messages[20])
    fresh = Grid(GRID.origin + 0.05, GRID.resolution, GRID.shape)  # off the lattice: a tile of its own
    assert fleet.occupancy_answer(fresh, patience=0.0).samples_per_cell == 1.0  # 21 nodes: thinned
    fleet.close()
    assert (fleet.occupancy_answer(fresh).kind, fleet.cache_stats()["trace_queued"]) == ("fresh", 0)
    with pytest.raises(TracingStopped):
        fleet.occupancy_answer(GRID, patience=PATIENCE_S)
    monkeypatch.setattr(TracerPool, "load", lambda pool: TracerLoad(pool.threads, 0, pool.threads, 0.0))
    time.sleep(tile_serving.COALESCE_S)  # too old to coalesce
    with pytest.raises(TracingStopped):
        fleet.occupancy_answer(GRID)


def test_updates_begun_while_the_tracers_are_busy_thin_the_samples_and_idle_tracers_refine_them(messages, monkeypatch):
    """While every tracer is busy, an update counts the nodes it traces with busy_samples_per_cell,
    new and moved alike (a moved node is taken out as it was counted); the answer says so. Idle
    tracers refine the tile in the background, REFINE_NODES at a time, to the bytes of a fresh map."""
    monkeypatch.setattr(tile_updates, "REPOSE_CELLS", 0.0)  # every move traced
    monkeypatch.setattr(tiles, "REFINE_NODES", 3)  # the 4 thinned nodes in two refinements
    fleet = fleet_of(messages[:20], busy_samples_per_cell=1.0)
    assert fleet.occupancy_answer(GRID).samples_per_cell == 4.0  # idle tracers: the map's
    idle = TracerPool.load
    monkeypatch.setattr(TracerPool, "load", lambda pool: TracerLoad(pool.threads, 0, pool.threads, 0.0))
    fleet.add_scan(messages[20])
    shift = np.array([0.3, -0.2, 0.05])
    update = PoseGraphUpdate(
        "f", "r1", 1, tuple((m.node, Pose.from_xytheta(*(m.pose.as_xytheta() + shift))) for m in messages[:3])
    )
    fleet.apply_poses(update)
    assert fleet.occupancy_answer(GRID).samples_per_cell == 4.0  # the previous state, served while busy
    wait_for(lambda: fleet.occupancy_answer(GRID).kind == "fresh", 30, "the background update")
    thin = {m.node: 1.0 for m in messages[:3] + messages[20:21]}
    assert fleet.occupancy_answer(GRID).samples_per_cell == 1.0
    assert np.array_equal(fleet.occupancy(GRID), offline(messages[:21], update, thin))
    assert not np.array_equal(offline(messages[:21], update, thin), offline(messages[:21], update, {}))
    monkeypatch.setattr(TracerPool, "load", idle)
    assert fleet.occupancy_answer(GRID).kind == "fresh"  # served as it is, refined behind it
    wait_for(lambda: fleet.occupancy_answer(GRID).samples_per_cell == 4.0, 30, "the refinement")
    assert np.array_equal(fleet.occupancy(GRID), offline(messages[:21], update, {}))
    assert fleet.cache_stats()["thinned_updates"] == 1 and fleet.cache_stats()["updates"] == 3, fleet.cache_stats()


def test_a_request_for_every_change_refines_a_thinned_tile_at_once(messages, monkeypatch):
    fleet = fleet_of(messages[:20], busy_samples_per_cell=2.0)
    monkeypatch.setattr(TracerPool, "load", lambda pool: TracerLoad(pool.threads, 0, pool.threads, 0.0))
    fleet.occupancy(GRID)  # the first trace, begun while busy
    assert fleet.occupancy_answer(GRID).samples_per_cell == 2.0
    exact = fleet.occupancy_answer(GRID, max_age=0)
    assert (exact.kind, exact.samples_per_cell) == ("updated", 4.0)
    assert np.array_equal(exact.prob, offline(messages[:20], None, {}))


def offline_counts(messages, update, samples_per_cell: dict[int, float], grid: Grid = GRID):
    """(hits, misses) on `grid` of `messages` re-posed by `update`, each node traced with
    `samples_per_cell[node]` (default the map's), summed exactly as a tile sums them."""
    fleet = fleet_of(messages)
    if update is not None:
        fleet.apply_poses(update)
    reaching = fleet._nodes.reaching(grid, None)
    counted = [posed._replace(samples_per_cell=samples_per_cell.get(key[1])) for key, posed in reaching.items()]
    return fleet._tracers.trace(grid, counted, [])


def offline(messages, update, samples_per_cell: dict[int, float], grid: Grid = GRID) -> np.ndarray:
    """p(occupied) of offline_counts (2D: Eq. 11 of the counts as they are)."""
    return map_estimate(*offline_counts(messages, update, samples_per_cell, grid), DEFAULT_PRIOR)


def viewer_tiles(resolution: float, side: int = 64) -> list[Grid]:
    """Tiles of `side` cells on the lattice of `resolution` over GRID's box, as the viewer asks."""
    size = side * resolution
    return [
        Grid([ix * size, iy * size], resolution, (side, side))
        for ix in range(int(GRID.origin[0] // size), int(-(-GRID.upper[0] // size)))
        for iy in range(int(GRID.origin[1] // size), int(-(-GRID.upper[1] // size)))
    ]


def test_tiles_on_the_lattice_are_windows_of_one_layer_kept_up_to_date(messages, monkeypatch):
    """The viewer's tiles of a resolution are windows of one layer, made over the map's extent and
    grown when a tile beyond it is asked for: a node is traced once for all of them. Their counts
    are those of tiles of their own but where a ray passes a cell corner within round-off (traced
    from another grid origin); updated, the windows have the bits of a fresh map's asked in the
    same order."""
    fleet, alone = fleet_of(messages[:20]), fleet_of(messages[:20])
    tiled = viewer_tiles(0.1)
    layered = [fleet.occupancy(grid) for grid in tiled]
    assert fleet.cache_stats()["tiles"] == 1 and fleet.cache_stats()["misses"] == 1  # one trace for every tile
    monkeypatch.setattr(tile_set, "LAYER_MAX_CELLS", 0)
    own = [alone.occupancy(grid) for grid in tiled]
    assert alone.cache_stats()["tiles"] == len(tiled)
    differ = sum(int(np.sum(a != b)) for a, b in zip(layered, own))
    assert differ <= 1e-3 * len(tiled) * 64 * 64
    monkeypatch.undo()

    for msg in messages[20:24]:
        fleet.add_scan(msg)
    fresh = fleet_of(messages[:24])
    for grid in tiled:
        fresh.occupancy(grid)
    for grid in reversed(tiled):  # the first asked brings the whole layer up to date
        assert np.array_equal(fleet.occupancy(grid), fresh.occupancy(grid))
    assert fleet.cache_stats()["updates"] == 1
    assert fleet.occupancy(tiled[3]) is fleet.occupancy(tiled[3])  # one window object per state: encoded once

    beyond = Grid([40.0, 0.0], 0.1, (64, 64))  # past the map's extent: the layer grows to take it in
    fleet.occupancy(beyond)
    assert fleet.cache_stats()["tiles"] == 1 and fleet.cache_stats()["misses"] == 2
    assert np.array_equal(fleet.occupancy(tiled[3]), fresh.occupancy(tiled[3]))

    off_lattice = Grid(GRID.origin + 0.05, 0.1, (64, 64))
    fleet.occupancy(off_lattice)
    assert fleet.cache_stats()["tiles"] == 2  # a tile of its own
    monkeypatch.setattr(tile_set, "LAYER_MAX_CELLS", 200 * 200)
    far = Grid([100.0, 100.0], 0.1, (64, 64))  # would grow the layer past its bound
    fleet.occupancy(far)
    assert fleet.cache_stats()["tiles"] == 3


def test_a_large_update_is_thinned_on_idle_tracers_unless_every_change_is_asked(messages, monkeypatch):
    """Idle tracers trace an HTTP request's update with every sample only up to FULL_UPDATE_NODES nodes:
    a larger one is thinned and refined behind it; a request for every change (max_age 0) and an
    in-process caller get every sample."""
    monkeypatch.setattr(tile_updates, "FULL_UPDATE_NODES", 10)
    fleet = fleet_of(messages[:20], busy_samples_per_cell=1.0)
    assert fleet.occupancy_answer(GRID, patience=0.0).samples_per_cell == 1.0  # 20 nodes, afresh: thinned
    wait_for(lambda: fleet.occupancy_answer(GRID).samples_per_cell == 4.0, 30, "the refinement")
    assert np.array_equal(fleet.occupancy(GRID), offline(messages[:20], None, {}))
    for msg in messages[20:32]:
        fleet.add_scan(msg)
    assert fleet.occupancy_answer(GRID, patience=0.0).samples_per_cell == 1.0  # 12 changed nodes: thinned
    exact = fleet.occupancy_answer(GRID, max_age=0)  # every change asked (its own tile, not the layer)
    assert exact.samples_per_cell == 4.0 and np.array_equal(exact.prob, offline(messages[:32], None, {}))


def test_an_answer_states_the_samples_per_cell_of_the_state_it_serves(messages, monkeypatch):
    """While a refinement has traced but not yet published its state, the thinned state is served
    as thinned: the samples per cell go with the state, not with the tile's bookkeeping. (They were
    read from the tile, which a refinement updates before it publishes: a client that waited for
    the map's samples per cell was served the thinned state, as bench/region_served.py saw.) A
    request for every change (max_age 0) meanwhile waits for the refined state."""
    monkeypatch.setattr(tile_updates, "FULL_UPDATE_NODES", 10)
    fleet = fleet_of(messages[:20], busy_samples_per_cell=1.0)
    grid = Grid(GRID.origin + 0.05, GRID.resolution, GRID.shape)  # off the lattice: max_age 0 asks this tile too
    thinned = fleet.occupancy_answer(grid, patience=0.0)  # 20 nodes, afresh: thinned
    assert thinned.samples_per_cell == 1.0
    estimating, publish = threading.Event(), threading.Event()
    estimate = tile_updates.monte_carlo_estimate

    def held(hits, misses, samples_per_cell, prior):  # the refinement's state, held before it is published
        estimating.set()
        assert publish.wait(30)
        return estimate(hits, misses, samples_per_cell, prior)

    monkeypatch.setattr(tile_updates, "monte_carlo_estimate", held)
    assert fleet.occupancy_answer(grid).kind == "fresh"  # served as it is, refined behind it
    assert estimating.wait(30)
    during = fleet.occupancy_answer(grid)
    exact = []
    every_change = threading.Thread(target=lambda: exact.append(fleet.occupancy_answer(grid, max_age=0)))
    every_change.start()
    every_change.join(0.3)
    waited = every_change.is_alive()
    publish.set()
    every_change.join(30)
    assert during.prob is thinned.prob and (during.kind, during.samples_per_cell) == ("fresh", 1.0)
    refined = offline(messages[:20], None, {}, grid)
    assert waited and exact[0].samples_per_cell == 4.0 and np.array_equal(exact[0].prob, refined)
    assert fleet.occupancy_answer(grid).samples_per_cell == 4.0
    assert np.array_equal(fleet.occupancy(grid), refined)


def test_a_correction_by_less_than_a_cell_reaches_the_tile_on_idle_tracers(messages, monkeypatch):
    """Busy tracers keep a node moved by less than BUSY_REPOSE_CELLS at the pose held; where it moved
    by more than REPOSE_CELLS it is loose, and idle tracers trace it again at its pose, as they refine
    thinned nodes. Idle tracers trace such a move at once, in a large update too (thinned, refined
    behind it). Half a cell here: a pose-graph correction of many nodes reaches the tile either way."""
    monkeypatch.setattr(tile_updates, "FULL_UPDATE_NODES", 2)  # the 3 moved nodes: a large update
    half_cell = np.array([0.5 * GRID.resolution, 0.0, 0.0])
    update = PoseGraphUpdate(
        "f", "r1", 1, tuple((m.node, Pose.from_xytheta(*(m.pose.as_xytheta() + half_cell))) for m in messages[:3])
    )
    moved = offline(messages[:20], update, {})

    busy_first = fleet_of(messages[:20], busy_samples_per_cell=1.0)
    before = busy_first.occupancy(GRID)
    assert not np.array_equal(moved, before)
    idle = TracerPool.load
    monkeypatch.setattr(TracerPool, "load", lambda pool: TracerLoad(pool.threads, 0, pool.threads, 0.0))
    busy_first.apply_poses(update)
    wait_for(lambda: busy_first.occupancy_answer(GRID).kind == "fresh", 30, "the background update")
    assert np.array_equal(busy_first.occupancy(GRID), before)  # within the busy tolerance: kept
    (tile,) = busy_first._tiles.values()
    assert len(tile.loose) == 3
    monkeypatch.setattr(TracerPool, "load", idle)
    wait_for(lambda: np.array_equal(busy_first.occupancy_answer(GRID).prob, moved), 30, "the refinement")
    assert not tile.loose

    idle_first = fleet_of(messages[:20], busy_samples_per_cell=1.0)
    idle_first.occupancy(GRID)
    idle_first.apply_poses(update)
    assert idle_first.occupancy_answer(GRID, patience=0.0).samples_per_cell == 1.0  # traced at once, thinned
    wait_for(lambda: idle_first.occupancy_answer(GRID).samples_per_cell == 4.0, 30, "the refinement")
    assert np.array_equal(idle_first.occupancy(GRID), moved)


def test_an_update_applies_at_most_max_update_nodes_the_longest_changed_first(messages, monkeypatch):
    """An HTTP request's update (patience given) applies a backlog of changes MAX_UPDATE_NODES at a
    time, oldest first: each answer says how long ago the first change it lacks was made, and the
    last has the bits of a fresh map. A request for every change (max_age 0) applies them all at once,
    and so does an in-process caller."""
    monkeypatch.setattr(tile_updates, "MAX_UPDATE_NODES", 5)
    monkeypatch.setattr(tile_set, "LAYER_MAX_CELLS", 0)  # max_age 0 asks the same tile
    fleet = fleet_of(messages[:20])
    fleet.occupancy(GRID)
    for msg in messages[20:32]:
        fleet.add_scan(msg)
    time.sleep(0.05)
    answers = [fleet.occupancy_answer(GRID, patience=0.0) for _ in range(4)]  # 5 + 5 + 2 changed nodes, then none
    assert [a.kind for a in answers] == ["updated", "updated", "updated", "fresh"]
    assert answers[0].age >= 0.05 and answers[1].age >= 0.05 and answers[2].age == answers[3].age == 0.0
    assert fleet.cache_stats()["updates"] == 3
    assert np.array_equal(answers[3].prob, fleet_of(messages[:32]).occupancy(GRID))
    assert not np.array_equal(answers[0].prob, answers[3].prob)
    shift = np.array([0.3, -0.2, 0.05])
    update = PoseGraphUpdate(
        "f", "r1", 1, tuple((m.node, Pose.from_xytheta(*(m.pose.as_xytheta() + shift))) for m in messages[:8])
    )
    fleet.apply_poses(update)  # 8 moved nodes
    assert np.array_equal(fleet.occupancy_answer(GRID, max_age=0).prob, offline(messages[:32], update, {}))
    assert fleet.cache_stats()["updates"] == 4 and fleet.cache_stats()["tiles"] == 1
    fleet.apply_poses(PoseGraphUpdate("f", "r1", 2, tuple((m.node, m.pose) for m in messages[:8])))
    assert np.array_equal(fleet.occupancy(GRID), offline(messages[:32], None, {}))  # all 8 moved back at once
    assert fleet.cache_stats()["updates"] == 5


def test_a_request_that_waited_for_another_update_is_served_its_state(messages):
    """A request whose previous state is too old waits for the update under way and is served what
    that update made, however much backlog it left, rather than waiting for a turn of its own."""
    fleet = fleet_of(messages[:20], trace_threads=1)
    fleet.occupancy(GRID)
    fleet.add_scan(messages[20])
    time.sleep(0.01)  # the previous state is older than the request takes
    (tile,) = fleet._tiles.values()
    answers = []
    with tile.lock:  # another request's update, under way
        waiting = threading.Thread(target=lambda: answers.append(fleet.occupancy_answer(GRID, max_age=0.005)))
        waiting.start()
        waiting.join(0.3)
        assert waiting.is_alive()
        made = np.zeros(GRID.array_shape, np.float32)
        with fleet._lock:
            tile.prob = made  # what that update published (a backlog left: not up to date)
    waiting.join(10)
    assert answers[0].kind == "updated" and answers[0].prob.base is made and answers[0].age > 0  # GRID: a window
    assert fleet.cache_stats()["updates"] == 0


def test_only_an_unbounded_update_gives_way_to_other_traces(messages, monkeypatch):
    """A bounded update (an HTTP request's, patience given) holds its tile while it traces a bounded
    number of nodes: its parts do not give way to other traces', even at every sample on idle
    tracers. A request for every change (max_age 0) may trace thousands: its parts give way."""
    monkeypatch.setattr(tile_set, "LAYER_MAX_CELLS", 0)  # max_age 0 asks the same tile
    fleet = fleet_of(messages[:20])
    flags, trace = [], TracerPool.trace

    def traced(pool, grid, plus, minus, background=False):
        flags.append(background)
        return trace(pool, grid, plus, minus, background)

    monkeypatch.setattr(TracerPool, "trace", traced)
    assert fleet.occupancy_answer(GRID, patience=0.0).samples_per_cell == fleet.samples_per_cell  # every sample
    fleet.add_scan(messages[20])
    fleet.occupancy_answer(GRID, patience=0.0)
    fleet.add_scan(messages[21])
    fleet.occupancy_answer(GRID, max_age=0)
    assert flags == [False, False, True]


def test_busy_samples_per_cell_by_dimension_and_3d_tiles_served_with_the_neighbourhoods_prior(monkeypatch):
    """A server's busy samples per cell are one per dimension (tile_updates.BUSY_SAMPLES_PER_CELL); a thinned
    3D tile is served as monte_carlo_estimate of its counts at those samples (the neighbourhood's prior)."""
    by_dim = FleetMap("f", busy_samples_per_cell=tile_updates.BUSY_SAMPLES_PER_CELL, trace_threads=1)
    grids = {dim: Grid(np.full(dim, -4.0), 0.25, (32,) * dim) for dim in (2, 3)}
    assert {d: by_dim._tiles.busy_samples_per_cell(g) for d, g in grids.items()} == tile_updates.BUSY_SAMPLES_PER_CELL
    one = FleetMap("f", busy_samples_per_cell=2.0, trace_threads=1)
    assert [one._tiles.busy_samples_per_cell(g) for g in grids.values()] == [2.0, 2.0]
    over = FleetMap("f", samples_per_cell=1.0, busy_samples_per_cell={2: 0.5, 3: 1.0}, trace_threads=1)
    assert [over._tiles.busy_samples_per_cell(g) for g in grids.values()] == [0.5, None]  # not below the map's

    rng = np.random.default_rng(5)
    monkeypatch.setattr(tile_updates, "FULL_UPDATE_NODES", 1)  # the 3 nodes: a large update, thinned
    scans = [
        ScanMessage(
            "f",
            "r1",
            n,
            float(n),
            ScanModel(scan_like_mixture(rng, 3, 12, 3.0), scan_like_mixture(rng, 3, 0), np.zeros(3), 20.0),
            Pose.identity(3),
        )
        for n in range(3)
    ]
    fleet = fleet_of(scans, busy_samples_per_cell={3: 0.3})
    grid = Grid(np.full(3, -4.05), 0.25, (32,) * 3)  # off the lattice: a tile of its own, not a layer's window
    thinned = fleet.occupancy_answer(grid, patience=0.0)
    assert thinned.samples_per_cell == 0.3
    hits, misses = offline_counts(scans, None, {n: 0.3 for n in range(3)}, grid)
    assert np.array_equal(thinned.prob, monte_carlo_estimate(hits, misses, 0.3, fleet.prior))
    assert not np.array_equal(thinned.prob, map_estimate(hits, misses, fleet.prior))


@pytest.mark.parametrize("asked, scanned", [(2, 3), (3, 2)])
def test_a_map_with_no_scan_answers_every_grid_unknown_and_caches_none(asked, scanned):
    """A tile of the dimension asked for before the first scan would outlive that scan in the cache,
    where the map's dimension and its own differ: every later scan failed to mark it stale."""
    fleet = FleetMap("f", trace_threads=1)
    grid = Grid.from_bbox([-20.0] * asked, [20.0] * asked, 0.5)
    answer = fleet.occupancy_answer(grid)
    assert answer.prob.shape == grid.array_shape and (answer.prob == 0.5).all()
    assert fleet.cache_stats()["tiles"] == 0
    assert fleet.add_scan(scan_of(scanned, 0))
    assert fleet.occupancy(Grid.from_bbox([-20.0] * scanned, [20.0] * scanned, 0.5)).min() < 0.5
    assert fleet.cache_stats()["tiles"] == 1
    assert (answer.kind, answer.age, answer.samples_per_cell) == ("fresh", 0.0, fleet.samples_per_cell)  # up to date
