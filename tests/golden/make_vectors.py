"""Write the golden vectors of the wire protocol (docs/PROTOCOL.md, "Golden vectors").

For each vector below, `<name>.msgpack` holds the bytes the reference encoder writes for the
explicit inputs given here and `<name>.json` what those bytes hold: the wire map (keys in order,
bins in hex), the values they decode to and, for encoding "q", every record's integer codes.

    .venv/bin/python tests/golden/make_vectors.py [FOLDER]     (default: tests/golden)

Run it once after a deliberate change of the protocol and commit the files with the change.
tests/unit/protocol/test_golden.py checks that the files decode to their JSON, that encoding the
decoded message or the inputs below gives their bytes again, and that this script rewrites them
unchanged. Every vector in encoding "q" is also encoded with its inputs moved by about 1e-9:
the bytes must not move, so no value of theirs sits at a rounding boundary where another libm or
LAPACK could round it the other way. The vectors of ties and folds keep their means and axes exact
(those ties are exact in IEEE arithmetic); their scales and weights are moved all the same.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import msgpack
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # runnable as a script from a checkout; tests/support

from gmm_core.mixture import Mixture  # noqa: E402
from gmm_core.pose import Pose  # noqa: E402
from gmm_core.scan import ScanModel  # noqa: E402
from protocol.codec import decode, encode  # noqa: E402
from protocol.errors import ProtocolError  # noqa: E402
from protocol.messages import (  # noqa: E402
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
from support.golden import FOLDER, describe, to_json, version_2_update  # noqa: E402

FLEET, ROBOT, STORE = "fleet-a", "robot_1", "0123456789abcdef0123456789abcdef"
STAMP = 1700000000.25


@dataclass(frozen=True)
class Vector:
    about: str
    build: Callable[[], Message]
    encoding: str = "q"
    exact: bool = False  # ties and folds: the robustness check leaves means and axes as they are
    fixed_point: bool = True  # encode(decode(bytes)) == bytes; see edges_3d for why not always
    # the bytes of an older version holding build()'s values, which the decoder must still read
    # (re-encoded they become the current version's bytes of build())
    older: Callable[[], bytes] | None = None


# --- inputs


def rotation_2d(theta: float) -> np.ndarray:
    return Pose.from_xytheta(0.0, 0.0, theta).R


def rotation_3d(q_wxyz) -> np.ndarray:
    return Pose.from_quaternion(np.zeros(3), q_wxyz).R


def covariances(rotations, stds) -> np.ndarray:
    """R diag(std^2) R^T per component, exactly symmetric."""
    covs = np.einsum(
        "kij,kj,klj->kil", np.asarray(rotations), np.asarray(stds, dtype=float) ** 2, np.asarray(rotations)
    )
    return 0.5 * (covs + np.swapaxes(covs, 1, 2))


def scan(dim: int, occupied: Mixture, free: Mixture, node: int = 42) -> ScanMessage:
    if dim == 2:
        pose, origin, max_range = Pose.from_xytheta(1.5, -2.25, 0.5), [0.125, 0.0], 30.0
    else:
        pose, origin, max_range = Pose.from_quaternion([1.0, 2.0, 3.0], [0.9, -0.1, 0.3, 0.2]), [0.0, 0.0, 0.25], 80.0
    return ScanMessage(FLEET, ROBOT, node, STAMP, ScanModel(occupied, free, np.array(origin), max_range), pose)


def wall_2d() -> ScanMessage:
    """Four thin components along a wall, one free component at the range limit."""
    thetas = [0.3, 0.31, 1.2, -2.0]
    occupied = Mixture(
        [0.4, 0.3, 0.2, 0.1],
        [[2.1, 0.7], [3.05, 1.0], [4.4, 1.9], [5.2, -0.6]],
        covariances([rotation_2d(t) for t in thetas], [[0.013, 0.41], [0.007, 0.33], [0.02, 0.6], [0.3, 0.05]]),
        120,
    )
    free = Mixture([1.0], [[27.0, 9.0]], covariances([rotation_2d(0.8)], [[0.6, 1.7]]), 8)
    return scan(2, occupied, free)


def surfaces_3d() -> ScanMessage:
    quaternions = [[0.8, 0.2, -0.5, 0.26], [0.3, -0.7, 0.1, 0.64], [-0.2, 0.1, 0.9, -0.37]]
    occupied = Mixture(
        [0.5, 0.35, 0.15],
        [[1.2, -0.4, 0.3], [2.7, 0.9, 1.1], [-3.3, 4.1, 0.05]],
        covariances([rotation_3d(q) for q in quaternions], [[0.004, 0.3, 0.45], [0.011, 0.2, 0.7], [0.05, 0.06, 0.9]]),
        900,
    )
    free = Mixture(
        [1.0], [[40.0, -61.0, 12.0]], covariances([rotation_3d([0.6, 0.1, 0.2, 0.3])], [[1.1, 2.3, 3.7]]), 30
    )
    return scan(3, occupied, free)


def empty_2d() -> ScanMessage:
    return scan(2, Mixture.empty(2), Mixture.empty(2), node=0)


def single_3d() -> ScanMessage:
    """K = 1: the box of the means is a point, every mean code is 0."""
    occupied = Mixture(
        [1.0], [[0.5, -1.5, 2.0]], covariances([rotation_3d([0.7, 0.3, 0.2, 0.61])], [[0.02, 0.15, 0.4]]), 17
    )
    return scan(3, occupied, Mixture.empty(3))


def edges_2d() -> ScanMessage:
    """Ties of the mean codes (box [0, 8191], so a code is the coordinate), the fold of the angle at
    pi/2 from both sides, a circle (equal std codes) with eigh's noise in its axes, weights at the floor."""
    means = [[0.0, 0.0], [8191.0, 8191.0], [2.5, 3.5], [4095.5, 1.5], [100.0, 200.0], [300.0, 400.0]]
    covs = np.array(
        [
            np.diag([0.04, 0.0025]),  # axis 0 (the smaller) along y: theta = pi/2 exactly, folds to 0, swapped
            covariances([rotation_2d(math.pi / 2 - 1e-4)], [[0.05, 0.3]])[0],  # just below the fold: code 128 -> 0
            covariances([rotation_2d(0.7)], [[0.2, 0.2]])[0],  # a circle: angle 0 whatever eigh returns
            np.diag([0.0025, 0.04]),  # axis-aligned: angle 0, not swapped
            covariances([rotation_2d(-0.9)], [[0.03, 0.08]])[0],
            covariances([rotation_2d(2.5)], [[1e-5, 150.0]])[0],  # stds outside [1e-4, 100] m: clamped
        ]
    )
    weights = [0.5, 0.25, 0.125, 0.125 - 1e-9, 1e-9, 0.0]  # 1e-9 and 0: below 2^-15.9, the floor code 0
    return scan(2, Mixture(weights, means, covs, 64), Mixture.empty(2), node=43)


