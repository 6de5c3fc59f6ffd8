"""Relocalisation of a frame when tracking is lost (ORB-SLAM Tracking::Relocalization;
Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. V-C).

1. the keyframe database returns the keyframes most similar to the frame's BoW vector
   (:meth:`KeyframeDatabase.detect_relocalization_candidates`; by default its shared-word
   filter counts words per word of each keyframe, ``common_words_per_word``);
2. each candidate's map points are matched to the frame through the vocabulary
   (SearchByBoW, ratio 0.75, rotation check); candidates with fewer than 15 matches are
   dropped. Beyond ORB-SLAM (``relocalization.exhaustive_fallback``): a candidate left
   with fewer is matched again over all its points' descriptors (same distance, ratio and
   rotation rules, mutual best), since a blurred or over-exposed frame's descriptors often
   fall under other vocabulary nodes than the keyframe's (``bench/bench_reloc.py``);
   and when every candidate fails, a few of their best covisible keyframes
   (``relocalization.covisible_fallback``) are tried in turn;
3. EPnP inside RANSAC (0.99, 10 inliers, 300 iterations, 4-point sets, 5.991 sigma^2 gate;
   :func:`orbslam_hgcn.geometry.pnp.solve_pnp_ransac`) gives a pose;
4. the pose is refined on the RANSAC inliers (motion-only BA); fewer than 10 inliers drop
   the candidate. With fewer than 50 inliers, the candidate's other points are searched by
   projection (window 10, Hamming distance 100), the pose refined again, and with 30 to 49
   inliers searched once more in a narrow window (3, distance 64) and refined;
5. the first candidate reaching 50 inliers relocalises the frame.

ORB-SLAM runs five RANSAC iterations per candidate in turn; here each candidate's RANSAC
runs to the end before the next candidate (the order of trying differs, not the rules).
The frame's pose and matches are returned (or written into the frame by
:class:`Relocalizer`); the map is not changed, so tracking resumes in the same map.
"""

from __future__ import annotations

import logging
from typing import Any, NamedTuple

import numpy as np

from orbslam_hgcn.backend.pose_only import optimize_pose
from orbslam_hgcn.config import BackendConfig, RelocalizationConfig
from orbslam_hgcn.geometry.pnp import solve_pnp_ransac
from orbslam_hgcn.map import Frame, KeyFrame, Map, predict_scale
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.match.matching import (
    TH_LOW,
    apply_rotation_check,
    brute_force_match,
    search_by_bow,
    search_by_projection,
)
from orbslam_hgcn.map.database import KeyframeDatabase

log = logging.getLogger(__name__)


class RelocalizationResult(NamedTuple):
    """ok; T_cw (4, 4) pose (None on failure); point_ids (N,) int64 map point matched to
    each feature of the frame (inliers only, -1 elsewhere); n_inliers; kf_id: the candidate
    that succeeded (-1 for none); n_candidates: candidates returned by the database;
    n_tried: candidates that reached PnP."""

    ok: bool
    T_cw: np.ndarray | None
    point_ids: np.ndarray
    n_inliers: int
    kf_id: int
    n_candidates: int
    n_tried: int


def _refine(frame: Frame, m: Map, T_cw: np.ndarray, pids: np.ndarray, backend: BackendConfig):
    """Motion-only BA against the matched points; returns (T_cw, (N,) inlier mask, count)."""
    idx = np.flatnonzero(pids >= 0)
    inl = np.zeros(len(pids), dtype=bool)
    if len(idx) < 3:
        return T_cw, inl, 0
    kp = frame.keypoints
    res = optimize_pose(T_cw, m.positions(pids[idx]), kp.uv[idx], kp.inv_level_sigma2[kp.octave[idx]], frame.camera.K, backend)
    inl[idx[res.inliers]] = True
    return res.T_cw, inl, int(res.inliers.sum())


def search_keyframe_points(
    frame: Frame,
    grid: FeatureGrid,
    T_cw: np.ndarray,
    kf: KeyFrame,
    m: Map,
    pids: np.ndarray,
    window: float,
    max_dist: int,
) -> int:
    """Project the keyframe's points not yet in ``pids`` with T_cw and match them to free
    features (ORB-SLAM SearchByProjection(Frame, KF, sAlreadyFound, th, ORBdist)): inside
    the image, within the distance range, window x scale of the predicted level, levels
    one either side, rotation check. Links the matches in ``pids`` (N,); returns their count."""
    slots, kf_pids = kf.observed_points()
    keep = ~np.isin(kf_pids, pids[pids >= 0])
    slots, kf_pids = slots[keep], kf_pids[keep]
    if len(kf_pids) == 0:
        return 0
    pts = m.point_arrays(kf_pids)
    X_c = pts.position @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = X_c[:, 2]
    K = frame.camera.K
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([K[0, 0] * X_c[:, 0] / z + K[0, 2], K[1, 1] * X_c[:, 1] / z + K[1, 2]], axis=1)
        center = -T_cw[:3, :3].T @ T_cw[:3, 3]
        dist = np.linalg.norm(pts.position - center, axis=1)
        ok = (
            (z > 0)
            & (uv[:, 0] >= grid.min_x) & (uv[:, 0] < grid.max_x)
            & (uv[:, 1] >= grid.min_y) & (uv[:, 1] < grid.max_y)
            & (dist >= pts.min_dist) & (dist <= pts.max_dist)
            & ~pts.bad
        )  # fmt: skip
    sel = np.flatnonzero(ok)
    if len(sel) == 0:
        return 0
    level = predict_scale(dist[sel], pts.max_dist[sel], frame.keypoints.scale_factors)
    match, _ = search_by_projection(
        frame.keypoints, grid, uv[sel], level, pts.desc[sel], window,
        level_range=(-1, 1), max_dist=max_dist, ref_angle=kf.keypoints.angle[slots[sel]], available=pids < 0,
    )  # fmt: skip
    hit = match >= 0
    pids[match[hit]] = kf_pids[sel][hit]
    return int(hit.sum())


