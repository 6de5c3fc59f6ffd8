"""Guided matching for loop closing: map points projected into a keyframe with a pose or a
similarity (ORB-SLAM's ORBmatcher::SearchByProjection(KF, Scw, ...), SearchBySim3 and
Fuse(KF, Scw, ...); Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. VII).

A similarity pose ``S_cw = [[s R, t], [0, 1]]`` and its rigid part ``[R, t / s]`` project
every world point to the same pixel and put the camera centre at the same place, so the
searches take the rigid pose; only the depth differs, and it is not used.
"""

from __future__ import annotations

import logging

import numpy as np

from orbslam_hgcn.map import KeyFrame, Map, predict_scale
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.match.hamming import TH_HIGH, TH_LOW
from orbslam_hgcn.match.matching import search_by_projection

log = logging.getLogger(__name__)


def _project(K: np.ndarray, X_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((M, 2) pixels, (M,) depth) of (M, 3) camera-frame points; nan pixels behind."""
    z = X_c[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.where(z > 0, 1.0 / z, np.nan)
    return np.stack([K[0, 0] * X_c[:, 0] * inv_z + K[0, 2], K[1, 1] * X_c[:, 1] * inv_z + K[1, 2]], axis=1), z


def match_points_in_keyframe(
    m: Map,
    kf: KeyFrame,
    grid: FeatureGrid,
    T_cw: np.ndarray,
    pids: np.ndarray,
    window: float,
    *,
    max_dist: int = TH_LOW,
    min_view_cos: float = 0.5,
    available: np.ndarray | None = None,
) -> np.ndarray:
    """Keypoint of ``kf`` matched to each map point projected with ``T_cw``.

    ORB-SLAM's SearchByProjection(KF, Scw) and Fuse(KF, Scw): a point is searched when it
    lies in front of the camera, inside the image, within its scale-invariance distance
    range and seen within acos(min_view_cos) of its mean viewing direction; at its predicted
    level, in a window of ``window x scale``, among keypoints of that level or the one below,
    best Hamming distance at most ``max_dist``. A keypoint wanted by several points goes to
    the closest. pids: (M,) good map point ids; T_cw: (4, 4) rigid pose of the keyframe
    (the rigid part of a corrected similarity); available: (N,) bool keypoints that may be
    matched (None: all).
    Returns (M,) int64 keypoint index or -1.
    """
    pids = np.asarray(pids, dtype=np.int64).reshape(-1)
    out = np.full(len(pids), -1, dtype=np.int64)
    if len(pids) == 0 or len(kf.keypoints) == 0:
        return out
    pts = m.point_arrays(pids)
    T_cw = np.asarray(T_cw, dtype=np.float64)
    X_c = pts.position @ T_cw[:3, :3].T + T_cw[:3, 3]
    uv, z = _project(kf.camera.K, X_c)
    center = -T_cw[:3, :3].T @ T_cw[:3, 3]
    PO = pts.position - center
    dist = np.linalg.norm(PO, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = (
            grid.contains(uv, z)
            & (dist >= pts.min_dist)
            & (dist <= pts.max_dist)
            & (np.sum(PO * pts.normal, axis=1) >= min_view_cos * dist)
            & ~pts.bad
        )
    sel = np.flatnonzero(ok)
    if len(sel) == 0:
        return out
    level = predict_scale(dist[sel], pts.max_dist[sel], kf.keypoints.scale_factors)
    match, _ = search_by_projection(
        kf.keypoints, grid, uv[sel], level, pts.desc[sel], window,
        level_range=(-1, 0), max_dist=max_dist, available=available,
    )  # fmt: skip
    out[sel] = match
    return out


def _search_one_way(
    m: Map,
    src: KeyFrame,
    dst: KeyFrame,
    dst_grid: FeatureGrid,
    src_slots: np.ndarray,
    S_dst_src: np.ndarray,
    window: float,
) -> np.ndarray:
    """Keypoints of ``dst`` matched to the points in ``src_slots`` of ``src`` projected with
    the similarity S_dst_src (camera src -> camera dst); (S,) int64 index or -1."""
    out = np.full(len(src_slots), -1, dtype=np.int64)
    if len(src_slots) == 0:
        return out
    pids = src.point_ids[src_slots]
    pts = m.point_arrays(pids)
    X_src = pts.position @ src.T_cw[:3, :3].T + src.T_cw[:3, 3]
    X_dst = X_src @ S_dst_src[:3, :3].T + S_dst_src[:3, 3]
    uv, z = _project(dst.camera.K, X_dst)
    dist = np.linalg.norm(X_dst, axis=1)
    ok = dst_grid.contains(uv, z) & (dist >= pts.min_dist) & (dist <= pts.max_dist) & ~pts.bad
    sel = np.flatnonzero(ok)
    if len(sel) == 0:
        return out
    level = predict_scale(dist[sel], pts.max_dist[sel], dst.keypoints.scale_factors)
    match, _ = search_by_projection(
        dst.keypoints, dst_grid, uv[sel], level, pts.desc[sel], window, level_range=(-1, 1), max_dist=TH_HIGH
    )
    out[sel] = match
    return out


def search_by_sim3(
    m: Map,
    kf1: KeyFrame,
    kf2: KeyFrame,
    matches12: np.ndarray,
    S_12: np.ndarray,
    window: float = 7.5,
) -> np.ndarray:
    """Add matches between two keyframes' points found with their similarity (ORB-SLAM
    SearchBySim3).

    matches12: (N1,) int64 map point id of kf2 matched to each feature of kf1, or -1.
    S_12: (4, 4) similarity mapping camera-2 coordinates into camera 1. The unmatched points
    of kf1 are projected into kf2 with S_21 and those of kf2 into kf1 with S_12 (window x
    scale of the predicted level, levels one either side, distance at most TH_HIGH); a pair
    is added when both directions agree. Returns the updated (N1,) copy.
    """
    out = np.asarray(matches12, dtype=np.int64).copy()
    slots1, pids1 = kf1.observed_points()
    slots2, pids2 = kf2.observed_points()
    good1 = ~m.point_arrays(pids1).bad
    good2 = ~m.point_arrays(pids2).bad
    matched2 = np.isin(pids2, out[out >= 0])
    free1 = slots1[good1 & (out[slots1] < 0)]
    free2 = slots2[good2 & ~matched2]
    if len(free1) == 0 or len(free2) == 0:
        return out
    s = float(np.cbrt(np.linalg.det(S_12[:3, :3])))
    R = S_12[:3, :3] / s
    S_21 = np.eye(4)
    S_21[:3, :3] = R.T / s
    S_21[:3, 3] = -R.T @ S_12[:3, 3] / s
    grid1 = kf1.grid
    grid2 = kf2.grid
    to2 = _search_one_way(m, kf1, kf2, grid2, free1, S_21, window)  # (F1,) keypoint of kf2
    to1 = _search_one_way(m, kf2, kf1, grid1, free2, S_12, window)  # (F2,) keypoint of kf1
    back = np.full(len(kf2.keypoints), -1, dtype=np.int64)  # kf2 keypoint -> kf1 keypoint
    back[free2] = to1
    ok = to2 >= 0
    ok[ok] &= back[to2[ok]] == free1[ok]
    out[free1[ok]] = kf2.point_ids[to2[ok]]
    log.debug("SearchBySim3 %d-%d: %d new matches", kf1.id, kf2.id, int(ok.sum()))
    return out
