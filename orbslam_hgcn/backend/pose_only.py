"""Motion-only bundle adjustment: refine one camera pose against fixed map points.

Follows ORB-SLAM's PoseOptimization (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. V-B;
Optimizer::PoseOptimization in ORB-SLAM2): 4 rounds of up to 10 Levenberg-Marquardt
iterations over the current inlier set; Huber kernel (delta = sqrt(5.991)) in the first two
rounds, none after; after each round every correspondence is re-classified as outlier when
its whitened squared error exceeds the chi-square 95% value 5.991 (or it lies behind the
camera). Fewer than 10 inliers: failure. One deliberate difference: ORB-SLAM restarts each
round from the initial pose, here a round starts from the previous round's estimate, which
reaches the round's minimum in about a quarter fewer iterations.

This runs twice on every frame, on 100-1000 correspondences, so :func:`optimize_pose` is
compiled with numba: the whole scheme (rounds, LM iterations, Huber weights, outlier test)
is one loop over the correspondences per step, without the GIL. As numpy over whole
arrays it cost 3.9 ms per call on 300 points, nearly all of it in the overhead of about 40
numpy calls per iteration on small arrays; compiled it costs 0.4 ms and gives the same
poses to 1e-15 (bench/bench_backend.py prints the figure). A gtsam graph of the same
problem costs several times more again (building 300 factors through the bindings):
:func:`optimize_pose_gtsam` is the same scheme through gtsam, kept as the reference the
compiled version is checked against (compile and cache: :mod:`orbslam_hgcn.compiled`).
"""

from __future__ import annotations

import logging
import math
import time
from typing import NamedTuple

import numpy as np

from orbslam_hgcn.backend.projection import reprojection_chi2
from orbslam_hgcn.compiled import jit
from orbslam_hgcn.config import BackendConfig

log = logging.getLogger(__name__)


class PoseResult(NamedTuple):
    """T_cw (4, 4) refined pose; inliers (M,) bool; ok: at least pose_min_inliers inliers."""

    T_cw: np.ndarray
    inliers: np.ndarray
    ok: bool


