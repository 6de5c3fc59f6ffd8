"""The scale pyramid of an image and per-pixel lookup tables of its levels.

The tables give, for any pixel of a level, ORB-SLAM's detection cell and the pixel's
quadtree key (:mod:`orbslam_hgcn.features.distribute`); they depend only on the image
size, so they are computed once and every detected corner is then classified by a lookup.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import cv2
import numpy as np

from orbslam_hgcn.features.distribute import cell_ids, quadtree_keys
from orbslam_hgcn.features.fast import MARGIN

log = logging.getLogger(__name__)


def level_sizes(width: int, height: int, scale_factor: float, n_levels: int) -> list[tuple[int, int]]:
    """(w, h) of each level: ``round(W / s**l)`` with ``s**l`` in float32 as OpenCV does."""
    sizes = []
    for level in range(n_levels):
        s = float(np.float32(scale_factor**level))
        sizes.append((int(round(width / s)), int(round(height / s))))
    return sizes


def build_pyramid(image: np.ndarray, scale_factor: float, n_levels: int) -> list[np.ndarray]:
    """Images of the scale pyramid, each resized from the previous level.

    image: (H, W) uint8. Bilinear resize as ORB-SLAM (``INTER_LINEAR``; ``cv2.ORB`` uses the
    bit-exact variant, which is slower and differs by at most one grey level).
    Returns L arrays (H_l, W_l) uint8.
    """
    h, w = image.shape
    sizes = level_sizes(w, h, scale_factor, n_levels)
    levels = [image]
    for size in sizes[1:]:
        levels.append(cv2.resize(levels[-1], size, interpolation=cv2.INTER_LINEAR))
    return levels


@dataclass(frozen=True, eq=False)
class PyramidMaps:
    """Per-pixel lookup tables of the pyramid levels of one image size.

    sizes:     (L, 2) int64 (w, h) of each level
    bounds:    (L, 4) float64 detection area (min_x, max_x, min_y, max_y) of each level in
               its own pixels: ORB-SLAM's minBorder = edge - 3 to size - minBorder (FAST
               then finds corners at least ``edge`` pixels inside the level)
    cell_maps: L arrays (h, w) int32, the detection cell of each pixel
               (:func:`~orbslam_hgcn.features.distribute.cell_ids`), -1 outside the area
    key_maps:  L arrays (h, w) int64, the quadtree key of each pixel
               (:func:`~orbslam_hgcn.features.distribute.quadtree_keys`), -1 outside
    cell_boxes: (C, 4) int64 pixel box (x0, x1, y0, y1), ends exclusive, of each cell
               over all levels
    level_cells: (L + 1,) int64 first cell index of each level (and the total count)
    """

    sizes: np.ndarray
    bounds: np.ndarray
    cell_maps: list[np.ndarray]
    key_maps: list[np.ndarray]
    cell_boxes: np.ndarray
    level_cells: np.ndarray

    @classmethod
    def create(
        cls, width: int, height: int, scale_factor: float, n_levels: int, edge: int, cell_size: float
    ) -> PyramidMaps:
        """Evaluate the cell and key functions once for every pixel of every level."""
        sizes = level_sizes(width, height, scale_factor, n_levels)
        lo = edge - MARGIN  # ORB-SLAM's detection area starts edge - 3 in
        bounds = np.array([[lo, w - lo, lo, h - lo] for w, h in sizes], dtype=np.float64)
        cell_maps, key_maps = [], []
        for level, (w, h) in enumerate(sizes):
            cmap = np.full((h, w), -1, dtype=np.int32)
            kmap = np.full((h, w), -1, dtype=np.int64)
            if w > 2 * lo and h > 2 * lo:
                yy, xx = np.mgrid[lo : h - lo, lo : w - lo]
                x = xx.ravel().astype(np.float64)
                y = yy.ravel().astype(np.float64)
                g = np.full(len(x), level, dtype=np.int64)
                cells = cell_ids(x, y, g, bounds, cell_size)
                cmap[lo : h - lo, lo : w - lo] = cells.reshape(yy.shape)
                kmap[lo : h - lo, lo : w - lo] = quadtree_keys(x, y, g, bounds).reshape(yy.shape)
            cell_maps.append(cmap)
            key_maps.append(kmap)
        n_cells = max((int(c.max()) + 1 for c in cell_maps), default=0)
        big = np.iinfo(np.int64).max
        x0, y0 = np.full(n_cells, big, np.int64), np.full(n_cells, big, np.int64)
        x1, y1 = np.full(n_cells, -1, np.int64), np.full(n_cells, -1, np.int64)
        level_cells = np.zeros(len(sizes) + 1, dtype=np.int64)
        for level, cmap in enumerate(cell_maps):
            ys, xs = np.nonzero(cmap >= 0)
            ids = cmap[ys, xs]
            np.minimum.at(x0, ids, xs)
            np.maximum.at(x1, ids, xs + 1)
            np.minimum.at(y0, ids, ys)
            np.maximum.at(y1, ids, ys + 1)
            level_cells[level + 1] = max(level_cells[level], int(cmap.max()) + 1)
        boxes = np.stack([x0, x1, y0, y1], axis=1)
        return cls(np.asarray(sizes, dtype=np.int64), bounds, cell_maps, key_maps, boxes, level_cells)


@functools.lru_cache(maxsize=8)
def pyramid_maps(
    width: int, height: int, scale_factor: float, n_levels: int, edge: int, cell_size: float
) -> PyramidMaps:
    """The :class:`PyramidMaps` of one image size and pyramid, built once per process."""
    return PyramidMaps.create(width, height, scale_factor, n_levels, edge, cell_size)
