"""Bundle adjustment with gtsam: local BA, global BA and the two-view BA of initialisation.

The schemes follow ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. VI-D and IV;
Optimizer.cc of ORB-SLAM2): monocular projection factors whitened by the keypoint's octave
(sigma = scale_factor ** octave pixels) with a Huber kernel of delta = sqrt(5.991); local BA
runs 5 robust iterations, drops observations whose whitened squared error exceeds 5.991 or
that lie behind their camera, runs 10 more iterations without kernel, and reports every
observation failing the same test as an outlier for the caller to erase.

gtsam layout: camera poses are gtsam Pose3 variables holding T_wc (gtsam's camera pose
convention) under keys 0..K-1; points are Point3 variables under keys K..K+P-1; a fixed
pose is a variable pinned by a PriorFactorPose3 of sigma 1e-6 (its input value is returned
unchanged). Factors are inserted in bulk with
gtsam.utilities.insertProjectionFactors (one call per keyframe and octave).

gtsam keeps the GIL while it iterates; LM is therefore driven one iteration at a time from
Python (LevenbergMarquardtOptimizer.iterate) so a time budget or stop request is honoured
between iterations and other threads get the interpreter there.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from orbslam_hgcn.backend.problem import BAProblem, BAResult, as_problem
from orbslam_hgcn.backend.projection import reprojection_chi2
from orbslam_hgcn.backend.schur_ba import schur_bundle_adjustment
from orbslam_hgcn.config import BackendConfig
from orbslam_hgcn.geometry.se3 import inv_T

# gtsam is imported inside the functions that solve with it: a run that never does (no loop,
# local BA compiled) does not spend its start-up importing it.
if TYPE_CHECKING:
    import gtsam

log = logging.getLogger(__name__)

# A fixed pose is pinned by a prior this tight (sigma); NonlinearEqualityPose3 (a constrained
# noise model) makes every elimination about ten times slower in gtsam 4.3.
_FIXED_POSE_SIGMA = 1e-6


def observation_chi2(
    T_cw: np.ndarray, points: np.ndarray, obs_kf: np.ndarray, obs_pt: np.ndarray, uv: np.ndarray, inv_sigma2: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """((O,) whitened squared reprojection error, (O,) depth) of every observation."""
    return reprojection_chi2(T_cw[obs_kf], points[obs_pt], uv, inv_sigma2, K)


def _run_lm(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    iterations: int,
    deadline: float | None,
    should_stop: Callable[[], bool] | None,
    ordering: gtsam.Ordering | None = None,
) -> gtsam.Values | None:
    """Levenberg-Marquardt one iteration at a time, with gtsam's default convergence test
    (relative or absolute error decrease below 1e-5). None when stopped before the first.
    ordering: elimination order (None: gtsam's COLAMD)."""
    import gtsam
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    if ordering is not None:
        params.setOrdering(ordering)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    err = opt.error()
    done = 0
    for _ in range(iterations):
        if (deadline is not None and time.perf_counter() > deadline) or (should_stop is not None and should_stop()):
            break
        opt.iterate()
        done += 1
        new = opt.error()
        if err - new <= 1e-5 or err - new <= 1e-5 * err:
            break
        err = new
    return opt.values() if done else None


def _optimise(
    p: BAProblem,
    active: np.ndarray,
    robust: bool,
    iterations: int,
    cfg: BackendConfig,
    deadline: float | None,
    should_stop: Callable[[], bool] | None,
) -> tuple[np.ndarray, np.ndarray]:
    """One LM run over the active observations; returns updated (T_cw, points)."""
    import gtsam
    n_kf, n_pt = len(p.T_cw), len(p.points)
    T_cw, points = p.T_cw.copy(), p.points.copy()
    # Points need two active observations to be determined; poses need at least one.
    pt_count = np.bincount(p.obs_pt[active], minlength=n_pt)
    use = active & (pt_count[p.obs_pt] >= 2)
    if not use.any():
        return T_cw, points
    kf_used = np.zeros(n_kf, dtype=bool)
    kf_used[p.obs_kf[use]] = True
    pt_used = np.flatnonzero(np.bincount(p.obs_pt[use], minlength=n_pt) > 0)
    fixed_noise = gtsam.noiseModel.Isotropic.Sigma(6, _FIXED_POSE_SIGMA)
    cal = gtsam.Cal3_S2(p.K[0, 0], p.K[1, 1], 0.0, p.K[0, 2], p.K[1, 2])
    delta = float(np.sqrt(cfg.chi2_mono))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for i in np.flatnonzero(kf_used):
        pose = gtsam.Pose3(inv_T(T_cw[i]))
        values.insert(int(i), pose)
        if p.fixed[i]:
            graph.add(gtsam.PriorFactorPose3(int(i), pose, fixed_noise))
    for j in pt_used:
        values.insertPoint3(int(n_kf + j), points[j])
    o_kf, o_pt, uv, info = p.obs_kf[use], p.obs_pt[use], p.uv[use], p.inv_sigma2[use]
    levels, level_idx = np.unique(info, return_inverse=True)
    models = []
    for s in levels:
        base = gtsam.noiseModel.Isotropic.Sigma(2, 1.0 / np.sqrt(s))
        if robust:
            base = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(delta), base)
        models.append(base)
    group = o_kf * len(levels) + level_idx
    order = np.argsort(group, kind="stable")
    bounds = np.flatnonzero(np.diff(group[order])) + 1
    for sel in np.split(order, bounds):
        i, lv = int(o_kf[sel[0]]), int(level_idx[sel[0]])
        keys = (n_kf + o_pt[sel]).astype(np.float64)
        gtsam.utilities.insertProjectionFactors(graph, i, keys, np.ascontiguousarray(uv[sel].T), models[lv], cal)
    # Points first, then poses: eliminating every point leaves the reduced camera system of
    # the Schur complement (Triggs et al., "Bundle adjustment - a modern synthesis", 2000),
    # about a third faster than COLAMD's order on local-BA windows.
    ordering = gtsam.Ordering()
    for j in pt_used.tolist():
        ordering.push_back(n_kf + j)
    for i in np.flatnonzero(kf_used).tolist():
        ordering.push_back(i)
    result = _run_lm(graph, values, iterations, deadline, should_stop, ordering)
    if result is None:
        return T_cw, points
    for i in np.flatnonzero(kf_used & ~p.fixed):
        T_cw[i] = inv_T(result.atPose3(int(i)).matrix())
    points[pt_used] = gtsam.utilities.extractPoint3(result)
    return T_cw, points


