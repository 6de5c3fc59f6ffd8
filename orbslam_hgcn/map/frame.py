"""One tracked image: its measurements (keypoints) and the tracker's estimates for it.

A :class:`Frame` lives outside the :class:`~orbslam_hgcn.map.map.Map`: the tracker owns it
and may change its estimates freely (pose, point links, outlier flags). Only keyframes and
map points are linked by the Map.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import inv_T

log = logging.getLogger(__name__)


@dataclass(eq=False)
class Frame:
    """Measurements of one image plus the estimates made while tracking it.

    Measurements (never changed after construction):
        id:        frame index in the sequence
        timestamp: seconds
        camera:    intrinsics of the image
        keypoints: ORB keypoints and descriptors, N features
    Estimates:
        T_cw:       (4, 4) float64 world-to-camera pose, or None before tracking
        point_ids:  (N,) int64 map point id matched to each feature, -1 for none
        outlier:    (N,) bool, matched features rejected by pose optimisation
        ref_kf_id:  id of the reference keyframe, -1 for none
        bow, featvec: bag-of-words vector and feature vector, set by the vocabulary
    """

    id: int
    timestamp: float
    camera: PinholeCamera
    keypoints: KeypointSet
    T_cw: np.ndarray | None = None
    point_ids: np.ndarray = field(default=None)  # type: ignore[assignment]
    outlier: np.ndarray = field(default=None)  # type: ignore[assignment]
    ref_kf_id: int = -1
    bow: Any = None
    featvec: Any = None

    def __post_init__(self) -> None:
        n = len(self.keypoints)
        if self.point_ids is None:
            self.point_ids = np.full(n, -1, dtype=np.int64)
        else:
            self.point_ids = np.asarray(self.point_ids, dtype=np.int64)
        if self.outlier is None:
            self.outlier = np.zeros(n, dtype=bool)
        else:
            self.outlier = np.asarray(self.outlier, dtype=bool)
        if self.point_ids.shape != (n,) or self.outlier.shape != (n,):
            raise ValueError(f"point_ids and outlier must have shape ({n},)")
        if self.T_cw is not None:
            self.T_cw = np.asarray(self.T_cw, dtype=np.float64).reshape(4, 4)

    def __len__(self) -> int:
        return len(self.keypoints)

    @property
    def T_wc(self) -> np.ndarray | None:
        """(4, 4) camera-to-world pose, or None when the pose is unknown."""
        return None if self.T_cw is None else inv_T(self.T_cw)

    @property
    def center(self) -> np.ndarray | None:
        """(3,) camera centre in the world frame, or None when the pose is unknown."""
        if self.T_cw is None:
            return None
        R = self.T_cw[:3, :3]
        return -R.T @ self.T_cw[:3, 3]

    def set_pose(self, T_cw: np.ndarray) -> None:
        self.T_cw = np.asarray(T_cw, dtype=np.float64).reshape(4, 4).copy()

    @property
    def matched(self) -> np.ndarray:
        """(N,) bool: features linked to a map point and not flagged as outliers."""
        return (self.point_ids >= 0) & ~self.outlier

    @property
    def inv_sigma2(self) -> np.ndarray:
        """(N,) float64 information of each keypoint (1 / scale_factor ** (2 octave))."""
        return self.keypoints.inv_level_sigma2[self.keypoints.octave]

    def clear_links(self) -> None:
        """Forget every point match and outlier flag."""
        self.point_ids[:] = -1
        self.outlier[:] = False
