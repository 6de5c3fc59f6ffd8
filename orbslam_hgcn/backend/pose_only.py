"""Motion-only bundle adjustment: refine one camera pose against fixed map points.

Follows ORB-SLAM's PoseOptimization (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. V-B;
Optimizer::PoseOptimization in ORB-SLAM2): 4 rounds of up to 10 Levenberg-Marquardt
iterations over the current inlier set; Huber kernel (delta = sqrt(5.991)) in the first two
rounds, none after; after each round every correspondence is re-classified as outlier when
its whitened squared error exceeds the chi-square 95% value 5.991 (or it lies behind the
camera). Fewer than 10 inliers: failure. One deliberate difference: ORB-SLAM restarts each
round from the initial pose, here a round starts from the previous round's estimate, which
reaches the round's minimum in about a quarter fewer iterations.

This runs on every frame, so :func:`optimize_pose` is a vectorised numpy Levenberg-
Marquardt on SE(3) rather than a gtsam graph: building a gtsam graph of 300 factors and
running 4 x 10 iterations through the Python bindings costs several times more per call
(bench/bench_backend.py measures both; see its output). :func:`optimize_pose_gtsam` is the
same scheme through gtsam, kept as the reference the numpy version is checked against.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np

from orbslam_hgcn.backend.projection import reprojection_chi2
from orbslam_hgcn.config import BackendConfig

log = logging.getLogger(__name__)


class PoseResult(NamedTuple):
    """T_cw (4, 4) refined pose; inliers (M,) bool; ok: at least pose_min_inliers inliers."""

    T_cw: np.ndarray
    inliers: np.ndarray
    ok: bool


_I3 = np.eye(3)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """(4, 4) exponential of a twist (6,) = (omega, upsilon) (rotation first)."""
    w0, w1, w2, v0, v1, v2 = (float(t) for t in xi)
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-20:
        a, b, c = 1.0, 0.5, 1.0 / 6.0
    else:
        th = math.sqrt(th2)
        a, b, c = math.sin(th) / th, (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    # W = [w]x, W2 = W @ W = w w^T - th2 I
    W = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    W2 = np.array([
        [-(w1 * w1 + w2 * w2), w0 * w1, w0 * w2],
        [w0 * w1, -(w0 * w0 + w2 * w2), w1 * w2],
        [w0 * w2, w1 * w2, -(w0 * w0 + w1 * w1)],
    ])  # fmt: skip
    T = np.zeros((4, 4))
    T[:3, :3] = _I3 + a * W + b * W2
    T[:3, 3] = (_I3 + b * W + c * W2) @ (v0, v1, v2)
    T[3, 3] = 1.0
    return T


class _Problem:
    """One round's correspondences, laid out for :func:`_levenberg_marquardt`: XT (3, M)
    world points, obs (2M,) observed u then v, info2 (2M,) their information."""

    def __init__(self, X: np.ndarray, uv: np.ndarray, info: np.ndarray, K: np.ndarray) -> None:
        self.XT = np.ascontiguousarray(X.T)
        self.obs = np.concatenate([uv[:, 0], uv[:, 1]])
        self.info = info
        self.info2 = np.concatenate([info, info])
        self.fx, self.fy, self.cx, self.cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        self.M = len(info)

    def residuals(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(2M,) residuals e = obs - project(T X) (u rows, then v rows) and (3, M) the
        normalised coordinates x/z, y/z and 1/z. Depths of exactly 0 are nudged to 1e-12
        (points behind the camera keep their meaningless error, as in g2o; the outlier
        test after each round rejects them)."""
        Xc = T[:3, :3] @ self.XT + T[:3, 3:4]
        z = Xc[2]
        if not np.all(z):
            z[z == 0.0] = 1e-12
        np.divide(1.0, z, out=z)  # Xc rows: x, y, 1/z
        Xc[:2] *= z
        e = np.empty(2 * self.M)
        M = self.M
        np.multiply(Xc[0], -self.fx, out=e[:M])
        np.multiply(Xc[1], -self.fy, out=e[M:])
        e += self.obs
        e[:M] -= self.cx
        e[M:] -= self.cy
        return e, Xc

    def cost(self, e: np.ndarray, delta: float | None) -> float:
        """Sum of Huber-robust (or plain, delta None) whitened squared errors.

        Huber rho(s) = s - max(sqrt(s) - delta, 0) ** 2 equals s inside and 2 delta sqrt(s) -
        delta ** 2 outside, without a branch."""
        M = self.M
        e2 = e * e
        chi2 = self.info * (e2[:M] + e2[M:])
        total = float(chi2.sum())
        if delta is not None:
            d = np.sqrt(chi2) - delta
            np.maximum(d, 0.0, out=d)
            total -= float(d @ d)
        return total

    def jacobian(self, n: np.ndarray) -> np.ndarray:
        """(6, 2M) Jacobian rows of e for u then v, with respect to a left perturbation
        d = (omega, upsilon) of T; n (3, M) from :meth:`residuals`."""
        xz, yz, iz = n
        fx, fy, M = self.fx, self.fy, self.M
        J = np.empty((6, 2 * M))
        Ju, Jv = J[:, :M], J[:, M:]
        fxz, fyz = fx * xz, fy * yz
        np.multiply(fxz, yz, out=Ju[0])
        np.multiply(fxz, xz, out=Ju[1])
        Ju[1] += fx
        Ju[1] *= -1.0
        np.multiply(yz, fx, out=Ju[2])
        np.multiply(iz, -fx, out=Ju[3])
        Ju[4] = 0.0
        np.multiply(fxz, iz, out=Ju[5])
        np.multiply(fyz, yz, out=Jv[0])
        Jv[0] += fy
        np.multiply(fyz, xz, out=Jv[1])
        Jv[1] *= -1.0
        np.multiply(xz, -fy, out=Jv[2])
        Jv[3] = 0.0
        np.multiply(iz, -fy, out=Jv[4])
        np.multiply(fyz, iz, out=Jv[5])
        return J


