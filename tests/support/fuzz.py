"""Scan-like random mixtures and mutated wire bytes, shared by tests, bench/protocol_fuzz.py and
bench/fuzz_ingest.py.

Nothing here runs in a service; it makes inputs that a weak radio or a hostile peer could send.
"""

from __future__ import annotations

import math
from dataclasses import replace

import msgpack
import numpy as np

from gmm_core.mixture import Mixture
from gmm_core.pose import Pose
from gmm_core.scan import ScanModel
from protocol.codec import encode
from protocol.messages import (
    Ack,
    MapQuery,
    MapReply,
    PointQuery,
    PointReply,
    PoseGraphUpdate,
    Rejection,
    ScanMessage,
    StoreInventory,
)
from support.golden import version_2_update


def random_rotations(rng: np.random.Generator, count: int, dim: int) -> np.ndarray:
    if dim == 2:
        theta = rng.uniform(-np.pi, np.pi, count)
        c, s = np.cos(theta), np.sin(theta)
        return np.stack([np.stack([c, -s], axis=1), np.stack([s, c], axis=1)], axis=1)
    q, r = np.linalg.qr(rng.normal(size=(count, 3, 3)))
    q *= np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return q


def scan_like_mixture(rng: np.random.Generator, dim: int, count: int, extent: float = 10.0) -> Mixture:
    """Components like a range scan's: means within `extent` of the sensor, one thin axis (the
    surface normal, 1 mm - 2 cm) and long axes along the surface (1 cm - 1 m)."""
    means = rng.uniform(-extent, extent, size=(count, dim))
    log_std = rng.uniform(math.log(0.01), math.log(1.0), size=(count, dim))
    log_std[:, 0] = rng.uniform(math.log(1e-3), math.log(2e-2), size=count)
    rotations = random_rotations(rng, count, dim)
    covs = np.einsum("kij,kj,klj->kil", rotations, np.exp(2 * log_std), rotations)
    weights = rng.dirichlet(np.ones(count)) if count else np.zeros(0)
    return Mixture(weights, means, covs, int(rng.integers(count, 20 * count + 1)))


def scan_message(rng: np.random.Generator, dim: int, occupied: int, free: int, node: int = 7) -> ScanMessage:
    max_range = 30.0 if dim == 2 else 80.0
    model = ScanModel(
        scan_like_mixture(rng, dim, occupied),
        scan_like_mixture(rng, dim, free, max_range),
        rng.normal(scale=0.1, size=dim),
        max_range,
    )
    if dim == 2:
        pose = Pose.from_xytheta(*rng.uniform(-20, 20, 2), rng.uniform(-np.pi, np.pi))
    else:
        pose = Pose.from_quaternion(rng.uniform(-20, 20, 3), rng.normal(size=4))
    return ScanMessage("fleet-a", "robot_1", node, 1.7e9 + rng.uniform(0, 1e6), model, pose)


def seed_messages(rng: np.random.Generator) -> list[bytes]:
    """Valid encodings of every message type, both encodings, both dimensions."""
    messages = []
    for dim in (2, 3):
        for encoding in ("q", "f32"):
            messages.append(encode(scan_message(rng, dim, int(rng.integers(1, 12)), int(rng.integers(0, 3))), encoding))
        messages.append(encode(scan_message(rng, dim, 0, 0)))
        nodes = rng.choice(40, size=int(rng.integers(1, 8)), replace=False).tolist()  # a few ranges
        rotations = random_rotations(rng, len(nodes), dim)
        poses = tuple((node, Pose(R, rng.normal(0, 50, dim))) for node, R in zip(nodes, rotations))
        update = PoseGraphUpdate("fleet-a", "robot_1", 3, poses, Pose.identity(dim))
        messages += [encode(update), version_2_update(update)]  # stores and outboxes hold version 2
        messages.append(encode(MapQuery("fleet-a", np.zeros(dim), np.ones(dim), 0.1, ("robot_1",))))
        messages.append(encode(MapReply("fleet-a", np.zeros(dim), 0.5, rng.uniform(size=(2,) * dim))))
        messages.append(encode(PointQuery("fleet-a", rng.normal(0, 20, (3, dim)), 0.1, None, "analytic")))
        messages.append(encode(PointReply("fleet-a", 0.1, rng.uniform(size=3), "mc")))
    store = "0123456789abcdef0123456789abcdef"
    messages.append(encode(Ack("fleet-a", "robot_1", store, "scan", (1, 2, 3), queued=(4,))))
    messages.append(encode(Rejection("fleet-a", "robot_1", store, "scan", (4, 5), "quota", "512 MiB used")))
    messages.append(encode(StoreInventory("fleet-a", "robot_1", store, ((0, 5), (7, 9)), 3)))
    return messages


