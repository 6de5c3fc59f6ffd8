"""Plain-array records that the pipeline fills for the visualiser, and the entity layout.

The visualiser never reads map objects: the pipeline copies what it wants shown into a
:class:`FrameLog` (every frame) and a :class:`MapSnapshot` (when the map is logged), so
logging never holds the map lock and never sees half-updated links.

This module imports numpy only, so that the pipeline can build records without importing
the rerun SDK.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

# --- Entity paths: the contract between the logger and the default blueprint ----------
WORLD = "world"
CAMERA = "world/camera"  # Transform3D of the current camera (T_wc), one per tracked frame
IMAGE = "world/camera/image"  # Pinhole (static) and the current image
KEYPOINTS_TRACKED = "world/camera/image/keypoints/tracked"
KEYPOINTS_UNTRACKED = "world/camera/image/keypoints/untracked"
MAP_POINTS = "world/map/points"
KEYFRAMES = "world/map/keyframes"  # all keyframe frustums as line strips in one entity
KEYFRAME_PATH = "world/map/keyframe_path"  # keyframe centres in id order
COVISIBILITY = "world/map/covisibility"
LOOP_EDGES = "world/map/loop_edges"
TRAJECTORY = "world/trajectory/estimate"
GROUND_TRUTH = "world/trajectory/ground_truth"
PLOT_TRACKING = "plots/tracking"  # two series: tracked map points, keypoints
PLOT_FPS = "plots/fps"
PLOT_STATE = "plots/state"
PLOT_KEYFRAMES = "plots/keyframes"
PLOT_MAP_POINTS = "plots/map_points"
PLOT_ATE = "plots/ate"
PLOT_LOOPS = "plots/loops"
EVENTS = "events"
OTHER_MAPS = "world/other_maps"  # the inactive maps of an atlas: OTHER_MAPS/map_<id>/{points,keyframes}

# Numeric codes of tracking states for the time-series plot (higher is healthier, except
# lost). ORB-SLAM's states plus the names a tracker is likely to use for them.
TRACKING_STATE_CODES: dict[str, int] = {
    "system_not_ready": -1,
    "no_images_yet": 0,
    "not_initialized": 0,
    "not_initialised": 0,
    "initializing": 1,
    "initialising": 1,
    "ok": 2,
    "tracking": 2,
    "relocalized": 2,
    "relocalised": 2,
    "recently_lost": 3,
    "relocalizing": 3,
    "relocalising": 3,
    "lost": 4,
}
UNKNOWN_STATE_CODE = -1


def state_name(state: str | Enum) -> str:
    """Normalised name of a tracking state given as a string or an Enum member."""
    raw = state.name if isinstance(state, Enum) else str(state)
    return raw.strip().lower().replace("-", "_").replace(" ", "_")


def state_code(state: str | Enum) -> int:
    """Numeric code of a tracking state (:data:`TRACKING_STATE_CODES`; -1 when unknown)."""
    return TRACKING_STATE_CODES.get(state_name(state), UNKNOWN_STATE_CODE)


def _check(arr: np.ndarray, name: str, shape: tuple[int | None, ...]) -> None:
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")


@dataclass(frozen=True, eq=False)
class FrameLog:
    """What is shown of one processed frame.

    index:        frame number in the sequence (the ``frame`` timeline)
    timestamp:    seconds (dataset clock); epochs above 1e8 s are shown as dates
    image:        (H, W) uint8 gray or (H, W, 3) uint8 BGR, as read (distorted)
    keypoints_uv: (N, 2) pixel coords in ``image`` (``KeypointSet.uv_raw``)
    tracked:      (N,) bool, keypoint matched to a map point
    T_wc:         (4, 4) camera-to-world pose, or None when not tracked
    state:        tracking state name (str or Enum member; see TRACKING_STATE_CODES)
    n_tracked:    number of tracked map points
    fps:          processing rate, frames per second
    n_keyframes, n_map_points: map size if known (cheap counters, plotted every frame)
    """

    index: int
    timestamp: float
    image: np.ndarray | None
    keypoints_uv: np.ndarray
    tracked: np.ndarray
    T_wc: np.ndarray | None
    state: str | Enum
    n_tracked: int
    fps: float
    n_keyframes: int | None = None
    n_map_points: int | None = None

    def __post_init__(self) -> None:
        uv = np.asarray(self.keypoints_uv, dtype=np.float32).reshape(-1, 2)
        tracked = np.asarray(self.tracked, dtype=bool).reshape(-1)
        if len(tracked) != len(uv):
            raise ValueError(f"tracked: {len(tracked)} flags for {len(uv)} keypoints")
        object.__setattr__(self, "keypoints_uv", uv)
        object.__setattr__(self, "tracked", tracked)
        if self.T_wc is not None:
            T = np.asarray(self.T_wc, dtype=np.float64)
            _check(T, "T_wc", (4, 4))
            object.__setattr__(self, "T_wc", T)
        if self.image is not None:
            img = np.asarray(self.image)
            if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)):
                raise ValueError(f"image: expected (H, W) or (H, W, 3), got {img.shape}")
            object.__setattr__(self, "image", img[:, :, 0] if img.ndim == 3 and img.shape[2] == 1 else img)


def _empty_edges() -> np.ndarray:
    return np.zeros((0, 2), dtype=np.int64)


@dataclass(frozen=True, eq=False)
class MapSnapshot:
    """A copy of the map as arrays, taken by the pipeline when the map is to be logged.

    keyframe_ids:    (K,) int64 keyframe ids
    keyframe_T_wc:   (K, 4, 4) camera-to-world keyframe poses
    point_ids:       (P,) int64 map point ids
    points_w:        (P, 3) map point positions in the world frame
    point_obs_count: (P,) int number of keyframes observing each point
    covis_edges:     (E, 2) keyframe-id pairs of the covisibility graph (strong edges)
    loop_edges:      (L, 2) keyframe-id pairs joined by loop closures
    """

    keyframe_ids: np.ndarray
    keyframe_T_wc: np.ndarray
    point_ids: np.ndarray
    points_w: np.ndarray
    point_obs_count: np.ndarray
    covis_edges: np.ndarray = field(default_factory=_empty_edges)
    loop_edges: np.ndarray = field(default_factory=_empty_edges)

    def __post_init__(self) -> None:
        conv = {
            "keyframe_ids": (np.int64, (None,)),
            "keyframe_T_wc": (np.float64, (None, 4, 4)),
            "point_ids": (np.int64, (None,)),
            "points_w": (np.float64, (None, 3)),
            "point_obs_count": (np.int64, (None,)),
            "covis_edges": (np.int64, (None, 2)),
            "loop_edges": (np.int64, (None, 2)),
        }
        for name, (dtype, shape) in conv.items():
            arr = np.asarray(getattr(self, name), dtype=dtype)
            if arr.size == 0:
                arr = arr.reshape((0,) + tuple(s for s in shape[1:]))
            _check(arr, name, shape)
            object.__setattr__(self, name, arr)
        if len(self.keyframe_T_wc) != len(self.keyframe_ids):
            raise ValueError(
                f"keyframe_T_wc: {len(self.keyframe_T_wc)} poses for {len(self.keyframe_ids)} ids"
            )
        if not (len(self.point_ids) == len(self.points_w) == len(self.point_obs_count)):
            raise ValueError(
                f"points: {len(self.point_ids)} ids, {len(self.points_w)} positions, "
                f"{len(self.point_obs_count)} observation counts"
            )

    @classmethod
    def empty(cls) -> MapSnapshot:
        """A snapshot of an empty map."""
        return cls(
            keyframe_ids=np.zeros(0, np.int64),
            keyframe_T_wc=np.zeros((0, 4, 4)),
            point_ids=np.zeros(0, np.int64),
            points_w=np.zeros((0, 3)),
            point_obs_count=np.zeros(0, np.int64),
        )

    @property
    def keyframe_centres(self) -> np.ndarray:
        """(K, 3) keyframe camera centres in the world frame."""
        return self.keyframe_T_wc[:, :3, 3]
