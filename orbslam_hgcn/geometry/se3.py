"""Rigid and similarity transforms as 4x4 numpy matrices, and quaternion conversions.

Conventions: ``T_cw`` maps world points into the camera frame, ``T_wc`` is its inverse,
``S_wc`` is a similarity (``[[s R, t], [0, 1]]``). Quaternions follow the TUM file order
``(qx, qy, qz, qw)`` unless a function says otherwise.
"""

from __future__ import annotations

import numpy as np


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) float64 transform from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform, or of a stack (N, 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def inv_S(S: np.ndarray) -> np.ndarray:
    """Inverse of a similarity (4, 4) ``[[s R, t], [0, 1]]``."""
    sR = S[:3, :3]
    s = np.cbrt(np.linalg.det(sR))
    R = sR / s
    out = np.eye(4)
    out[:3, :3] = R.T / s
    out[:3, 3] = -(R.T @ S[:3, 3]) / s
    return out


def transform_points(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) rigid or similarity transform to (N, 3) points."""
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    return X @ T[:3, :3].T + T[:3, 3]


def quat_to_R(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) or (N, 3, 3) from quaternion(s) ``(qx, qy, qz, qw)``, each
    normalised first (a zero quaternion is a ValueError). numpy only: reading a TUM or EuRoC
    ground truth at start-up no longer imports ``scipy.spatial`` (0.2 s)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    if q.shape[-1:] != (4,) or q.ndim > 2:
        raise ValueError(f"quaternions must be (4,) or (N, 4), found {q.shape}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(norm)) or np.any(norm == 0.0):
        raise ValueError("quaternions must be finite and non-zero")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[..., 0, 1] = 2.0 * (x * y - z * w)
    R[..., 0, 2] = 2.0 * (x * z + y * w)
    R[..., 1, 0] = 2.0 * (x * y + z * w)
    R[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[..., 1, 2] = 2.0 * (y * z - x * w)
    R[..., 2, 0] = 2.0 * (x * z - y * w)
    R[..., 2, 1] = 2.0 * (y * z + x * w)
    R[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return R


def R_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion(s) ``(qx, qy, qz, qw)`` with qw >= 0 from (3, 3) or (N, 3, 3) rotations."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return np.where(q[..., 3:4] < 0, -q, q)


def skew(v: np.ndarray) -> np.ndarray:
    """(3, 3) cross-product matrix of a 3-vector."""
    x, y, z = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle in degrees of a (3, 3) rotation."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between two 3-vectors."""
    a = np.asarray(a, dtype=np.float64).reshape(3)
    b = np.asarray(b, dtype=np.float64).reshape(3)
    c = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
