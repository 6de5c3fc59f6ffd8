"""Culling of recent map points and of redundant keyframes.

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. VI-B and VI-E; LocalMapping::
MapPointCulling and KeyFrameCulling of ORB-SLAM2, monocular):

* a recent point is discarded when it is found in fewer than 25% of the frames predicted
  to see it, or when, two keyframes after its creation, it is seen by at most two
  keyframes; it leaves the recent list after three keyframes;
* a covisible keyframe of the new one (never the first keyframe) is discarded when more
  than 90% of its points are seen by at least three other keyframes at the same or a
  finer scale (an octave at most one level above the keyframe's own).

Both tests run on arrays: the observation table of every good keyframe is gathered once
(one array per keyframe) and counted with numpy.
"""

from __future__ import annotations

import logging

import numpy as np

from orbslam_hgcn.config import LocalMappingConfig
from orbslam_hgcn.map import KeyFrame, Map

log = logging.getLogger(__name__)


def observation_table(m: Map, kf_ids: list[int] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """((O,) keyframe id, (O,) point id, (O,) octave) of every observation of the keyframes
    (all good keyframes when None)."""
    kfs = m.keyframes() if kf_ids is None else [m.keyframe(k) for k in kf_ids if not m.keyframe(k).bad]
    ks, ps, os_ = [], [], []
    for kf in kfs:
        idx, pids = kf.observed_points()
        ks.append(np.full(len(idx), kf.id, dtype=np.int64))
        ps.append(pids)
        os_.append(kf.keypoints.octave[idx].astype(np.int64))
    if not ks:
        z = np.zeros(0, np.int64)
        return z, z, z
    return np.concatenate(ks), np.concatenate(ps), np.concatenate(os_)


def cull_recent_points(
    m: Map, recent: np.ndarray, current_kf_id: int, config: LocalMappingConfig
) -> tuple[np.ndarray, int]:
    """Apply ORB-SLAM's recent-point tests. recent: (R,) point ids.

    Returns ((R',) ids still on probation, number of points discarded).
    """
    recent = np.asarray(recent, dtype=np.int64)
    if len(recent) == 0:
        return recent, 0
    bad = m.bad_points(recent)
    recent = recent[~bad]
    with m.lock:  # one consistent view of the counters
        found, visible, first_kf = m.point_counters(recent)
        n_obs = m.n_observations(recent)
    found_ratio = found / np.maximum(visible, 1)  # ORB-SLAM GetFoundRatio
    age = current_kf_id - first_kf
    cull = (found_ratio < config.cull_found_ratio) | (
        (age >= config.cull_after_keyframes) & (n_obs <= config.cull_max_obs)
    )
    for pid in recent[cull].tolist():
        m.set_bad_point(pid)
    keep = ~cull & (age < config.cull_settled_keyframes)
    return recent[keep], int(cull.sum())


def redundant_keyframes(m: Map, kf: KeyFrame, config: LocalMappingConfig) -> list[int]:
    """Cull the covisible keyframes of ``kf`` whose points are mostly seen elsewhere at the
    same or a finer scale; returns the ids culled."""
    cand = [int(k) for k in m.covisible_keyframes(kf.id) if int(k) != m.origin_id]
    cand = [k for k in cand if not m.keyframe(k).bad and not m.keyframe(k).not_erase]
    if not cand:
        return []
    # Observations of every point seen by a candidate, in every keyframe.
    pts = np.unique(np.concatenate([m.keyframe(k).observed_points()[1] for k in cand]))
    if len(pts) == 0:
        return []
    # Every keyframe seeing one of these points shares it with a candidate.
    near = sorted(set(cand).union(*(m.keyframe(k).shared.keys() for k in cand)))

    def table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        o_kf, o_pt, o_oct = observation_table(m, near)
        keep = np.isin(o_pt, pts)
        return o_kf[keep], np.searchsorted(pts, o_pt[keep]), o_oct[keep]

    o_kf, col, o_oct = table()
    culled = []
    for k in cand:
        mine = o_kf == k
        if not mine.any():
            continue
        # Octave of each point in keyframe k, by point column (-1: not seen by k).
        oct_k = np.full(len(pts), -1, dtype=np.int64)
        oct_k[col[mine]] = o_oct[mine]
        finer = (o_kf != k) & (oct_k[col] >= 0) & (o_oct <= oct_k[col] + 1)
        n_finer = np.bincount(col[finer], minlength=len(pts))
        n_points = int(mine.sum())
        n_redundant = int(np.count_nonzero(n_finer[col[mine]] >= config.cull_kf_min_obs))
        if n_redundant > config.cull_kf_redundant * n_points and m.set_bad_keyframe(k):
            culled.append(k)
            # Culling unlinks the keyframe's observations and may discard points.
            o_kf, col, o_oct = table()
    return culled
