"""Frame-to-frame tracking: the constant-velocity motion model and the reference keyframe.

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. V-B; Tracking::TrackWithMotionModel
and TrackReferenceKeyFrame of ORB-SLAM2): the points matched in the last frame are
projected with the pose predicted by a constant velocity and searched in a window of
15 px times the scale of their last keypoint's level (doubled when fewer than 20 matches
are found), with the rotation-consistency check; the pose is then refined and the
outliers dropped. When the model fails, or there is no velocity yet, the points of the
reference keyframe are matched by BoW (with a vocabulary) or by projection from the last
pose in a wide window (without one), and the pose is refined from the last frame's.
"""

from __future__ import annotations

import logging

import numpy as np

from orbslam_hgcn.config import BackendConfig, TrackingConfig
from orbslam_hgcn.map import Frame, KeyFrame, Map, predict_scale
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.match.matching import search_by_bow, search_by_projection
from orbslam_hgcn.tracking.frame_ops import (
    discard_outliers,
    optimize_frame_pose,
    orthonormalize,
    project,
    refresh_frame_points,
)

log = logging.getLogger(__name__)


def _link(frame: Frame, pids: np.ndarray, match: np.ndarray) -> int:
    ok = match >= 0
    frame.point_ids[match[ok]] = pids[ok]
    return int(ok.sum())


def search_last_frame(frame: Frame, grid: FeatureGrid, last: Frame, m: Map, window: float) -> int:
    """Project the last frame's matched points with frame.T_cw and match them (ORB-SLAM2
    SearchByProjection(Frame, LastFrame, th, mono)); returns the number of new matches."""
    idx = np.flatnonzero(last.matched)
    if len(idx) == 0:
        return 0
    pids = last.point_ids[idx]
    pts = m.point_arrays(pids)
    uv, z = project(frame.T_cw, pts.position, frame.camera.K)
    keep = grid.contains(uv, z) & ~pts.bad
    idx, pids, uv = idx[keep], pids[keep], uv[keep]
    lkp = last.keypoints
    match, _ = search_by_projection(
        frame.keypoints,
        grid,
        uv,
        lkp.octave[idx],
        pts.desc[keep],
        window,
        level_range=(-1, 1),
        ref_angle=lkp.angle[idx],
        available=frame.point_ids < 0,
    )
    return _link(frame, pids, match)


def track_with_motion_model(
    frame: Frame,
    grid: FeatureGrid,
    last: Frame,
    velocity: np.ndarray,
    m: Map,
    cfg: TrackingConfig,
    backend: BackendConfig,
) -> bool:
    """Predict ``frame``'s pose as velocity @ last.T_cw, match, refine; True on success
    (at least cfg.motion_min_inliers inliers)."""
    frame.set_pose(orthonormalize(velocity @ last.T_cw))
    frame.clear_links()
    n = search_last_frame(frame, grid, last, m, cfg.motion_window)
    if n < cfg.motion_min_matches:
        frame.clear_links()
        n = search_last_frame(frame, grid, last, m, 2.0 * cfg.motion_window)
    if n < cfg.motion_min_matches:
        log.debug("frame %d: motion model found %d matches", frame.id, n)
        return False
    optimize_frame_pose(frame, m, backend)
    discard_outliers(frame)
    n_in = int(np.count_nonzero(frame.point_ids >= 0))
    log.debug("frame %d: motion model %d matches, %d inliers", frame.id, n, n_in)
    return n_in >= cfg.motion_min_inliers


def match_reference_by_projection(
    frame: Frame, grid: FeatureGrid, ref: KeyFrame, m: Map, cfg: TrackingConfig
) -> int:
    """Match the reference keyframe's points projected with frame.T_cw in a wide window
    (cfg.ref_window x scale of the predicted level), ratio and rotation checks."""
    slots, pids = ref.observed_points()
    if len(pids) == 0:
        return 0
    pts = m.point_arrays(pids)
    uv, z = project(frame.T_cw, pts.position, frame.camera.K)
    keep = grid.contains(uv, z) & ~pts.bad
    slots, pids, uv = slots[keep], pids[keep], uv[keep]
    center = frame.center
    dist = np.linalg.norm(pts.position[keep] - center, axis=1)
    level = predict_scale(dist, pts.max_dist[keep], frame.keypoints.scale_factors)
    match, _ = search_by_projection(
        frame.keypoints,
        grid,
        uv,
        level,
        pts.desc[keep],
        cfg.ref_window,
        level_range=(-2, 2),
        ratio=cfg.ref_bow_ratio,
        ref_angle=ref.keypoints.angle[slots],
        available=frame.point_ids < 0,
    )
    return _link(frame, pids, match)


def match_reference_by_bow(frame: Frame, ref: KeyFrame, cfg: TrackingConfig) -> int:
    """ORB-SLAM2 SearchByBoW(KF, Frame): features under one vocabulary node, the keyframe's
    keypoint descriptors, ratio cfg.ref_bow_ratio, rotation check."""
    valid = ref.point_ids >= 0
    match = search_by_bow(
        ref.featvec,
        frame.featvec,
        ref.keypoints.desc,
        frame.keypoints.desc,
        ref.keypoints.angle,
        frame.keypoints.angle,
        valid1=valid,
        ratio=cfg.ref_bow_ratio,
    )
    ok = np.flatnonzero(match >= 0)
    frame.point_ids[match[ok]] = ref.point_ids[ok]
    return len(ok)


def track_reference_keyframe(
    frame: Frame,
    grid: FeatureGrid,
    last: Frame,
    ref: KeyFrame,
    m: Map,
    cfg: TrackingConfig,
    backend: BackendConfig,
) -> bool:
    """Match the reference keyframe's points, refine from the last pose; True on success."""
    frame.set_pose(last.T_cw)
    frame.clear_links()
    if ref.featvec is not None and frame.featvec is not None:
        n = match_reference_by_bow(frame, ref, cfg)
    else:
        n = match_reference_by_projection(frame, grid, ref, m, cfg)
    if n < cfg.ref_min_matches:
        log.debug("frame %d: reference keyframe %d gave %d matches", frame.id, ref.id, n)
        return False
    # Points fused meanwhile may appear twice; keep one slot each.
    ids = frame.point_ids[frame.point_ids >= 0]
    if len(np.unique(ids)) != len(ids):
        refresh_frame_points(frame, m)
    optimize_frame_pose(frame, m, backend)
    discard_outliers(frame)
    n_in = int(np.count_nonzero(frame.point_ids >= 0))
    log.debug("frame %d: reference keyframe %d: %d matches, %d inliers", frame.id, ref.id, n, n_in)
    return n_in >= cfg.motion_min_inliers