def edges_3d() -> ScanMessage:
    """Zero quaternion components (a tie: 255.5 codes as 256), a tie of the largest component, and
    equal std codes: a sphere, two equal small axes (a needle), two equal large axes (a disc).

    Not a fixed point: the tie of w and y decodes with |y| > w (code 256 is +0.0014, not 0, and w
    is what is left), and a needle's decoded frame is no longer the smallest turn onto its axis, so
    re-encoding the decoded message gives other codes (within a step) for the same covariances."""
    needle, disc = rotation_3d([0.8, 0.2, -0.5, 0.26]), rotation_3d([0.3, -0.7, 0.1, 0.64])
    covs = np.array(
        [
            np.diag([0.0004, 0.09, 2.25]),  # principal axes = coordinate axes: identity, three zero components
            np.diag([2.25, 0.09, 0.0004]),  # axes z, y, -x: (w, y) = (0.7071, -0.7071), w first of the largest
            covariances([rotation_3d([0.9, 0.3, -0.2, 0.1])], [[0.3, 0.3, 0.3]])[0],  # sphere: identity
            covariances([needle], [[0.02, 0.02, 0.9]])[0],  # only axis 2 counts: smallest turn of z onto it
            covariances([disc], [[0.01, 0.7, 0.7]])[0],  # only axis 0 counts: smallest turn of x onto it
        ]
    )
    means = [[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [-1.0, 0.5, 2.0], [3.0, -2.0, 1.0], [0.25, 0.75, -1.0]]
    return scan(3, Mixture([0.375, 0.25, 0.125, 0.125, 0.125], means, covs, 200), Mixture.empty(3), node=44)


def poses_2d() -> PoseGraphUpdate:
    """theta = -pi and pi are one code, -2^31; a negative zero is code 0; node 2^63 - 1 is the
    range [2^63 - 1, 2^63); no anchor (nil)."""
    half_turn = Pose(np.array([[-1.0, 0.0], [-0.0, -1.0]]), np.array([4.0, -0.0]))  # atan2(-0.0, -1) = -pi
    poses = ((3, Pose.from_xytheta(10.5, -3.25, 0.5)), (4, half_turn), (2**63 - 1, Pose.from_xytheta(-0.0, 7.0, -0.0)))
    return PoseGraphUpdate(FLEET, ROBOT, 7, poses)


def poses_3d() -> PoseGraphUpdate:
    """A half turn (w = 0) whose quaternion comes out as (0, -1, 0, 0): sent as (0, 1, 0, 0); an
    anchor (float64) far out, as world frames are."""
    c, s = math.cos(-math.pi), math.sin(-math.pi)
    half_turn = Pose(np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]), np.array([0.0, 1.0, 0.0]))
    poses = ((10, Pose.from_quaternion([1.0, 2.0, 3.0], [0.5, 0.5, 0.5, 0.5])), (11, half_turn))
    anchor = Pose.from_quaternion([1e6, -2e6, 30.5], [1.0, 0.0, 0.0, 0.0])
    return PoseGraphUpdate(FLEET, ROBOT, 2**40, poses, anchor)


