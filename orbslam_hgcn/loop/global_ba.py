"""Global bundle adjustment after a loop correction, and the propagation of its result to
keyframes and points created while it ran (ORB-SLAM2 LoopClosing::RunGlobalBundleAdjustment;
Mur-Artal & Tardos, T-RO 2017).

The problem is cut from the map (every good keyframe and point, the origin keyframe fixed)
and solved with gtsam without holding the map lock. Writing back, the keyframes of the
problem take their optimised pose; a keyframe added meanwhile follows its spanning-tree
parent (its pose relative to the parent is kept), and a point added meanwhile follows its
reference keyframe (its position in that camera is kept). A keyframe added meanwhile was
tracked on the map as the loop correction left it, which the global BA then moves by up to
the remaining loop error, and its parent may lie on either side of the loop; so after
following its parent it is refined by motion-only BA on the optimised points it sees (when
it sees at least ``BackendConfig.pose_min_inliers`` of them), as the map's next local BA
would do. A ``solver``
(:mod:`orbslam_hgcn.backend.solver`) may run the optimisation in another process; with
``pause_mapping``, local mapping is held still while the result is written back (ORB-SLAM
stops local mapping there), so that a local BA solved meanwhile cannot overwrite it.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from orbslam_hgcn.backend.problem import BAResult, as_problem
from orbslam_hgcn.backend.pose_only import optimize_pose
from orbslam_hgcn.backend.solver import InProcessSolver
from orbslam_hgcn.config import BackendConfig
from orbslam_hgcn.map import Map
from orbslam_hgcn.map.window import BAWindow, apply_window, global_window

log = logging.getLogger(__name__)


@dataclass
class GlobalBAResult:
    """Keyframes and points optimised, and those propagated (created during the BA)."""

    n_keyframes: int = 0
    n_points: int = 0
    n_keyframes_propagated: int = 0
    n_keyframes_refined: int = 0  # of the propagated ones, refined on the optimised points
    n_points_propagated: int = 0


def run_global_ba(
    m: Map,
    iterations: int = 10,
    backend: BackendConfig | None = None,
    time_budget_s: float = 0.0,
    should_stop: Callable[[], bool] | None = None,
    solver: Any = None,
    pause_mapping: Callable[[bool], None] | None = None,
) -> GlobalBAResult:
    """Global BA of the whole map (bounded by ``iterations`` and ``time_budget_s``)."""
    cfg = dataclasses.replace(backend or BackendConfig(), ba_time_budget_s=time_budget_s)
    with m.lock:
        w = global_window(m)
    if w.n_observations == 0 or not (~w.fixed).any():
        return GlobalBAResult()
    solver = solver if solver is not None else InProcessSolver()
    problem = as_problem(w.T_cw, w.fixed, w.points, w.obs_kf, w.obs_pt, w.uv, w.inv_sigma2, w.K)
    res = solver.global_ba(problem, iterations, cfg, should_stop)
    if pause_mapping is not None:
        pause_mapping(True)
    try:
        out = _write_back(m, w, res, cfg)
    finally:
        if pause_mapping is not None:
            pause_mapping(False)
    log.info("global BA: %d keyframes, %d points; propagated to %d keyframes (%d refined), %d points created "
             "meanwhile", out.n_keyframes, out.n_points, out.n_keyframes_propagated, out.n_keyframes_refined,
             out.n_points_propagated)  # fmt: skip
    return out


def _refine_on_optimised_points(m: Map, kf_id: int, T_cw: np.ndarray, optimised: np.ndarray,
                                cfg: BackendConfig) -> np.ndarray | None:
    """Motion-only BA of keyframe ``kf_id`` from ``T_cw`` on the points of ``optimised``
    (ids) it observes; None when too few of them, or too few inliers."""
    kf = m.keyframe(kf_id)
    slots, pids = kf.observed_points()
    use = np.isin(pids, optimised) & ~m.point_arrays(pids).bad
    if int(use.sum()) < cfg.pose_min_inliers:
        return None
    slots, pids = slots[use], pids[use]
    kp = kf.keypoints
    r = optimize_pose(T_cw, m.positions(pids), kp.uv[slots], kp.inv_level_sigma2[kp.octave[slots]], kf.camera.K, cfg)
    return r.T_cw if r.ok else None


def _write_back(m: Map, w: BAWindow, res: BAResult, cfg: BackendConfig) -> GlobalBAResult:
    out = GlobalBAResult(len(w.kf_ids), len(w.point_ids))
    with m.lock:
        in_window = set(w.kf_ids.tolist())
        before = {kf.id: kf.T_cw.copy() for kf in m.keyframes()}
        apply_window(m, w, res.T_cw, res.points)
        # Keyframes added during the BA: follow their parent, root first.
        new_T: dict[int, np.ndarray] = {k: m.keyframe(k).T_cw.copy() for k in in_window if not m.keyframe(k).bad}
        stack = [m.origin_id] if m.origin_id in new_T else []
        while stack:
            k = stack.pop()
            for c in sorted(m.keyframe(k).children):
                child = m.keyframe(c)
                if child.bad:
                    continue
                if c not in new_T:
                    T_cp = before[c] @ np.linalg.inv(before[k])
                    new_T[c] = T_cp @ new_T[k]
                    refined = _refine_on_optimised_points(m, c, new_T[c], w.point_ids, cfg)
                    if refined is not None:
                        new_T[c] = refined
                        out.n_keyframes_refined += 1
                    m.set_keyframe_pose(c, new_T[c])
                    out.n_keyframes_propagated += 1
                stack.append(c)
        # Points added during the BA: follow their reference keyframe (whose pose is now
        # the optimised or propagated one).
        pids = m.point_ids()
        moved = []
        for p in pids[~np.isin(pids, w.point_ids)].tolist():
            r = m.point(p).ref_kf
            if r not in before or m.keyframe(r).bad:
                continue
            M = m.keyframe(r).T_wc @ before[r]
            X = m.positions(np.array([p]))[0]
            m.set_point_positions(np.array([p]), (M[:3, :3] @ X + M[:3, 3])[None])
            moved.append(p)
        if moved:
            m.update_points(np.array(moved, dtype=np.int64), descriptors=False)
        out.n_points_propagated = len(moved)
    return out
