"""Batched homography and fundamental-matrix RANSAC with ORB-SLAM's symmetric scores.

ORB-SLAM's Initializer (Mur-Artal, Montiel & Tardos, T-RO 2015, section IV) fits a
homography (normalised DLT) and a fundamental matrix (normalised 8-point) to the same
random 8-point sets and scores every hypothesis over all matches with the symmetric
transfer error: for each image, ``score += T_S - chi2`` where ``chi2 = d^2 / sigma^2`` is
below the chi-square gate (5.991 for H, 3.841 for F, whose score still uses 5.991 so that
both models score alike). Here all hypotheses are solved with one batched SVD and scored
as (hypotheses x matches) arrays.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from orbslam_hgcn.geometry.epipolar import decompose_essential, epipolar_sq_distances, normalize_points

log = logging.getLogger(__name__)

TH_H = 5.991  # chi-square 95%, 2 DoF: homography transfer gate and score base
TH_F = 3.841  # chi-square 95%, 1 DoF: point-to-epipolar-line gate
TH_SCORE = 5.991  # score base of both models


def ransac_sets(n_matches: int, n_iterations: int, rng: np.random.Generator, size: int = 8) -> np.ndarray:
    """(I, size) int64 random sets of distinct match indices (one set per RANSAC iteration)."""
    keys = rng.random((n_iterations, n_matches))
    return np.argpartition(keys, size - 1, axis=1)[:, :size].astype(np.int64)


def homographies_dlt(p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(I, 3, 3) homographies H21 (x2 ~ H21 x1) from (I, k, 2) point sets, k >= 4."""
    u1, v1 = p1[..., 0], p1[..., 1]
    u2, v2 = p2[..., 0], p2[..., 1]
    z, o = np.zeros_like(u1), np.ones_like(u1)
    r1 = np.stack([z, z, z, -u1, -v1, -o, v2 * u1, v2 * v1, v2], axis=-1)
    r2 = np.stack([u1, v1, o, z, z, z, -u2 * u1, -u2 * v1, -u2], axis=-1)
    A = np.concatenate([r1, r2], axis=-2)  # (I, 2k, 9)
    # Right singular vector of the smallest singular value = eigenvector of A^T A.
    _, vecs = np.linalg.eigh(np.swapaxes(A, -1, -2) @ A)
    return vecs[..., :, 0].reshape(-1, 3, 3)