def anchor_only_2d() -> PoseGraphUpdate:
    return PoseGraphUpdate(FLEET, ROBOT, 8, (), Pose.from_xytheta(250.0, -125.5, 1.0))


def poses_2d_version_2() -> bytes:
    return version_2_update(poses_2d())


VECTORS: dict[str, Vector] = {
    "scan_2d_q": Vector("2D scan, encoding q: four wall components, one free", wall_2d),
    "scan_2d_f32": Vector("the same scan in encoding f32", wall_2d, "f32"),
    "scan_3d_q": Vector("3D scan, encoding q: three surface components, one free", surfaces_3d),
    "scan_3d_f32": Vector("the same scan in encoding f32", surfaces_3d, "f32"),
    "scan_2d_q_empty": Vector("2D scan, both mixtures empty (K = 0): no bounds key", empty_2d),
    "scan_2d_f32_empty": Vector("2D scan, both mixtures empty, encoding f32", empty_2d, "f32"),
    "scan_3d_q_single": Vector("3D scan, K = 1: a flat box of means", single_3d),
    "scan_2d_q_edges": Vector("2D ties, folds, a circle, weights at the floor", edges_2d, exact=True),
    "scan_3d_q_edges": Vector("3D zero components, equal std codes", edges_3d, exact=True, fixed_point=False),
    "poses_2d": Vector("2D pose-graph update: theta at -pi, negative zeros, anchor nil", poses_2d),
    "poses_3d": Vector("3D pose-graph update: a half turn (w = 0), an anchor", poses_3d),
    "poses_anchor_only": Vector("2D pose-graph update with an anchor and no poses", anchor_only_2d),
    "poses_2d_v2": Vector(
        "poses_2d in protocol version 2 (float64 poses): still read",
        poses_2d,
        fixed_point=False,
        older=poses_2d_version_2,
    ),
    "ack_scan_queued": Vector(
        "acknowledgement of scans, some queued", lambda: Ack(FLEET, ROBOT, STORE, "scan", (1, 2, 3, 2**63 - 1), (4, 5))
    ),
    "ack_poses": Vector("acknowledgement of a revision, none queued", lambda: Ack(FLEET, ROBOT, STORE, "poses", (7,))),
    "rejection_non_ascii": Vector(
        "rejection whose detail is not ASCII (its limit counts UTF-8 bytes)",
        lambda: Rejection(FLEET, ROBOT, STORE, "scan", (4, 5), "quota", "Kontingent für robot_1 erschöpft — 512 MiB ✓"),
    ),
    "inventory_ranges": Vector(
        "store inventory: four ranges, revision 4",
        lambda: StoreInventory(FLEET, ROBOT, STORE, ((0, 3), (5, 6), (7, 10), (2**40, 2**40 + 1)), 4),
    ),
    "inventory_empty": Vector(
        "store inventory: nothing stored, no revision (nil)", lambda: StoreInventory(FLEET, ROBOT, STORE, ())
    ),
    "map_query_2d": Vector(
        "2D map query, every robot (robots nil)", lambda: MapQuery(FLEET, [-10.5, -0.0], [10.5, 20.0], 0.05)
    ),
    "map_query_3d": Vector(
        "3D map query of two robots",
        lambda: MapQuery(FLEET, [-5.0, -5.0, -1.0], [5.0, 5.0, 3.0], 0.2, (ROBOT, "robot-2")),
    ),
    "map_reply_2d": Vector(
        "2D map reply, 2 x 3 cells",
        lambda: MapReply(FLEET, [-1.0, -2.0], 0.1, np.array([[0.0, 0.5, 1.0], [0.25, 0.75, 0.125]])),
    ),
    "map_reply_3d": Vector(
        "3D map reply, 2 x 2 x 2 cells",
        lambda: MapReply(FLEET, [0.0, 0.0, -0.5], 0.25, np.arange(8).reshape(2, 2, 2) / 8),
    ),
    "point_query_2d": Vector(
        "2D point query, three points, every robot (robots nil), method auto",
        lambda: PointQuery(FLEET, [[1.5, -2.25], [-0.0, 10.0], [3.0, 3.0]], 0.05),
    ),
    "point_query_3d": Vector(
        "3D point query of one robot, two points, method analytic",
        lambda: PointQuery(FLEET, [[0.25, 0.5, 1.0], [-4.0, 2.0, 0.125]], 0.1, (ROBOT,), "analytic"),
    ),
    "point_reply": Vector(
        "point reply: three probabilities, evaluated by Monte Carlo",
        lambda: PointReply(FLEET, 0.05, np.array([0.5, 0.875, 0.0625]), "mc"),
    ),
}


