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
    w, v = xi[:3], xi[3:]
    th2 = float(w @ w)
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    W2 = W @ W
    if th2 < 1e-20:
        a, b, c = 1.0, 0.5, 1.0 / 6.0
    else:
        th = np.sqrt(th2)
        a, b, c = np.sin(th) / th, (1.0 - np.cos(th)) / th2, (th - np.sin(th)) / (th2 * th)
    T = np.zeros((4, 4))
    T[:3, :3] = _I3 + a * W + b * W2
    T[:3, 3] = (_I3 + b * W + c * W2) @ v
    T[3, 3] = 1.0
    return T


def _camera_points(T: np.ndarray, XT: np.ndarray) -> np.ndarray:
    """(3, M) camera-frame coordinates of (3, M) world points; depths of exactly 0 are
    nudged to 1e-12 (points behind the camera keep their meaningless projection error, as
    in g2o; the outlier test after each round rejects them)."""
    Xc = T[:3, :3] @ XT + T[:3, 3:4]
    z = Xc[2]
    if not np.all(z):
        z[z == 0.0] = 1e-12
    return Xc


def _linearise(T: np.ndarray, XT: np.ndarray, obs: np.ndarray, fx: float, fy: float, cx: float, cy: float):
    """Residual rows eu, ev (M,) and Jacobian rows Ju, Jv (6, M) of e = obs - project(exp(d) T X),
    d = (omega, upsilon) a left perturbation of T; XT (3, M) world points, obs (2, M) pixels."""
    x, y, z = _camera_points(T, XT)
    iz = 1.0 / z
    xz, yz = x * iz, y * iz
    eu = obs[0] - (fx * xz + cx)
    ev = obs[1] - (fy * yz + cy)
    M = XT.shape[1]
    Ju = np.empty((6, M))
    Jv = np.empty((6, M))
    fxz, fyz = fx * xz, fy * yz
    Ju[0] = fxz * yz
    Ju[1] = -fx - fxz * xz
    Ju[2] = fx * yz
    Ju[3] = -fx * iz
    Ju[4] = 0.0
    Ju[5] = fxz * iz
    Jv[0] = fy + fyz * yz
    Jv[1] = -fyz * xz
    Jv[2] = -fy * xz
    Jv[3] = 0.0
    Jv[4] = -fy * iz
    Jv[5] = fyz * iz
    return eu, ev, Ju, Jv


def _cost(T, XT, obs, info, fx, fy, cx, cy, delta) -> float:
    """Sum of Huber-robust (or plain, delta None) whitened squared errors.

    Huber rho(s) = s - max(sqrt(s) - delta, 0) ** 2 equals s inside and 2 delta sqrt(s) -
    delta ** 2 outside, without a branch."""
    x, y, z = _camera_points(T, XT)
    du = obs[0] - (fx * x / z + cx)
    dv = obs[1] - (fy * y / z + cy)
    chi2 = info * (du * du + dv * dv)
    total = float(chi2.sum())
    if delta is not None:
        d = np.sqrt(chi2) - delta
        np.maximum(d, 0.0, out=d)
        total -= float(d @ d)
    return total


def _levenberg_marquardt(
    T0: np.ndarray, X: np.ndarray, uv: np.ndarray, info: np.ndarray, K: np.ndarray, iters: int, delta: float | None
) -> np.ndarray:
    """g2o-style LM (Nielsen damping update, up to 10 tries per iteration) with IRLS Huber
    weights; stops early once a step changes the cost by less than 1e-10 relative."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    XT = np.ascontiguousarray(X.T)
    obs = np.ascontiguousarray(uv.T)
    T = T0.copy()
    cost = _cost(T, XT, obs, info, fx, fy, cx, cy, delta)
    lam, nu = None, 2.0
    eye6 = np.eye(6)
    for _ in range(iters):
        eu, ev, Ju, Jv = _linearise(T, XT, obs, fx, fy, cx, cy)
        if delta is not None:
            # IRLS weight of the Huber kernel: 1 inside, delta / |e| outside.
            w = info * (delta / np.maximum(np.sqrt(info * (eu * eu + ev * ev)), delta))
        else:
            w = info
        Juw, Jvw = Ju * w, Jv * w
        H = Juw @ Ju.T + Jvw @ Jv.T
        g = Juw @ eu + Jvw @ ev
        if lam is None:
            lam = 1e-5 * float(H.diagonal().max())
        accepted = False
        for _try in range(10):
            dx = np.linalg.solve(H + lam * eye6, -g)
            gain = float(dx @ (lam * dx - g))
            if gain <= 1e-12 * max(cost, 1e-300):
                break  # converged: no step can lower the cost measurably
            T_new = se3_exp(dx) @ T
            new_cost = _cost(T_new, XT, obs, info, fx, fy, cx, cy, delta)
            rho = (cost - new_cost) / (gain + 1e-3)
            if rho > 0 and np.isfinite(new_cost):
                accepted = True
                break
            lam *= nu
            nu *= 2.0
        if not accepted:
            break
        decrease = cost - new_cost
        T, cost = T_new, new_cost
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
