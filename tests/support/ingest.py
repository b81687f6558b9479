"""The map server's write path without a network: small scans of either dimension, one ingest
batch run to its answers, and the quota usage a server reports."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from protocol import Ack, PoseGraphUpdate, Rejection, ScanMessage, decode, encode, poses_key, scan_key
from services.map_server.ingest import Ingest
from services.map_server.state import ServerState
from support.fuzz import scan_message
from support.net import metric


def scan_of(dim: int, node: int = 0, robot: str = "r", fleet: str = "default") -> ScanMessage:
    """A scan-like message of `dim` dimensions (a few components, support.fuzz): `robot`'s node `node`."""
    message = scan_message(np.random.default_rng(node), dim, occupied=4, free=4, node=node)
    return replace(message, fleet=fleet, robot=robot)


def key_of(message: ScanMessage | PoseGraphUpdate) -> str:
    """The key its robot puts `message` on."""
    if isinstance(message, ScanMessage):
        return scan_key(message.fleet, message.robot, message.node)
    return poses_key(message.fleet, message.robot)


def ingested(
    state: ServerState, messages: Sequence[ScanMessage | PoseGraphUpdate], quota_bytes: int | None = None
) -> list[Ack | Rejection]:
    """The answers (Acks and Rejections listing ids) to `messages`, submitted in order to an Ingest
    of `state` and stored in one batch."""
    answers: list[Ack | Rejection] = []
    ingest = Ingest(state, lambda _, payload: answers.append(decode(payload)), quota_bytes)
    for message in messages:
        ingest.submit(key_of(message), encode(message))
    ingest.start()
    # Drains the queue, however long numba takes to load its kernels in a fresh checkout (the
    # default 1.5 s drops what is left unanswered, as a stopping server does).
    ingest.stop(timeout=60)
    return [a for a in answers if a.ids]  # an Ack that only lists scans still queued answers nothing


def stored_bytes(state: ServerState, robot: str) -> float:
    """The scan bytes `robot` holds on the server as its quota counts them (gmmap_robot_stored_bytes)."""
    return metric(state.metrics.render().decode(), "gmmap_robot_stored_bytes", robot=robot)