# --- the robustness check: generic inputs moved by ~1e-9 must give the same bytes


def nudged(message: Message, sign: float, exact: bool) -> Message:
    """The same scan with its inputs moved by about 1e-9 (relative): covariance scale and weights,
    and unless `exact` the means and the axes (a turn of 1e-9 rad). Other messages: unchanged."""
    if not isinstance(message, ScanMessage):
        return message

    def move(mixture: Mixture) -> Mixture:
        if mixture.n_components == 0:
            return mixture
        d, eps = mixture.dim, sign * 1e-9
        turn = np.eye(d) if exact else rotation_2d(eps) if d == 2 else rotation_3d([1.0, eps / 2, -eps / 2, eps / 2])
        covs = np.einsum("ij,kjl,ml->kim", turn, mixture.covariances * (1 + eps), turn)
        weights = mixture.weights * (1 + eps * np.linspace(-1, 1, mixture.n_components))
        means = mixture.means if exact else mixture.means + eps * (1 + np.abs(mixture.means))
        return Mixture(weights / weights.sum(), means, 0.5 * (covs + np.swapaxes(covs, 1, 2)), mixture.support)

    model = message.model
    moved = ScanModel(move(model.occupied), move(model.free), model.origin, model.max_range)
    return ScanMessage(message.fleet, message.robot, message.node, message.stamp, moved, message.pose)


# --- refused: bytes a decoder must reject, and the field its error names


@dataclass(frozen=True)
class Refused:
    about: str
    build: Callable[[], bytes]
    field: str


def edited(name: str, *edits: tuple) -> Callable[[], bytes]:
    """The bytes of vector `name` re-packed with edits (path, value) or (path,) to delete a key."""

    def build() -> bytes:
        vector = VECTORS[name]
        raw = msgpack.unpackb(encode(vector.build(), vector.encoding), raw=False)
        for path, *value in edits:
            target = raw
            for key in path[:-1]:
                target = target[key]
            if value:
                target[path[-1]] = value[0]
            else:
                del target[path[-1]]
        return msgpack.packb(raw, use_bin_type=True)

    return build


def with_padding_bit() -> bytes:
    raw = msgpack.unpackb(encode(wall_2d()), raw=False)
    raw["F"]["c"] = raw["F"]["c"][:-1] + bytes([raw["F"]["c"][-1] | 0x80])  # 1 record of 58 bits: 6 pad bits
    return msgpack.packb(raw, use_bin_type=True)


def with_long_quaternion() -> bytes:
    raw = msgpack.unpackb(encode(poses_3d()), raw=False)
    codes = np.frombuffer(raw["poses"], "<i4").copy()
    codes[3:7] = np.rint(codes[3:7] * 1.002)  # the codes of (0.5, 0.5, 0.5, 0.5) * 1.002: beyond 1e-3 of 1
    raw["poses"] = codes.tobytes()
    return msgpack.packb(raw, use_bin_type=True)


def version_1_ack() -> bytes:
    return msgpack.packb({"v": 1, "t": 3, "f": FLEET, "r": ROBOT, "kind": "scan", "ids": b""}, use_bin_type=True)


