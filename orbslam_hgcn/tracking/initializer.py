"""Monocular map initialisation: the driver around the two-view solver.

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. IV; Tracking::MonocularInitialization
and CreateInitialMapMonocular of ORB-SLAM2):

1. the first frame with more than 100 keypoints becomes the reference; the level-0
   keypoints of each following frame are matched to it in a 100 px window around their
   last matched position (ratio 0.9, rotation check); fewer than 100 matches and the
   reference is dropped (the next frame becomes the reference);
2. the homography and the fundamental matrix are fitted in parallel RANSACs, the model
   chosen by R_H, the motion recovered and the points triangulated with parallax,
   reprojection and cheirality checks (:class:`~orbslam_hgcn.geometry.two_view.TwoViewInitializer`);
3. the two keyframes and the points are added to the map and refined by a full BA over the
   two views; observations the BA still rejects (chi-square 5.991) are dropped;
4. the scale is fixed by setting the median scene depth of the first keyframe to 1; a map
   whose second keyframe then tracks fewer than 100 points is discarded and initialisation
   starts over.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.backend.bundle_adjustment import two_view_bundle_adjustment
from orbslam_hgcn.config import BackendConfig, InitializerConfig, TrackingConfig
from orbslam_hgcn.features.grid import FeatureGrid
from orbslam_hgcn.features.matching import search_for_initialization
from orbslam_hgcn.geometry.two_view import TwoViewInitializer
from orbslam_hgcn.map import Frame, KeyFrame, Map

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InitialMap:
    """A freshly initialised map: its two keyframes and the slots of the second keyframe's
    features that see each point.

    kf_first, kf_second: the keyframes (poses T_cw, scale: median depth of the first = 1);
    point_ids: (P,) int64 points created; slots_second: (P,) int64 their feature indices in
    the second keyframe; model: "H" or "F"; parallax_deg: of the reconstruction.
    """

    kf_first: KeyFrame
    kf_second: KeyFrame
    point_ids: np.ndarray
    slots_second: np.ndarray
    model: str
    parallax_deg: float


class MonocularInitializer:
    """Keeps the reference frame and its running matches until a map can be made."""

    def __init__(
        self,
        tracking: TrackingConfig | None = None,
        initializer: InitializerConfig | None = None,
        backend: BackendConfig | None = None,
    ) -> None:
        self.cfg = tracking or TrackingConfig()
        self.init_cfg = initializer or InitializerConfig()
        self.backend = backend or BackendConfig()
        self.solver = TwoViewInitializer(self.init_cfg)
        self.reference: Frame | None = None
        self._prev_uv: np.ndarray | None = None
        self.attempts = 0

    def reset(self) -> None:
        self.reference = None
        self._prev_uv = None

    def add_frame(self, frame: Frame, grid: FeatureGrid, m: Map) -> InitialMap | None:
        """Offer a frame; returns the initial map once one is made (added to ``m``)."""
        cfg = self.cfg
        if self.reference is None or len(frame) <= cfg.init_min_keypoints:
            self.reset()
            if len(frame) > cfg.init_min_keypoints:
                self.reference = frame
                self._prev_uv = frame.keypoints.uv.copy()
            return None
        ref = self.reference
        match, self._prev_uv = search_for_initialization(
            ref.keypoints, frame.keypoints, grid, self._prev_uv, cfg.init_window, cfg.init_ratio
        )
        i1 = np.flatnonzero(match >= 0)
        if len(i1) < cfg.init_min_matches:
            log.debug("initialisation: %d matches with frame %d; new reference", len(i1), ref.id)
            self.reset()
            self.reference = frame
            self._prev_uv = frame.keypoints.uv.copy()
            return None
        i2 = match[i1]
        self.attempts += 1
        res = self.solver.initialize(ref.keypoints.uv[i1], frame.keypoints.uv[i2], frame.camera.K)
        if res is None:
            return None
        good = res.triangulated
        log.debug(
            "initialisation: frames %d-%d model %s R_H %.2f, %d points, parallax %.2f deg",
            ref.id, frame.id, res.model, res.rh, int(good.sum()), res.parallax_deg,
        )  # fmt: skip
        return self._create_map(
            ref, frame, i1[good], i2[good], res.points[good], res.T_21, m, res.model, res.parallax_deg
        )

    def _create_map(
        self,
        ref: Frame,
        cur: Frame,
        i1: np.ndarray,
        i2: np.ndarray,
        X: np.ndarray,
        T_21: np.ndarray,
        m: Map,
        model: str,
        parallax: float,
    ) -> InitialMap | None:
        kp1, kp2, K = ref.keypoints, cur.keypoints, cur.camera.K
        T_1w = np.eye(4)
        # Full BA over the two views (ORB-SLAM: 20 iterations, first keyframe fixed).
        ba = two_view_bundle_adjustment(
            T_1w, T_21, X, kp1.uv[i1], kp2.uv[i2],
            kp1.inv_level_sigma2[kp1.octave[i1]], kp2.inv_level_sigma2[kp2.octave[i2]], K, self.backend,
        )  # fmt: skip
        n = len(X)
        inlier = ~(ba.outlier[:n] | ba.outlier[n:])
        T_2w, X = ba.T_cw[1], ba.points
        z1 = X[:, 2]
        inlier &= np.isfinite(z1) & (z1 > 0)
        if inlier.sum() < self.cfg.init_min_points:
            log.info("initialisation rejected: %d points after BA (< %d)", int(inlier.sum()), self.cfg.init_min_points)
            self.reset()
            return None
        median = float(np.median(z1[inlier]))
        if not median > 0:
            self.reset()
            return None
        inv = 1.0 / median
        T_2w = T_2w.copy()
        T_2w[:3, 3] *= inv
        X = X[inlier] * inv
        i1, i2 = i1[inlier], i2[inlier]
        ref.set_pose(T_1w)
        cur.set_pose(T_2w)
        with m.lock:
            kf1 = m.add_keyframe(ref)
            kf2 = m.add_keyframe(cur)
            pids = np.array([m.add_map_point(x, kf1.id) for x in X], dtype=np.int64)
            m.add_observations(kf1.id, pids, i1)
            m.add_observations(kf2.id, pids, i2)
            m.update_points(pids)
            m.update_connections(kf1.id)
            m.update_connections(kf2.id)
        self.reset()
        log.info(
            "map initialised from frames %d and %d (%s model, %d points, parallax %.1f deg)",
            ref.id, cur.id, model, len(pids), parallax,
        )  # fmt: skip
        return InitialMap(kf1, kf2, pids, i2, model, parallax)