def bundle_adjustment(
    T_cw: np.ndarray,
    fixed: np.ndarray,
    points: np.ndarray,
    obs_kf: np.ndarray,
    obs_pt: np.ndarray,
    uv: np.ndarray,
    inv_sigma2: np.ndarray,
    K: np.ndarray,
    iterations: int,
    refine_iterations: int = 0,
    robust: bool = True,
    config: BackendConfig | None = None,
    should_stop: Callable[[], bool] | None = None,
    stop_first: bool = True,
) -> BAResult:
    """Jointly refine keyframe poses and points from their observations.

    T_cw: (K, 4, 4) world-to-camera poses; fixed: (K,) bool poses held constant;
    points: (P, 3) world points; obs_kf, obs_pt: (O,) int rows into T_cw and points;
    uv: (O, 2) undistorted pixel observations; inv_sigma2: (O,) their information;
    K: (3, 3) intrinsics. Runs ``iterations`` LM iterations (Huber kernel if ``robust``);
    with ``refine_iterations`` > 0, then excludes outliers and runs that many more without
    kernel (ORB-SLAM local BA). ``should_stop`` is polled between iterations (ORB-SLAM's
    abort flag), from the refining iterations on when ``stop_first`` is False;
    BackendConfig.ba_time_budget_s caps the wall time.
    Returns BAResult(T_cw, points, outlier (O,) bool).
    """
    cfg = config or BackendConfig()
    p = as_problem(T_cw, fixed, points, obs_kf, obs_pt, uv, inv_sigma2, K)
    if len(p.fixed) != len(p.T_cw):
        raise ValueError("fixed must have one flag per pose")
    deadline = time.perf_counter() + cfg.ba_time_budget_s if cfg.ba_time_budget_s > 0 else None
    active = np.ones(len(p.obs_kf), dtype=bool)
    T_new, X_new = _optimise(p, active, robust, iterations, cfg, deadline, should_stop if stop_first else None)
    if refine_iterations > 0:
        chi2, z = observation_chi2(T_new, X_new, p.obs_kf, p.obs_pt, p.uv, p.inv_sigma2, p.K)
        active = (chi2 <= cfg.chi2_mono) & (z > 0)
        p = p._replace(T_cw=T_new, points=X_new)
        T_new, X_new = _optimise(p, active, False, refine_iterations, cfg, deadline, should_stop)
    chi2, z = observation_chi2(T_new, X_new, p.obs_kf, p.obs_pt, p.uv, p.inv_sigma2, p.K)
    return BAResult(T_new, X_new, (chi2 > cfg.chi2_mono) | (z <= 0))


