"""Batched rigid transforms on ``(..., 4, 4)`` float64 homogeneous matrices.

Quaternions are scalar-last ``(qx, qy, qz, qw)`` as in scipy and PyBullet, with ``qw >= 0`` so that a
pose has one spelling. This is the only module that converts between matrices and the Parquet pose
columns ``x y z qx qy qz qw`` (DESIGN.md, Conventions). Names follow Drake's monogram notation:
``X_WO`` is the pose of frame O in frame W, ``p_OC`` a point C in O.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

POSE_COLUMNS = ("x", "y", "z", "qx", "qy", "qz", "qw")


def identity(n: int | None = None) -> np.ndarray:
    """Identity transform, ``(4, 4)`` or ``(n, 4, 4)``."""
    if n is None:
        return np.eye(4)
    return np.tile(np.eye(4), (n, 1, 1))


def make_transform(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Transforms from rotations ``R (..., 3, 3)`` and translations ``p (..., 3)``."""
    R = np.asarray(R, dtype=float)
    p = np.asarray(p, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], p.shape[:-1])
    X = np.zeros(shape + (4, 4))
    X[..., :3, :3] = R
    X[..., :3, 3] = p
    X[..., 3, 3] = 1.0
    return X


def invert(X: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``X (..., 4, 4)``: ``X_BA`` from ``X_AB``."""
    R = np.swapaxes(X[..., :3, :3], -1, -2)
    return make_transform(R, -np.einsum("...ij,...j->...i", R, X[..., :3, 3]))


def transform_points(X: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply ``X (..., 4, 4)`` to points ``p (..., 3)``, broadcasting leading dimensions."""
    return np.einsum("...ij,...j->...i", X[..., :3, :3], p) + X[..., :3, 3]


def rotate_vectors(X: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Apply the rotation of ``X (..., 4, 4)`` (or ``R (..., 3, 3)``) to vectors ``v (..., 3)``."""
    return np.einsum("...ij,...j->...i", X[..., :3, :3], v)


def rotation_about_axis(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` about unit ``axis (..., 3)`` by ``angle (...)`` rad (Rodrigues)."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = np.asarray(angle, dtype=float)
    shape = np.broadcast_shapes(axis.shape[:-1], angle.shape)
    axis = np.broadcast_to(axis, shape + (3,))
    angle = np.broadcast_to(angle, shape)
    K = skew(axis)
    s = np.sin(angle)[..., None, None]
    c = np.cos(angle)[..., None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def transform_about_line(point: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Transforms ``(..., 4, 4)`` rotating by ``angle`` about the line through ``point`` along ``axis``."""
    R = rotation_about_axis(axis, angle)
    point = np.asarray(point, dtype=float)
    return make_transform(R, point - np.einsum("...ij,...j->...i", R, point))


def rot_z(angle: np.ndarray) -> np.ndarray:
    """Rotations ``(..., 3, 3)`` about z by ``angle (...)`` rad."""
    return rotation_about_axis(np.array([0.0, 0.0, 1.0]), angle)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``(..., 3, 3)``: ``skew(a) @ b == cross(a, b)``."""
    v = np.asarray(v, dtype=float)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotations ``(..., 3, 3)`` taking unit vectors ``a`` onto unit vectors ``b``.

    Antiparallel pairs turn by pi about an axis perpendicular to ``a`` chosen deterministically.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a, b = np.broadcast_arrays(a / np.linalg.norm(a, axis=-1, keepdims=True),
                               b / np.linalg.norm(b, axis=-1, keepdims=True))
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1)
    c = np.sum(a * b, axis=-1)
    # Antiparallel: any axis perpendicular to a works; take a x e, e the least-aligned basis vector.
    e = np.eye(3)[np.argmin(np.abs(a), axis=-1)]
    perp = np.cross(a, e)
    flip = s < 1e-9
    axis = np.where(flip[..., None], perp, axis)
    angle = np.arctan2(s, c)
    angle = np.where(flip & (c > 0), 0.0, angle)
    axis = np.where((np.linalg.norm(axis, axis=-1) < 1e-12)[..., None], e, axis)
    return rotation_about_axis(axis, angle)


def columns_from_matrix(X: np.ndarray) -> dict[str, np.ndarray]:
    """Pose columns ``x y z qx qy qz qw`` (each ``(n,)``) from transforms ``X (n, 4, 4)``."""
    X = np.asarray(X, dtype=float).reshape(-1, 4, 4)
    q = quat_from_matrix(X[:, :3, :3]) if len(X) else np.zeros((0, 4))
    cols = {"x": X[:, 0, 3], "y": X[:, 1, 3], "z": X[:, 2, 3]}
    cols.update({"qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]})
    return {k: np.ascontiguousarray(v) for k, v in cols.items()}


def matrix_from_columns(cols) -> np.ndarray:
    """Transforms ``(n, 4, 4)`` from a mapping with pose columns ``x y z qx qy qz qw``."""
    p = np.stack([np.asarray(cols[k], dtype=float) for k in POSE_COLUMNS[:3]], axis=-1)
    q = np.stack([np.asarray(cols[k], dtype=float) for k in POSE_COLUMNS[3:]], axis=-1)
    if len(p) == 0:
        return np.zeros((0, 4, 4))
    return make_transform(matrix_from_quat(q), p)


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` scalar-last with ``qw >= 0`` from rotations ``(..., 3, 3)``."""
    R = np.asarray(R, dtype=float)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(R.shape[:-2] + (4,))
    return np.where(q[..., 3:4] < 0, -q, q)


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotations ``(..., 3, 3)`` from quaternions ``(..., 4)`` scalar-last."""
    q = np.asarray(q, dtype=float)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(q.shape[:-1] + (3, 3))


def yaw_of(R: np.ndarray) -> np.ndarray:
    """Heading angle (rad) of the rotated x axis projected on the xy plane, ``(...,)``."""
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def tilt_of(R: np.ndarray) -> np.ndarray:
    """Angle (rad) between the rotated z axis and world z, ``(...,)``."""
    return np.arccos(np.clip(R[..., 2, 2], -1.0, 1.0))