@jit
def se3_exp(xi: np.ndarray) -> np.ndarray:
    """(4, 4) exponential of a twist (6,) = (omega, upsilon) (rotation first)."""
    w0, w1, w2, v0, v1, v2 = xi[0], xi[1], xi[2], xi[3], xi[4], xi[5]
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-20:
        a, b, c = 1.0, 0.5, 1.0 / 6.0
    else:
        th = math.sqrt(th2)
        a, b, c = math.sin(th) / th, (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    # W = [w]x, W2 = W @ W = w w^T - th2 I; R = I + a W + b W2, t = (I + b W + c W2) v.
    W = np.zeros((3, 3))
    W[0, 1], W[0, 2], W[1, 0], W[1, 2], W[2, 0], W[2, 1] = -w2, w1, w2, -w0, -w1, w0
    W2 = np.empty((3, 3))
    W2[0, 0], W2[0, 1], W2[0, 2] = -(w1 * w1 + w2 * w2), w0 * w1, w0 * w2
    W2[1, 0], W2[1, 1], W2[1, 2] = w0 * w1, -(w0 * w0 + w2 * w2), w1 * w2
    W2[2, 0], W2[2, 1], W2[2, 2] = w0 * w2, w1 * w2, -(w0 * w0 + w1 * w1)
    v = (v0, v1, v2)
    T = np.zeros((4, 4))
    T[3, 3] = 1.0
    for i in range(3):
        for k in range(3):
            eye = 1.0 if i == k else 0.0
            T[i, k] = eye + a * W[i, k] + b * W2[i, k]
            T[i, 3] += (eye + b * W[i, k] + c * W2[i, k]) * v[k]
    return T


@jit
def se3_compose(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(4, 4) A @ B of two rigid transforms (compiled; also the pose update of :mod:`.schur_ba`)."""
    out = np.zeros((4, 4))
    out[3, 3] = 1.0
    for i in range(3):
        for j in range(4):
            acc = A[i, 3] if j == 3 else 0.0
            for k in range(3):
                acc += A[i, k] * B[k, j]
            out[i, j] = acc
    return out


@jit
def _solve_spd6(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(6,) x with A x = b, A (6, 6) symmetric positive definite (Cholesky)."""
    L = np.zeros((6, 6))
    for i in range(6):
        for j in range(i + 1):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                L[i, i] = math.sqrt(s) if s > 0.0 else 1e-300
            else:
                L[i, j] = s / L[j, j]
    y = np.empty(6)
    for i in range(6):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    x = np.empty(6)
    for i in range(5, -1, -1):
        s = y[i]
        for k in range(i + 1, 6):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return x


@jit
def _error(T, X, uv, j, fx, fy, cx, cy):
    """Residual (u, v) = observed - projected of correspondence j, and x/z, y/z, 1/z.
    Depths of exactly 0 are nudged to 1e-12 (points behind the camera keep their
    meaningless error, as in g2o; the outlier test after each round rejects them)."""
    x = T[0, 0] * X[j, 0] + T[0, 1] * X[j, 1] + T[0, 2] * X[j, 2] + T[0, 3]
    y = T[1, 0] * X[j, 0] + T[1, 1] * X[j, 1] + T[1, 2] * X[j, 2] + T[1, 3]
    z = T[2, 0] * X[j, 0] + T[2, 1] * X[j, 1] + T[2, 2] * X[j, 2] + T[2, 3]
    if z == 0.0:
        z = 1e-12
    iz = 1.0 / z
    xz, yz = x * iz, y * iz
    return uv[j, 0] - fx * xz - cx, uv[j, 1] - fy * yz - cy, xz, yz, iz


@jit
def _cost(T, X, uv, info, act, fx, fy, cx, cy, delta, robust):
    """Sum over ``act`` of the Huber-robust (robust False: plain) whitened squared errors.
    Huber rho(s) = s - max(sqrt(s) - delta, 0) ** 2."""
    total = 0.0
    for j in act:
        eu, ev, _, _, _ = _error(T, X, uv, j, fx, fy, cx, cy)
        s = info[j] * (eu * eu + ev * ev)
        if robust:
            d = math.sqrt(s) - delta
            if d > 0.0:
                s -= d * d
        total += s
    return total


@jit
def _levenberg_marquardt(T0, X, uv, info, act, fx, fy, cx, cy, iters, delta, robust):
    """g2o-style LM over the correspondences ``act`` (Nielsen damping update, up to 10 tries
    per iteration) with IRLS Huber weights; stops early once a step changes the cost by
    less than 1e-10 relative. The Jacobian is taken for a left perturbation
    (omega, upsilon) of T."""
    T = T0.copy()
    cost = _cost(T, X, uv, info, act, fx, fy, cx, cy, delta, robust)
    lam, nu = -1.0, 2.0
    H, g = np.empty((6, 6)), np.empty(6)
    ju, jv = np.empty(6), np.empty(6)
    for _ in range(iters):
        H[:], g[:] = 0.0, 0.0
        for j in act:
            eu, ev, xz, yz, iz = _error(T, X, uv, j, fx, fy, cx, cy)
            w = info[j]
            if robust:  # IRLS weight of the Huber kernel: 1 inside, delta / |e| outside
                w *= delta / max(math.sqrt(w * (eu * eu + ev * ev)), delta)
            fxz, fyz = fx * xz, fy * yz
            ju[0], ju[1], ju[2] = fxz * yz, -(fxz * xz + fx), fx * yz
            ju[3], ju[4], ju[5] = -fx * iz, 0.0, fxz * iz
            jv[0], jv[1], jv[2] = fyz * yz + fy, -fyz * xz, -fy * xz
            jv[3], jv[4], jv[5] = 0.0, -fy * iz, fyz * iz
            for a in range(6):
                g[a] += w * (ju[a] * eu + jv[a] * ev)
                for b in range(a, 6):
                    H[a, b] += w * (ju[a] * ju[b] + jv[a] * jv[b])
        for a in range(6):
            for b in range(a):
                H[a, b] = H[b, a]
        if lam < 0.0:
            lam = 1e-5 * max([H[a, a] for a in range(6)])
        accepted, new_cost, rho, T_new = False, cost, 0.0, T
        for _try in range(10):
            A = H.copy()
            for a in range(6):
                A[a, a] += lam
            dx = _solve_spd6(A, -g)
            gain = 0.0
            for a in range(6):
                gain += dx[a] * (lam * dx[a] - g[a])
            if gain <= 1e-12 * max(cost, 1e-300):
                break  # converged: no step can lower the cost measurably
            T_new = se3_compose(se3_exp(dx), T)
            new_cost = _cost(T_new, X, uv, info, act, fx, fy, cx, cy, delta, robust)
            rho = (cost - new_cost) / (gain + 1e-3)
            if rho > 0.0 and math.isfinite(new_cost):
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


@jit
def _optimize(T0, X, uv, info, K, rounds, iters, robust_rounds, chi2_th):
    """The rounds of :func:`optimize_pose`: (T_cw (4, 4), inliers (M,) bool)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    delta = math.sqrt(chi2_th)
    inlier = np.ones(len(X), dtype=np.bool_)
    T = T0.copy()
    for r in range(rounds):
        act = np.flatnonzero(inlier)
        if len(act) < 3:
            break
        T = _levenberg_marquardt(T, X, uv, info, act, fx, fy, cx, cy, iters, delta, r < robust_rounds)
        for j in range(len(X)):  # chi2 test; a point at depth <= 0 is an outlier
            eu, ev, _, _, _ = _error(T, X, uv, j, fx, fy, cx, cy)
            z = T[2, 0] * X[j, 0] + T[2, 1] * X[j, 1] + T[2, 2] * X[j, 2] + T[2, 3]
            inlier[j] = z > 0.0 and info[j] * (eu * eu + ev * ev) <= chi2_th
    return T, inlier


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
    if len(X) < 3:
        return PoseResult(T0.copy(), np.zeros(len(X), dtype=bool), False)
    T, inlier = _optimize(
        T0, np.ascontiguousarray(X), np.ascontiguousarray(uv), np.ascontiguousarray(info), np.ascontiguousarray(K),
        cfg.pose_rounds, cfg.pose_iterations, cfg.pose_robust_rounds, float(cfg.chi2_mono),
    )  # fmt: skip
    return PoseResult(T, inlier, int(inlier.sum()) >= cfg.pose_min_inliers)


def warm_up() -> float:
    """Compile (first use after an install) or load from numba's cache the kernels of
    :func:`optimize_pose`, on a tiny problem with the argument types of a real one; returns
    the seconds it took."""
    t0 = time.perf_counter()
    uv = np.array([[20.0, 30.0], [60.0, 40.0], [45.0, 70.0], [75.0, 75.0]])
    X = np.column_stack([(uv - 50.0) / 100.0 * 2.0, np.full(len(uv), 2.0)])
    K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])
    optimize_pose(np.eye(4), X, uv, np.ones(len(uv)), K)
    return time.perf_counter() - t0


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
