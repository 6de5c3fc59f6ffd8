"""Monocular map initialisation from two views, as ORB-SLAM's Initializer.

Mur-Artal, Montiel & Tardos, "ORB-SLAM", T-RO 2015, section IV: a homography and a
fundamental matrix are fitted in parallel RANSACs over the same 200 random 8-point sets
(:mod:`orbslam_hgcn.geometry.two_view_models`, all hypotheses at once), the homography is
chosen when ``R_H = S_H / (S_H + S_F)`` exceeds 0.45 (the paper's value; ORB-SLAM2's code
uses 0.40), and the motion is recovered from the chosen model:

* F: ``E = K^T F K`` gives four motions (Hartley & Zisserman 9.6);
* H: Faugeras & Lustman's decomposition ("Motion and structure from motion in a piecewise
  planar environment", 1988) gives eight;

each is checked by triangulating the inliers (cheirality with parallax, reprojection error
below ``4 sigma^2``), and the reconstruction is accepted only when one motion clearly wins,
enough points are triangulated and their parallax exceeds 1 degree.

One addition to ORB-SLAM (``InitializerConfig.refine``, on by default): before it is
decomposed, the chosen model is refined on its inliers by robust least squares (symmetric
transfer error for H; Sampson error over the five degrees of freedom of a calibrated
essential matrix for F). ORB-SLAM decomposes the 8-point estimate and relies on the global
bundle adjustment that follows; with pixel noise of 0.5 px or more the 8-point motion often
fails the "90% of inliers triangulated" test, which the refined model passes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.geometry.epipolar import decompose_essential
from orbslam_hgcn.geometry.triangulation import triangulate_dlt
from orbslam_hgcn.geometry.two_view_models import (
    find_fundamental,
    find_homography,
    ransac_sets,
    refine_fundamental,
    refine_homography,
    score_fundamentals,
    score_homographies,
)

log = logging.getLogger(__name__)

COS_PARALLAX_INF = 0.99998  # ORB-SLAM CheckRT: rays this close count as points at infinity


@dataclass(frozen=True)
class InitializerConfig:
    """Monocular two-view initialisation (ORB-SLAM Initializer, T-RO 2015 section IV)."""

    sigma: float = 1.0  # pixel standard deviation of a level-0 keypoint
    ransac_iterations: int = 200  # 8-point sets shared by the H and F RANSACs
    rh_threshold: float = 0.45  # choose the homography when S_H / (S_H + S_F) exceeds this
    min_parallax_deg: float = 1.0  # reject a reconstruction whose parallax is below this
    min_triangulated: int = 50  # reject a reconstruction with fewer good points
    seed: int = 0  # seed of the random 8-point sets (reproducible initialisation)
    # Refine the winning H / F on its inliers (symmetric transfer / Sampson error) before
    # decomposing it; ORB-SLAM keeps the 8-point estimate and relies on its global BA.
    refine: bool = True


@dataclass(frozen=True, eq=False)
class TwoViewResult:
    """A two-view reconstruction.

    model:        "H" or "F", the model the motion came from
    R21, t21:     (3, 3), (3,) motion from camera 1 to camera 2 (``X2 = R21 X1 + t21``),
                  ``|t21| = 1``
    points:       (N, 3) triangulated points in camera 1's frame (nan where not good)
    triangulated: (N,) bool points good for the map (in front, low reprojection error,
                  enough parallax)
    parallax_deg: parallax of the reconstruction (ORB-SLAM: the 51st largest ray angle)
    score_h, score_f: RANSAC scores of the two models; rh = score_h / (score_h + score_f)
    inliers:      (N,) bool inliers of the chosen model
    """

    model: str
    R21: np.ndarray
    t21: np.ndarray
    points: np.ndarray
    triangulated: np.ndarray
    parallax_deg: float
    score_h: float
    score_f: float
    rh: float
    inliers: np.ndarray

    @property
    def T_21(self) -> np.ndarray:
        """(4, 4) camera-1-to-camera-2 transform."""
        T = np.eye(4)
        T[:3, :3] = self.R21
        T[:3, 3] = self.t21
        return T


@dataclass(frozen=True)
class _MotionCheck:
    n_good: int
    points: np.ndarray
    good: np.ndarray
    parallax_deg: float


def check_motion(
    R: np.ndarray, t: np.ndarray, uv1: np.ndarray, uv2: np.ndarray, inliers: np.ndarray, K: np.ndarray, th2: float
) -> _MotionCheck:
    """ORB-SLAM's CheckRT: triangulate the inliers under motion (R, t) and count good points.

    A point counts when it is finite, in front of both cameras (unless its rays are
    parallel, cos > 0.99998) and reprojects within squared error th2 in both images; it
    is flagged good for the map when its rays also differ (cos < 0.99998).
    """
    n = len(uv1)
    pts = np.full((n, 3), np.nan)
    good = np.zeros(n, dtype=bool)
    idx = np.flatnonzero(inliers)
    if len(idx) == 0:
        return _MotionCheck(0, pts, good, 0.0)
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = K @ np.hstack([R, t.reshape(3, 1)])
    X = triangulate_dlt(P1, P2, uv1[idx], uv2[idx])
    O2 = -R.T @ t
    with np.errstate(invalid="ignore", divide="ignore"):
        finite = np.all(np.isfinite(X), axis=1)
        n1 = np.linalg.norm(X, axis=1)
        n2 = np.linalg.norm(X - O2, axis=1)
        cos_par = np.sum(X * (X - O2), axis=1) / (n1 * n2)
        X2 = X @ R.T + t
        inf_like = cos_par >= COS_PARALLAX_INF
        ok = finite & ((X[:, 2] > 0) | inf_like) & ((X2[:, 2] > 0) | inf_like)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        e1 = (fx * X[:, 0] / X[:, 2] + cx - uv1[idx, 0]) ** 2 + (fy * X[:, 1] / X[:, 2] + cy - uv1[idx, 1]) ** 2
        e2 = (fx * X2[:, 0] / X2[:, 2] + cx - uv2[idx, 0]) ** 2 + (fy * X2[:, 1] / X2[:, 2] + cy - uv2[idx, 1]) ** 2
        ok &= (e1 <= th2) & (e2 <= th2)
    n_good = int(ok.sum())
    pts[idx[ok]] = X[ok]
    good[idx[ok & ~inf_like]] = True
    if n_good > 0:
        cs = np.sort(cos_par[ok])
        parallax = float(np.degrees(np.arccos(np.clip(cs[min(50, len(cs) - 1)], -1.0, 1.0))))
    else:
        parallax = 0.0
    return _MotionCheck(n_good, pts, good, parallax)


def homography_motions(H21: np.ndarray, K: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The 8 (R21, unit t21) motions of Faugeras' homography decomposition (ORB-SLAM ReconstructH).

    Returns an empty list when the singular values are too close (no reliable decomposition).
    """
    A = np.linalg.inv(K) @ H21 @ K
    U, w, Vt = np.linalg.svd(A)
    s = np.linalg.det(U) * np.linalg.det(Vt)
    d1, d2, d3 = w
    if d1 / d2 < 1.00001 or d2 / d3 < 1.00001:
        return []
    aux1 = np.sqrt((d1 * d1 - d2 * d2) / (d1 * d1 - d3 * d3))
    aux3 = np.sqrt((d2 * d2 - d3 * d3) / (d1 * d1 - d3 * d3))
    x1 = [aux1, aux1, -aux1, -aux1]
    x3 = [aux3, -aux3, aux3, -aux3]
    motions = []
    # Case d' = d2.
    aux_st = np.sqrt((d1 * d1 - d2 * d2) * (d2 * d2 - d3 * d3)) / ((d1 + d3) * d2)
    ct = (d2 * d2 + d1 * d3) / ((d1 + d3) * d2)
    for i, st in enumerate([aux_st, -aux_st, -aux_st, aux_st]):
        Rp = np.array([[ct, 0.0, -st], [0.0, 1.0, 0.0], [st, 0.0, ct]])
        tp = np.array([x1[i], 0.0, -x3[i]]) * (d1 - d3)
        t = U @ tp
        motions.append((s * U @ Rp @ Vt, t / np.linalg.norm(t)))
    # Case d' = -d2.
    aux_sp = np.sqrt((d1 * d1 - d2 * d2) * (d2 * d2 - d3 * d3)) / ((d1 - d3) * d2)
    cp = (d1 * d3 - d2 * d2) / ((d1 - d3) * d2)
    for i, sp in enumerate([aux_sp, -aux_sp, -aux_sp, aux_sp]):
        Rp = np.array([[cp, 0.0, sp], [0.0, -1.0, 0.0], [sp, 0.0, -cp]])
        tp = np.array([x1[i], 0.0, x3[i]]) * (d1 + d3)
        t = U @ tp
        motions.append((s * U @ Rp @ Vt, t / np.linalg.norm(t)))
    return motions


