"""ORB extraction as ORB-SLAM does it: a scale pyramid, FAST corners spread per cell and by
quadtree, orientation by intensity centroid, rBRIEF descriptors.

References: Rublee et al., "ORB: an efficient alternative to SIFT or SURF", ICCV 2011 (the
descriptor and intensity-centroid orientation); Mur-Artal, Montiel & Tardos, "ORB-SLAM: a
versatile and accurate monocular SLAM system", T-RO 2015, section III-A (8 levels, factor
1.2, features spread over a grid, per-cell FAST thresholds) and its ORBextractor.

Choices of this implementation:

* the pyramid is built level from level by bilinear resizing, as ORB-SLAM;
* the detection cell and quadtree node of every pixel are tabulated once per image size
  (:mod:`orbslam_hgcn.features.pyramid`);
* FAST runs once per level at the high threshold (20); only the cells where it found no
  corner are searched again at the low threshold (7), each on its own window, as ORB-SLAM
  does per cell (a corner's FAST score does not depend on the threshold, so the high-pass
  corners are exactly those of ORB-SLAM's cells). Both passes are one compiled call per
  level that finds the corners ``cv2.FAST`` finds on those windows
  (:mod:`orbslam_hgcn.features.fast`); the quadtree is one compiled pass over the corners
  of all levels (:mod:`orbslam_hgcn.features.distribute`);
* orientation and descriptors are compiled loops (:mod:`orbslam_hgcn.features.rbrief`):
  the moments on the level image, the rBRIEF tests on the level image blurred with a 7x7,
  sigma 2 Gaussian as ORB-SLAM does; they equal ``cv2.ORB.compute``'s bit for bit, which
  describes instead where they cannot be made to;
* levels are searched, and then described, on ``ORBConfig.threads`` threads (the compiled
  loops and OpenCV release the GIL); the keypoints are the same for any number of threads.
"""

from __future__ import annotations

import functools
import logging
import math
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from orbslam_hgcn.config import ORBConfig
from orbslam_hgcn.features.distribute import distribute_quadtree, features_per_level
from orbslam_hgcn.features.fast import MARGIN, circle_offsets, detect_level
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.features.pyramid import PyramidMaps, build_pyramid, pyramid_maps
from orbslam_hgcn.features.rbrief import ic_moments, opencv_rbrief
from orbslam_hgcn.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)


def circular_patch_offsets(half_patch: int) -> tuple[np.ndarray, np.ndarray]:
    """(P,) int offsets (du, dv) of ORB-SLAM's symmetric circular orientation patch.

    ORB-SLAM's ``umax``: row ``v`` spans ``|u| <= umax[|v|]``, made symmetric in u and v.
    """
    vmax = math.floor(half_patch * math.sqrt(2.0) / 2 + 1)
    vmin = math.ceil(half_patch * math.sqrt(2.0) / 2)
    umax = [0] * (half_patch + 1)
    for v in range(vmax + 1):
        umax[v] = int(round(math.sqrt(half_patch * half_patch - v * v)))
    v0 = 0
    for v in range(half_patch, vmin - 1, -1):
        while umax[v0] == umax[v0 + 1]:
            v0 += 1
        umax[v] = v0
        v0 += 1
    du, dv = [], []
    for v in range(-half_patch, half_patch + 1):
        w = umax[abs(v)]
        du.extend(range(-w, w + 1))
        dv.extend([v] * (2 * w + 1))
    return np.asarray(du, dtype=np.int64), np.asarray(dv, dtype=np.int64)


@functools.lru_cache(maxsize=4)
def _patch_rows(half_patch: int) -> np.ndarray:
    """(half_patch + 1,) int64 half-width ``umax[v]`` of row v of the circular patch."""
    du, dv = circular_patch_offsets(half_patch)
    return np.array([du[dv == v].max() for v in range(half_patch + 1)], dtype=np.int64)


