"""protocol/message_codec.py: pose-graph updates, acknowledgements, rejections, store inventories,
map and point queries and replies round trip, and each rule of their validation names its field."""

from __future__ import annotations

import numpy as np
import pytest

from gmm_core.pose import Pose
from protocol import (
    Ack,
    MapQuery,
    MapReply,
    PointQuery,
    PointReply,
    PoseGraphUpdate,
    ProtocolError,
    decode,
    encode,
)
from support.wire_maps import pack, set_path, wire

pytestmark = pytest.mark.filterwarnings("error")  # a numpy warning means a value slipped through


def test_other_messages_round_trip():
    poses = ((3, Pose.from_xytheta(1, 2, 0.5)), (9, Pose.from_xytheta(-1, 0, -3.0)))
    update = decode(encode(PoseGraphUpdate("f", "r", 12, poses, Pose.from_xytheta(1e6, 5e6, 0.1))))
    assert update.revision == 12 and [node for node, _ in update.poses] == [3, 9]
    np.testing.assert_allclose(update.poses[1][1].R, poses[1][1].R, atol=1e-9)  # 2pi / 2^32 steps
    np.testing.assert_allclose(update.poses[1][1].t, poses[1][1].t, atol=0.5e-4, rtol=0)  # 0.1 mm steps
    np.testing.assert_array_equal(update.anchor.t, [1e6, 5e6])  # the anchor is float64 on the wire
    update3 = decode(encode(PoseGraphUpdate("f", "r", 0, ((0, Pose.from_quaternion([1, 2, 3], [1, 2, 3, 4])),))))
    assert update3.anchor is None and update3.dim == 3
    assert decode(encode(Ack("f", "r", "s1", "poses", (12,)))) == Ack("f", "r", "s1", "poses", (12,))
    queued = Ack("f", "r", "s1", "scan", (1, 2), queued=(3,))
    assert decode(encode(queued)) == queued
    query = decode(encode(MapQuery("f", [0, 0, 0], [1, 2, 3], 0.05, ("a", "b"))))
    assert query.robots == ("a", "b") and query.resolution == 0.05
    np.testing.assert_array_equal(query.hi, [1, 2, 3])
    assert decode(encode(MapQuery("f", [0, 0], [1, 1], 0.1))).robots is None
    grid = np.random.default_rng(0).uniform(size=(3, 4)).astype(np.float32)
    reply = decode(encode(MapReply("f", [1.0, 2.0], 0.1, grid)), expect=MapReply)
    np.testing.assert_array_equal(reply.probabilities, grid)
    points = np.random.default_rng(1).normal(0, 50, (5, 3))
    asked = decode(encode(PointQuery("f", points, 0.2, ("b", "a"), "analytic")), expect=PointQuery)
    assert (asked.dim, asked.resolution, asked.robots, asked.method) == (3, 0.2, ("b", "a"), "analytic")
    np.testing.assert_array_equal(asked.points, points)  # float64 on the wire, as a MapQuery's box
    assert decode(encode(PointQuery("f", [[1.0, 2.0]], 0.05))).method == "auto"
    answered = decode(encode(PointReply("f", 0.2, grid[0], "mc")), expect=PointReply)
    assert answered.method == "mc" and answered.resolution == 0.2
    np.testing.assert_array_equal(answered.probabilities, grid[0])