class TwoViewInitializer:
    """``initialize(uv1, uv2, K) -> TwoViewResult | None`` over matched pixel pairs."""

    def __init__(self, config: InitializerConfig | None = None) -> None:
        self.config = config or InitializerConfig()

    def initialize(self, uv1: np.ndarray, uv2: np.ndarray, K: np.ndarray) -> TwoViewResult | None:
        """Reconstruct the motion and structure from matched undistorted pixels.

        uv1, uv2: (N, 2) matched undistorted pixel coordinates in images 1 and 2 (the same
        camera K, (3, 3)). Returns None when N < 8 or no reconstruction passes the checks.
        """
        c = self.config
        uv1 = np.asarray(uv1, dtype=np.float64).reshape(-1, 2)
        uv2 = np.asarray(uv2, dtype=np.float64).reshape(-1, 2)
        n = len(uv1)
        if n < 8:
            return None
        rng = np.random.default_rng(c.seed)
        sets = ransac_sets(n, c.ransac_iterations, rng)
        H21, s_h, in_h = find_homography(uv1, uv2, sets, c.sigma)
        F21, s_f, in_f = find_fundamental(uv1, uv2, sets, c.sigma)
        total = s_h + s_f
        rh = s_h / total if total > 0 else 0.0
        log.debug("two-view scores S_H %.1f S_F %.1f R_H %.3f", s_h, s_f, rh)
        th2 = 4.0 * c.sigma * c.sigma
        # The model is chosen on the RANSAC scores; only the chosen one is refined.
        if rh > c.rh_threshold:
            if c.refine and in_h.sum() >= 8:
                H_ref = refine_homography(H21, uv1[in_h], uv2[in_h])
                H21, in_h = self._refined(H21, s_h, in_h, H_ref, score_homographies, uv1, uv2)
            res = self._reconstruct_h(H21, in_h, uv1, uv2, K, th2)
            model, inliers = "H", in_h
        else:
            if c.refine and in_f.sum() >= 8:
                F_ref = refine_fundamental(F21, K, uv1[in_f], uv2[in_f])
                F21, in_f = self._refined(F21, s_f, in_f, F_ref, score_fundamentals, uv1, uv2)
            res = self._reconstruct_f(F21, in_f, uv1, uv2, K, th2)
            model, inliers = "F", in_f
        if res is None:
            return None
        R, t, chk = res
        return TwoViewResult(model, R, t, chk.points, chk.good, chk.parallax_deg, s_h, s_f, rh, inliers)

    def _refined(self, M, score, inliers, M_refined, scorer, uv1, uv2):
        """The refined model and its inliers when it scores at least as well, else the original."""
        if not np.all(np.isfinite(M_refined)):
            return M, inliers
        try:
            s_new, in_new = scorer(M_refined[None], uv1, uv2, self.config.sigma)
        except np.linalg.LinAlgError:  # a singular refined homography
            return M, inliers
        if np.isfinite(s_new[0]) and s_new[0] >= score:
            return M_refined, in_new[0]
        return M, inliers

    def _reconstruct_f(self, F21, inliers, uv1, uv2, K, th2):
        c = self.config
        n_in = int(inliers.sum())
        E21 = K.T @ F21 @ K
        R1, R2, t = decompose_essential(E21)
        motions = [(R1, t), (R2, t), (R1, -t), (R2, -t)]
        checks = [check_motion(R, tt, uv1, uv2, inliers, K, th2) for R, tt in motions]
        goods = np.array([ch.n_good for ch in checks])
        max_good = int(goods.max())
        min_good = max(int(0.9 * n_in), c.min_triangulated)
        n_similar = int(np.sum(goods > 0.7 * max_good))
        if max_good < min_good or n_similar > 1:
            log.debug("F reconstruction rejected: good %s of %d inliers", goods.tolist(), n_in)
            return None
        best = int(np.argmax(goods))
        if checks[best].parallax_deg <= c.min_parallax_deg:
            log.debug("F reconstruction rejected: parallax %.2f deg", checks[best].parallax_deg)
            return None
        R, t = motions[best]
        return R, t, checks[best]

    def _reconstruct_h(self, H21, inliers, uv1, uv2, K, th2):
        c = self.config
        n_in = int(inliers.sum())
        motions = homography_motions(H21, K)
        if not motions:
            return None
        checks = [check_motion(R, t, uv1, uv2, inliers, K, th2) for R, t in motions]
        goods = np.array([ch.n_good for ch in checks])
        order = np.argsort(-goods, kind="stable")
        best, best_good = int(order[0]), int(goods[order[0]])
        second_good = int(goods[order[1]])
        par = checks[best].parallax_deg
        if (
            second_good < 0.75 * best_good
            and par >= c.min_parallax_deg
            and best_good > c.min_triangulated
            and best_good > 0.9 * n_in
        ):
            R, t = motions[best]
            return R, t, checks[best]
        log.debug("H reconstruction rejected: good %s of %d inliers, parallax %.2f", goods.tolist(), n_in, par)
        return None
