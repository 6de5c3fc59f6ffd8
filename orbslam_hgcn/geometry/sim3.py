"""Similarity transforms from 3D-3D matches: Horn's closed form and ORB-SLAM's Sim3Solver.

Horn, "Closed-form solution of absolute orientation using unit quaternions", JOSA A 1987:
the rotation is the eigenvector of the largest eigenvalue of a 4x4 symmetric matrix built
from the cross-covariance of the centred point sets; scale and translation follow. Loop
closing in ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, section VII-B) runs it in
RANSAC on 3-point sets, counting as inliers the matches that reproject, in both
keyframes, within the 99% chi-square gate (9.210 sigma^2 of the keypoint level). Here all
hypotheses of a batch are solved with one batched eigendecomposition.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.geometry.ransac import ransac_iterations

log = logging.getLogger(__name__)

CHI2_99_2DOF = 9.210  # chi-square 99% for 2 DoF (ORB-SLAM Sim3Solver)


def horn_similarity(
    P1: np.ndarray, P2: np.ndarray, fixed_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Similarities mapping set 2 onto set 1: ``P1 ~ s R P2 + t``.

    P1, P2: (k, 3) or batched (B, k, 3) corresponding points, k >= 3. Returns (s, R, t)
    with shapes ((), (3, 3), (3,)) or ((B,), (B, 3, 3), (B, 3)). The scale is Horn's
    asymmetric one, ``sum(p1 . R p2) / sum(|p2|^2)`` over centred points (as ORB-SLAM).
    """
    P1 = np.asarray(P1, dtype=np.float64)
    P2 = np.asarray(P2, dtype=np.float64)
    single = P1.ndim == 2
    if single:
        P1, P2 = P1[None], P2[None]
    O1 = P1.mean(axis=1)
    O2 = P2.mean(axis=1)
    Q1 = P1 - O1[:, None]
    Q2 = P2 - O2[:, None]
    M = np.einsum("bki,bkj->bij", Q2, Q1)  # sum of p2 p1^T
    Sxx, Sxy, Sxz = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    Syx, Syy, Syz = M[:, 1, 0], M[:, 1, 1], M[:, 1, 2]
    Szx, Szy, Szz = M[:, 2, 0], M[:, 2, 1], M[:, 2, 2]
    N = np.empty((len(M), 4, 4))
    N[:, 0, 0] = Sxx + Syy + Szz
    N[:, 0, 1] = N[:, 1, 0] = Syz - Szy
    N[:, 0, 2] = N[:, 2, 0] = Szx - Sxz
    N[:, 0, 3] = N[:, 3, 0] = Sxy - Syx
    N[:, 1, 1] = Sxx - Syy - Szz
    N[:, 1, 2] = N[:, 2, 1] = Sxy + Syx
    N[:, 1, 3] = N[:, 3, 1] = Szx + Sxz
    N[:, 2, 2] = -Sxx + Syy - Szz
    N[:, 2, 3] = N[:, 3, 2] = Syz + Szy
    N[:, 3, 3] = -Sxx - Syy + Szz
    _, vecs = np.linalg.eigh(N)
    w, x, y, z = np.moveaxis(vecs[:, :, -1], -1, 0)  # unit quaternion of the largest eigenvalue
    R = np.empty((len(M), 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 2, 1] = 2 * (y * z + w * x)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    if fixed_scale:
        s = np.ones(len(M))
    else:
        RQ2 = np.einsum("bij,bkj->bki", R, Q2)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.sum(Q1 * RQ2, axis=(1, 2)) / np.sum(Q2 * Q2, axis=(1, 2))
    t = O1 - s[:, None] * np.einsum("bij,bj->bi", R, O2)
    if single:
        return s[0], R[0], t[0]
    return s, R, t


def similarity_matrix(s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) ``[[s R, t], [0, 1]]``."""
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = t
    return S


@dataclass(frozen=True, eq=False)
class Sim3Result:
    """S_12: (4, 4) similarity mapping camera-2 coordinates to camera 1 (``X1 = s R X2 + t``);
    inliers: (N,) bool; scale: s; iterations: hypotheses tried."""

    S_12: np.ndarray
    inliers: np.ndarray
    scale: float
    iterations: int


def _project(K: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = X[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * X[..., 0] / z + K[0, 2]
        v = K[1, 1] * X[..., 1] / z + K[1, 2]
    return np.stack([u, v], axis=-1), z


def sim3_inliers(
    s: np.ndarray, R: np.ndarray, t: np.ndarray, X1: np.ndarray, X2: np.ndarray,
    uv1: np.ndarray, uv2: np.ndarray, K1: np.ndarray, K2: np.ndarray, gate1: np.ndarray, gate2: np.ndarray,
) -> np.ndarray:
    """(B, N) bool: matches reprojecting within the gates in both images (ORB-SLAM CheckInliers).

    s, R, t: batched (B,), (B, 3, 3), (B, 3) similarities S_12; X1, X2: (N, 3) points in
    each camera; uv1, uv2: (N, 2) their observations; gate1, gate2: (N,) squared-pixel gates.
    """
    X2in1 = s[:, None, None] * np.einsum("bij,nj->bni", R, X2) + t[:, None, :]
    # Inverse similarity: X2 = R^T (X1 - t) / s.
    X1in2 = np.einsum("bji,bnj->bni", R, X1[None] - t[:, None, :]) / s[:, None, None]
    p1, z1 = _project(K1, X2in1)
    p2, z2 = _project(K2, X1in2)
    e1 = np.sum((p1 - uv1) ** 2, axis=-1)
    e2 = np.sum((p2 - uv2) ** 2, axis=-1)
    with np.errstate(invalid="ignore"):
        return (z1 > 0) & (z2 > 0) & (e1 < gate1) & (e2 < gate2)


def sim3_ransac(
    X1: np.ndarray,
    X2: np.ndarray,
    uv1: np.ndarray,
    uv2: np.ndarray,
    K1: np.ndarray,
    K2: np.ndarray,
    sigma2_1: np.ndarray | float = 1.0,
    sigma2_2: np.ndarray | float = 1.0,
    *,
    probability: float = 0.99,
    min_inliers: int = 20,
    max_iterations: int = 300,
    fixed_scale: bool = False,
    th2: float = CHI2_99_2DOF,
    batch: int = 50,
    rng: np.random.Generator | None = None,
) -> Sim3Result | None:
    """ORB-SLAM's Sim3Solver: the similarity S_12 between two keyframes' matched map points.

    X1, X2: (N, 3) matched points in camera-1 and camera-2 coordinates; uv1, uv2: (N, 2)
    their pixels in each keyframe (ORB-SLAM uses the projections of X1 and X2 themselves;
    keypoint observations work as well); K1, K2: (3, 3); sigma2_1, sigma2_2: (N,) level
    variances of the observations. Loop closing uses (0.99, 20, 300). The best hypothesis
    is re-estimated on all its inliers and its inliers recomputed.
    Returns None when no hypothesis has at least min_inliers inliers.
    """
    X1 = np.asarray(X1, dtype=np.float64).reshape(-1, 3)
    X2 = np.asarray(X2, dtype=np.float64).reshape(-1, 3)
    uv1 = np.asarray(uv1, dtype=np.float64).reshape(-1, 2)
    uv2 = np.asarray(uv2, dtype=np.float64).reshape(-1, 2)
    n = len(X1)
    if n < max(3, min_inliers):
        return None
    rng = rng or np.random.default_rng(0)
    gate1 = th2 * np.broadcast_to(np.asarray(sigma2_1, dtype=np.float64), (n,))
    gate2 = th2 * np.broadcast_to(np.asarray(sigma2_2, dtype=np.float64), (n,))
    n_iter = ransac_iterations(probability, min_inliers / n, 3, max_iterations)
    best = None
    best_count = -1
    done = 0
    while done < n_iter:
        b = min(batch, n_iter - done)
        sets = np.argpartition(rng.random((b, n)), 2, axis=1)[:, :3]
        s, R, t = horn_similarity(X1[sets], X2[sets], fixed_scale)
        done += b
        valid = np.isfinite(s) & (s > 0)
        if not valid.any():
            continue
        s, R, t = s[valid], R[valid], t[valid]
        inl = sim3_inliers(s, R, t, X1, X2, uv1, uv2, K1, K2, gate1, gate2)
        counts = inl.sum(axis=1)
        j = int(np.argmax(counts))
        if counts[j] > best_count:
            best_count = int(counts[j])
            best = (s[j], R[j], t[j], inl[j])
            if best_count == n:
                break
            n_iter = min(n_iter, max(done, ransac_iterations(probability, best_count / n, 3, max_iterations)))
    if best is None or best_count < min_inliers:
        log.debug("Sim3 RANSAC failed: best %d inliers of %d", best_count, n)
        return None
    s, R, t, inliers = best
    for _ in range(2):
        idx = np.flatnonzero(inliers)
        s2, R2, t2 = horn_similarity(X1[idx], X2[idx], fixed_scale)
        if not (np.isfinite(s2) and s2 > 0):
            break
        inl2 = sim3_inliers(np.array([s2]), R2[None], t2[None], X1, X2, uv1, uv2, K1, K2, gate1, gate2)[0]
        if inl2.sum() < inliers.sum():
            break
        s, R, t, inliers = s2, R2, t2, inl2
    return Sim3Result(S_12=similarity_matrix(float(s), R, t), inliers=inliers, scale=float(s), iterations=done)
