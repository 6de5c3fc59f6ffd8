"""Linear triangulation of many points at once, and the checks ORB-SLAM applies to them.

The DLT of Hartley & Zisserman (section 12.2), as ORB-SLAM's Initializer::Triangulate and
LocalMapping::CreateNewMapPoints use it, solved for all points in one OpenCV call.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

log = logging.getLogger(__name__)

CHI2_MONO = 5.991  # chi-square 95% for 2 DoF
COS_MAX_PARALLAX = 0.9998  # ORB-SLAM's mapping: rays closer than ~1.1 degrees are not triangulated


def projection_matrix(K: np.ndarray, T_cw: np.ndarray) -> np.ndarray:
    """(3, 4) P = K [R | t] of a (3, 3) K and a (4, 4) world-to-camera pose."""
    return np.asarray(K, dtype=np.float64) @ np.asarray(T_cw, dtype=np.float64)[:3, :4]


def triangulate_dlt(P1: np.ndarray, P2: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """(N, 3) points from two views by the homogeneous DLT.

    P1, P2: (3, 4) projection matrices; uv1, uv2: (N, 2) matched (undistorted) pixels.
    Points at infinity come back as inf/nan; callers check with np.isfinite.
    """
    uv1 = np.asarray(uv1, dtype=np.float64).reshape(-1, 2)
    uv2 = np.asarray(uv2, dtype=np.float64).reshape(-1, 2)
    if len(uv1) == 0:
        return np.zeros((0, 3))
    # OpenCV solves the same 4x4 homogeneous system per point (SVD) in one call.
    Xh = cv2.triangulatePoints(
        np.asarray(P1, dtype=np.float64), np.asarray(P2, dtype=np.float64), uv1.T.copy(), uv2.T.copy()
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        return (Xh[:3] / Xh[3]).T


def parallax_cos(X: np.ndarray, C1: np.ndarray, C2: np.ndarray) -> np.ndarray:
    """(N,) cosine of the angle at each point X (N, 3) between the rays to centres C1, C2."""
    a = X - np.asarray(C1).reshape(1, 3)
    b = X - np.asarray(C2).reshape(1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))


def reprojection_sq_error(
    K: np.ndarray, T_cw: np.ndarray, X_w: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Squared pixel reprojection errors and depths of points in one camera.

    K: (3, 3); T_cw: (4, 4); X_w: (N, 3); uv: (N, 2). Returns ((N,) squared error,
    (N,) depth in the camera).
    """
    X_c = np.asarray(X_w) @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = X_c[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * X_c[:, 0] / z + K[0, 2]
        v = K[1, 1] * X_c[:, 1] / z + K[1, 2]
    e2 = (u - uv[:, 0]) ** 2 + (v - uv[:, 1]) ** 2
    return np.nan_to_num(e2, nan=np.inf), z


def triangulate_checked(
    K1: np.ndarray,
    T_1w: np.ndarray,
    uv1: np.ndarray,
    sigma2_1: np.ndarray,
    K2: np.ndarray,
    T_2w: np.ndarray,
    uv2: np.ndarray,
    sigma2_2: np.ndarray,
    scale1: np.ndarray | None = None,
    scale2: np.ndarray | None = None,
    scale_factor: float = 1.2,
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate matches between two keyframes with ORB-SLAM's acceptance tests.

    LocalMapping::CreateNewMapPoints (monocular): the viewing rays must differ by more
    than acos(0.9998); the point must lie in front of both cameras, reproject within the
    95% chi-square gate (5.991 sigma2 of the keypoint's level) in both images, and, when
    the keypoint scales are given, have a distance ratio to the two centres consistent
    with the ratio of the scales (within 1.5 scale_factor).
    uv1, uv2: (N, 2) undistorted pixels; sigma2_1, sigma2_2: (N,) level variances;
    scale1, scale2: (N,) level scale factors. Returns ((N, 3) world points, (N,) bool good).
    """
    uv1 = np.asarray(uv1, dtype=np.float64).reshape(-1, 2)
    uv2 = np.asarray(uv2, dtype=np.float64).reshape(-1, 2)
    n = len(uv1)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=bool)
    R1, R2 = T_1w[:3, :3], T_2w[:3, :3]
    C1 = -R1.T @ T_1w[:3, 3]
    C2 = -R2.T @ T_2w[:3, 3]
    # Parallax of the viewing rays, from the bearing vectors alone.
    b1 = np.concatenate([(uv1 - K1[:2, 2]) / np.diag(K1)[:2], np.ones((n, 1))], axis=1) @ R1
    b2 = np.concatenate([(uv2 - K2[:2, 2]) / np.diag(K2)[:2], np.ones((n, 1))], axis=1) @ R2
    cos_rays = np.sum(b1 * b2, axis=1) / (np.linalg.norm(b1, axis=1) * np.linalg.norm(b2, axis=1))
    X = triangulate_dlt(projection_matrix(K1, T_1w), projection_matrix(K2, T_2w), uv1, uv2)
    good = (cos_rays > 0) & (cos_rays < COS_MAX_PARALLAX) & np.all(np.isfinite(X), axis=1)
    e1, z1 = reprojection_sq_error(K1, T_1w, X, uv1)
    e2, z2 = reprojection_sq_error(K2, T_2w, X, uv2)
    with np.errstate(invalid="ignore"):
        good &= (z1 > 0) & (z2 > 0)
        good &= e1 <= CHI2_MONO * np.asarray(sigma2_1)
        good &= e2 <= CHI2_MONO * np.asarray(sigma2_2)
    if scale1 is not None and scale2 is not None:
        d1 = np.linalg.norm(X - C1, axis=1)
        d2 = np.linalg.norm(X - C2, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio_dist = d2 / d1
            ratio_octave = np.asarray(scale1, dtype=np.float64) / np.asarray(scale2, dtype=np.float64)
            factor = 1.5 * scale_factor
            good &= (d1 > 0) & (d2 > 0)
            good &= ~((ratio_dist * factor < ratio_octave) | (ratio_dist > ratio_octave * factor))
    return X, good
