"""Rigid poses in 2D (x, y, theta) and 3D (translation, unit quaternion w, x, y, z)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_IDENTITY = {2: np.eye(2), 3: np.eye(3)}


def _determinant(R: np.ndarray) -> float:
    """Of a 2x2 or 3x3 matrix, by cofactors: for a near-rotation (|det| near 1) its sign is np.linalg.det's."""
    rows = R.tolist()
    if len(rows) == 2:
        (a, b), (c, d) = rows
        return a * d - b * c
    (a, b, c), (d, e, f), (g, h, i) = rows
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


NEAR_HALF_TURN = 0.25  # 4 w^2 under this (turns over about 150 degrees): Pose.as_quaternion's second branch


@dataclass(frozen=True, slots=True)  # a server holds a pose per node for a whole shift
class Pose:
    """A rigid transform x_world = R @ x_local + t, in 2D or 3D."""

    R: np.ndarray  # (d, d) rotation, det +1
    t: np.ndarray  # (d,)

    def __post_init__(self):
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64)
        d = t.shape[0]
        if t.shape not in ((2,), (3,)) or R.shape != (d, d):
            raise ValueError(f"pose: R must be (d, d) and t (d,) with d in 2, 3; got {R.shape}, {t.shape}")
        if not (np.isfinite(R).all() and np.isfinite(t).all()):
            raise ValueError("pose: non-finite values")
        # Plain arithmetic rather than np.allclose or np.linalg.det: poses are built per scan, by the thousand.
        if np.abs(R @ R.T - _IDENTITY[d]).max() > 1e-6 or _determinant(R) < 0:
            raise ValueError("pose: R is not a rotation matrix")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @property
    def dim(self) -> int:
        return self.t.shape[0]

    @staticmethod
    def identity(dim: int) -> Pose:
        return Pose(np.eye(dim), np.zeros(dim))

    @staticmethod
    def from_xytheta(x: float, y: float, theta: float) -> Pose:
        c, s = np.cos(theta), np.sin(theta)
        return Pose(np.array([[c, -s], [s, c]]), np.array([x, y]))

    @staticmethod
    def from_quaternion(t, q_wxyz) -> Pose:
        w, x, y, z = np.asarray(q_wxyz, dtype=np.float64) / np.linalg.norm(q_wxyz)
        R = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        return Pose(R, np.asarray(t, dtype=np.float64))

    def as_xytheta(self) -> tuple[float, float, float]:
        if self.dim != 2:
            raise ValueError("as_xytheta: pose is not 2D")
        return float(self.t[0]), float(self.t[1]), float(np.arctan2(self.R[1, 0], self.R[0, 0]))

    def as_quaternion(self) -> np.ndarray:
        """Unit quaternion (w, x, y, z) with w >= 0, for a 3D pose."""
        if self.dim != 3:
            raise ValueError("as_quaternion: pose is not 3D")
        R = self.R
        squares = np.array([1.0 + R[0, 0] + R[1, 1] + R[2, 2], 1.0 + R[0, 0] - R[1, 1] - R[2, 2],
                            1.0 - R[0, 0] + R[1, 1] - R[2, 2], 1.0 - R[0, 0] - R[1, 1] + R[2, 2]])  # fmt: skip
        if squares[0] >= NEAR_HALF_TURN:  # 4 w^2: x, y, z take their signs from 4 w (x, y, z)
            w, x, y, z = np.sqrt(np.maximum(squares, 0.0)) / 2
            q = np.array([w, np.copysign(x, R[2, 1] - R[1, 2]), np.copysign(y, R[0, 2] - R[2, 0]),
                          np.copysign(z, R[1, 0] - R[0, 1])])  # fmt: skip
            return q / np.linalg.norm(q)
        # Near a half turn those differences vanish: Shepperd's method divides the off-diagonal sums
        # and differences by the largest of 4 x^2, 4 y^2, 4 z^2 instead.
        k = int(np.argmax(squares[1:]))  # x, y or z
        s = 2.0 * np.sqrt(squares[k + 1])  # 4 |q_k|
        differences = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # 4 w (x, y, z)
        vector = (R + R.T)[k] / s  # 4 q_k (x, y, z) / s off the diagonal
        vector[k] = s / 4
        q = np.concatenate([[differences[k] / s], vector])
        q /= np.linalg.norm(q)
        return -q if q[0] < 0 else q

    def compose(self, other: Pose) -> Pose:
        """self ∘ other: first apply other, then self."""
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def inverse(self) -> Pose:
        return Pose(self.R.T, -self.R.T @ self.t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform (n, d) points from the local frame to the parent frame."""
        return np.asarray(points) @ self.R.T + self.t

    def displacement(self, other: Pose, reach: float) -> float:
        """The farthest any point within `reach` of the local origin moves from this pose to `other`
        (`displacements` of one pair)."""
        return float(displacements(self.t[None], self.R[None], other.t[None], other.R[None], np.array([reach]))[0])

    def between(self, other: Pose, fraction: float) -> Pose:
        """The pose a `fraction` of the way from this one to `other`: translation on the line,
        rotation along the shorter arc (2D: the angle; 3D: slerp of the quaternions)."""
        t = self.t + fraction * (other.t - self.t)
        if self.dim == 2:
            a, b = np.arctan2(self.R[1, 0], self.R[0, 0]), np.arctan2(other.R[1, 0], other.R[0, 0])
            turn = (b - a + np.pi) % (2 * np.pi) - np.pi
            return Pose.from_xytheta(t[0], t[1], a + fraction * turn)
        return Pose.from_quaternion(t, slerp(self.as_quaternion(), other.as_quaternion(), fraction))


def displacements(t0: np.ndarray, R0: np.ndarray, t1: np.ndarray, R1: np.ndarray, reach) -> np.ndarray:
    """(n,) the farthest any point within `reach` of the local origin moves from pose (R0, t0) to
    (R1, t1), for (n, d) translations and (n, d, d) rotations: |t1 - t0| + reach ||R1 - R0||_2, where
    ||R1 - R0||_2 = 2 sin(phi / 2) for the angle phi of R0^T R1 (reached in 2D, where every point
    turns by phi). phi by atan2 of its sine and cosine: arccos of the cosine loses half the digits of
    a small turn."""
    d = t0.shape[1]
    M = np.einsum("nji,njk->nik", R0, R1)  # R0^T R1: trace 2 cos + (d - 2), M - M^T carries sin
    cos = (np.trace(M, axis1=1, axis2=2) - (d - 2)) / 2
    skew = M - M.transpose(0, 2, 1)
    if d == 2:
        sin = np.abs(skew[:, 1, 0]) / 2
    else:
        sin = np.sqrt(skew[:, 2, 1] ** 2 + skew[:, 0, 2] ** 2 + skew[:, 1, 0] ** 2) / 2
    return np.linalg.norm(t1 - t0, axis=1) + reach * 2 * np.sin(np.arctan2(sin, cos) / 2)


def slerp(q0: np.ndarray, q1: np.ndarray, fraction: float) -> np.ndarray:
    """The unit quaternion a `fraction` of the way from q0 to q1 along the shorter arc."""
    dot = float(q0 @ q1)
    if dot < 0:  # q and -q are one rotation: go the short way round
        q1, dot = -q1, -dot
    if dot > 1 - 1e-12:  # (nearly) the same rotation: sin(angle) would divide by ~0
        q = q0 + fraction * (q1 - q0)
        return q / np.linalg.norm(q)
    angle = np.arccos(dot)
    return (np.sin((1 - fraction) * angle) * q0 + np.sin(fraction * angle) * q1) / np.sin(angle)


def poses_from_arrays(R: np.ndarray, t: np.ndarray) -> list[Pose]:
    """Pose(R[i], t[i]) for each i, with Pose's checks made once over all of them (vectorised):
    a store reads its poses by the hundred thousand at a restart, and Pose's own checks cost ten
    times the object. Raises what Pose raises for the first pose it would refuse."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] not in (2, 3) or R.shape != (*t.shape, t.shape[1]):
        raise ValueError(f"pose: R must be (n, d, d) and t (n, d) with d in 2, 3; got {R.shape}, {t.shape}")
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise ValueError("pose: non-finite values")
    if len(t) and (np.abs(R @ R.transpose(0, 2, 1) - np.eye(t.shape[1])).max() > 1e-6 or np.linalg.det(R).min() < 0):
        raise ValueError("pose: R is not a rotation matrix")
    poses = []
    for rotation, translation in zip(R, t):
        pose = object.__new__(Pose)  # checked above: __post_init__ would only repeat the checks
        object.__setattr__(pose, "R", rotation)
        object.__setattr__(pose, "t", translation)
        poses.append(pose)
    return poses


def poses_from_xytheta(xytheta: np.ndarray) -> list[Pose]:
    """Pose.from_xytheta of each row (x, y, theta) of an (n, 3) array, built at once
    (poses_from_arrays): a CARMEN log's reader makes two poses a scan, 27,000 for Intel's raw log."""
    xytheta = np.asarray(xytheta, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(xytheta[:, 2]), np.sin(xytheta[:, 2])
    return poses_from_arrays(np.stack([np.stack([c, -s], axis=1), np.stack([s, c], axis=1)], axis=1), xytheta[:, :2])
