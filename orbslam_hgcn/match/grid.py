"""Bucketing of keypoints on a coarse grid for fast area queries (ORB-SLAM's Frame grid).

ORB-SLAM assigns the undistorted keypoints of a frame to 64x48 cells spanning the
undistorted image bounds and answers "features within r pixels of (x, y)" from the cells
the square window touches. Here the cells are a CSR index (keypoints sorted by cell plus
cell start offsets) and many windows are answered at once as candidate (query, feature)
pairs, so matchers never loop over keypoints in Python.
"""

from __future__ import annotations

import functools
import logging

import numpy as np

from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)

GRID_COLS = 64
GRID_ROWS = 48


@functools.lru_cache(maxsize=64)
def image_bounds(camera: PinholeCamera) -> tuple[float, float, float, float]:
    """(min_x, max_x, min_y, max_y) of the undistorted image (ORB-SLAM ComputeImageBounds).

    Without distortion these are the image borders; otherwise the undistorted corners.
    Kept per camera: every frame's grid asks.
    """
    if not camera.is_distorted:
        return 0.0, float(camera.width), 0.0, float(camera.height)
    w, h = float(camera.width), float(camera.height)
    c = camera.undistort_points(np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]))
    return (
        float(min(c[0, 0], c[2, 0])),
        float(max(c[1, 0], c[3, 0])),
        float(min(c[0, 1], c[1, 1])),
        float(max(c[2, 1], c[3, 1])),
    )


class FeatureGrid:
    """Cell index of the undistorted keypoints of one image.

    keypoints: the image's KeypointSet; camera: its intrinsics (for the image bounds).
    Keypoints outside the undistorted bounds are left out of the grid, as in ORB-SLAM.
    """

    def __init__(
        self,
        keypoints: KeypointSet,
        camera: PinholeCamera,
        cols: int = GRID_COLS,
        rows: int = GRID_ROWS,
    ) -> None:
        self.keypoints = keypoints
        self.cols, self.rows = cols, rows
        self.min_x, self.max_x, self.min_y, self.max_y = image_bounds(camera)
        self.inv_w = cols / (self.max_x - self.min_x)
        self.inv_h = rows / (self.max_y - self.min_y)
        uv = np.asarray(keypoints.uv, dtype=np.float64).reshape(-1, 2)
        self.uv = uv
        self.octave = np.asarray(keypoints.octave, dtype=np.int64)
        cx = np.floor((uv[:, 0] - self.min_x) * self.inv_w).astype(np.int64)
        cy = np.floor((uv[:, 1] - self.min_y) * self.inv_h).astype(np.int64)
        inside = (cx >= 0) & (cx < cols) & (cy >= 0) & (cy < rows)
        cell = np.where(inside, cy * cols + cx, cols * rows)
        self.order = np.argsort(cell, kind="stable")
        counts = np.bincount(cell, minlength=cols * rows + 1)
        self.start = np.concatenate([[0], np.cumsum(counts)])  # (cols*rows + 2,)

    def candidate_pairs(
        self,
        x: np.ndarray,
        y: np.ndarray,
        r: np.ndarray | float,
        min_level: np.ndarray | int = -1,
        max_level: np.ndarray | int = -1,
    ) -> tuple[np.ndarray, np.ndarray]:
        """All (query, feature) pairs with the feature inside the query's square window.

        x, y: (M,) window centres in undistorted pixels; r: (M,) or scalar half side;
        min_level / max_level: (M,) or scalar octave limits, -1 for none (ORB-SLAM's
        GetFeaturesInArea). Returns ((K,) int64 query index, (K,) int64 feature index),
        grouped by query in increasing order.
        """
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        y = np.asarray(y, dtype=np.float64).reshape(-1)
        m = len(x)
        r = np.broadcast_to(np.asarray(r, dtype=np.float64), (m,))
        empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        if m == 0 or len(self.uv) == 0:
            return empty
        c0 = np.floor((x - self.min_x - r) * self.inv_w)
        c1 = np.floor((x - self.min_x + r) * self.inv_w)
        r0 = np.floor((y - self.min_y - r) * self.inv_h)
        r1 = np.floor((y - self.min_y + r) * self.inv_h)
        valid = np.isfinite(c0 + c1 + r0 + r1) & (c1 >= 0) & (c0 < self.cols) & (r1 >= 0) & (r0 < self.rows)
        c0 = np.clip(np.nan_to_num(c0), 0, self.cols - 1).astype(np.int64)
        c1 = np.clip(np.nan_to_num(c1), 0, self.cols - 1).astype(np.int64)
        r0 = np.clip(np.nan_to_num(r0), 0, self.rows - 1).astype(np.int64)
        r1 = np.clip(np.nan_to_num(r1), 0, self.rows - 1).astype(np.int64)
        # Cells are numbered row by row, so the cells of one window row hold one contiguous
        # run of the sorted features: one entry per (query, window row) ...
        n_rows = np.where(valid, r1 - r0 + 1, 0)
        total = int(n_rows.sum())
        if total == 0:
            return empty
        q = np.repeat(np.arange(m), n_rows)
        row = r0[q] + np.arange(total) - np.repeat(np.cumsum(n_rows) - n_rows, n_rows)
        a = self.start[row * self.cols + c0[q]]
        cnt = self.start[row * self.cols + c1[q] + 1] - a
        tot = int(cnt.sum())
        if tot == 0:
            return empty
        # ... expanded to one entry per (query, feature in the row's cells).
        q2 = np.repeat(q, cnt)
        pos = np.repeat(a - (np.cumsum(cnt) - cnt), cnt) + np.arange(tot)
        f = self.order[pos]
        d = self.uv[f]
        keep = (np.abs(d[:, 0] - x[q2]) < r[q2]) & (np.abs(d[:, 1] - y[q2]) < r[q2])
        min_level = np.broadcast_to(np.asarray(min_level, dtype=np.int64), (m,))
        max_level = np.broadcast_to(np.asarray(max_level, dtype=np.int64), (m,))
        oc = self.octave[f]
        lo, hi = min_level[q2], max_level[q2]
        keep &= (lo < 0) | (oc >= lo)
        keep &= (hi < 0) | (oc <= hi)
        return q2[keep], f[keep]

    def contains(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """(M,) bool: points in front of the camera (``z`` > 0) whose (M, 2) undistorted
        pixel coords ``uv`` fall inside the image bounds; nan coords are outside."""
        with np.errstate(invalid="ignore"):
            return (
                (z > 0)
                & (uv[:, 0] >= self.min_x)
                & (uv[:, 0] < self.max_x)
                & (uv[:, 1] >= self.min_y)
                & (uv[:, 1] < self.max_y)
            )

    def features_in_area(
        self, x: float, y: float, r: float, min_level: int = -1, max_level: int = -1
    ) -> np.ndarray:
        """(K,) int64 sorted indices of the features within the square of half side r.

        ORB-SLAM's Frame::GetFeaturesInArea: |u - x| < r and |v - y| < r, octave within
        [min_level, max_level] where a limit of -1 means none.
        """
        _, f = self.candidate_pairs(np.array([x]), np.array([y]), r, min_level, max_level)
        return np.sort(f)
