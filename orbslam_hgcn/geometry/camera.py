"""Pinhole camera with optional radial-tangential (OpenCV ``k1 k2 p1 p2 [k3]``) distortion."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of one monocular camera.

    ``dist`` holds OpenCV's radial-tangential coefficients ``(k1, k2, p1, p2, k3)``;
    all zeros means an undistorted (or already rectified) image.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))
    fps: float = 30.0
    name: str = "camera"

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    @property
    def dist_coeffs(self) -> np.ndarray:
        """(5,) float64 distortion coefficients in OpenCV order."""
        d = np.zeros(5, dtype=np.float64)
        d[: len(self.dist)] = self.dist
        return d

    @property
    def is_distorted(self) -> bool:
        return bool(np.any(self.dist_coeffs != 0.0))

    def undistort_points(self, pts: np.ndarray) -> np.ndarray:
        """Undistort pixel coordinates.

        pts: (N, 2) float pixel coords in the distorted image.
        Returns (N, 2) float64 pixel coords of the ideal pinhole camera with the same K.
        """
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if not self.is_distorted or len(pts) == 0:
            return pts.copy()
        # The default 5 iterations leave ~0.03 px error near the corners of strongly
        # distorted lenses (EuRoC); iterate to convergence instead.
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
        out = cv2.undistortPoints(
            pts.reshape(-1, 1, 2), self.K, self.dist_coeffs, R=None, P=self.K, criteria=criteria
        )
        return out.reshape(-1, 2)

    def project(self, X_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project camera-frame points with the ideal pinhole model (no distortion).

        X_c: (N, 3) points in the camera frame.
        Returns ((N, 2) float64 pixel coords, (N,) float64 depths).
        """
        X_c = np.asarray(X_c, dtype=np.float64).reshape(-1, 3)
        z = X_c[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * X_c[:, 0] / z + self.cx
            v = self.fy * X_c[:, 1] / z + self.cy
        return np.stack([u, v], axis=1), z

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Bearing rays (z = 1) of undistorted pixel coords: (N, 2) -> (N, 3)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        x = (uv[:, 0] - self.cx) / self.fx
        y = (uv[:, 1] - self.cy) / self.fy
        return np.stack([x, y, np.ones_like(x)], axis=1)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel coords inside the image bounds shrunk by ``margin``."""
        uv = np.asarray(uv).reshape(-1, 2)
        return (
            (uv[:, 0] >= margin)
            & (uv[:, 0] < self.width - margin)
            & (uv[:, 1] >= margin)
            & (uv[:, 1] < self.height - margin)
        )
