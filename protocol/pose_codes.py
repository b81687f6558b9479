"""Poses of pose-graph updates as int32 codes (protocol version 3; docs/PROTOCOL.md, "Pose-graph
update"), all poses of an update at once.

A pose-graph update is a robot's recurring cost over a mission: a shift's corrections resend its
nodes again and again. float64 (v2) spent 24 bytes on a 2D pose and 56 on a 3D one, most of them
on digits nothing uses; int32 codes take half:

* translation: 0.1 mm steps (TRANSLATION_STEP), ±214 km in range: 1/500 of the finest 5 cm map
  cell and 1/100 of the agent's default pose tolerance of 1 cm;
* 2D theta: 2π / 2^32 steps over the whole turn, int32 wrapping round as the angle does (error
  1e-9 rad: 7 nm at 10 m);
* 3D quaternion components: 1 / (2^31 - 1) steps (error 2e-10 per component), normalised again
  by the decoder.

Rounding is half to even (numpy rint), as the scan encoding's. A message decoded from codes encodes
to the same codes: a code's value lies half a step from every rounding boundary.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from gmm_core.pose import Pose, poses_from_arrays
from protocol.errors import ProtocolError
from protocol.quantize import quaternion_from_matrix
from protocol.wire import QUATERNION_NORM_TOLERANCE

TRANSLATION_SCALE = 10000.0  # codes per metre: a step of 0.1 mm
TRANSLATION_STEP = 1 / TRANSLATION_SCALE
THETA_CODES = 2.0**31  # codes per half turn (π): 2^32 per turn
QUATERNION_SCALE = 2.0**31 - 1  # codes per unit of a quaternion component
INT32 = (-(2**31), 2**31 - 1)


def pose_codes(poses: Sequence[Pose], dim: int, field: str) -> np.ndarray:
    """(n, 3 or 7) int32 codes of poses of dimension `dim`: 2D x, y, theta; 3D tx, ty, tz, qw, qx, qy, qz.

    ProtocolError(field) for a translation beyond the int32 range of 0.1 mm codes (±214748.3647 m)."""
    R = np.array([pose.R for pose in poses]).reshape(-1, dim, dim)
    t = np.array([pose.t for pose in poses]).reshape(-1, dim)
    translation = np.rint(t * TRANSLATION_SCALE)
    if not ((translation >= INT32[0]) & (translation <= INT32[1])).all():
        bad = int(np.argmax(((translation < INT32[0]) | (translation > INT32[1])).any(axis=1)))
        raise ProtocolError(field, f"translation {t[bad].tolist()} of pose {bad} is beyond ±214748.3647 m")
    if dim == 2:
        theta = np.rint(np.arctan2(R[:, 1, 0], R[:, 0, 0]) / math.pi * THETA_CODES)
        rotation = np.where(theta == THETA_CODES, -THETA_CODES, theta)[:, None]  # π and -π: one code, -2^31
    else:
        # Shepperd's quaternion, as the scan encoding's: Pose.as_quaternion takes the signs of x, y, z
        # from differences that vanish at a half turn, which an oblique half turn gets wrong
        rotation = np.clip(np.rint(quaternion_from_matrix(R) * QUATERNION_SCALE), -QUATERNION_SCALE, QUATERNION_SCALE)
        first = np.take_along_axis(rotation, np.argmax(rotation != 0, axis=1)[:, None], axis=1)
        rotation = np.where(first < 0, -rotation, rotation)  # q and -q: the first non-zero code positive
    return np.concatenate([translation, rotation], axis=1).astype("<i4")


def poses_of_codes(codes: np.ndarray, dim: int, field: str) -> list[Pose]:
    """(n, 3 or 7) int32 codes -> poses. Every 2D code is a pose; a 3D quaternion must have a norm
    within 1e-3 of 1 (ProtocolError(field) otherwise) and is normalised."""
    codes = codes.astype(np.float64)
    t = codes[:, :dim] / TRANSLATION_SCALE
    if dim == 2:
        theta = codes[:, 2] / THETA_CODES * math.pi
        c, s = np.cos(theta), np.sin(theta)
        R = np.stack([np.stack([c, -s], axis=1), np.stack([s, c], axis=1)], axis=1)
        return poses_from_arrays(R, t)
    q = codes[:, 3:] / QUATERNION_SCALE
    w, x, y, z = q.T
    norm = np.sqrt(((w * w + x * x) + y * y) + z * z)
    off = np.abs(norm - 1) > QUATERNION_NORM_TOLERANCE
    if off.any():
        bad = int(np.argmax(off))
        raise ProtocolError(field, f"quaternion norm {norm[bad]:.6g} of pose {bad} is not 1")
    w, x, y, z = (q / norm[:, None]).T
    R = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1),
        ],
        axis=1,
    )
    return poses_from_arrays(R, t)
