"""Monocular map initialisation: the driver around the two-view solver.

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. IV; Tracking::MonocularInitialization
and CreateInitialMapMonocular of ORB-SLAM2):

1. the first frame with more than 100 keypoints becomes the reference; its keypoints are
   followed into each later frame and the reference is dropped (the next frame becomes
   the reference) when fewer than 100 of them are found;
2. the homography and the fundamental matrix are fitted in parallel RANSACs, the model
   chosen by R_H, the motion recovered and the points triangulated with parallax,
   reprojection and cheirality checks (:class:`~orbslam_hgcn.geometry.two_view.TwoViewInitializer`);
3. the two keyframes and the points are added to the map and refined by a full BA over the
   two views; observations the BA still rejects (chi-square 5.991) are dropped;
4. the scale is fixed by setting the median scene depth of the first keyframe to 1; a map
   whose second keyframe then tracks fewer than 100 points is discarded and initialisation
   starts over.

How the reference's keypoints are followed differs from ORB-SLAM, which searches only the
reference's level-0 keypoints, with the reference's descriptors, at level 0 of each new
frame, in a 100 px window around their last matched position. On real forward driving
(KITTI 00, 2000 features) that found only 50-90 matches between consecutive frames, so
the reference was dropped every frame or two and the parallax never reached 1 degree.
Here every keypoint of the reference is followed frame to frame
(:func:`~orbslam_hgcn.match.matching.search_for_initialization_tracks`): searched
with its descriptor, level and orientation as last seen, within one level of it, around
its last position moved by its last image motion, in a window of ``init_window`` px at
640 px image width, scaled with the image (194 px on KITTI's 1241 px). A keypoint not
found in one frame is searched for again in the next; after two misses it is dropped.
Matches that did not follow one rigid motion are left to the two-view RANSAC, as before.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.backend.bundle_adjustment import two_view_bundle_adjustment
from orbslam_hgcn.config import BackendConfig, InitializerConfig, TrackingConfig
from orbslam_hgcn.geometry.two_view import TwoViewInitializer
from orbslam_hgcn.map import Frame, KeyFrame, Map
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.match.matching import search_for_initialization_tracks

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


# Init windows are given for a 640 px wide image and scaled with the image's larger side.
REFERENCE_IMAGE_SIDE = 640.0
# A followed keypoint not found in this many consecutive frames is dropped.
MAX_MISSES = 1


@dataclass
class _Tracks:
    """The reference's keypoints as last seen: (N, 2) position, (N, 2) image motion per
    frame, (N, 32) descriptor, (N,) level, (N,) angle, (N,) consecutive misses, (N,) alive."""

    uv: np.ndarray
    motion: np.ndarray
    desc: np.ndarray
    octave: np.ndarray
    angle: np.ndarray
    missed: np.ndarray
    alive: np.ndarray

    @classmethod
    def start(cls, frame: Frame) -> _Tracks:
        kp = frame.keypoints
        n = len(kp)
        return cls(
            kp.uv.astype(np.float64).copy(), np.zeros((n, 2)), kp.desc.copy(), kp.octave.astype(np.int64),
            kp.angle.astype(np.float64), np.zeros(n, dtype=np.int64), np.ones(n, dtype=bool),
        )  # fmt: skip


class MonocularInitializer:
    """Keeps the reference frame and its followed keypoints until a map can be made."""

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
        self._tracks: _Tracks | None = None
        self.attempts = 0

    def reset(self) -> None:
        self.reference = None
        self._tracks = None

    def _start(self, frame: Frame) -> None:
        self.reference = frame
        self._tracks = _Tracks.start(frame)

    def _follow(self, frame: Frame, grid: FeatureGrid) -> tuple[np.ndarray, np.ndarray]:
        """Search the live tracks in ``frame``; returns (reference indices, frame indices)
        of the keypoints found, and updates the tracks."""
        cfg, t, kp = self.cfg, self._tracks, frame.keypoints
        cam = frame.camera
        window = cfg.init_window * max(cam.width, cam.height) / REFERENCE_IMAGE_SIDE
        q = np.flatnonzero(t.alive)
        centre = t.uv[q] + t.motion[q] * (t.missed[q] + 1)[:, None]
        match, _ = search_for_initialization_tracks(
            t.desc[q], t.octave[q], t.angle[q], centre, kp, grid, window, cfg.init_ratio
        )
        found = match >= 0
        i1, i2 = q[found], match[found]
        t.motion[i1] = (kp.uv[i2] - t.uv[i1]) / (t.missed[i1] + 1)[:, None]
        t.uv[i1] = kp.uv[i2]
        t.desc[i1] = kp.desc[i2]
        t.octave[i1] = kp.octave[i2]
        t.angle[i1] = kp.angle[i2]
        t.missed[i1] = 0
        lost = q[~found]
        t.missed[lost] += 1
        t.alive[lost] = t.missed[lost] <= MAX_MISSES
        return i1, i2

    def add_frame(self, frame: Frame, grid: FeatureGrid, m: Map) -> InitialMap | None:
        """Offer a frame; returns the initial map once one is made (added to ``m``)."""
        cfg = self.cfg
        if self.reference is None or len(frame) <= cfg.init_min_keypoints:
            self.reset()
            if len(frame) > cfg.init_min_keypoints:
                self._start(frame)
            return None
        ref = self.reference
        i1, i2 = self._follow(frame, grid)
        if len(i1) < cfg.init_min_matches:
            log.debug("initialisation: %d matches with frame %d; new reference", len(i1), ref.id)
            self._start(frame)
            return None
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
            pids = m.add_map_points(X, kf1.id)
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