def _levenberg_marquardt(
    T0: np.ndarray, X: np.ndarray, uv: np.ndarray, info: np.ndarray, K: np.ndarray, iters: int, delta: float | None
) -> np.ndarray:
    """g2o-style LM (Nielsen damping update, up to 10 tries per iteration) with IRLS Huber
    weights; stops early once a step changes the cost by less than 1e-10 relative."""
    p = _Problem(X, uv, info, K)
    T = T0.copy()
    e, n = p.residuals(T)
    cost = p.cost(e, delta)
    lam, nu = None, 2.0
    eye6 = np.eye(6)
    for _ in range(iters):
        J = p.jacobian(n)
        if delta is not None:
            # IRLS weight of the Huber kernel: 1 inside, delta / |e| outside.
            e2 = e * e
            r = np.sqrt(p.info * (e2[: p.M] + e2[p.M :]))
            w = p.info * (delta / np.maximum(r, delta))
            w = np.concatenate([w, w])
        else:
            w = p.info2
        Jw = J * w
        H = Jw @ J.T
        g = Jw @ e
        if lam is None:
            lam = 1e-5 * float(H.diagonal().max())
        accepted = False
        for _try in range(10):
            dx = np.linalg.solve(H + lam * eye6, -g)
            gain = float(dx @ (lam * dx - g))
            if gain <= 1e-12 * max(cost, 1e-300):
                break  # converged: no step can lower the cost measurably
            T_new = se3_exp(dx) @ T
            e_new, n_new = p.residuals(T_new)
            new_cost = p.cost(e_new, delta)
            rho = (cost - new_cost) / (gain + 1e-3)
            if rho > 0 and math.isfinite(new_cost):
                accepted = True
                break
            lam *= nu
            nu *= 2.0
        if not accepted:
            break
        decrease = cost - new_cost
        T, cost, e, n = T_new, new_cost, e_new, n_new
        lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        nu = 2.0
        if decrease <= 1e-10 * cost:
            break
    return T