_ODD_VALUES = [
    None,
    True,
    False,
    -1,
    0,
    1,
    2,
    3,
    4,
    2**63,
    2**64 - 1,
    -(2**63),
    0.5,
    -1.0,
    math.nan,
    math.inf,
    "",
    "q",
    "f32",
    "scan",
    "a b",
    "x" * 65,
    b"",
    b"\x00" * 7,
    [],
    [1, 2],
    {},
    {"v": 1},
    {"v": 2},
]


def _leaves(value, path=()):
    """Paths to every value inside nested maps and arrays."""
    yield path
    children = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, child in children:
        yield from _leaves(child, path + (key,))


def _structural(rng: np.random.Generator, data: bytes) -> bytes:
    """Re-pack the message with one value replaced, removed, resized or added."""
    root = msgpack.unpackb(data, raw=False)
    paths = list(_leaves(root))[1:]
    path = paths[int(rng.integers(len(paths)))]
    parent = root
    for key in path[:-1]:
        parent = parent[key]
    key, value, choice = path[-1], parent[path[-1]], int(rng.integers(4))
    if choice == 0:
        parent[key] = _ODD_VALUES[int(rng.integers(len(_ODD_VALUES)))]
    elif choice == 1 and isinstance(parent, dict):
        del parent[key]
    elif choice == 2 and isinstance(value, bytes) and value:
        cut = int(rng.integers(len(value)))
        parent[key] = value[:cut] if rng.random() < 0.5 else value + value[cut:]
    elif isinstance(parent, dict):
        parent["zz" if rng.random() < 0.5 else key.upper() if isinstance(key, str) else "k"] = value
    return msgpack.packb(root, use_bin_type=True)


def keyed_message(rng: np.random.Generator, seeds: list[bytes], fleet: str = "fleet-a") -> tuple[str, bytes]:
    """(key, payload) for the ingest of a map server of `fleet`: a seed message (mutated 9 times
    in 10) on the key its content names when it decodes, so that it reaches the checks behind
    the decoder, now and then on a key of another robot or node; otherwise on any scan or pose
    key. Every key matches the server's subscriptions, so each message arrives and is counted."""
    from protocol.codec import decode  # here, not at the top: codec imports nothing of this module
    from protocol.errors import ProtocolError

    data = seeds[int(rng.integers(len(seeds)))]
    if rng.random() < 0.9:
        data = mutate(rng, data)[1]
    try:
        message = decode(data)
    except ProtocolError:
        message = None
    if isinstance(message, ScanMessage) and rng.random() < 0.5:  # new (robot, node): stored, not a resend
        message = replace(message, robot=f"robot_{rng.integers(1, 5)}", node=int(rng.integers(10**6)))
        data = encode(message)
    robot, node = getattr(message, "robot", "robot_1"), getattr(message, "node", int(rng.integers(1000)))
    roll = rng.random()
    if roll < 0.05:
        robot = "robot_2"  # not the message's robot
    elif roll < 0.08:
        node += 1  # not the message's node
    elif roll < 0.1:
        return f"gmmap/{fleet}/{robot}/scan/0{node}", data  # not canonical
    elif roll < 0.12:
        return f"gmmap/{fleet}/robot.{robot}/poses", data  # not an id
    if isinstance(message, PoseGraphUpdate) or (message is None and rng.random() < 0.3):
        return f"gmmap/{fleet}/{robot}/poses", data
    return f"gmmap/{fleet}/{robot}/scan/{node}", data


def mutate(rng: np.random.Generator, data: bytes) -> tuple[str, bytes]:
    """One random corruption of `data`: (name of the mutation, new bytes)."""
    buf = bytearray(data)
    kinds = ("flip", "truncate", "insert", "delete", "duplicate", "overwrite", "random", "structure")
    kind = kinds[int(rng.integers(8))]
    if kind == "flip":
        for _ in range(int(rng.integers(1, 9))):
            buf[int(rng.integers(len(buf)))] ^= 1 << int(rng.integers(8))
    elif kind == "truncate":
        del buf[int(rng.integers(len(buf))) :]
    elif kind == "insert":
        at = int(rng.integers(len(buf) + 1))
        buf[at:at] = rng.bytes(int(rng.integers(1, 17)))
    elif kind == "delete":
        at = int(rng.integers(len(buf)))
        del buf[at : at + int(rng.integers(1, 17))]
    elif kind == "duplicate":
        at = int(rng.integers(len(buf)))
        buf[at:at] = buf[at : at + int(rng.integers(1, 33))]
    elif kind == "overwrite":  # msgpack type markers, to reach the odd corners of the format
        for _ in range(int(rng.integers(1, 4))):
            buf[int(rng.integers(len(buf)))] = int(
                rng.choice(
                    [0xC0, 0xC1, 0xC2, 0xC4, 0xC5, 0xCA, 0xCB, 0xCF, 0xD3, 0xD4, 0xD9, 0xDC, 0xDE, 0x80, 0x90, 0xA0]
                )
            )
    elif kind == "random":
        buf = bytearray(rng.bytes(int(rng.integers(0, 300))))
    else:
        buf = bytearray(_structural(rng, data))
    return kind, bytes(buf)
