"""The local map of the tracker: local keyframes, local points, and their search.

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. V-D; Tracking::UpdateLocalMap and
SearchLocalPoints of ORB-SLAM2):

* local keyframes K1 are those observing a point matched in the frame; K2 adds, for each of
  them while fewer than 80 are chosen, one new keyframe among its 10 best covisible ones,
  one child and its parent in the spanning tree; the keyframe of K1 sharing the most points
  becomes the frame's reference keyframe;
* local points are the points of the local keyframes; each one not matched yet is
  searched when it passes the frustum test (in front of the camera, inside the image,
  distance within [0.8 d_min, 1.2 d_max], seen within 60 degrees of its mean viewing
  direction), at its predicted pyramid level, in a window of 2.5 (head-on) or 4 times the
  level's scale, with the 0.8 ratio test when the two best lie on one level.
"""

from __future__ import annotations

import logging
import numpy as np

from orbslam_hgcn.config import TrackingConfig
from orbslam_hgcn.map import Frame, Map, predict_scale
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.match.matching import radius_by_viewing_cos, search_by_projection
from orbslam_hgcn.tracking.frame_ops import project

log = logging.getLogger(__name__)


class LocalMap:
    """Local keyframes and points around the current frame (rebuilt every frame)."""

    def __init__(self, m: Map, config: TrackingConfig) -> None:
        self.map = m
        self.config = config
        self.kf_ids = np.zeros(0, dtype=np.int64)  # (K,) local keyframes, K1 first
        self.point_ids = np.zeros(0, dtype=np.int64)  # (P,) local points
        self.ref_kf_id = -1  # the K1 keyframe sharing the most points with the frame

    def update(self, frame: Frame) -> int:
        """Select local keyframes and points for ``frame`` (its matches must be fresh);
        returns the reference keyframe id (-1 when the frame has no match)."""
        m, cfg = self.map, self.config
        kf_ids, counts = m.observer_counts(frame.point_ids[frame.point_ids >= 0])
        if len(kf_ids) == 0:
            self.kf_ids = np.zeros(0, dtype=np.int64)
            self.point_ids = np.zeros(0, dtype=np.int64)
            self.ref_kf_id = -1
            return -1
        # Most shared points first, ties by id.
        k1 = [k for k in kf_ids[np.lexsort((kf_ids, -counts))].tolist() if not m.keyframe(k).bad]
        chosen = list(k1)
        seen = set(k1)

        def take(candidates) -> None:
            for c in candidates:
                c = int(c)
                if c not in seen and not m.keyframe(c).bad:
                    chosen.append(c)
                    seen.add(c)
                    return

        for k in k1:
            if len(chosen) >= cfg.max_local_keyframes:
                break
            kf = m.keyframe(k)
            take(m.covisible_keyframes(k, cfg.local_covisibles))
            take(sorted(kf.children))
            if kf.parent >= 0:
                take([kf.parent])
        self.kf_ids = np.array(chosen[: max(cfg.max_local_keyframes, len(k1))], dtype=np.int64)
        self.ref_kf_id = k1[0] if k1 else -1
        self.point_ids = self._points_of(self.kf_ids)
        return self.ref_kf_id

    def _points_of(self, kf_ids: np.ndarray) -> np.ndarray:
        """(P,) sorted unique good point ids of the keyframes."""
        m = self.map
        arrays = [m.keyframe(int(k)).point_ids for k in kf_ids]
        if not arrays:
            return np.zeros(0, dtype=np.int64)
        ids = np.concatenate(arrays)
        ids = ids[ids >= 0]
        if len(ids) == 0:
            return ids
        mask = np.zeros(int(ids.max()) + 1, dtype=bool)
        mask[ids] = True
        ids = np.flatnonzero(mask).astype(np.int64)
        return ids[~m.bad_points(ids)]

    def search(self, frame: Frame, grid: FeatureGrid, window: float, count_matched: bool = True) -> int:
        """Search the local points not yet matched in ``frame`` (ORB-SLAM2
        SearchLocalPoints): counts them as visible when they pass the frustum test and
        links the matches. Returns the number of new matches. ``count_matched``: the points
        already matched count as visible too (False when the frame was counted before)."""
        m, cfg = self.map, self.config
        matched = frame.point_ids[frame.point_ids >= 0]
        if len(matched) and count_matched:
            m.increase_visible(matched)
        cand = self.point_ids
        if len(matched) and len(cand):
            cand = cand[~np.isin(cand, matched, kind="table")]  # point ids are dense
        if len(cand) == 0:
            return 0
        pts = m.point_arrays(cand)
        uv, z = project(frame.T_cw, pts.position, frame.camera.K)
        PO = pts.position - frame.center
        dist = np.linalg.norm(PO, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            view_cos = np.sum(PO * pts.normal, axis=1) / dist
            vis = (
                (z > 0)
                & (uv[:, 0] >= grid.min_x)
                & (uv[:, 0] < grid.max_x)
                & (uv[:, 1] >= grid.min_y)
                & (uv[:, 1] < grid.max_y)
                & (dist >= 0.8 * pts.min_dist)
                & (dist <= 1.2 * pts.max_dist)
                & (view_cos >= cfg.frustum_min_cos)
                & ~pts.bad
            )
        sel = np.flatnonzero(vis)
        if len(sel) == 0:
            return 0
        m.increase_visible(cand[sel])
        level = predict_scale(dist[sel], pts.max_dist[sel], frame.keypoints.scale_factors)
        match, _ = search_by_projection(
            frame.keypoints,
            grid,
            uv[sel],
            level,
            pts.desc[sel],
            window * radius_by_viewing_cos(view_cos[sel]),
            level_range=(-1, 0),
            ratio=cfg.local_ratio,
            available=frame.point_ids < 0,
        )
        ok = match >= 0
        frame.point_ids[match[ok]] = cand[sel][ok]
        return int(ok.sum())
