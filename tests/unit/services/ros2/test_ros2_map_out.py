"""The OccupancyGrid's grid and cells, against plain loops."""

from __future__ import annotations

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from gmm_core import FitConfig, Pose, fit_scan
from protocol import ScanMessage
from services.map_server.fleet_map import FleetMap
from services.ros2.config import Ros2Config
from services.ros2.map_out import RosMapPublisher, grid_cells, map_grid, timestamped
from services.zenoh_config import zenoh_config
from support.net import wait_for

JAZZY = get_typestore(Stores.ROS2_JAZZY)


def test_grid_covers_the_extent_on_whole_cells():
    grid = map_grid(np.array([-1.23, 4.01]), np.array([2.5, 6.0]), 0.1, 10**6)
    np.testing.assert_allclose(grid.origin, [-1.3, 4.0])
    assert np.all(grid.upper >= [2.5 - 1e-9, 6.0 - 1e-9]) and grid.shape == (38, 20)


def test_grid_is_cut_around_its_centre_to_the_cell_limit():
    grid = map_grid(np.array([0.0, 0.0]), np.array([100.0, 10.0]), 0.1, 10_000)
    assert np.prod(grid.shape) <= 10_000 and grid.shape[0] > grid.shape[1]
    centre = (grid.origin + grid.upper) / 2
    np.testing.assert_allclose(centre, [50.0, 5.0], atol=0.1)


def test_a_3d_grid_takes_the_z_band():
    grid = map_grid(np.array([0.0, 0.0, -3.0]), np.array([1.0, 1.0, 9.0]), 0.25, 10**6, (0.1, 1.9))
    np.testing.assert_allclose(grid.origin, [0.0, 0.0, 0.0])
    assert grid.shape == (4, 4, 8)


def test_cells_2d_and_3d_against_loops():
    rng = np.random.default_rng(3)
    prob = rng.choice([0.5, 0.0, 1.0, 0.234, 0.876, 0.5, 0.5], size=(4, 5, 6)).astype(np.float32)
    flat = grid_cells(prob[0])
    expect = [-1 if p == 0.5 else int(round(float(p) * 100)) for p in prob[0].ravel()]
    assert flat.dtype == np.int8 and flat.tolist() == expect
    projected = grid_cells(prob).reshape(5, 6)
    for iy in range(5):
        for ix in range(6):
            seen = [int(round(float(p) * 100)) for p in prob[:, iy, ix] if p != 0.5]
            assert projected[iy, ix] == (max(seen) if seen else -1)


@pytest.mark.parametrize(
    "layout, grid_key, path_key",
    [
        ({}, "0/map/**", "0/r_1/trajectory/**"),
        # a bridge started with namespace fleet routes Zenoh's fleet/map to the DDS side's /map
        ({"mapping": "bridge", "namespace": "fleet"}, "fleet/map", "fleet/r_1/trajectory"),
    ],
    ids=["rmw_zenoh", "bridge"],
)
def test_a_3d_map_goes_out_as_the_projection_of_its_z_band_and_each_robots_path(layout, grid_key, path_key):
    """A FleetMap of two 3D scans published on a real session; a subscriber of the same session
    decodes the grid and the trajectory with rosbags."""
    rng = np.random.default_rng(0)
    fleet_map = FleetMap("f", trace_threads=1)
    poses = [Pose.from_quaternion([0.0, 0.0, 0.5], [1, 0, 0, 0]), Pose.from_quaternion([1.0, 0.5, 0.5], [1, 0, 0, 0])]
    wall = np.column_stack([np.full(400, 3.0), rng.uniform(-2, 2, 400), rng.uniform(-1, 1, 400)])
    for node, pose in enumerate(poses):
        model = fit_scan(wall - pose.t, np.zeros((0, 3)), FitConfig().for_dimension(3))
        fleet_map.add_scan(ScanMessage("f", "r-1", node, float(node), model, pose))
    ros = Ros2Config(map_topic="/map", map_period=0.1, map_resolution=0.25, map_z="0.0,1.0", **layout)
    session = zenoh.open(timestamped(zenoh_config("peer")))
    received: dict[str, list] = {"grid": [], "path": []}
    subscribers = [
        session.declare_subscriber(grid_key, lambda s: received["grid"].append(s.payload.to_bytes())),
        session.declare_subscriber(path_key, lambda s: received["path"].append(s.payload.to_bytes())),
    ]
    publisher = RosMapPublisher(session, fleet_map, ros, "f")
    try:
        wait_for(lambda: received["grid"] and received["path"], 30, "a grid and a path")
    finally:
        publisher.close()
        for s in subscribers:
            s.undeclare()
        session.close()
    grid_message = JAZZY.deserialize_cdr(received["grid"][-1], "nav_msgs/msg/OccupancyGrid")
    info = grid_message.info
    lo, hi = fleet_map.extent()
    grid = map_grid(lo, hi, 0.25, ros.map_cells, (0.0, 1.0))
    assert (info.width, info.height) == grid.shape[:2] and info.origin.position.z == 0.0
    expected = grid_cells(fleet_map.occupancy(grid))
    assert np.array_equal(np.asarray(grid_message.data), expected)
    assert (expected > 65).any() and (expected == -1).any() and ((expected >= 0) & (expected < 35)).any()
    path = JAZZY.deserialize_cdr(received["path"][-1], "nav_msgs/msg/Path")
    positions = [(p.pose.position.x, p.pose.position.y, p.pose.position.z) for p in path.poses]
    np.testing.assert_allclose(positions, [p.t for p in poses])
