"""Epipolar geometry helpers: fundamental and essential matrices, epipoles, normalisation.

Conventions follow ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015): ``F21`` maps points
of image 1 to lines of image 2 (``x2^T F21 x1 = 0``); ``F12`` is its transpose
(``x1^T F12 x2 = 0``). Poses are ``T_cw`` (world to camera).
"""

from __future__ import annotations

import logging

import numpy as np

from orbslam_hgcn.geometry.se3 import skew

log = logging.getLogger(__name__)


def relative_pose(T_1w: np.ndarray, T_2w: np.ndarray) -> np.ndarray:
    """(4, 4) T_21 = T_2w @ inv(T_1w): maps camera-1 coordinates into camera 2."""
    R1, t1 = T_1w[:3, :3], T_1w[:3, 3]
    R2, t2 = T_2w[:3, :3], T_2w[:3, 3]
    T = np.eye(4)
    T[:3, :3] = R2 @ R1.T
    T[:3, 3] = t2 - T[:3, :3] @ t1
    return T


def fundamental_from_pose(R21: np.ndarray, t21: np.ndarray, K1: np.ndarray, K2: np.ndarray) -> np.ndarray:
    """(3, 3) F21 = K2^-T [t21]x R21 K1^-1 of a camera-1-to-camera-2 motion."""
    E = skew(t21) @ R21
    return np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)


def fundamental_12_from_poses(T_1w: np.ndarray, T_2w: np.ndarray, K1: np.ndarray, K2: np.ndarray) -> np.ndarray:
    """(3, 3) F12 with ``x1^T F12 x2 = 0`` (ORB-SLAM LocalMapping::ComputeF12)."""
    T_12 = relative_pose(T_2w, T_1w)
    E12 = skew(T_12[:3, 3]) @ T_12[:3, :3]
    return np.linalg.inv(K1).T @ E12 @ np.linalg.inv(K2)


def epipole(T_1w: np.ndarray, T_2w: np.ndarray, K2: np.ndarray) -> np.ndarray:
    """(2,) projection of camera 1's centre into image 2 (may lie outside the image)."""
    C1 = -T_1w[:3, :3].T @ T_1w[:3, 3]
    X2 = T_2w[:3, :3] @ C1 + T_2w[:3, 3]
    p = K2 @ X2
    z = p[2] if abs(p[2]) > 1e-12 else 1e-12
    return p[:2] / z


def normalize_points(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hartley-style normalisation as ORB-SLAM's Initializer::Normalize.

    uv: (N, 2). Centres the points and scales each axis by the inverse mean absolute
    deviation. Returns ((N, 2) normalised points, (3, 3) T with x_n = T x).
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    mean = uv.mean(axis=0)
    dev = np.abs(uv - mean).mean(axis=0)
    s = 1.0 / np.where(dev > 0, dev, 1.0)
    T = np.array([[s[0], 0.0, -mean[0] * s[0]], [0.0, s[1], -mean[1] * s[1]], [0.0, 0.0, 1.0]])
    return (uv - mean) * s, T


def decompose_essential(E: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two rotations and the unit translation of an essential matrix (Hartley & Zisserman 9.6).

    Returns (R1, R2, t): the four motions are (R1, t), (R2, t), (R1, -t), (R2, -t).
    """
    U, _, Vt = np.linalg.svd(E)
    t = U[:, 2] / np.linalg.norm(U[:, 2])
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R1 = U @ W @ Vt
    R2 = U @ W.T @ Vt
    if np.linalg.det(R1) < 0:
        R1 = -R1
    if np.linalg.det(R2) < 0:
        R2 = -R2
    return R1, R2, t


def epipolar_sq_distances(F21: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared distances of matched points to their epipolar lines.

    F21: (3, 3) or (H, 3, 3); uv1, uv2: (N, 2). Returns (d2 in image 2, d1 in image 1),
    each (N,) or (H, N): distance of x2 to F21 x1 and of x1 to F21^T x2 (nan where a
    line is undefined).
    """
    x1 = np.concatenate([uv1, np.ones((len(uv1), 1))], axis=1).T  # (3, N)
    x2 = np.concatenate([uv2, np.ones((len(uv2), 1))], axis=1).T
    l2 = F21 @ x1  # (..., 3, N) lines in image 2
    l1 = np.swapaxes(F21[..., :, :2], -1, -2) @ x2  # (..., 2, N) first two line coefficients in image 1
    num = l2[..., 0, :] * x2[0] + l2[..., 1, :] * x2[1] + l2[..., 2, :]  # x2^T F21 x1
    num *= num
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = num / (l2[..., 0, :] ** 2 + l2[..., 1, :] ** 2)
        d1 = num / (l1[..., 0, :] ** 2 + l1[..., 1, :] ** 2)
    return d2, d1