def _match_all(desc_kf: np.ndarray, desc_fr: np.ndarray, angle_kf: np.ndarray, angle_fr: np.ndarray,
               valid: np.ndarray, ratio: float) -> np.ndarray:
    """The candidate's points matched to the frame over all descriptors, not only those
    under the same vocabulary node: distance below ORB-SLAM's TH_LOW, ratio test, mutual
    best, rotation check. (N_kf,) frame feature index or -1."""
    match = np.full(len(desc_kf), -1, dtype=np.int64)
    idx = np.flatnonzero(valid)
    pairs = brute_force_match(desc_kf[idx], desc_fr, ratio=ratio, cross_check=True, max_dist=TH_LOW - 1)
    match[idx[pairs[:, 0]]] = pairs[:, 1]
    return apply_rotation_check(match, np.asarray(angle_kf), np.asarray(angle_fr))


def _try_candidate(
    frame: Frame, grid: FeatureGrid, kf: KeyFrame, m: Map, cfg: RelocalizationConfig, backend: BackendConfig,
    rng: np.random.Generator,
) -> tuple[bool, np.ndarray | None, np.ndarray, int, bool]:  # fmt: skip
    """(ok, T_cw, (N,) point ids, inliers, reached PnP) for one candidate keyframe."""
    n = len(frame.keypoints)
    none = np.full(n, -1, dtype=np.int64)
    valid = kf.point_ids >= 0
    idx = np.flatnonzero(valid)
    valid[idx[m.point_arrays(kf.point_ids[idx]).bad]] = False
    kkp, fkp = kf.keypoints, frame.keypoints
    match = search_by_bow(
        kf.featvec, frame.featvec, kkp.desc, fkp.desc, kkp.angle, fkp.angle, valid1=valid, ratio=cfg.bow_ratio
    )
    i_kf = np.flatnonzero(match >= 0)
    if len(i_kf) < cfg.min_bow_matches and cfg.exhaustive_fallback:
        match = _match_all(kkp.desc, fkp.desc, kkp.angle, fkp.angle, valid, cfg.bow_ratio)
        i_kf = np.flatnonzero(match >= 0)
    if len(i_kf) < cfg.min_bow_matches:
        return False, None, none, 0, False
    i_fr = match[i_kf]
    pids_m = kf.point_ids[i_kf]
    pnp = solve_pnp_ransac(
        m.positions(pids_m), fkp.uv[i_fr], frame.camera.K, fkp.level_sigma2[fkp.octave[i_fr]],
        probability=cfg.pnp_probability, min_inliers=cfg.pnp_min_inliers, max_iterations=cfg.pnp_max_iterations,
        min_set=cfg.pnp_min_set, epsilon=cfg.pnp_epsilon, th2=cfg.pnp_chi2, rng=rng,
    )  # fmt: skip
    if pnp is None:
        return False, None, none, 0, True
    pids = none.copy()
    pids[i_fr[pnp.inliers]] = pids_m[pnp.inliers]
    T, inl, n_good = _refine(frame, m, pnp.T_cw, pids, backend)
    if n_good < cfg.min_pose_inliers:
        return False, None, none, n_good, True
    pids[~inl] = -1
    if n_good < cfg.min_inliers:
        n_add = search_keyframe_points(frame, grid, T, kf, m, pids, cfg.wide_window, cfg.wide_max_dist)
        if n_add + n_good >= cfg.min_inliers:
            T, inl, n_good = _refine(frame, m, T, pids, backend)
            if cfg.narrow_min_inliers < n_good < cfg.min_inliers:
                # Matches flagged as outliers keep their slots and are not searched again.
                n_add = search_keyframe_points(frame, grid, T, kf, m, pids, cfg.narrow_window, cfg.narrow_max_dist)
                if n_good + n_add >= cfg.min_inliers:
                    T, inl, n_good = _refine(frame, m, T, pids, backend)
        pids[~inl] = -1
    if n_good < cfg.min_inliers:
        return False, None, none, n_good, True
    return True, T, pids, n_good, True


