"""Reading one msgpack map field by field, each check raising ProtocolError(field), and writing
floats and poses in their one canonical form (docs/PROTOCOL.md, "Canonical form").

Wire maps come from an untrusted decoder: values can have any msgpack type, so every read
states the type it wants. bool is rejected where an int is wanted (in Python it is one).
"""

from __future__ import annotations

import builtins
import functools
import math

import numpy as np

from gmm_core.pose import Pose
from protocol.errors import ProtocolError
from protocol.keys import MAX_NODE


class Fields:
    """A wire map whose errors are reported as `<prefix>.<name>`."""

    def __init__(self, raw, prefix: str = ""):
        if not isinstance(raw, dict):
            raise ProtocolError(prefix or "message", f"must be a msgpack map, got {type(raw).__name__}")
        self.raw = raw
        self.prefix = prefix

    def name(self, name: str) -> str:
        return f"{self.prefix}.{name}" if self.prefix else name

    def get(self, key: str, name: str):
        if key not in self.raw:
            raise ProtocolError(self.name(name), f"missing (key {key!r})")
        return self.raw[key]

    def int(self, key: str, name: str, lo: int = 0, hi: int = MAX_NODE) -> int:
        value = self.get(key, name)
        if type(value) is not int or not lo <= value <= hi:
            raise ProtocolError(self.name(name), f"must be an integer in [{lo}, {hi}], got {value!r:.80}")
        return value

    def float(self, key: str, name: str) -> float:
        value = self.get(key, name)
        if type(value) not in (int, float) or not math.isfinite(value):
            raise ProtocolError(self.name(name), f"must be a finite number, got {value!r:.80}")
        return float(value)

    def array(self, key: str, name: str, dtype: str, count: builtins.int | None = None, nullable: bool = False):
        """A bin of little-endian numbers; floats must be finite. None for nil if nullable."""
        value = self.get(key, name)
        if value is None and nullable:
            return None
        if type(value) is not bytes:
            raise ProtocolError(self.name(name), f"must be bin (raw bytes), got {type(value).__name__}")
        array = np.frombuffer(value, dtype=dtype) if len(value) % _itemsize(dtype) == 0 else None
        if array is None or (count is not None and len(array) != count):
            itemsize = _itemsize(dtype)
            wanted = f"{count} x {itemsize}" if count is not None else f"a multiple of {itemsize}"
            raise ProtocolError(self.name(name), f"must hold {wanted} bytes, got {len(value)}")
        if array.dtype.kind == "f" and not _all_finite(array):
            raise ProtocolError(self.name(name), "must be finite (no NaN or inf)")
        return array


@functools.cache
def _itemsize(dtype: str) -> int:
    return np.dtype(dtype).itemsize


SMALL_ARRAY = 32  # entries; below it numpy's two calls per check cost more than Python's loop


def _all_finite(array: np.ndarray) -> bool:
    if len(array) < SMALL_ARRAY:  # poses, sensor origins, boxes of means: the checks of every scan
        return all(map(math.isfinite, array.tolist()))
    return bool(np.isfinite(array).all())


# --- writing: one byte string per value


def float32_bytes(values, field: str) -> bytes:
    """Little-endian float32 (rounded to nearest, ties to even), refusing what float32 cannot hold
    (NaN, inf, > 3.4e38); a negative zero is written as 0.0."""
    with np.errstate(over="ignore"):
        array = np.asarray(values, dtype="<f4")
    if not np.isfinite(array).all():
        raise ProtocolError(field, "must be finite in float32")
    return (array + 0).tobytes()  # -0.0 + 0 is +0.0 and every other value is unchanged


def float64_bytes(values, field: str) -> bytes:
    """Little-endian float64, finite; a negative zero is written as 0.0."""
    array = np.asarray(values, dtype="<f8")
    if not np.isfinite(array).all():
        raise ProtocolError(field, "must be finite")
    return (array + 0).tobytes()


# --- poses: 2D [x, y, theta], 3D [tx, ty, tz, qw, qx, qy, qz]

QUATERNION_NORM_TOLERANCE = 1e-3


def pose_width(dim: int) -> int:
    return 3 if dim == 2 else 7


def pose_vector(pose: Pose) -> np.ndarray:
    """A pose's wire values in float64: theta = atan2(R10, R00) with -pi sent as pi, or t and the
    unit quaternion of Pose.as_quaternion (w >= 0)."""
    if pose.dim == 2:
        x, y, theta = pose.as_xytheta()
        return np.array([x, y, math.pi if theta == -math.pi else theta])
    return np.concatenate([pose.t, pose.as_quaternion()])


def pose_bytes(poses, dtype: str, field: str) -> bytes:
    """Poses as rows of `dtype` ("<f4" or "<f8"). q and -q are one rotation: the first non-zero
    component of (w, x, y, z) is made positive after rounding, so w = 0 (a half turn) is one form too."""
    vectors = np.array([pose_vector(pose) for pose in poses], dtype=np.float64)
    with np.errstate(over="ignore"):
        array = np.asarray(vectors, dtype=dtype)
    if not np.isfinite(array).all():
        raise ProtocolError(field, "must be finite" + (" in float32" if dtype == "<f4" else ""))
    if array.shape[1:] == (7,):
        q = array[:, 3:]
        first = np.take_along_axis(q, np.argmax(q != 0, axis=1)[:, None], axis=1)
        array[:, 3:] = np.where(first < 0, -q, q)
    return (array + 0).tobytes()


def pose_from_vector(vector: np.ndarray, field: str) -> Pose:
    """Wire values -> Pose: 2D theta may be any finite number; a 3D quaternion must have a norm
    within 1e-3 of 1 and is normalised."""
    if len(vector) == 3:
        return Pose.from_xytheta(*vector.tolist())  # Python floats: exact, and quicker than numpy scalars
    vector = vector.astype(np.float64)
    with np.errstate(over="ignore"):  # components near 1e308 square to inf: a norm that is not 1
        norm = np.linalg.norm(vector[3:])
    if abs(norm - 1) > QUATERNION_NORM_TOLERANCE:
        raise ProtocolError(field, f"quaternion norm {norm:.6g} is not 1")
    return Pose.from_quaternion(vector[:3], vector[3:])
