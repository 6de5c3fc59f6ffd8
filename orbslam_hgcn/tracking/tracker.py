"""The monocular tracker: one entry, :meth:`Tracker.track`, per frame.

ORB-SLAM's tracking thread as a plain class (Mur-Artal, Montiel & Tardos, T-RO 2015,
Sec. V; Tracking::Track of ORB-SLAM2): initialise the map from two views; then, per frame,
predict with the constant-velocity model (or match the reference keyframe), refine the
pose, track the local map, refine again, decide on a keyframe. States are NOT_INITIALIZED,
OK and LOST; a map with few keyframes is discarded when tracking is lost and
initialisation starts over. Relocalisation plugs in as an object with
``relocalize(frame, grid) -> bool`` (it sets the frame's pose and matches).

The tracker never calls the local mapper: a keyframe it makes is returned in the
:class:`TrackResult` (its observations already linked in the map) and the caller hands it
on. For every frame it records the pose relative to its reference keyframe, so the camera
trajectory can be rebuilt at the end from the optimised keyframes (ORB-SLAM's
mlRelativeFramePoses).
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from orbslam_hgcn.config import BackendConfig, InitializerConfig, TrackingConfig
from orbslam_hgcn.features.orb import ORBExtractor
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import inv_T
from orbslam_hgcn.map import Frame, KeyFrame, Map
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.tracking.frame_ops import (
    FrameMatches,
    discard_outliers,
    good_keyframe,
    optimize_frame_pose,
    orthonormalize,
    pose_from_reference,
    refresh_frame_points,
    scale_motion,
)
from orbslam_hgcn.tracking.initializer import InitialMap, MonocularInitializer
from orbslam_hgcn.tracking.keyframe_decision import (
    KeyFrameQuery,
    keyframe_starved,
    max_frames,
    min_observations,
    need_new_keyframe,
)
from orbslam_hgcn.tracking.local_map import LocalMap
from orbslam_hgcn.tracking.motion import track_reference_keyframe, track_with_motion_model

log = logging.getLogger(__name__)


class TrackingState(enum.Enum):
    NOT_INITIALIZED = "not initialised"
    OK = "ok"
    LOST = "lost"


class Relocalizer(Protocol):
    def relocalize(self, frame: Frame, grid: FeatureGrid) -> bool: ...


@dataclass
class PoseRecord:
    """The tracker's estimate for one frame.

    ref_kf_id: reference keyframe (-1: none); T_cr: (4, 4) pose relative to it
    (T_cw = T_cr @ T_rw), None when the frame has no pose; state: after tracking;
    generation: the map it refers to (a reset starts a new generation); dropped: the
    frame was not processed because the system was behind its camera; unreadable: the
    frame was not processed because its image could not be read (and was skipped).
    """

    frame_id: int
    timestamp: float
    ref_kf_id: int
    T_cr: np.ndarray | None
    state: TrackingState
    generation: int
    dropped: bool = False  # never processed: the system was behind its camera
    unreadable: bool = False  # never processed: its image could not be read
    # The inlier matches the pose was tracked with (TrackingConfig.refine_frame_poses).
    matches: FrameMatches | None = None


@dataclass
class TrackResult:
    """Outcome of one frame: state, inliers, keyframes to hand to local mapping, events."""

    frame: Frame | None
    state: TrackingState
    n_inliers: int = 0
    new_keyframes: list[KeyFrame] = field(default_factory=list)
    initialized: bool = False
    lost: bool = False  # tracking was lost on this frame
    reset: bool = False  # the map was discarded on this frame (tracker.map is a new one)
    new_map: bool = False  # a new map was started on this frame; the previous one is kept (atlas)
    switched_map: bool = False  # relocalised into another map of the atlas, now the active one
    why: str = ""  # why the map was reset or a new one started
    # A keyframe was due by the rules (keyframe_decision.keyframe_starved) but local mapping
    # was busy: the caller may let mapping catch up before the next frame.
    keyframe_starved: bool = False
    time_ms: float = 0.0  # wall-clock time of track()
    # CPU time of the tracking thread in track() (time.thread_time: the process's clock sums
    # every thread's and cost 0.3 ms a call here, with mapping's threads running)
    cpu_ms: float = 0.0


class Tracker:
    """Monocular ORB-SLAM tracking over one :class:`Map`, or over the active map of an
    :class:`~orbslam_hgcn.map.atlas.Atlas`.

    m: the map (an atlas's active map when ``atlas`` is given); vocabulary: optional
    (``transform(desc) -> (BowVector, FeatureVector)``), used to match the reference
    keyframe by BoW; mapping_idle: tells whether local mapping accepts keyframes (always
    True when stages run in order); relocalizer: optional.

    With an atlas (ORB-SLAM3's, Campos et al., T-RO 2021): when tracking has been lost for
    ``new_map_after_s`` of camera time and relocalisation keeps failing, a new map is
    started and the lost one kept; relocalisation may land in any map, which becomes the
    active one. A map lost with at most ``reset_max_keyframes`` keyframes is discarded.
    """

    def __init__(
        self,
        m: Map,
        config: TrackingConfig | None = None,
        initializer: InitializerConfig | None = None,
        backend: BackendConfig | None = None,
        vocabulary: Any = None,
        mapping_idle: Callable[[], bool] | None = None,
        relocalizer: Relocalizer | None = None,
        extractor: ORBExtractor | None = None,
        camera: PinholeCamera | None = None,
        atlas: Any = None,
    ) -> None:
        self.atlas = atlas
        self.config = config or TrackingConfig()
        self.backend = backend or BackendConfig()
        self.vocabulary = vocabulary
        self.mapping_idle = mapping_idle or (lambda: True)
        # A keyframe counts as starved (TrackResult.keyframe_starved) also when only c1b's
        # idle mapping is missing (keyframe_decision.keyframe_starved's on_interval).
        self.starved_on_interval = False
        self.relocalizer = relocalizer
        self.extractor = extractor
        self.init_extractor = None
        if extractor is not None:
            n_init = max(1, int(round(extractor.config.n_features * self.config.init_features_factor)))
            self.init_extractor = ORBExtractor(dataclasses.replace(extractor.config, n_features=n_init))
        self.camera = camera
        self.initializer = MonocularInitializer(self.config, initializer, self.backend)
        self.records: list[PoseRecord] = []
        self.generation = 0
        # Localisation only (ORB-SLAM2's mbOnlyTracking): track against the map without
        # making keyframes, and never discard the map when tracking is lost.
        self.localization = False
        self._next_frame_id = 0
        self._bind(m)

    # --- state ------------------------------------------------------------------------
    def _bind(self, m: Map) -> None:
        self.map = m
        self.local_map = LocalMap(m, self.config)
        self.state = TrackingState.NOT_INITIALIZED
        self.last_frame: Frame | None = None
        self.velocity: np.ndarray | None = None
        self.velocity_dt = 0.0  # camera time the velocity covers (s)
        self.ref_kf_id = -1
        self.last_kf_frame_id = -1
        self.last_kf_timestamp = float("nan")
        self.last_reloc_frame_id = -1
        self.lost_since = float("nan")  # camera time tracking was lost (nan: not lost)
        self.initializer.reset()

    def reset(self, m: Map | None = None) -> None:
        """Forget the map (a new empty one unless given) and start initialising again. In
        an atlas the map is discarded and a new one started."""
        self.generation += 1
        if m is None and self.atlas is not None:
            self.atlas.drop(self.map)
            m = self.atlas.new_map()
        self._bind(m if m is not None else Map(self.map.config))

    def start_new_map(self) -> None:
        """Keep the current map (inactive) and start initialising a new one (atlas only)."""
        m = self.atlas.new_map()
        self._bind(m)

    def switch_map(self, m: Map) -> None:
        """Make ``m`` (another map of the atlas) the active one, tracking state kept: the
        current frame was relocalised against it."""
        self.atlas.set_active(m)
        self.map = m
        self.local_map = LocalMap(m, self.config)
        self.last_kf_frame_id = -1
        self.last_kf_timestamp = float("nan")

    def rescale_records(self, kf_ids: set[int], scale: float) -> None:
        """A merge moved keyframes ``kf_ids`` by a similarity of ``scale``: the poses kept
        relative to them (T_cr) take the new scale (an atlas merge hook)."""
        for rec in self.records:
            if rec.T_cr is not None and rec.ref_kf_id in kf_ids:
                T = rec.T_cr.copy()
                T[:3, 3] *= scale
                rec.T_cr = T

    @property
    def can_recover(self) -> bool:
        """False once tracking is lost with no way back (no relocaliser and no atlas)."""
        return self.state != TrackingState.LOST or self.relocalizer is not None or self.atlas is not None

    # --- entry points ------------------------------------------------------------------
    def track_image(self, image: np.ndarray, timestamp: float) -> TrackResult:
        """Extract ORB features of an (H, W) uint8 image and track it."""
        if self.extractor is None or self.camera is None:
            raise ValueError("track_image needs the tracker built with an extractor and a camera")
        initializing = self.state == TrackingState.NOT_INITIALIZED
        kps = (self.init_extractor if initializing else self.extractor).extract(image, self.camera)
        return self.track(Frame(self._next_frame_id, timestamp, self.camera, kps))

    def skip(self, frame_id: int, timestamp: float) -> TrackResult:
        """Record a frame that is not processed (lost with no way to recover)."""
        self._next_frame_id = frame_id + 1
        self._record(frame_id, timestamp, None)
        return TrackResult(None, self.state)

    def drop(self, frame_id: int, timestamp: float, unreadable: bool = False) -> None:
        """Record a frame the system dropped unprocessed, as a camera driver drops the frames
        a busy reader misses (or, with ``unreadable``, a frame whose image could not be
        read); the tracking state is unchanged."""
        self._next_frame_id = frame_id + 1
        self.records.append(PoseRecord(frame_id, timestamp, -1, None, self.state, self.generation,
                                       dropped=not unreadable, unreadable=unreadable))  # fmt: skip

    def track(self, frame: Frame) -> TrackResult:
        """Track one frame (features extracted); returns what happened."""
        t0, c0 = time.perf_counter(), time.thread_time()
        self._next_frame_id = frame.id + 1
        grid = FeatureGrid(frame.keypoints, frame.camera)
        if self.state == TrackingState.NOT_INITIALIZED:
            result = self._initialize(frame, grid)
        else:
            result = self._track(frame, grid)
        result.time_ms = 1000.0 * (time.perf_counter() - t0)
        result.cpu_ms = 1000.0 * (time.thread_time() - c0)
        return result

    # --- initialisation ----------------------------------------------------------------
    def _initialize(self, frame: Frame, grid: FeatureGrid) -> TrackResult:
        back = self._relocalise_elsewhere(frame, grid)
        if back is not None:
            return back
        init = self.initializer.add_frame(frame, grid, self.map)
        if init is None:
            self._record(frame.id, frame.timestamp, None)
            return TrackResult(frame, self.state)
        self._on_initialized(frame, init)
        if self.generation > 0:
            log.warning(
                "frame %d (t=%.3f): map re-initialised after %d reset(s); earlier frames have no pose",
                frame.id, frame.timestamp, self.generation,
            )  # fmt: skip
        self._record(frame.id, frame.timestamp, frame)
        return TrackResult(
            frame, self.state, len(init.point_ids), [init.kf_first, init.kf_second], initialized=True
        )

    def _relocalise_elsewhere(self, frame: Frame, grid: FeatureGrid) -> TrackResult | None:
        """While a new map of an atlas has no keyframe yet: relocalise the frame against the
        other maps, and on success go on in that map (the empty new one is dropped). None
        when there is nothing to try or it fails (the frame then goes to initialisation)."""
        atlas = self.atlas
        if atlas is None or self.relocalizer is None or self.localization or self.map.n_keyframes() > 0:
            return None
        if not any(m.n_keyframes() for m in atlas.maps.values() if m is not self.map):
            return None
        self._compute_bow(frame)
        if not self.relocalizer.relocalize(frame, grid):
            return None
        kf_id = int(self.relocalizer.last.kf_id)
        other = atlas.map_of(kf_id)
        if other is None or other is self.map:
            return None
        empty = self.map
        self.switch_map(other)
        self.ref_kf_id = kf_id
        self.last_reloc_frame_id = frame.id
        ok, n_in = self._track_local_map(frame, grid)
        if not ok:  # back to initialising the new map, its initialiser untouched
            self.atlas.set_active(empty)
            self.map, self.local_map = empty, LocalMap(empty, self.config)
            self.ref_kf_id = self.last_reloc_frame_id = -1
            frame.clear_links()
            frame.T_cw = None
            return None
        atlas.remove(empty)
        self.initializer.reset()
        log.warning("frame %d (t=%.3f): relocalised in map %d before the new map was made; going on there",
                    frame.id, frame.timestamp, other.map_id)  # fmt: skip
        self.state = TrackingState.OK
        self.lost_since = float("nan")
        self.velocity = None
        discard_outliers(frame)
        frame.ref_kf_id = self.ref_kf_id
        self._record(frame.id, frame.timestamp, frame)
        self.last_frame = frame
        return TrackResult(frame, self.state, n_in, switched_map=True)

    def _on_initialized(self, frame: Frame, init: InitialMap) -> None:
        kf1, kf2 = init.kf_first, init.kf_second
        # The reference frame of the initialisation is the first keyframe: its record,
        # written while not initialised, now gets a pose.
        for rec in reversed(self.records):
            if rec.frame_id == kf1.frame_id and rec.generation == self.generation:
                rec.ref_kf_id, rec.T_cr, rec.state = kf1.id, np.eye(4), TrackingState.OK
                break
        frame.clear_links()
        frame.point_ids[init.slots_second] = init.point_ids
        frame.ref_kf_id = kf2.id
        self.ref_kf_id = kf2.id
        self.last_kf_frame_id = frame.id
        self.last_kf_timestamp = frame.timestamp
        self.local_map.update(frame)
        self.local_map.ref_kf_id = kf2.id
        self.velocity = None
        self.state = TrackingState.OK
        self.last_frame = frame

    # --- tracking ----------------------------------------------------------------------
    def _track(self, frame: Frame, grid: FeatureGrid) -> TrackResult:
        cfg, m = self.config, self.map
        was_ok = self.state == TrackingState.OK
        ok = False
        if was_ok:
            last = self.last_frame
            self._update_last_frame()
            if self.velocity is not None and frame.id >= self.last_reloc_frame_id + 2:
                ok = track_with_motion_model(frame, grid, last, self._predicted_motion(frame, last), m, cfg,
                                             self.backend)  # fmt: skip
            if not ok:
                ok = self._track_reference(frame, grid, last)
        elif self.relocalizer is not None:
            self._compute_bow(frame)
            ok = self.relocalizer.relocalize(frame, grid)
            if ok:
                self.last_reloc_frame_id = frame.id
                log.warning("frame %d (t=%.3f): relocalised", frame.id, frame.timestamp)
        switched = False
        if ok and not was_ok and self.atlas is not None:
            other = self.atlas.map_of(int(self.relocalizer.last.kf_id))
            if other is not None and other is not m:
                log.warning("frame %d: relocalised in map %d, now the active map (map %d kept)",
                            frame.id, other.map_id, m.map_id)  # fmt: skip
                self.switch_map(other)
                self.ref_kf_id = int(self.relocalizer.last.kf_id)
                m, switched = other, True
        n_in = 0
        if ok:
            ok, n_in = self._track_local_map(frame, grid)
        result = TrackResult(frame, self.state, n_in, switched_map=switched)
        if ok:
            self.state = TrackingState.OK
            self.lost_since = float("nan")
            if self.last_frame is not None and self.last_frame.T_cw is not None:
                self.velocity = orthonormalize(frame.T_cw @ inv_T(self.last_frame.T_cw))
                self.velocity_dt = frame.timestamp - self.last_frame.timestamp
            kf, result.keyframe_starved = self._maybe_keyframe(frame, n_in)
            if kf is not None:
                result.new_keyframes.append(kf)
            discard_outliers(frame)
            frame.ref_kf_id = self.ref_kf_id
            self._record(frame.id, frame.timestamp, frame)
            self.last_frame = frame
        else:
            self.velocity = None
            self.state = TrackingState.LOST
            frame.T_cw = None
            self._record(frame.id, frame.timestamp, None)
            if was_ok:
                result.lost = True
                self.lost_since = frame.timestamp
                log.warning(
                    "frame %d (t=%.3f): tracking lost (%d inliers after the local map, %d keyframes in the map)",
                    frame.id, frame.timestamp, n_in, m.n_keyframes(),
                )  # fmt: skip
            if m.n_keyframes() <= cfg.reset_max_keyframes and not self.localization:
                result.why = f"tracking lost with only {m.n_keyframes()} keyframe(s) in the map"
                log.warning("map reset: %s; initialising again", result.why)
                self.reset()
                result.reset = True
            elif (
                self.atlas is not None and not self.localization
                and not frame.timestamp - self.lost_since < cfg.new_map_after_s
            ):  # fmt: skip
                log.warning("frame %d (t=%.3f): lost for %.1f s; map %d kept, a new map is started",
                            frame.id, frame.timestamp, frame.timestamp - self.lost_since, m.map_id)  # fmt: skip
                self.start_new_map()
                result.new_map = True
                result.why = f"tracking lost for {frame.timestamp - self.lost_since:.1f} s"
            elif was_ok and self.relocalizer is None and self.atlas is None:
                log.warning("no relocalisation available: the remaining frames are counted as lost")
        result.state = self.state
        return result

    def _predicted_motion(self, frame: Frame, last: Frame) -> np.ndarray:
        """The constant-velocity motion from ``last`` to ``frame``: the last frame-to-frame
        motion, scaled by the ratio of the time gaps when frames were skipped or dropped
        between them (ORB-SLAM applies the last motion as it is, every frame being
        processed; a dropped frame would then leave the prediction a whole frame short)."""
        dt = frame.timestamp - last.timestamp
        if self.velocity_dt > 0 and np.isfinite(dt) and dt > 0:
            r = dt / self.velocity_dt
            if abs(r - 1.0) > 0.25:
                return scale_motion(self.velocity, min(r, 5.0))
        return self.velocity

    def _compute_bow(self, frame: Frame) -> None:
        if self.vocabulary is not None and frame.featvec is None:
            frame.bow, frame.featvec = self.vocabulary.transform(frame.keypoints.desc)

    def _track_reference(self, frame: Frame, grid: FeatureGrid, last: Frame) -> bool:
        """Track against the reference keyframe (its nearest good ancestor if culled)."""
        ref_id = good_keyframe(self.map, self.ref_kf_id)
        if ref_id < 0:
            return False
        self.ref_kf_id = ref_id
        ref = self.map.keyframe(ref_id)
        if ref.featvec is not None:
            self._compute_bow(frame)
        return track_reference_keyframe(frame, grid, last, ref, self.map, self.config, self.backend)

    def _update_last_frame(self) -> None:
        """Refresh the last frame: fused points, and its pose from its reference keyframe
        (which local BA may have moved; ORB-SLAM2 UpdateLastFrame)."""
        last = self.last_frame
        refresh_frame_points(last, self.map)
        rec = self.records[-1] if self.records else None
        if rec is not None and rec.frame_id == last.id and rec.T_cr is not None and rec.ref_kf_id >= 0:
            T_cw = pose_from_reference(self.map, rec.ref_kf_id, rec.T_cr)
            if T_cw is not None:
                last.set_pose(orthonormalize(T_cw))

    def _track_local_map(self, frame: Frame, grid: FeatureGrid) -> tuple[bool, int]:
        cfg, m = self.config, self.map
        refresh_frame_points(frame, m)
        ref = self.local_map.update(frame)
        if ref >= 0:
            self.ref_kf_id = ref
        recent_reloc = self.last_reloc_frame_id >= 0 and frame.id < self.last_reloc_frame_id + 2
        window = cfg.local_window_relocalised if recent_reloc else cfg.local_window
        self.local_map.search(frame, grid, window)
        optimize_frame_pose(frame, m, self.backend)
        inl = frame.point_ids[frame.matched]
        if len(inl):
            m.increase_found(inl)
        n_in = len(inl)
        n_max = max_frames(cfg, frame.camera.fps)
        if self.last_reloc_frame_id >= 0 and frame.id < self.last_reloc_frame_id + n_max:
            return n_in >= cfg.min_inliers_relocalised, n_in
        return n_in >= cfg.min_inliers, n_in

    def keyframe_now(self, frame: Frame, n_in: int, retrack: bool = False) -> KeyFrame | None:
        """After waiting for a busy local mapping (a keyframe_starved frame): make the
        keyframe the rules asked for on ``frame``, the last frame tracked, if they still
        ask for it now that mapping may take it; None otherwise. ``retrack``: first search
        the local map again, which now holds the points mapping made meanwhile."""
        if frame is not self.last_frame or self.state != TrackingState.OK or frame.T_cw is None:
            return None
        if retrack:
            n_in = self._retrack_local_map(frame)
        kf, _ = self._maybe_keyframe(frame, n_in)
        if kf is not None:
            # The frame's record was written relative to the reference keyframe it was tracked
            # in; it now refers to the keyframe made from it (ORB-SLAM: a frame's reference is
            # the keyframe it became), so the pose written for it is that keyframe's, however
            # local BA moves it. Relative to the old reference, the frame would keep its
            # tracked pose while BA moved its keyframe: over a loaded KITTI run such frames
            # were 25-39 cm off their own keyframe's pose.
            rec = self.records[-1]
            if rec.frame_id == frame.id and rec.generation == self.generation:
                rec.ref_kf_id, rec.T_cr = kf.id, frame.T_cw @ kf.T_wc
            frame.ref_kf_id = kf.id
        return kf

    def _retrack_local_map(self, frame: Frame) -> int:
        """Search the local map of ``frame`` (tracked, outliers discarded) again and
        optimise its pose; its matches counted as visible and found already are not
        counted again. Returns the inliers."""
        m = self.map
        refresh_frame_points(frame, m)
        before = frame.point_ids.copy()
        ref = self.local_map.update(frame)
        if ref >= 0:
            self.ref_kf_id = ref
        self.local_map.search(frame, FeatureGrid(frame.keypoints, frame.camera), self.config.local_window,
                              count_matched=False)  # fmt: skip
        optimize_frame_pose(frame, m, self.backend)
        new = frame.matched & (before < 0)
        if new.any():
            m.increase_found(frame.point_ids[new])
        discard_outliers(frame)
        return int(np.count_nonzero(frame.point_ids >= 0))

    def _maybe_keyframe(self, frame: Frame, n_in: int) -> tuple[KeyFrame | None, bool]:
        """(the new keyframe or None, whether one was due but local mapping was busy)."""
        if self.localization:
            return None, False
        m = self.map
        # The rules compare the count with small numbers only: counting past the largest
        # of them would cost a pass over every keyframe of a long run's map per frame.
        bound = max(3, max_frames(self.config, frame.camera.fps), self.config.min_keyframe_interval_from) + 1
        n_kfs = m.n_keyframes(limit=bound)
        ref_id = good_keyframe(m, self.ref_kf_id)
        ref_tracked = 0 if ref_id < 0 else m.tracked_points(ref_id, min_observations(n_kfs))
        q = KeyFrameQuery(
            frame_id=frame.id,
            last_kf_frame_id=self.last_kf_frame_id,
            last_reloc_frame_id=self.last_reloc_frame_id,
            n_keyframes=n_kfs,
            n_inliers=n_in,
            ref_tracked=ref_tracked,
            mapping_idle=bool(self.mapping_idle()),
            fps=frame.camera.fps,
            timestamp=frame.timestamp,
            last_kf_timestamp=self.last_kf_timestamp,
        )
        if not need_new_keyframe(q, self.config):
            return None, keyframe_starved(q, self.config, self.starved_on_interval)
        keep = frame.point_ids >= 0
        if not self.config.keyframe_keeps_outliers:
            keep &= ~frame.outlier
        slots = np.flatnonzero(keep)
        with m.lock:
            kf = m.add_keyframe(frame)
            good = ~m.point_arrays(frame.point_ids[slots]).bad
            m.add_observations(kf.id, frame.point_ids[slots[good]], slots[good])
        self.ref_kf_id = kf.id
        self.last_kf_frame_id = frame.id
        self.last_kf_timestamp = frame.timestamp
        return kf, False

    # --- trajectory records ------------------------------------------------------------
    def _record(self, frame_id: int, timestamp: float, frame: Frame | None) -> None:
        T_cr, ref = None, -1
        ref_id = good_keyframe(self.map, self.ref_kf_id) if frame is not None and frame.T_cw is not None else -1
        if ref_id >= 0:
            ref = ref_id
            T_cr = frame.T_cw @ self.map.keyframe(ref).T_wc
        matches = None
        if T_cr is not None and self.config.refine_frame_poses:
            idx = np.flatnonzero(frame.point_ids >= 0)  # the outliers are discarded by now
            kp = frame.keypoints
            matches = FrameMatches(frame.point_ids[idx], kp.uv[idx].astype(np.float32), kp.octave[idx].astype(np.uint8),
                                   kp.scale_factors, frame.camera.K)  # fmt: skip
        self.records.append(PoseRecord(frame_id, timestamp, ref, T_cr, self.state, self.generation, matches=matches))