def _with_neighbours(cands: list[int], m: Map, n: int):
    """The database's candidates, then (``relocalization.covisible_fallback`` = ``n`` > 0)
    up to ``n`` keyframes more: the candidates' covisible keyframes that are not candidates,
    the best-connected first (a candidate's best neighbour before the next's second); tried
    only once every candidate has failed (the generator stops at the first success)."""
    yield from cands
    if n <= 0:
        return
    seen = set(cands)
    lists = [[int(c) for c in m.covisible_keyframes(int(k), n)] for k in cands]
    extra = 0
    for rank in range(n):
        for neighbours in lists:
            if rank < len(neighbours) and neighbours[rank] not in seen and not m.keyframe(neighbours[rank]).bad:
                seen.add(neighbours[rank])
                yield neighbours[rank]
                extra += 1
                if extra >= n:
                    return


def relocalize(
    frame: Frame,
    grid: FeatureGrid,
    m: Map,
    database: KeyframeDatabase,
    config: RelocalizationConfig | None = None,
    backend: BackendConfig | None = None,
    rng: np.random.Generator | None = None,
) -> RelocalizationResult:
    """Relocalise ``frame`` (its BoW vectors set) against the map, or, in an atlas, against
    any of its maps (the active map's candidates first); the frame is not changed. The
    result's ``kf_id`` tells which map it landed in."""
    cfg = config or RelocalizationConfig()
    backend = backend or BackendConfig()
    rng = rng or np.random.default_rng(cfg.seed)
    fail = RelocalizationResult(False, None, np.full(len(frame.keypoints), -1, dtype=np.int64), 0, -1, 0, 0)
    if frame.bow is None or frame.featvec is None or len(frame.keypoints) == 0 or len(database) == 0:
        return fail
    with m.lock:
        found = database.detect_relocalization_candidates(
            frame.bow, covisible=lambda k: m.covisible_keyframes(int(k), database.n_covisible),
            per_word=cfg.common_words_per_word,
        )  # fmt: skip
        cands = [c.kf_id for c in found if not m.keyframe(c.kf_id).bad]
        # In an atlas the candidates of the active map are tried first, then the others'.
        cands.sort(key=lambda k: not m.owns(k))
        tried, best = 0, 0
        for k in _with_neighbours(cands, m, cfg.covisible_fallback):
            kf = m.keyframe(k)
            if kf.featvec is None:
                continue
            ok, T, pids, n_good, reached = _try_candidate(frame, grid, kf, m, cfg, backend, rng)
            tried += int(reached)
            best = max(best, n_good)
            if ok:
                log.info("frame %d relocalised against keyframe %d: %d inliers (%d candidates, %d tried)",
                         frame.id, k, n_good, len(cands), tried)  # fmt: skip
                return RelocalizationResult(True, T, pids, n_good, k, len(cands), tried)
    log.debug("frame %d: relocalisation failed (%d candidates, %d tried, best %d inliers)", frame.id, len(cands), tried, best)
    return fail._replace(n_candidates=len(cands), n_tried=tried, n_inliers=best)


class Relocalizer:
    """The tracker's relocaliser (``relocalize(frame, grid) -> bool``) over a map and the
    keyframe database shared with loop closing.

    vocabulary: optional, computes the frame's BoW vectors when they are missing.
    ``attempts`` and ``successes`` count calls; ``last`` is the last result; ``history``
    lists (frame id, keyframe id, inliers) of every success.
    """

    def __init__(
        self,
        m: Map,
        database: KeyframeDatabase,
        config: RelocalizationConfig | None = None,
        backend: BackendConfig | None = None,
        vocabulary: Any = None,
    ) -> None:
        self.map = m
        self.database = database
        self.config = config or RelocalizationConfig()
        self.backend = backend or BackendConfig()
        self.vocabulary = vocabulary
        self.rng = np.random.default_rng(self.config.seed)
        self.attempts = 0
        self.successes = 0
        self.last: RelocalizationResult | None = None
        self.history: list[tuple[int, int, int]] = []

    def reset(self, m: Map) -> None:
        """Work on map ``m`` from now on (the database is reset by its owner)."""
        self.map = m

    def stats(self) -> dict[str, Any]:
        """Attempts, successes and the successes' (frame, keyframe, inliers)."""
        return {"attempts": self.attempts, "successes": self.successes, "history": [list(h) for h in self.history]}

    def relocalize(self, frame: Frame, grid: FeatureGrid) -> bool:
        """Relocalise ``frame``; on success its pose and matches are set (no outliers)."""
        if frame.bow is None and self.vocabulary is not None:
            frame.bow, frame.featvec = self.vocabulary.transform(frame.keypoints.desc)
        self.attempts += 1
        res = relocalize(frame, grid, self.map, self.database, self.config, self.backend, self.rng)
        self.last = res
        if not res.ok:
            return False
        self.successes += 1
        self.history.append((frame.id, res.kf_id, res.n_inliers))
        frame.set_pose(res.T_cw)
        frame.point_ids[:] = res.point_ids
        frame.outlier[:] = False
        return True
