"""Geometric verification of loop candidates: the similarity between the current keyframe
and a candidate (ORB-SLAM LoopClosing::ComputeSim3; Mur-Artal, Montiel & Tardos, T-RO
2015, Sec. VII-B).

For each consistent candidate, in the order the detector gives them:

1. match the two keyframes' map points through the vocabulary (SearchByBoW, features under
   one node, ratio 0.75, rotation check); at least 20 matches;
2. Horn's closed-form similarity inside RANSAC (0.99, 20 inliers, 300 iterations);
3. more matches guided by that similarity (SearchBySim3, window 7.5);
4. refine the similarity on the matches (OptimizeSim3, gtsam; :mod:`orbslam_hgcn.backend.sim3_refine`); at
   least 20 inliers;
5. project the points of the candidate and its covisible keyframes into the current
   keyframe with the corrected pose ``S_cw = S_cm T_mw`` (window 10) and accept the loop
   with at least 40 matched points in all.

ORB-SLAM runs the RANSAC of all candidates five iterations at a time, round robin; here each
candidate runs its RANSAC to the end before the next one starts (the first accepted
candidate wins either way; only the order of trying differs). As in ORB-SLAM, a candidate
passing step 4 ends the search, and the loop is rejected when it then fails step 5.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from orbslam_hgcn.backend.sim3_refine import optimize_sim3
from orbslam_hgcn.config import LoopClosingConfig
from orbslam_hgcn.geometry.sim3 import sim3_ransac
from orbslam_hgcn.loop.projection import match_points_in_keyframe, search_by_sim3
from orbslam_hgcn.map import KeyFrame, Map
from orbslam_hgcn.match.matching import search_by_bow

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class LoopMatch:
    """An accepted loop between the current keyframe and a loop keyframe.

    kf_id / loop_kf_id: current and matched keyframe; S_cm: (4, 4) similarity mapping
    loop-camera coordinates into the current camera; S_cw: (4, 4) corrected similarity pose
    of the current keyframe (S_cm T_mw); matched: (N,) int64 loop-side map point matched to
    each feature of the current keyframe, -1 for none; loop_kf_ids: (L,) the loop keyframe
    and its covisible keyframes; loop_pids: (P,) their good map points; n_sim3_inliers:
    inliers of the refined similarity; n_matches: matched features in all.
    """

    kf_id: int
    loop_kf_id: int
    S_cm: np.ndarray
    S_cw: np.ndarray
    matched: np.ndarray
    loop_kf_ids: np.ndarray
    loop_pids: np.ndarray
    n_sim3_inliers: int
    n_matches: int


@dataclass
class Sim3Attempt:
    """What happened to one candidate (for logs and benchmarks): ``stage`` reached
    (bow, ransac, optimize, projection, accepted) and the counts there."""

    candidate: int
    stage: str
    counts: dict[str, int] = field(default_factory=dict)


def _bow_matches(m: Map, kf1: KeyFrame, kf2: KeyFrame, ratio: float) -> np.ndarray:
    """(N1,) int64 feature of kf2 matched to each feature of kf1 (both holding good map
    points), or -1 (ORB-SLAM SearchByBoW(KF, KF))."""
    valid1 = kf1.point_ids >= 0
    valid2 = kf2.point_ids >= 0
    for kf, valid in ((kf1, valid1), (kf2, valid2)):
        idx = np.flatnonzero(valid)
        valid[idx[m.point_arrays(kf.point_ids[idx]).bad]] = False
    kp1, kp2 = kf1.keypoints, kf2.keypoints
    return search_by_bow(
        kf1.featvec, kf2.featvec, kp1.desc, kp2.desc, kp1.angle, kp2.angle, valid1=valid1, valid2=valid2, ratio=ratio
    )


def _point_data(m: Map, kf1: KeyFrame, kf2: KeyFrame, i1: np.ndarray, i2: np.ndarray):
    """Data of the matches (slot i1 of kf1, slot i2 of kf2), i1 / i2: (M,) int.

    Returns ((M, 3) kf1's points in camera 1, (M, 3) kf2's points in camera 2, (M, 2) and
    (M, 2) their undistorted keypoints, (M,) and (M,) their level variances sigma^2)."""
    kp1, kp2 = kf1.keypoints, kf2.keypoints
    P1 = m.positions(kf1.point_ids[i1])
    P2 = m.positions(kf2.point_ids[i2])
    X1 = P1 @ kf1.T_cw[:3, :3].T + kf1.T_cw[:3, 3]
    X2 = P2 @ kf2.T_cw[:3, :3].T + kf2.T_cw[:3, 3]
    s2_1 = kp1.level_sigma2[kp1.octave[i1]]
    s2_2 = kp2.level_sigma2[kp2.octave[i2]]
    return X1, X2, kp1.uv[i1], kp2.uv[i2], s2_1, s2_2


def _slots_of(kf: KeyFrame, pids: np.ndarray) -> np.ndarray:
    """(M,) slot of each point in ``kf`` (-1 where it does not observe it)."""
    order = np.argsort(kf.point_ids, kind="stable")
    sorted_ids = kf.point_ids[order]
    pos = np.clip(np.searchsorted(sorted_ids, pids), 0, len(order) - 1)
    return np.where(sorted_ids[pos] == pids, order[pos], -1) if len(order) else np.full(len(pids), -1)


def check_candidate(
    m: Map, kf: KeyFrame, cand: KeyFrame, config: LoopClosingConfig, rng: np.random.Generator
) -> tuple[np.ndarray | None, np.ndarray, Sim3Attempt]:
    """Steps 1-4 for one candidate: (S_cm or None, (N,) matched loop points, attempt)."""
    cfg = config
    att = Sim3Attempt(cand.id, "bow")
    none = np.full(len(kf.keypoints), -1, dtype=np.int64)
    if cand.featvec is None or kf.featvec is None:
        return None, none, att
    match = _bow_matches(m, kf, cand, cfg.bow_ratio)
    i1 = np.flatnonzero(match >= 0)
    i2 = match[i1]
    att.counts["bow"] = len(i1)
    if len(i1) < cfg.min_bow_matches:
        return None, none, att
    att.stage = "ransac"
    X1, X2, uv1, uv2, s2_1, s2_2 = _point_data(m, kf, cand, i1, i2)
    res = sim3_ransac(
        X1, X2, uv1, uv2, kf.camera.K, cand.camera.K, s2_1, s2_2,
        probability=cfg.sim3_probability, min_inliers=cfg.sim3_min_inliers,
        max_iterations=cfg.sim3_max_iterations, fixed_scale=cfg.fix_scale, rng=rng,
    )  # fmt: skip
    if res is None:
        return None, none, att
    att.counts["ransac"] = int(res.inliers.sum())
    att.stage = "optimize"
    matched = none.copy()
    matched[i1[res.inliers]] = cand.point_ids[i2[res.inliers]]
    matched = search_by_sim3(m, kf, cand, matched, res.S_12, cfg.sim3_search_window)
    j1 = np.flatnonzero(matched >= 0)
    j2 = _slots_of(cand, matched[j1])
    keep = j2 >= 0
    j1, j2 = j1[keep], j2[keep]
    att.counts["guided"] = len(j1)
    X1, X2, uv1, uv2, s2_1, s2_2 = _point_data(m, kf, cand, j1, j2)
    ref = optimize_sim3(
        res.S_12, X1, X2, uv1, uv2, 1.0 / s2_1, 1.0 / s2_2, kf.camera.K, cand.camera.K,
        chi2=cfg.sim3_opt_chi2, iterations=cfg.sim3_opt_iterations,
        more_iterations=cfg.sim3_opt_more_iterations, fix_scale=cfg.fix_scale,
        scale_prior_sigma=cfg.sim3_scale_prior_sigma,
    )  # fmt: skip
    att.counts["optimized"] = ref.n_inliers
    if ref.n_inliers < cfg.sim3_opt_min_inliers:
        return None, none, att
    matched = none.copy()
    matched[j1[ref.inliers]] = cand.point_ids[j2[ref.inliers]]
    return ref.S_12, matched, att


def loop_neighbourhood(m: Map, loop_kf_id: int) -> tuple[np.ndarray, np.ndarray]:
    """((L,) the loop keyframe and its covisible keyframes, (P,) their good map points)."""
    kf_ids = [loop_kf_id] + [int(k) for k in m.covisible_keyframes(loop_kf_id) if not m.keyframe(int(k)).bad]
    arrays = [m.keyframe(k).point_ids for k in kf_ids]
    pids = np.unique(np.concatenate(arrays))
    pids = pids[pids >= 0]
    pids = pids[~m.point_arrays(pids).bad]
    return np.array(kf_ids, dtype=np.int64), pids


def compute_sim3(
    m: Map,
    kf: KeyFrame,
    candidates: list[int],
    config: LoopClosingConfig | None = None,
    rng: np.random.Generator | None = None,
    attempts: list[Sim3Attempt] | None = None,
) -> LoopMatch | None:
    """Verify the candidates of keyframe ``kf``; the accepted loop, or None.

    candidates: keyframe ids (consistent loop candidates); attempts: optional list that
    receives one :class:`Sim3Attempt` per candidate tried.
    """
    cfg = config or LoopClosingConfig()
    rng = rng or np.random.default_rng(cfg.seed)
    with m.lock:
        for c in candidates:
            cand = m.keyframe(int(c))
            if cand.bad:
                continue
            S_cm, matched, att = check_candidate(m, kf, cand, cfg, rng)
            if attempts is not None:
                attempts.append(att)
            if S_cm is None:
                continue
            n_sim3 = int(np.count_nonzero(matched >= 0))
            att.stage = "projection"
            S_cw = S_cm @ cand.T_cw
            s = float(np.cbrt(np.linalg.det(S_cw[:3, :3])))
            T_cw = S_cw / s
            T_cw[3] = (0.0, 0.0, 0.0, 1.0)
            loop_kf_ids, loop_pids = loop_neighbourhood(m, cand.id)
            search = loop_pids[~np.isin(loop_pids, matched[matched >= 0])]
            grid = kf.grid
            found = match_points_in_keyframe(
                m, kf, grid, T_cw, search, cfg.projection_window,
                min_view_cos=cfg.min_view_cos, available=matched < 0,
            )  # fmt: skip
            ok = found >= 0
            matched[found[ok]] = search[ok]
            n_total = int(np.count_nonzero(matched >= 0))
            att.counts["total"] = n_total
            if n_total < cfg.min_total_matches:
                log.info("loop %d-%d rejected: %d matches after projection (need %d)",
                         kf.id, cand.id, n_total, cfg.min_total_matches)  # fmt: skip
                return None
            att.stage = "accepted"
            log.info("loop %d-%d accepted: %d Sim3 inliers, %d matches, scale %.3f",
                     kf.id, cand.id, n_sim3, n_total, np.cbrt(np.linalg.det(S_cm[:3, :3])))  # fmt: skip
            return LoopMatch(kf.id, cand.id, S_cm, S_cw, matched, loop_kf_ids, loop_pids, n_sim3, n_total)
    return None