def fundamentals_8point(p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(I, 3, 3) rank-2 fundamental matrices F21 (x2^T F21 x1 = 0) from (I, k, 2) sets, k >= 8."""
    u1, v1 = p1[..., 0], p1[..., 1]
    u2, v2 = p2[..., 0], p2[..., 1]
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=-1)
    if A.shape[-2] == 8:
        # Exactly determined: the last column of a complete QR of A^T spans the null space.
        q, _ = np.linalg.qr(np.swapaxes(A, -1, -2), mode="complete")
        F = q[..., :, -1].reshape(-1, 3, 3)
    else:
        _, vecs = np.linalg.eigh(np.swapaxes(A, -1, -2) @ A)
        F = vecs[..., :, 0].reshape(-1, 3, 3)
    U, w, Vt2 = np.linalg.svd(F)
    w[..., 2] = 0.0
    return U @ (w[..., :, None] * Vt2)


def score_homographies(
    H21: np.ndarray, uv1: np.ndarray, uv2: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """ORB-SLAM's CheckHomography for (I, 3, 3) hypotheses over (N, 2) matches.

    Returns ((I,) scores, (I, N) bool inliers: transfer error below the gate both ways).
    """
    inv_s2 = 1.0 / (sigma * sigma)
    H12 = np.linalg.inv(H21)
    x1 = np.concatenate([uv1, np.ones((len(uv1), 1))], axis=1).T  # (3, N)
    x2 = np.concatenate([uv2, np.ones((len(uv2), 1))], axis=1).T

    def transfer_sq(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
        p = H @ src  # (I, 3, N)
        with np.errstate(divide="ignore", invalid="ignore"):
            w = 1.0 / p[:, 2]
            du = p[:, 0] * w - dst[0]
            dv = p[:, 1] * w - dst[1]
            return du * du + dv * dv  # nan (never an inlier) for points mapped to infinity

    chi1 = transfer_sq(H12, x2, x1) * inv_s2  # error in image 1 of x2 mapped by H12
    chi2 = transfer_sq(H21, x1, x2) * inv_s2  # error in image 2 of x1 mapped by H21
    return _symmetric_score(chi1, chi2, TH_H, TH_H)


def _symmetric_score(chi1: np.ndarray, chi2: np.ndarray, gate: float, base: float) -> tuple[np.ndarray, np.ndarray]:
    """((I,) sum over both images of ``base - chi`` where ``chi <= gate``, (I, N) inliers)."""
    with np.errstate(invalid="ignore"):
        ok1 = chi1 <= gate
        ok2 = chi2 <= gate
    s1 = base - chi1
    s1[~ok1] = 0.0
    s2 = base - chi2
    s2[~ok2] = 0.0
    return s1.sum(axis=1) + s2.sum(axis=1), ok1 & ok2


def score_fundamentals(
    F21: np.ndarray, uv1: np.ndarray, uv2: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """ORB-SLAM's CheckFundamental for (I, 3, 3) hypotheses over (N, 2) matches.

    Returns ((I,) scores, (I, N) bool inliers: both point-to-line distances below the gate).
    """
    inv_s2 = 1.0 / (sigma * sigma)
    d2, d1 = epipolar_sq_distances(F21, uv1, uv2)
    return _symmetric_score(d1 * inv_s2, d2 * inv_s2, TH_F, TH_SCORE)


def find_homography(
    uv1: np.ndarray, uv2: np.ndarray, sets: np.ndarray, sigma: float
) -> tuple[np.ndarray, float, np.ndarray]:
    """Best homography H21 over the RANSAC sets: ((3, 3) H21, score, (N,) bool inliers)."""
    p1, T1 = normalize_points(uv1)
    p2, T2 = normalize_points(uv2)
    Hn = homographies_dlt(p1[sets], p2[sets])
    H21 = np.linalg.inv(T2) @ Hn @ T1
    # Degenerate samples (collinear points) give singular hypotheses: score them zero.
    ok = np.abs(np.linalg.det(H21)) > 1e-12 * np.abs(H21).max(axis=(1, 2)) ** 3
    H21[~ok] = np.eye(3)
    scores, inliers = score_homographies(H21, uv1, uv2, sigma)
    scores[~ok] = 0.0
    best = int(np.argmax(scores))
    return H21[best], float(scores[best]), inliers[best]


def find_fundamental(
    uv1: np.ndarray, uv2: np.ndarray, sets: np.ndarray, sigma: float
) -> tuple[np.ndarray, float, np.ndarray]:
    """Best fundamental matrix F21 over the RANSAC sets: ((3, 3) F21, score, (N,) bool inliers)."""
    p1, T1 = normalize_points(uv1)
    p2, T2 = normalize_points(uv2)
    Fn = fundamentals_8point(p1[sets], p2[sets])
    F21 = T2.T @ Fn @ T1
    scores, inliers = score_fundamentals(F21, uv1, uv2, sigma)
    best = int(np.argmax(scores))
    return F21[best], float(scores[best]), inliers[best]


def _robust_gauss_newton(
    residuals: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, huber: float = 1.0, n_iter: int = 15
) -> np.ndarray:
    """Minimise a Huber cost with damped Gauss-Newton (Levenberg-Marquardt) and IRLS weights.

    residuals: maps (B, P) parameter vectors to (B, M) residuals, so the forward-difference
    Jacobian of one step is a single batched call. Returns the (P,) solution.
    """
    x = np.asarray(x0, dtype=np.float64).copy()
    lam = 1e-3

    def cost(r: np.ndarray) -> float:
        a = np.abs(r)
        return float(np.sum(np.where(a <= huber, 0.5 * r * r, huber * (a - 0.5 * huber))))

    r = residuals(x[None])[0]
    c = cost(r)
    for _ in range(n_iter):
        h = 1e-6 * np.maximum(np.abs(x), 1e-2)
        rp = residuals(x[None] + np.diag(h))
        J = ((rp - r) / h[:, None]).T  # (M, P)
        w = np.where(np.abs(r) <= huber, 1.0, huber / np.maximum(np.abs(r), 1e-300))
        JtW = J.T * w
        A = JtW @ J
        g = JtW @ r
        improved = False
        for _ in range(6):
            try:
                dx = -np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            r_new = residuals((x + dx)[None])[0]
            c_new = cost(r_new)
            if np.isfinite(c_new) and c_new < c:
                x, r, lam, improved = x + dx, r_new, max(lam / 10, 1e-9), True
                converged = c - c_new < 1e-10 * max(c, 1e-300)
                c = c_new
                break
            lam *= 10
        if not improved or converged:
            break
    return x


def _rotvec_to_R(w: np.ndarray) -> np.ndarray:
    """(B, 3, 3) rotations of (B, 3) rotation vectors (Rodrigues' formula)."""
    th = np.linalg.norm(w, axis=1)
    k = w / np.maximum(th, 1e-300)[:, None]
    Kx = np.zeros((len(w), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2] = -k[:, 2], k[:, 1]
    Kx[:, 1, 0], Kx[:, 1, 2] = k[:, 2], -k[:, 0]
    Kx[:, 2, 0], Kx[:, 2, 1] = -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3) + s * Kx + (1 - c) * (Kx @ Kx)


def _sampson_f(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distances in pixels of homogeneous matches (N, 3) under F21 (..., 3, 3)."""
    Fx1 = F @ x1.T  # (..., 3, N)
    Ftx2 = np.swapaxes(F, -1, -2) @ x2.T
    num = np.sum(Fx1 * x2.T, axis=-2)
    den = Fx1[..., 0, :] ** 2 + Fx1[..., 1, :] ** 2 + Ftx2[..., 0, :] ** 2 + Ftx2[..., 1, :] ** 2
    return num / np.sqrt(np.maximum(den, 1e-300))


def refine_fundamental(F21: np.ndarray, K: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """(3, 3) F21 refined over matches (N, 2) as a calibrated essential matrix.

    Minimises the Sampson distance (pixels, Huber loss at 1 px) over the 5 degrees of
    freedom of ``E = [t]x R`` starting from ``K^T F21 K``, so the result is an exact
    essential matrix for K. ORB-SLAM keeps the 8-point estimate and relies on the global
    bundle adjustment after initialisation; refining here makes the recovered motion
    accurate enough for the reconstruction checks on noisier matches.
    """
    K_inv = np.linalg.inv(K)
    R0, _, t0 = decompose_essential(K.T @ F21 @ K)
    x1 = np.concatenate([uv1, np.ones((len(uv1), 1))], axis=1)
    x2 = np.concatenate([uv2, np.ones((len(uv2), 1))], axis=1)

    def to_f(p: np.ndarray) -> np.ndarray:  # (B, 6) -> (B, 3, 3)
        R = _rotvec_to_R(p[:, :3]) @ R0
        t = p[:, 3:] / np.linalg.norm(p[:, 3:], axis=1, keepdims=True)
        tx = np.zeros((len(p), 3, 3))
        tx[:, 0, 1], tx[:, 0, 2] = -t[:, 2], t[:, 1]
        tx[:, 1, 0], tx[:, 1, 2] = t[:, 2], -t[:, 0]
        tx[:, 2, 0], tx[:, 2, 1] = -t[:, 1], t[:, 0]
        return K_inv.T @ tx @ R @ K_inv

    p = _robust_gauss_newton(lambda q: _sampson_f(to_f(q), x1, x2), np.concatenate([np.zeros(3), t0]))
    return to_f(p[None])[0]


def refine_homography(H21: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """(3, 3) H21 refined over matches (N, 2) by the symmetric transfer error (Huber, 1 px)."""
    x1 = np.concatenate([uv1, np.ones((len(uv1), 1))], axis=1)
    x2 = np.concatenate([uv2, np.ones((len(uv2), 1))], axis=1)

    def resid(h: np.ndarray) -> np.ndarray:  # (B, 9) -> (B, 4N)
        H = h.reshape(-1, 3, 3)
        p2 = np.swapaxes(H @ x1.T, 1, 2)  # (B, N, 3)
        p1 = np.swapaxes(np.linalg.inv(H) @ x2.T, 1, 2)
        r2 = p2[..., :2] / p2[..., 2:] - uv2
        r1 = p1[..., :2] / p1[..., 2:] - uv1
        return np.concatenate([r1.reshape(len(H), -1), r2.reshape(len(H), -1)], axis=1)

    try:
        h = _robust_gauss_newton(resid, (H21 / np.linalg.norm(H21)).ravel())
    except np.linalg.LinAlgError:  # a step through a singular homography: keep the input
        return H21
    return h.reshape(3, 3)
