"""A message's msgpack map, to edit before it is packed again: how the tests of protocol/ write
wire maps that a peer could send but the encoder never would."""

from __future__ import annotations

import msgpack

from protocol import encode


def wire(message, encoding="q") -> dict:
    return msgpack.unpackb(encode(message, encoding), raw=False)


def pack(raw: dict) -> bytes:
    return msgpack.packb(raw, use_bin_type=True)


def without(raw: dict, *path) -> dict:
    target = raw
    for key in path[:-1]:
        target = target[key]
    del target[path[-1]]
    return raw


def set_path(raw: dict, path: tuple, value) -> dict:
    target = raw
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return raw
