"""msgpack codec: encode(message) -> bytes and decode(bytes) -> message; layout in docs/PROTOCOL.md.

Every message is one msgpack map with a version "v" and a type code "t". Scan messages also
name the encoding "e" of their two mixtures: "f32" (float32 tables, lossless for float32
inputs) or "q" (quantised, about a third of the size; see protocol.quantize). Pose-graph updates
carry int32 pose codes (protocol.pose_codes) since version 3; version 2 messages are still read.
decode() trusts nothing: whatever the bytes, it returns a valid message or raises ProtocolError.

This module is the framing ("Framing" in docs/PROTOCOL.md): version, type code, limits, and the
table of each type's encoder and decoder; protocol.scan_codec writes and reads a scan's map,
protocol.message_codec those of the other messages.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import msgpack

from protocol.errors import ProtocolError
from protocol.message_codec import (
    _decode_ack,
    _decode_inventory,
    _decode_map_query,
    _decode_map_reply,
    _decode_point_query,
    _decode_point_reply,
    _decode_poses,
    _decode_poses_v2,
    _decode_rejection,
    _encode_ack,
    _encode_inventory,
    _encode_map_query,
    _encode_map_reply,
    _encode_point_query,
    _encode_point_reply,
    _encode_poses,
    _encode_rejection,
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
from protocol.scan_codec import ENCODINGS, _decode_scan, _encode_scan
from protocol.wire import Fields

VERSION = 3  # what the encoder writes
# Versions the decoder reads: version 2 differs only in its pose-graph updates (float64 poses,
# listed node by node), which map servers' stores and robots' outboxes still hold.
READS = (2, 3)
# What changed from a version no longer read, for the error an old peer's message gets.
VERSION_CHANGES = {1: "acknowledgements name the store; pose-graph updates apply node by node"}
MAX_COMPONENTS = 4096  # default cap on occupied + free components of one scan
MAX_BYTES = 1 << 20  # default cap on a payload, checked before unpacking
MAX_LIST = 65536  # msgpack arrays (robot lists, grid shapes) are short
UNCHECKED = "unchecked error"  # prefix of errors caught by the safety net, not a named check

TYPE_CODES = {
    ScanMessage: 1,
    PoseGraphUpdate: 2,
    Ack: 3,
    MapQuery: 4,
    MapReply: 5,
    Rejection: 6,
    StoreInventory: 7,
    PointQuery: 8,
    PointReply: 9,
}


def encode(message: Message, encoding: str = "q") -> bytes:
    """Message -> bytes. `encoding` ("q" or "f32") applies to scan mixtures; other messages
    ignore it. Raises ProtocolError for anything decode() would reject (NaN, non-PD, ...)."""
    if encoding not in ENCODINGS:
        raise ProtocolError("encoding", f"must be one of {ENCODINGS}, got {encoding!r:.80}")
    code = TYPE_CODES.get(type(message))
    if code is None:
        raise ProtocolError("message", f"cannot encode {type(message).__name__}")
    body = _ENCODERS[code](message, encoding)
    return msgpack.packb({"v": VERSION, "t": code, **body}, use_bin_type=True)


def decode(
    data: bytes, *, expect: type | None = None, max_components: int = MAX_COMPONENTS, max_bytes: int = MAX_BYTES
) -> Message:
    """bytes -> a valid message, or ProtocolError naming the offending field; nothing else.

    `expect` (a message class) rejects any other type; `max_components` caps the components
    of a scan (occupied + free); `max_bytes` caps the payload (raise it for large MapReply).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("message", f"must be bytes, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise ProtocolError("message", f"payload of {len(data)} bytes exceeds the maximum of {max_bytes}")
    try:
        raw = msgpack.unpackb(
            bytes(data),
            raw=False,
            strict_map_key=True,
            object_pairs_hook=_map_without_duplicates,
            max_str_len=1024,
            max_bin_len=max_bytes,
            max_array_len=MAX_LIST,
            max_map_len=64,
            max_ext_len=0,
            ext_hook=_refuse_ext,  # max_ext_len lets an ext of 0 bytes through
        )
    except Exception as error:  # msgpack raises several types (FormatError, ValueError, StackError, ...)
        raise ProtocolError("message", f"malformed msgpack: {type(error).__name__}: {error}") from None
    try:
        message = _decode_message(Fields(raw), max_components)
    except ProtocolError:
        raise
    except Exception as error:  # a check we missed must still surface as a protocol error
        raise ProtocolError("message", f"{UNCHECKED}: {type(error).__name__}: {error}") from None
    if expect is not None and not isinstance(message, expect):
        raise ProtocolError("type", f"expected {expect.__name__}, got {type(message).__name__}")
    return message


def _refuse_ext(code, data):
    raise ValueError(f"ext type {code} is not part of the protocol")


def _map_without_duplicates(pairs):
    result = dict(pairs)
    if len(result) != len(pairs):
        raise ValueError("duplicate map key")
    return result


def _decode_message(f: Fields, max_components: int) -> Message:
    version = f.get("v", "version")
    if type(version) is not int or version not in READS:
        known = type(version) is int and version in VERSION_CHANGES
        change = f" (version {version + 1}: {VERSION_CHANGES[version]}; upgrade the peer)" if known else ""
        reads = " and ".join(map(str, READS))
        raise ProtocolError("version", f"unsupported version {version!r:.80}, this decoder reads {reads}{change}")
    code = f.get("t", "type")
    decoder = (_DECODERS if version == VERSION else _DECODERS_V2).get(code) if type(code) is int else None
    if decoder is None:
        raise ProtocolError("type", f"unknown message type {code!r:.80}")
    return decoder(f, max_components)


# An encoder takes the message class that TYPE_CODES gives its code.
_ENCODERS: dict[int, Callable[[Any, str], dict]] = {
    1: _encode_scan,
    2: _encode_poses,
    3: _encode_ack,
    4: _encode_map_query,
    5: _encode_map_reply,
    6: _encode_rejection,
    7: _encode_inventory,
    8: _encode_point_query,
    9: _encode_point_reply,
}
_DECODERS: dict[int, Callable[[Fields, int], Message]] = {
    1: _decode_scan,
    2: _decode_poses,
    3: _decode_ack,
    4: _decode_map_query,
    5: _decode_map_reply,
    6: _decode_rejection,
    7: _decode_inventory,
    8: _decode_point_query,
    9: _decode_point_reply,
}
_DECODERS_V2 = _DECODERS | {2: _decode_poses_v2}
