"""ROS 2 samples on Zenoh: CDR payloads (with their 4-byte encapsulation header, as both rmw_zenoh
and zenoh-bridge-ros2dds carry them) and rmw_zenoh's attachment.

The attachment of every rmw_zenoh sample (docs/design.md, "Publishers"): the sequence number
(int64, little-endian), the source timestamp (int64 ns since the UNIX epoch, little-endian), the
GID's length (one byte, 16) and the publisher's GID (16 bytes).
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass

from .names import typestore

ATTACHMENT = struct.Struct("<qqB16s")
GID_BYTES = 16


class RosWireError(ValueError):
    """A sample that is not what its topic carries; the message names the field."""


@dataclass(frozen=True)
class Attachment:
    sequence: int
    stamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        return ATTACHMENT.pack(self.sequence, self.stamp_ns, GID_BYTES, self.gid)

    @classmethod
    def decode(cls, raw: bytes) -> Attachment:
        if len(raw) != ATTACHMENT.size:
            raise RosWireError(f"attachment: {len(raw)} bytes, rmw_zenoh's has {ATTACHMENT.size}")
        sequence, stamp, length, gid = ATTACHMENT.unpack(raw)
        if length != GID_BYTES:
            raise RosWireError(f"attachment: GID length {length}, expected {GID_BYTES}")
        return cls(sequence, stamp, gid)


def gid_of(token: str) -> bytes:
    """A publisher's GID: 16 bytes hashed from its liveliness token, unique as the token is
    (rmw_zenoh hashes the token too, with XXH3; receivers only compare GIDs)."""
    return hashlib.blake2b(token.encode(), digest_size=GID_BYTES).digest()


def decode(raw: bytes, msgtype: str, distro: str = "jazzy"):
    """A CDR sample (encapsulation header first) as a rosbags message object; RosWireError if it is not one."""
    try:
        return typestore(distro).deserialize_cdr(raw, msgtype)
    except Exception as error:  # rosbags' SerdeError, struct.error, IndexError...: the bytes' fault
        raise RosWireError(f"payload: not a CDR {msgtype} ({type(error).__name__}: {error})") from None


def encode(message, msgtype: str, distro: str) -> bytes:
    """CDR, little-endian, with its encapsulation header."""
    return bytes(typestore(distro).serialize_cdr(message, msgtype))
