"""Camera pose from 2D-3D matches: EPnP in RANSAC as ORB-SLAM's PnPsolver (relocalisation).

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, section V-C) relocalises with EPnP
(Lepetit, Moreno-Noguer & Fua, IJCV 2009) in RANSAC with probability 0.99, at least 10
inliers and at most 300 iterations, a 4-point minimal set, and a per-match gate of
``5.991 sigma^2`` of the keypoint's pyramid level. Hypotheses come from OpenCV's EPnP;
they are scored in batches on whole arrays; the winner is refined on its inliers by
Levenberg-Marquardt (OpenCV's iterative solver) and its inliers recomputed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from orbslam_hgcn.geometry.ransac import ransac_iterations

log = logging.getLogger(__name__)

CHI2_MONO = 5.991  # chi-square 95% for 2 DoF


@dataclass(frozen=True, eq=False)
class PnPResult:
    """T_cw: (4, 4) world-to-camera pose; inliers: (N,) bool; iterations: hypotheses tried."""

    T_cw: np.ndarray
    inliers: np.ndarray
    iterations: int


def _pose_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return T


def reprojection_sq_errors(T_cw: np.ndarray, X_w: np.ndarray, uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Squared pixel errors for one (4, 4) pose or a stack (B, 4, 4): (N,) or (B, N).

    Points behind the camera get an infinite error.
    """
    X_c = np.einsum("...ij,nj->...ni", T_cw[..., :3, :3], X_w) + T_cw[..., None, :3, 3]
    z = X_c[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * X_c[..., 0] / z + K[0, 2]
        v = K[1, 1] * X_c[..., 1] / z + K[1, 2]
        e2 = (u - uv[:, 0]) ** 2 + (v - uv[:, 1]) ** 2
    return np.where(z > 0, np.nan_to_num(e2, nan=np.inf), np.inf)


def _solve(
    X: np.ndarray, uv: np.ndarray, K: np.ndarray, flags: int, guess: np.ndarray | None = None
) -> np.ndarray | None:
    try:
        if guess is None:
            ok, rvec, tvec = cv2.solvePnP(X, uv, K, None, flags=flags)
        else:
            rvec0 = cv2.Rodrigues(guess[:3, :3])[0]
            ok, rvec, tvec = cv2.solvePnP(
                X, uv, K, None, rvec=rvec0, tvec=guess[:3, 3].reshape(3, 1).copy(), useExtrinsicGuess=True, flags=flags
            )
    except cv2.error:
        return None
    if not ok or not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
        return None
    return _pose_from_rvec(rvec, tvec)


def solve_pnp_ransac(
    X_w: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
    sigma2: np.ndarray | float = 1.0,
    *,
    probability: float = 0.99,
    min_inliers: int = 10,
    max_iterations: int = 300,
    min_set: int = 4,
    epsilon: float = 0.5,
    th2: float = CHI2_MONO,
    batch: int = 25,
    rng: np.random.Generator | None = None,
) -> PnPResult | None:
    """Pose of a camera from 3D points and their undistorted pixel observations.

    X_w: (N, 3) world points; uv: (N, 2) undistorted pixels; K: (3, 3); sigma2: (N,) or
    scalar variance of each observation's level (the gate is ``th2 * sigma2``).
    ORB-SLAM's SetRansacParameters(0.99, 10, 300, 4, 0.5, 5.991): the expected inlier
    ratio epsilon also sets the minimum inlier count ``max(min_inliers, epsilon N)``.
    Returns None when no hypothesis reaches the minimum inlier count.
    """
    X_w = np.ascontiguousarray(X_w, dtype=np.float64).reshape(-1, 3)
    uv = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 2)
    K = np.asarray(K, dtype=np.float64)
    n = len(X_w)
    if n < max(min_set, 4):
        return None
    rng = rng or np.random.default_rng(0)
    gate = th2 * np.broadcast_to(np.asarray(sigma2, dtype=np.float64), (n,))
    need = max(min_inliers, min_set, int(epsilon * n))
    n_iter = ransac_iterations(probability, max(epsilon, need / n), min_set, max_iterations)
    best_T, best_in, best_count = None, None, -1
    done = 0
    while done < n_iter:
        b = min(batch, n_iter - done)
        sets = np.argpartition(rng.random((b, n)), min_set - 1, axis=1)[:, :min_set]
        poses = [_solve(X_w[s], uv[s], K, cv2.SOLVEPNP_EPNP) for s in sets]
        done += b
        poses = [T for T in poses if T is not None]
        if not poses:
            continue
        inl = reprojection_sq_errors(np.stack(poses), X_w, uv, K) < gate
        counts = inl.sum(axis=1)
        j = int(np.argmax(counts))
        if counts[j] > best_count:
            best_T, best_in, best_count = poses[j], inl[j], int(counts[j])
            # Adaptive termination as in standard RANSAC, bounded by max_iterations.
            if best_count == n:
                break
            n_iter = min(n_iter, max(done, ransac_iterations(probability, best_count / n, min_set, max_iterations)))
    if best_T is None or best_count < need:
        log.debug("PnP RANSAC failed: best %d inliers of %d (need %d)", best_count, n, need)
        return None
    # Refine on the inliers by LM from the RANSAC pose, recomputing the inliers each time.
    T, inliers = best_T, best_in
    for _ in range(2):
        idx = np.flatnonzero(inliers)
        T_new = _solve(X_w[idx], uv[idx], K, cv2.SOLVEPNP_ITERATIVE, guess=T)
        if T_new is None:
            break
        inl_new = reprojection_sq_errors(T_new, X_w, uv, K) < gate
        if inl_new.sum() < inliers.sum():
            break
        T, inliers = T_new, inl_new
    if inliers.sum() < need:
        return None
    return PnPResult(T_cw=T, inliers=inliers, iterations=done)