def ic_angles(image: np.ndarray, x: np.ndarray, y: np.ndarray, half_patch: int) -> np.ndarray:
    """(N,) float32 intensity-centroid orientation in degrees [0, 360) (Rublee et al. 2011).

    image: (H, W) uint8 level image; x, y: (N,) int pixel positions at least ``half_patch``
    away from the border. ORB-SLAM's IC_Angle: ``atan2(m01, m10)`` of the moments of the
    circular patch (:func:`circular_patch_offsets`) on the unblurred level image.
    """
    if len(x) == 0:
        return np.zeros(0, dtype=np.float32)
    x = np.asarray(x, np.int64)
    y = np.asarray(y, np.int64)
    h, w = image.shape
    if x.min() < half_patch or y.min() < half_patch or x.max() >= w - half_patch or y.max() >= h - half_patch:
        raise ValueError(f"keypoints closer than {half_patch} px to the image border have no orientation")
    moments = ic_moments(np.ascontiguousarray(image), x, y, _patch_rows(half_patch))  # (N, 2): m10, m01
    ang = np.degrees(np.arctan2(moments[:, 1], moments[:, 0]))
    return np.mod(ang, 360.0).astype(np.float32)


class ORBExtractor:
    """ORB-SLAM's feature extractor: ``extract(image, camera) -> KeypointSet``."""

    def __init__(self, config: ORBConfig | None = None) -> None:
        self.config = config or ORBConfig()
        c = self.config
        if c.n_levels < 1 or c.scale_factor <= 1.0 or c.n_features < 1 or c.threads < 1:
            raise ValueError("ORBConfig needs n_levels >= 1, scale_factor > 1, n_features >= 1, threads >= 1")
        self.scale_factors = np.array(
            [float(np.float32(c.scale_factor**level)) for level in range(c.n_levels)], dtype=np.float64
        )
        self.n_per_level = features_per_level(c.n_features, c.scale_factor, c.n_levels)
        if not (0 <= c.min_th_fast <= c.ini_th_fast <= 255):
            raise ValueError("ORBConfig needs FAST thresholds 0 <= min_th_fast <= ini_th_fast <= 255")
        # Descriptors of given keypoints on a level image: compiled (equal to OpenCV's, see
        # orbslam_hgcn.features.rbrief), or by a one-level cv2.ORB where they cannot be.
        self._rbrief = opencv_rbrief(c.patch_size, c.edge_threshold)
        self._orb = cv2.ORB_create(
            nfeatures=c.n_features,
            scaleFactor=c.scale_factor,
            nlevels=1,
            edgeThreshold=c.edge_threshold,
            patchSize=c.patch_size,
        )
        # Pyramid levels are searched and described on `threads` threads (1: in the caller).
        self._pool = ThreadPoolExecutor(c.threads, thread_name_prefix="orb-level") if c.threads > 1 else None

    def maps(self, height: int, width: int) -> PyramidMaps:
        """The per-pixel cell and quadtree-key tables of a (height, width) image (cached)."""
        c = self.config
        return pyramid_maps(width, height, c.scale_factor, c.n_levels, c.edge_threshold, float(c.cell_size))

    def _detect(self, levels: list[np.ndarray], maps: PyramidMaps) -> tuple[np.ndarray, ...]:
        """FAST corners of every level inside ORB-SLAM's border, with its per-cell thresholds
        (:meth:`_detect_level`, levels on the extractor's threads). Returns (x, y, level,
        score, cell, key), each (N,) over all levels."""
        parts = [p for p in self._map(functools.partial(self._detect_level, maps=maps), levels) if p is not None]
        if not parts:
            empty = np.zeros(0, np.int64)
            return empty, empty, empty, np.zeros(0, np.float32), empty, empty
        return tuple(np.concatenate(col) for col in zip(*parts))

    def _detect_level(self, level: int, img: np.ndarray, maps: PyramidMaps) -> tuple[np.ndarray, ...] | None:
        """The corners of one level (None when it is too small to hold any): the level is
        searched at the high threshold, and the cells left without a corner again at the
        low threshold on their own windows (:func:`~orbslam_hgcn.features.fast.detect_level`)."""
        c = self.config
        h, w = img.shape
        if w <= 2 * c.edge_threshold or h <= 2 * c.edge_threshold:
            return None
        first, last = int(maps.level_cells[level]), int(maps.level_cells[level + 1])
        x, y, score, cell_of = detect_level(
            np.ascontiguousarray(img), c.edge_threshold - MARGIN, int(c.ini_th_fast), int(c.min_th_fast),
            maps.cell_maps[level], first, maps.cell_boxes[first:last], circle_offsets(w),
        )  # fmt: skip
        key = maps.key_maps[level].ravel().take(y * w + x)
        return x, y, np.full(len(x), level, np.int64), score, cell_of, key

    def _map(self, fn, levels: list[np.ndarray]) -> list:
        """[fn(level, image) for each level], on the extractor's threads when it has them
        (OpenCV releases the GIL; results come back in level order)."""
        if self._pool is None:
            return [fn(level, img) for level, img in enumerate(levels)]
        return list(self._pool.map(fn, range(len(levels)), levels))

    def _describe(self, img: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Orientation (N,) float32 degrees and rBRIEF descriptors (N, 32) uint8 of the
        keypoints (x, y) (N,) of one level image."""
        angle = ic_angles(img, x, y, self.config.patch_size // 2)
        if self._rbrief is not None:
            return angle, self._rbrief.describe(img, x, y, angle)
        return angle, self._describe_opencv(img, x, y, angle)

    def _describe_opencv(self, img: np.ndarray, x: np.ndarray, y: np.ndarray, angle: np.ndarray) -> np.ndarray:
        """rBRIEF descriptors (N, 32) uint8 of keypoints (x, y) (N,) with orientation
        ``angle`` (N,) by ``cv2.ORB.compute``."""
        size = float(self.config.patch_size)
        kps = [
            cv2.KeyPoint(float(u), float(v), size, float(t)) for u, v, t in zip(x.tolist(), y.tolist(), angle.tolist())
        ]
        out, d = self._orb.compute(img, kps)
        if d is None or len(out) != len(x):
            raise RuntimeError("cv2.ORB.compute dropped keypoints that lie inside the edge threshold")
        return d

    def extract(self, image: np.ndarray, camera: PinholeCamera | None = None) -> KeypointSet:
        """ORB keypoints and descriptors of one image.

        image: (H, W) uint8 grayscale. camera: intrinsics used to undistort the keypoints
        (None: coordinates are used as they are). Returns a KeypointSet ordered by level,
        ``n_features`` keypoints (fewer on images with too few corners).
        """
        image = np.ascontiguousarray(image)
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(f"expected an (H, W) uint8 image, got {image.shape} {image.dtype}")
        c = self.config
        levels = build_pyramid(image, c.scale_factor, c.n_levels)
        x, y, level, score, cell, key = self._detect(levels, self.maps(*image.shape))
        keep = distribute_quadtree(key, score, self.n_per_level)
        sel = keep[np.argsort(key[keep], kind="stable")]  # by level, then quadtree order
        x, y, level, score = x[sel], y[sel], level[sel], score[sel]
        angle = np.zeros(len(sel), dtype=np.float32)
        desc = np.zeros((len(sel), 32), dtype=np.uint8)
        bounds = np.searchsorted(level, np.arange(c.n_levels + 1)).tolist()

        def describe(lvl: int, img: np.ndarray) -> None:
            a, b = bounds[lvl], bounds[lvl + 1]
            if a < b:
                angle[a:b], desc[a:b] = self._describe(img, x[a:b], y[a:b])

        self._map(describe, levels)
        scale = self.scale_factors[level].astype(np.float32)
        uv_raw = np.stack([x, y], axis=1).astype(np.float32) * scale[:, None]
        uv = camera.undistort_points(uv_raw) if camera is not None else uv_raw.astype(np.float64)
        return KeypointSet(
            uv_raw=uv_raw,
            uv=uv,
            octave=level.astype(np.int32),
            angle=angle,
            response=score,
            desc=desc,
            scale_factors=self.scale_factors.copy(),
        )