INVALID_OTHERS = [
    (
        PoseGraphUpdate("f", "r", 1, ((1, Pose.identity(2)), (2, Pose.identity(2)))),
        lambda r: set_path(r, ("nodes",), np.array([4, 4], "<u8").tobytes()),  # an empty range
        "poses.nodes",
    ),
    (
        PoseGraphUpdate("f", "r", 1, ((1, Pose.identity(2)), (3, Pose.identity(2)))),
        lambda r: set_path(r, ("nodes",), np.array([1, 2, 2, 3], "<u8").tobytes()),  # touching ranges
        "poses.nodes",
    ),
    (
        PoseGraphUpdate("f", "r", 1, ((1, Pose.identity(2)),)),
        lambda r: set_path(r, ("nodes",), np.array([2**63, 2**63 + 1], "<u8").tobytes()),
        "poses.nodes",
    ),
    (
        PoseGraphUpdate("f", "r", 1, ((1, Pose.identity(2)),)),
        lambda r: set_path(r, ("nodes",), np.array([1], "<u8").tobytes()),  # a start without its stop
        "poses.nodes",
    ),
    (
        PoseGraphUpdate("f", "r", 1, ((1, Pose.identity(2)),)),
        lambda r: set_path(r, ("nodes",), np.array([0, 2**62], "<u8").tobytes()),  # 2^62 poses: not sent
        "poses.poses",
    ),
    (
        PoseGraphUpdate("f", "r", 1, ((1, Pose.identity(2)),)),
        lambda r: set_path(r, ("poses",), r["poses"][:-4]),
        "poses.poses",
    ),
    (
        PoseGraphUpdate("f", "r", 1, ((1, Pose.identity(3)),)),
        lambda r: set_path(r, ("poses",), np.array([0, 0, 0, 2**31 - 1, 2**31 - 1, 0, 0], "<i4").tobytes()),
        "poses.poses",  # a quaternion of norm sqrt(2)
    ),
    (PoseGraphUpdate("f", "r", 1, ((1, Pose.identity(2)),)), lambda r: set_path(r, ("rev",), -2), "revision"),
    (
        PoseGraphUpdate("f", "r", 1, ((1, Pose.identity(3)),)),
        lambda r: set_path(r, ("anchor",), np.array([0, 0, 0, 0, 0, 0, 0], "<f8").tobytes()),
        "anchor",
    ),
    (PoseGraphUpdate("f", "r", 1, (), Pose.identity(2)), lambda r: set_path(r, ("anchor",), None), "poses"),
    (Ack("f", "r", "s", "scan", (1,)), lambda r: set_path(r, ("kind",), "map"), "kind"),
    (Ack("f", "r", "s", "scan", (1,)), lambda r: set_path(r, ("ids",), b"\x01\x02"), "ids"),
    (Ack("f", "r", "s", "scan", (1,)), lambda r: set_path(r, ("store",), "a/b"), "store"),
    (Ack("f", "r", "s", "scan", (1,)), lambda r: set_path(r, ("queued",), None), "queued"),
    (MapQuery("f", [0, 0], [1, 1], 0.1), lambda r: set_path(r, ("hi",), r["lo"]), "bbox"),
    (MapQuery("f", [0, 0], [1, 1], 0.1), lambda r: set_path(r, ("res",), 0.0), "resolution"),
    (MapQuery("f", [0, 0], [1, 1], 0.1), lambda r: set_path(r, ("robots",), ["ok", "no/slash"]), "robots"),
    (MapQuery("f", [0, 0], [1, 1], 0.1), lambda r: set_path(r, ("robots",), "ok"), "robots"),
    (MapReply("f", [0, 0], 0.1, np.zeros((2, 2))), lambda r: set_path(r, ("shape",), [2, 3]), "probabilities"),
    (MapReply("f", [0, 0], 0.1, np.zeros((2, 2))), lambda r: set_path(r, ("shape",), [4]), "shape"),
    (
        MapReply("f", [0, 0], 0.1, np.zeros((2, 2))),
        lambda r: set_path(r, ("p",), np.array([0, 0.5, 1, 1.5], "<f4").tobytes()),
        "probabilities",
    ),
    (PointQuery("f", [[0, 0], [1, 1]], 0.1), lambda r: set_path(r, ("n",), 3), "points"),
    (PointQuery("f", [[0, 0], [1, 1]], 0.1), lambda r: set_path(r, ("n",), 0), "count"),
    (PointQuery("f", [[0, 0], [1, 1]], 0.1), lambda r: set_path(r, ("n",), 10_001), "count"),
    (PointQuery("f", [[0, 0], [1, 1]], 0.1), lambda r: set_path(r, ("d",), 4), "dimension"),
    (PointQuery("f", [[0, 0], [1, 1]], 0.1), lambda r: set_path(r, ("m",), "exact"), "method"),
    (PointQuery("f", [[0, 0], [1, 1]], 0.1), lambda r: set_path(r, ("m",), None), "method"),
    (PointQuery("f", [[0, 0], [1, 1]], 0.1), lambda r: set_path(r, ("res",), -1.0), "resolution"),
    (PointQuery("f", [[0, 0], [1, 1]], 0.1), lambda r: set_path(r, ("robots",), ["a b"]), "robots"),
    (
        PointQuery("f", [[0, 0], [1, 1]], 0.1),
        lambda r: set_path(r, ("p",), np.array([0, 0, np.nan, 1], "<f8").tobytes()),
        "points",
    ),
    (PointReply("f", 0.1, [0.5], "mc"), lambda r: set_path(r, ("m",), "auto"), "method"),
    (PointReply("f", 0.1, [0.5], "mc"), lambda r: set_path(r, ("p",), b""), "probabilities"),
    (
        PointReply("f", 0.1, [0.5], "mc"),
        lambda r: set_path(r, ("p",), np.array([2.0], "<f4").tobytes()),
        "probabilities",
    ),
]


