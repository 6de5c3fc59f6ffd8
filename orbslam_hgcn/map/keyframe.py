"""KeyFrame: a frame kept in the map, with its links (point slots, covisibility, tree).

The link fields (point slots, shared counts, parent/children, loop edges, bad flag) are
written only by :class:`~orbslam_hgcn.map.map.Map`, under its lock. Read them through Map
queries (which take the lock) or while holding ``map.lock`` yourself when another thread may
be changing the map; call Map methods to change them. Measurements are shared with the source frame, never copied
or changed.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import inv_T
from orbslam_hgcn.map.frame import Frame
from orbslam_hgcn.match.grid import FeatureGrid

log = logging.getLogger(__name__)


class KeyFrame:
    """A keyframe of the map.

    Measurements: id, frame_id, timestamp, camera, keypoints (N features).
    Estimates: T_cw (4, 4) (with T_wc and center derived), bow/featvec (set by the
    vocabulary).
    Links (Map-owned): point_ids (N,) int64 map point id per feature slot (-1: none);
    shared {kf_id: number of map points both observe} for every keyframe sharing at least
    one point (the covisibility weights); parent id (-1 for the root) and children ids of the
    spanning tree; loop_edges; bad.
    """

    __slots__ = (
        "id",
        "frame_id",
        "timestamp",
        "camera",
        "keypoints",
        "bow",
        "featvec",
        "_T_cw",
        "_T_wc",
        "_point_ids",
        "shared",
        "parent",
        "children",
        "loop_edges",
        "bad",
        "not_erase",
        "to_be_erased",
        "first_connection",
        "T_cp",
        "_covis_cache",
        "_grid",
    )

    def __init__(
        self,
        kf_id: int,
        frame_id: int,
        timestamp: float,
        camera: PinholeCamera,
        keypoints: KeypointSet,
        T_cw: np.ndarray,
        bow: Any = None,
        featvec: Any = None,
    ) -> None:
        self.id = int(kf_id)
        self.frame_id = int(frame_id)
        self.timestamp = float(timestamp)
        self.camera = camera
        self.keypoints = keypoints
        self.bow = bow
        self.featvec = featvec
        self._T_cw = np.eye(4)
        self._T_wc = np.eye(4)
        self._set_pose(T_cw)
        self._point_ids = np.full(len(keypoints), -1, dtype=np.int64)
        self.shared: dict[int, int] = {}
        self.parent = -1
        self.children: set[int] = set()
        self.loop_edges: set[int] = set()
        self.bad = False
        self.not_erase = False
        self.to_be_erased = False
        self.first_connection = True
        # Pose relative to the parent, kept when the keyframe is culled so the trajectory
        # can still be written for its frames (ORB-SLAM KeyFrame::mTcp).
        self.T_cp: np.ndarray | None = None
        self._covis_cache: tuple[int, np.ndarray, np.ndarray] | None = None
        self._grid: FeatureGrid | None = None

    @property
    def grid(self) -> FeatureGrid:
        """The cell index of the keypoints (built on first use; the keypoints never
        change): fusion and loop closing search every keyframe's many times."""
        if self._grid is None:
            self._grid = FeatureGrid(self.keypoints, self.camera)
        return self._grid

    @classmethod
    def from_frame(cls, frame: Frame, kf_id: int) -> KeyFrame:
        """A keyframe sharing ``frame``'s measurements; its point slots start empty."""
        if frame.T_cw is None:
            raise ValueError(f"frame {frame.id} has no pose; track it before making a keyframe")
        return cls(
            kf_id,
            frame.id,
            frame.timestamp,
            frame.camera,
            frame.keypoints,
            frame.T_cw,
            bow=frame.bow,
            featvec=frame.featvec,
        )

    def __len__(self) -> int:
        return len(self.keypoints)

    def __repr__(self) -> str:
        return f"KeyFrame(id={self.id}, frame={self.frame_id}, points={self.n_points()}, bad={self.bad})"

    # --- estimates ---------------------------------------------------------------------
    def _set_pose(self, T_cw: np.ndarray) -> None:
        T_cw = np.array(T_cw, dtype=np.float64).reshape(4, 4)
        self._T_cw = T_cw
        self._T_wc = inv_T(T_cw)
        self._T_cw.flags.writeable = False
        self._T_wc.flags.writeable = False

    @property
    def T_cw(self) -> np.ndarray:
        """(4, 4) world-to-camera pose (read-only; Map.set_keyframe_pose changes it)."""
        return self._T_cw

    @property
    def T_wc(self) -> np.ndarray:
        """(4, 4) camera-to-world pose (read-only)."""
        return self._T_wc

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in the world frame."""
        return self._T_wc[:3, 3].copy()

    # --- links (read-only views) -------------------------------------------------------
    @property
    def point_ids(self) -> np.ndarray:
        """(N,) int64 read-only view: map point id in each feature slot, -1 for none."""
        view = self._point_ids.view()
        view.flags.writeable = False
        return view

    def n_points(self) -> int:
        """Number of feature slots linked to a map point."""
        return int(np.count_nonzero(self._point_ids >= 0))

    def observed_points(self) -> tuple[np.ndarray, np.ndarray]:
        """((M,) int64 feature indices, (M,) int64 point ids) of the linked slots."""
        idx = np.flatnonzero(self._point_ids >= 0)
        return idx, self._point_ids[idx]

    def covisible(self, min_weight: int) -> tuple[np.ndarray, np.ndarray]:
        """Covisibility neighbours ordered by weight (ORB-SLAM's ordered connected keyframes).

        Neighbours share at least ``min_weight`` points; when none does, the single best
        keyframe (if any point is shared at all) is the only neighbour, as ORB-SLAM keeps it.
        Returns ((C,) int64 keyframe ids, (C,) int64 weights), weights descending, ties by
        ascending id.
        """
        cache = self._covis_cache
        if cache is not None and cache[0] == min_weight:
            return cache[1], cache[2]
        if self.shared:
            ids = np.fromiter(self.shared.keys(), dtype=np.int64, count=len(self.shared))
            w = np.fromiter(self.shared.values(), dtype=np.int64, count=len(self.shared))
            order = np.lexsort((ids, -w))
            ids, w = ids[order], w[order]
            keep = w >= min_weight
            if not keep.any():
                keep[0] = True
            ids, w = ids[keep], w[keep]
        else:
            ids = np.zeros(0, dtype=np.int64)
            w = np.zeros(0, dtype=np.int64)
        ids.flags.writeable = False
        w.flags.writeable = False
        self._covis_cache = (min_weight, ids, w)
        return ids, w

    def _invalidate_covisibility(self) -> None:
        self._covis_cache = None
