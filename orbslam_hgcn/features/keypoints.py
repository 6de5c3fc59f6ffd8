"""The measurement record of one image: ORB keypoints and descriptors.

Measurements never change after extraction; estimates (poses, point links) live in the
map model, not here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class KeypointSet:
    """Keypoints of one image, all arrays indexed by feature.

    uv_raw:        (N, 2) float32 pixel coords as detected, in the (distorted) level-0 image
    uv:            (N, 2) float64 undistorted pixel coords (equal to uv_raw without distortion)
    octave:        (N,) int32 pyramid level of detection
    angle:         (N,) float32 orientation in degrees
    response:      (N,) float32 FAST/Harris response
    desc:          (N, 32) uint8 ORB descriptors (256 bits)
    scale_factors: (L,) float64 scale of each level (scale_factor ** level)
    """

    uv_raw: np.ndarray
    uv: np.ndarray
    octave: np.ndarray
    angle: np.ndarray
    response: np.ndarray
    desc: np.ndarray
    scale_factors: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)

    @property
    def n_levels(self) -> int:
        return len(self.scale_factors)

    @property
    def level_sigma2(self) -> np.ndarray:
        """(L,) variance of a keypoint's position at each level (scale_factor ** (2 level))."""
        return self.scale_factors**2

    @property
    def inv_level_sigma2(self) -> np.ndarray:
        return 1.0 / self.level_sigma2