@pytest.mark.parametrize("message, edit, field", INVALID_OTHERS)
def test_invalid_other_messages_name_field(message, edit, field):
    with pytest.raises(ProtocolError) as caught:
        decode(pack(edit(wire(message))))
    assert caught.value.field == field


def test_rejection_round_trip_and_never_mistaken_for_an_ack():
    from protocol import Rejection

    refusal = Rejection("f", "r", "s1", "scan", (3, 4), "quota", "robot r holds 512 MiB")
    assert decode(encode(refusal)) == refusal
    with pytest.raises(ProtocolError, match="type"):  # a receiver that waits for Acks drops it
        decode(encode(refusal), expect=Ack)
    for bad, field in (
        (dict(reason="no quota"), "reason"),
        (dict(detail="x" * 1001), "detail"),
        (dict(kind="map"), "kind"),
        (dict(ids=(-1,)), "ids"),
    ):
        args = dict(fleet="f", robot="r", store="s1", kind="scan", ids=(1,), reason="quota", detail="") | bad
        with pytest.raises(ProtocolError, match=field):
            Rejection(**args)


def test_store_inventory_round_trip_and_ranges():
    from protocol import StoreInventory

    nodes = [0, 1, 2, 5, 7, 8, 9, 2**40]
    inventory = StoreInventory.of("f", "r", "s1", nodes, revision=4)
    assert inventory.ranges == ((0, 3), (5, 6), (7, 10), (2**40, 2**40 + 1))
    assert decode(encode(inventory)) == inventory
    assert [n in inventory for n in range(11)] == [n in nodes for n in range(11)] and 2**40 in inventory
    assert len(inventory) == len(nodes)
    assert decode(encode(StoreInventory.of("f", "r", "s1", []))).revision is None
    for bad in (((3, 3),), ((0, 2), (2, 4)), ((5, 6), (0, 1))):  # empty, touching, unsorted
        with pytest.raises(ProtocolError, match="ranges"):
            StoreInventory("f", "r", "s1", bad)


def test_pose_translations_beyond_the_int32_codes_are_refused_by_the_encoder():
    edge = 214748.3647  # 2^31 - 1 steps of 0.1 mm
    update = decode(encode(PoseGraphUpdate("f", "r", 1, ((1, Pose.from_xytheta(edge, -edge, 0.0)),))))
    assert update.poses[0][1].t.tolist() == [edge, -edge]
    for t in ([edge + 1e-4, 0.0], [0.0, -edge - 2e-4]):
        with pytest.raises(ProtocolError, match="^poses.poses: translation .* beyond"):
            encode(
                PoseGraphUpdate("f", "r", 1, ((1, Pose.from_xytheta(0.0, 0.0, 0.0)), (2, Pose.from_xytheta(*t, 0.0))))
            )
    far = Pose.from_quaternion([5e6, -3e6, 100.0], [1.0, 0.0, 0.0, 0.0])  # UTM-like: the anchor is float64
    assert decode(encode(PoseGraphUpdate("f", "r", 1, (), far))).anchor.t.tolist() == [5e6, -3e6, 100.0]
