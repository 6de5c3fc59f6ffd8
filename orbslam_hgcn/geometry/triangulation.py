"""Linear triangulation of many points at once, and the checks ORB-SLAM applies to them.

The DLT of Hartley & Zisserman (section 12.2), as ORB-SLAM's Initializer::Triangulate and
LocalMapping::CreateNewMapPoints use it, solved for all points in one OpenCV call.
"""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np

from orbslam_hgcn.compiled import jit

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
    X = triangulate_dlt(projection_matrix(K1, T_1w), projection_matrix(K2, T_2w), uv1, uv2)
    with_scale = scale1 is not None and scale2 is not None

    def plain(a: object) -> np.ndarray:
        # C-ordered and writeable, whatever the caller's array: numba compiles a version per
        # layout and read-only flag, and warm_up() compiles (caches) this one only.
        return np.require(a, np.float64, ["C_CONTIGUOUS", "WRITEABLE"])

    def per_point(v: object) -> np.ndarray:
        return plain(np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)))

    good = _checks(
        plain(X), plain(uv1), plain(uv2), plain(K1), plain(K2),
        plain(T_1w), plain(T_2w), per_point(sigma2_1), per_point(sigma2_2),
        per_point(scale1 if with_scale else 1.0), per_point(scale2 if with_scale else 1.0),
        with_scale, 1.5 * float(scale_factor),
    )  # fmt: skip
    return X, good


@jit
def _checks(X, uv1, uv2, K1, K2, T1, T2, sigma2_1, sigma2_2, scale1, scale2, with_scale, factor):
    """(N,) bool: the tests of :func:`triangulate_checked` on each DLT point ``X``, one
    point at a time (the rays' parallax from the bearing vectors, depth and reprojection
    in both cameras, and with ``with_scale`` the distance ratio against the scale ratio
    within ``factor``)."""
    n = len(X)
    good = np.zeros(n, dtype=np.bool_)
    C1 = np.empty(3)
    C2 = np.empty(3)
    for j in range(3):  # camera centres -R^T t
        C1[j] = -(T1[0, j] * T1[0, 3] + T1[1, j] * T1[1, 3] + T1[2, j] * T1[2, 3])
        C2[j] = -(T2[0, j] * T2[0, 3] + T2[1, j] * T2[1, 3] + T2[2, j] * T2[2, 3])
    for i in range(n):
        x, y, z = X[i, 0], X[i, 1], X[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        # Bearing vectors in the world frame: the normalised ray (K^-1 x) times R.
        h1x, h1y = (uv1[i, 0] - K1[0, 2]) / K1[0, 0], (uv1[i, 1] - K1[1, 2]) / K1[1, 1]
        h2x, h2y = (uv2[i, 0] - K2[0, 2]) / K2[0, 0], (uv2[i, 1] - K2[1, 2]) / K2[1, 1]
        dot = n1 = n2 = 0.0
        for j in range(3):
            a = h1x * T1[0, j] + h1y * T1[1, j] + T1[2, j]
            b = h2x * T2[0, j] + h2y * T2[1, j] + T2[2, j]
            dot += a * b
            n1 += a * a
            n2 += b * b
        cos_rays = dot / (np.sqrt(n1) * np.sqrt(n2))
        if not (cos_rays > 0.0 and cos_rays < COS_MAX_PARALLAX):
            continue
        ok = True
        for T, K, uv, s2 in ((T1, K1, uv1, sigma2_1), (T2, K2, uv2, sigma2_2)):
            xc = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
            yc = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
            zc = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
            if not zc > 0.0:
                ok = False
                break
            du = K[0, 0] * xc / zc + K[0, 2] - uv[i, 0]
            dv = K[1, 1] * yc / zc + K[1, 2] - uv[i, 1]
            if not du * du + dv * dv <= CHI2_MONO * s2[i]:
                ok = False
                break
        if not ok:
            continue
        if with_scale:
            d1 = np.sqrt((x - C1[0]) ** 2 + (y - C1[1]) ** 2 + (z - C1[2]) ** 2)
            d2 = np.sqrt((x - C2[0]) ** 2 + (y - C2[1]) ** 2 + (z - C2[2]) ** 2)
            if not (d1 > 0.0 and d2 > 0.0):
                continue
            ratio_dist = d2 / d1
            ratio_octave = scale1[i] / scale2[i]
            if ratio_dist * factor < ratio_octave or ratio_dist > ratio_octave * factor:
                continue
        good[i] = True
    return good


def warm_up() -> float:
    """Compile (first use after an install) or load from numba's cache the checks of
    :func:`triangulate_checked`; returns the seconds it took."""
    t0 = time.perf_counter()
    K, T2 = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]), np.eye(4)
    T2[0, 3] = -0.2
    uv = np.array([[50.0, 50.0]])
    triangulate_checked(K, np.eye(4), uv, np.ones(1), K, T2, uv - [[10.0, 0.0]], np.ones(1), np.ones(1), np.ones(1))
    return time.perf_counter() - t0
