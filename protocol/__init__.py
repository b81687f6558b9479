"""What crosses the wire between robots and map servers: messages, codec, key expressions."""

from protocol.codec import MAX_BYTES, MAX_COMPONENTS, VERSION, decode, encode
from protocol.errors import ProtocolError
from protocol.keys import (
    ack_key,
    check_id,
    inventory_key,
    inventory_wildcard,
    occupancy_key,
    occupancy_wildcard,
    parse_key,
    points_key,
    poses_key,
    poses_wildcard,
    scan_key,
    scan_wildcard,
)
from protocol.messages import (
    Ack,
    MapQuery,
    MapReply,
    Message,
    PointQuery,
    PointReply,
    PoseGraphUpdate,
    Rejection,
    ScanMessage,
    StoreInventory,
)
from protocol.scan_codec import ENCODINGS

__all__ = [
    "ENCODINGS",
    "MAX_BYTES",
    "MAX_COMPONENTS",
    "VERSION",
    "decode",
    "encode",
    "ProtocolError",
    "ack_key",
    "check_id",
    "inventory_key",
    "inventory_wildcard",
    "occupancy_key",
    "occupancy_wildcard",
    "parse_key",
    "points_key",
    "poses_key",
    "poses_wildcard",
    "scan_key",
    "scan_wildcard",
    "Ack",
    "MapQuery",
    "MapReply",
    "Message",
    "PointQuery",
    "PointReply",
    "PoseGraphUpdate",
    "Rejection",
    "ScanMessage",
    "StoreInventory",
]