def local_bundle_adjustment(
    T_cw, fixed, points, obs_kf, obs_pt, uv, inv_sigma2, K, config: BackendConfig | None = None, should_stop=None
) -> BAResult:
    """ORB-SLAM local BA: robust iterations, outliers out, refining iterations (see
    :func:`bundle_adjustment` for the arrays; counts from BackendConfig, and whether
    ``should_stop`` may end the robust iterations: ``local_ba_abort_robust``), solved by
    the compiled Schur-complement LM or through gtsam (``local_ba_solver``)."""
    cfg = config or BackendConfig()
    solve = schur_bundle_adjustment if cfg.local_ba_solver == "schur" else bundle_adjustment
    return solve(
        T_cw, fixed, points, obs_kf, obs_pt, uv, inv_sigma2, K,
        iterations=cfg.local_ba_iterations, refine_iterations=cfg.local_ba_refine_iterations,
        robust=True, config=cfg, should_stop=should_stop, stop_first=cfg.local_ba_abort_robust,
    )  # fmt: skip


def global_bundle_adjustment(
    T_cw, fixed, points, obs_kf, obs_pt, uv, inv_sigma2, K, iterations: int | None = None,
    config: BackendConfig | None = None, should_stop=None,
) -> BAResult:  # fmt: skip
    """ORB-SLAM global BA: every keyframe and point, Huber kernel, no outlier stage; fix at
    least the origin keyframe (the monocular scale gauge is left to the damping, as there)."""
    cfg = config or BackendConfig()
    it = cfg.global_ba_iterations if iterations is None else iterations
    return bundle_adjustment(
        T_cw, fixed, points, obs_kf, obs_pt, uv, inv_sigma2, K,
        iterations=it, robust=True, config=cfg, should_stop=should_stop,
    )  # fmt: skip


def two_view_bundle_adjustment(
    T_cw_1: np.ndarray, T_cw_2: np.ndarray, points: np.ndarray, uv_1: np.ndarray, uv_2: np.ndarray,
    inv_sigma2_1: np.ndarray, inv_sigma2_2: np.ndarray, K: np.ndarray, config: BackendConfig | None = None,
) -> BAResult:  # fmt: skip
    """Global BA of the initial map: two keyframes, the first fixed, every point seen in both.

    T_cw_1, T_cw_2: (4, 4); points: (P, 3); uv_1, uv_2: (P, 2) observations in each view;
    inv_sigma2_1/2: (P,). Returns BAResult with T_cw (2, 4, 4) and outlier (2P,) ordered as
    all view-1 observations, then all view-2 observations.
    """
    cfg = config or BackendConfig()
    n = len(points)
    idx = np.arange(n)
    return bundle_adjustment(
        np.stack([T_cw_1, T_cw_2]), np.array([True, False]), points,
        np.r_[np.zeros(n, dtype=np.int64), np.ones(n, dtype=np.int64)], np.r_[idx, idx],
        np.vstack([uv_1, uv_2]), np.r_[inv_sigma2_1, inv_sigma2_2], K,
        iterations=cfg.two_view_ba_iterations, robust=True, config=cfg,
    )  # fmt: skip