def optimize_pose(
    T_cw_init: np.ndarray,
    points_w: np.ndarray,
    uv: np.ndarray,
    inv_sigma2: np.ndarray,
    K: np.ndarray,
    config: BackendConfig | None = None,
) -> PoseResult:
    """Refine a camera pose from 2D-3D correspondences, rejecting outliers.

    T_cw_init: (4, 4) initial world-to-camera pose; points_w: (M, 3) fixed map points;
    uv: (M, 2) undistorted observations in pixels; inv_sigma2: (M,) information of each
    observation (1 / scale_factor ** (2 octave)); K: (3, 3) intrinsics.
    Returns PoseResult(T_cw, inliers (M,) bool, ok).
    """
    cfg = config or BackendConfig()
    T0 = np.asarray(T_cw_init, dtype=np.float64).reshape(4, 4)
    X = np.asarray(points_w, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    info = np.asarray(inv_sigma2, dtype=np.float64).reshape(-1)
    K = np.asarray(K, dtype=np.float64)
    inlier = np.ones(len(X), dtype=bool)
    if len(X) < 3:
        return PoseResult(T0.copy(), np.zeros(len(X), dtype=bool), False)
    delta = float(np.sqrt(cfg.chi2_mono))
    T = T0
    for r in range(cfg.pose_rounds):
        act = np.flatnonzero(inlier)
        if len(act) < 3:
            break
        robust = delta if r < cfg.pose_robust_rounds else None
        T = _levenberg_marquardt(T, X[act], uv[act], info[act], K, cfg.pose_iterations, robust)
        chi2, _ = reprojection_chi2(T, X, uv, info, K)
        inlier = chi2 <= cfg.chi2_mono
    n_in = int(inlier.sum())
    return PoseResult(T, inlier, n_in >= cfg.pose_min_inliers)


def optimize_pose_gtsam(
    T_cw_init: np.ndarray,
    points_w: np.ndarray,
    uv: np.ndarray,
    inv_sigma2: np.ndarray,
    K: np.ndarray,
    config: BackendConfig | None = None,
) -> PoseResult:
    """:func:`optimize_pose` through a gtsam factor graph (reference and benchmark).

    The pose variable is gtsam's camera pose T_wc; each map point is a variable pinned by a
    PriorFactorPoint3 of sigma 1e-6 (NonlinearEqualityPoint3 is several times slower),
    observed by GenericProjectionFactorCal3_S2 factors (inserted per octave with
    gtsam.utilities.insertProjectionFactors) with a Huber-robust isotropic noise model
    (sigma = 1 / sqrt(inv_sigma2)).
    """
    import gtsam

    from orbslam_hgcn.geometry.se3 import inv_T

    cfg = config or BackendConfig()
    T0 = np.asarray(T_cw_init, dtype=np.float64).reshape(4, 4)
    X = np.asarray(points_w, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    info = np.asarray(inv_sigma2, dtype=np.float64).reshape(-1)
    cal = gtsam.Cal3_S2(K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2])
    delta = float(np.sqrt(cfg.chi2_mono))
    pinned = gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)
    inlier = np.ones(len(X), dtype=bool)
    T = T0
    if len(X) < 3:
        return PoseResult(T0.copy(), np.zeros(len(X), dtype=bool), False)
    for r in range(cfg.pose_rounds):
        act = np.flatnonzero(inlier)
        if len(act) < 3:
            break
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        values.insert(0, gtsam.Pose3(inv_T(T)))
        for j in act:
            values.insertPoint3(1 + int(j), X[j])
            graph.add(gtsam.PriorFactorPoint3(1 + int(j), X[j], pinned))
        levels, level_idx = np.unique(info[act], return_inverse=True)
        for lv, s in enumerate(levels):
            model = gtsam.noiseModel.Isotropic.Sigma(2, 1.0 / np.sqrt(s))
            if r < cfg.pose_robust_rounds:
                model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(delta), model)
            sel = act[level_idx == lv]
            gtsam.utilities.insertProjectionFactors(
                graph, 0, (1 + sel).astype(np.float64), np.ascontiguousarray(uv[sel].T), model, cal
            )
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(cfg.pose_iterations)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        T = inv_T(result.atPose3(0).matrix())
        chi2, _ = reprojection_chi2(T, X, uv, info, K)
        inlier = chi2 <= cfg.chi2_mono
    return PoseResult(T, inlier, int(inlier.sum()) >= cfg.pose_min_inliers)
