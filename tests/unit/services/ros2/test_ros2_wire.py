"""rmw_zenoh's attachment and CDR samples (rosbags serialises, as a ROS publisher would)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from services.ros2 import wire
from support.rosbags_written import LASER_SCAN, RosMessages


def test_attachment_layout_and_round_trip():
    gid = bytes(range(16))
    raw = wire.Attachment(7, 1_700_000_000_123_456_789, gid).encode()
    # design.md: int64 LE sequence number, int64 LE ns timestamp, GID length byte (16), 16 GID bytes
    assert raw == struct.pack("<q", 7) + struct.pack("<q", 1_700_000_000_123_456_789) + b"\x10" + gid
    assert wire.Attachment.decode(raw) == wire.Attachment(7, 1_700_000_000_123_456_789, gid)


def test_bad_attachments_are_refused_by_field():
    with pytest.raises(wire.RosWireError, match="attachment: 32 bytes"):
        wire.Attachment.decode(bytes(32))
    with pytest.raises(wire.RosWireError, match="GID length 12"):
        wire.Attachment.decode(struct.pack("<qqB16s", 1, 2, 12, bytes(16)))


def test_cdr_round_trip_and_refusal():
    m = RosMessages("sqlite3")
    scan = m.laser_scan(12.5, "laser", np.array([1.0, np.inf, 2.5]), -1.0, 0.5, 0.1, 30.0)
    raw = bytes(m.store.serialize_cdr(scan, LASER_SCAN))
    assert raw[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation header
    decoded = wire.decode(raw, LASER_SCAN)
    assert decoded.header.frame_id == "laser" and decoded.ranges.tolist() == [1.0, np.inf, 2.5]
    assert wire.encode(decoded, LASER_SCAN, "jazzy") == raw
    with pytest.raises(wire.RosWireError, match="payload: not a CDR nav_msgs/msg/Path"):
        wire.decode(raw, "nav_msgs/msg/Path")
    assert wire.gid_of("a") != wire.gid_of("b") and len(wire.gid_of("a")) == 16
