"""Fusion of duplicated map points between a new keyframe and its neighbourhood.

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. VI-C; LocalMapping::SearchInNeighbors
and ORBmatcher::Fuse of ORB-SLAM2, monocular): the targets are the 20 best covisible
keyframes and the 5 best covisible of each of them. The new keyframe's points are projected
into every target and the targets' points into the new keyframe (window 3 x scale of the
predicted level, reprojection gate, Hamming distance at most 50). A point landing on a
keypoint that already holds a point is merged with it (the one with more observations
survives); a point landing on a free keypoint gains that observation.
"""

from __future__ import annotations

import logging

import numpy as np

from orbslam_hgcn.config import LocalMappingConfig
from orbslam_hgcn.map import KeyFrame, Map
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.match.matching import fuse_candidates

log = logging.getLogger(__name__)


def fuse_targets(m: Map, kf: KeyFrame, config: LocalMappingConfig) -> list[int]:
    """Keyframe ids to fuse with: best covisible ones and their best covisible ones."""
    first = [int(k) for k in m.covisible_keyframes(kf.id, config.fuse_neighbours) if not m.keyframe(int(k)).bad]
    targets = list(first)
    seen = set(first) | {kf.id}
    for k in first:
        for k2 in m.covisible_keyframes(k, config.fuse_second_neighbours):
            k2 = int(k2)
            if k2 not in seen and not m.keyframe(k2).bad:
                targets.append(k2)
                seen.add(k2)
    return targets


def fuse_into(m: Map, kf: KeyFrame, pids: np.ndarray, grid: FeatureGrid, window: float) -> tuple[int, int]:
    """Fuse points ``pids`` into keyframe ``kf`` (ORB-SLAM2 ORBmatcher::Fuse).

    Returns (points merged with the keyframe's own, observations added).
    """
    pids = np.asarray(pids, dtype=np.int64)
    if len(pids) == 0:
        return 0, 0
    # Already seen by the keyframe (ids are dense: a lookup table beats sorting here).
    pids = pids[~np.isin(pids, kf.point_ids, kind="table")]
    pids = pids[~m.bad_points(pids)]
    if len(pids) == 0:
        return 0, 0
    pts = m.point_arrays(pids)
    match, _ = fuse_candidates(
        kf.keypoints, grid, kf.camera, kf.T_cw, pts.position, pts.desc, pts.normal, pts.min_dist, pts.max_dist, window
    )
    sel = np.flatnonzero(match >= 0)
    with m.lock:
        merged, added, survivors = m.fuse_points(kf.id, pids[sel], match[sel])
        if survivors:  # refreshed once at the end (the matches are already made)
            m.update_points(np.unique(np.array(survivors, dtype=np.int64)))
    return merged, added


def search_in_neighbors(m: Map, kf: KeyFrame, config: LocalMappingConfig) -> dict[str, int]:
    """Fuse the new keyframe's points with its neighbourhood's, both ways; refresh the
    keyframe's points and connections. Returns counts (targets, merged, added).

    The map lock is held for one target keyframe at a time, so the tracker waits for at
    most one target's fusion (threaded mode)."""
    with m.lock:
        targets = fuse_targets(m, kf, config)
    merged = added = 0
    for k in targets:
        with m.lock:
            t = m.keyframe(k)
            if t.bad:
                continue
            _, own = kf.observed_points()
            a, b = fuse_into(m, t, own, t.grid, config.fuse_window)
        merged, added = merged + a, added + b
    with m.lock:
        if targets:
            arrays = [m.keyframe(k).point_ids for k in targets if not m.keyframe(k).bad]
            cand = np.concatenate(arrays) if arrays else np.zeros(0, np.int64)
            cand = np.unique(cand[cand >= 0])
            a, b = fuse_into(m, kf, cand, kf.grid, config.fuse_window)
            merged, added = merged + a, added + b
        _, own = kf.observed_points()
        m.update_points(own)
        m.update_connections(kf.id)
    return {"targets": len(targets), "merged": merged, "added": added}