REFUSED: dict[str, Refused] = {
    "version_1": Refused("a version 1 acknowledgement: no store, no queued", version_1_ack, "version"),
    "anchor_absent": Refused("anchor is required, nil when none", edited("poses_2d", (("anchor",),)), "anchor"),
    "revision_absent": Refused("rev is required, nil when none", edited("inventory_empty", (("rev",),)), "revision"),
    "queued_absent": Refused("queued is required, empty when none", edited("ack_poses", (("queued",),)), "queued"),
    "bounds_absent": Refused("b is required when K > 0", edited("scan_2d_q", (("O", "b"),)), "occupied.bounds"),
    "dimension_bool": Refused("true is not an int", edited("scan_2d_q", (("d",), True)), "dimension"),
    "node_2_63": Refused("ids above 2^63 - 1", edited("ack_poses", (("ids",), (2**63).to_bytes(8, "little"))), "ids"),
    "detail_1001_bytes": Refused(
        "detail of 501 characters, 1001 bytes of UTF-8",
        edited("rejection_non_ascii", (("detail",), "é" * 500 + "x")),
        "detail",
    ),
    "string_1026_bytes": Refused(
        "an unknown key's string of 513 characters, 1026 bytes", edited("ack_poses", (("note",), "é" * 513)), "message"
    ),
    "ext_type": Refused(
        "an ext value, even of 0 bytes, under an unknown key",
        edited("ack_poses", (("x",), msgpack.ExtType(1, b""))),
        "message",
    ),
    "trailing_byte": Refused("a nil after the map", lambda: encode(VECTORS["ack_poses"].build()) + b"\xc0", "message"),
    "duplicate_key": Refused("v twice", lambda: b"\x83\xa1v\x02\xa1t\x03\xa1v\x02", "message"),
    "ranges_touching": Refused(
        "[0, 2) and [2, 4) touch",
        edited("inventory_empty", (("ranges",), np.array([0, 2, 2, 4], "<u8").tobytes())),
        "ranges",
    ),
    "quaternion_not_unit": Refused("pose-graph quaternion codes of norm 1.002", with_long_quaternion, "poses.poses"),
    "node_ranges_odd": Refused(
        "pose-graph node ids: a start without its stop",
        edited("poses_3d", (("nodes",), np.array([10], "<u8").tobytes())),
        "poses.nodes",
    ),
    "padding_bit": Refused("a set padding bit after the last record", with_padding_bit, "free.components"),
    "point_count": Refused(
        "a point query whose n says 4 points over the bytes of 3", edited("point_query_2d", (("n",), 4)), "points"
    ),
    "point_method": Refused(
        "a point query of an unknown method", edited("point_query_3d", (("m",), "exact")), "method"
    ),
    "stream_length": Refused(
        "a q stream of 28 bytes: no whole number of 58-bit records",
        edited("scan_2d_q", (("O", "c"), bytes(28))),
        "occupied.components",
    ),
}


def write_vectors(folder: Path = FOLDER) -> list[Path]:
    """Encode every vector into `folder` and the refused ones into folder/refused; raise if a
    vector's fixed_point is wrong, if one moves under the robustness check, or if a refused one
    is not refused with its field."""
    written = []
    for name, vector in VECTORS.items():
        message = vector.build()
        data = encode(message, vector.encoding) if vector.older is None else vector.older()
        if (encode(decode(data, max_bytes=len(data)), vector.encoding) == data) != vector.fixed_point:
            raise AssertionError(f"{name}: fixed_point is {vector.fixed_point}, re-encoding says otherwise")
        scan_q = isinstance(message, ScanMessage) and vector.encoding == "q"
        if scan_q and any(encode(nudged(message, s, vector.exact)) != data for s in (-1.0, 1.0)):
            raise AssertionError(f"{name}: a value sits at a rounding boundary (inputs moved by 1e-9 change the bytes)")
        written += write(folder, name, data, describe(data, vector.about, vector.encoding, vector.fixed_point))
    for name, refused in REFUSED.items():
        data = refused.build()
        try:
            decode(data)
        except ProtocolError as error:
            if error.field != refused.field:
                raise AssertionError(f"refused/{name}: names {error.field!r}, not {refused.field!r}") from None
        else:
            raise AssertionError(f"refused/{name}: decodes")
        written += write(folder / "refused", name, data, {"about": refused.about, "field": refused.field})
    return written


def write(folder: Path, name: str, data: bytes, description: dict) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.msgpack").write_bytes(data)
    (folder / f"{name}.json").write_text(to_json({"name": name} | description) + "\n", encoding="utf-8")
    return [folder / f"{name}.msgpack", folder / f"{name}.json"]


if __name__ == "__main__":
    for path in write_vectors(Path(sys.argv[1]) if len(sys.argv) > 1 else FOLDER):
        print(path.relative_to(Path.cwd()) if path.is_relative_to(Path.cwd()) else path)
