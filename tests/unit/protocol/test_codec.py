"""protocol/codec.py, the framing: malformed and oversized bytes, the versions read and refused,
and random and mutated bytes, which see only ProtocolError or a valid message."""

from __future__ import annotations

import msgpack
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
from protocol.codec import UNCHECKED
from support.fuzz import mutate, scan_message, seed_messages
from support.golden import version_2_update
from support.wire_maps import pack, wire

pytestmark = pytest.mark.filterwarnings("error")  # a numpy warning means a value slipped through


@pytest.mark.parametrize("data", [b"", b"\xc1", b"\x93\x01\x02", b"\xa3abc", b"\x81\xa1v"])
def test_malformed_msgpack(data):
    with pytest.raises(ProtocolError) as caught:
        decode(data)
    assert caught.value.field == "message"


def test_limits():
    data = encode(scan_message(np.random.default_rng(0), 2, 50, 5))
    assert decode(data, max_components=55).model.n_components == 55
    with pytest.raises(ProtocolError, match="^components: 55 components exceed"):
        decode(data, max_components=54)
    with pytest.raises(ProtocolError, match="^message: payload of"):
        decode(data, max_bytes=len(data) - 1)
    with pytest.raises(ProtocolError, match="^message: must be bytes"):
        decode("text")
    with pytest.raises(ProtocolError, match="^type: expected PoseGraphUpdate"):
        decode(data, expect=PoseGraphUpdate)
    duplicate = b"\x82\xa1v\x01\xa1v\x01"
    with pytest.raises(ProtocolError, match="^message: malformed"):
        decode(duplicate)


def test_a_version_1_message_is_refused_with_what_changed():
    old = pack({"v": 1, "t": 3, "f": "f", "r": "r", "kind": "scan", "ids": b""})
    with pytest.raises(
        ProtocolError, match=r"^version: unsupported version 1, this decoder reads 2 and 3 \(version 2: ackn"
    ):
        decode(old)
    with pytest.raises(ProtocolError, match=r"^version: unsupported version 4, this decoder reads 2 and 3$"):
        decode(pack(wire(Ack("f", "r", "s", "scan", (1,))) | {"v": 4}))


def test_version_2_messages_of_every_type_still_decode():
    """Stores and outboxes hold version-2 bytes: every type but the pose-graph update is the same
    map under v 2; a v2 update lists nodes one by one with float64 poses (its golden vector: poses_2d_v2)."""
    rng = np.random.default_rng(3)
    for message, encoding in (
        (scan_message(rng, 2, 8, 2), "q"),
        (scan_message(rng, 3, 8, 2), "f32"),
        (Ack("f", "r", "s", "scan", (1, 2), (3,)), "q"),
        (MapQuery("f", [0, 0], [1, 1], 0.1, ("a",)), "q"),
        (MapReply("f", [0, 0], 0.1, np.full((2, 3), 0.5)), "q"),
        (PointQuery("f", [[0, 0]], 0.1, None, "mc"), "q"),
        (PointReply("f", 0.1, [0.25], "analytic"), "q"),
    ):
        raw = wire(message, encoding)
        assert raw["v"] == 3
        assert encode(decode(pack(raw | {"v": 2})), encoding) == encode(message, encoding)
    poses = ((9, Pose.from_xytheta(1.23456789, -2.0, 0.3)), (2, Pose.from_xytheta(-5.0, 0.5, -1.0)))
    v2 = version_2_update(PoseGraphUpdate("f", "r", 4, poses))
    update = decode(v2)
    assert [node for node, _ in update.poses] == [2, 9]
    assert update.poses[1][1].t.tolist() == [1.23456789, -2.0]  # float64, as sent
    assert update.poses[0][1].as_xytheta()[2] == pytest.approx(-1.0, abs=1e-15)
    raw = msgpack.unpackb(v2, raw=False)
    with pytest.raises(ProtocolError, match="^poses.poses: must hold 6 x 8 bytes"):
        decode(pack(raw | {"poses": raw["poses"][:-8]}))


# --- fuzz: random and mutated bytes see only ProtocolError or a valid message


def test_fuzz_sees_only_protocol_errors():
    rng = np.random.default_rng(2024)
    seeds = seed_messages(rng)
    valid = 0
    for case in range(4000):
        _, data = mutate(rng, seeds[case % len(seeds)])
        try:
            message = decode(data)
        except ProtocolError as error:
            assert not error.message.startswith(UNCHECKED), error  # every rejection is a named check
            continue
        valid += 1
        try:
            decode(encode(message))  # whatever decodes can be forwarded
        except ProtocolError as error:  # but a version-2 pose beyond version 3's ±214 km
            assert isinstance(message, PoseGraphUpdate) and error.field == "poses.poses", error
            assert "beyond ±214748.3647 m" in error.message
    assert 0 < valid < 4000
