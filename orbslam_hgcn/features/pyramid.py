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
        """Evaluate the cell and key functions for every pixel of every level.

        Both are separable: a cell is ``first + row * n_cols + column`` and a key the
        disjoint bit fields ``level | root and x bits | y bits``, so the value at (x, y)
        is ``f(x, y0) + f(x0, y) - f(x0, y0)`` (``^`` for the keys). The tables are filled
        from one row and one column of each level (a few milliseconds at KITTI's size,
        against 0.2 s for every pixel), and each cell's box from the ranges of its row
        and column."""
        sizes = level_sizes(width, height, scale_factor, n_levels)
        lo = edge - MARGIN  # ORB-SLAM's detection area starts edge - 3 in
        bounds = np.array([[lo, w - lo, lo, h - lo] for w, h in sizes], dtype=np.float64)
        cell_maps, key_maps, boxes_of = [], [], []
        for level, (w, h) in enumerate(sizes):
            cmap = np.full((h, w), -1, dtype=np.int32)
            kmap = np.full((h, w), -1, dtype=np.int64)
            if w > 2 * lo and h > 2 * lo:
                xs = np.arange(lo, w - lo, dtype=np.int64)
                ys = np.arange(lo, h - lo, dtype=np.int64)
                # One row (y = lo), one column (x = lo), and their corner last.
                x = np.concatenate([xs, np.full(len(ys), lo), [lo]]).astype(np.float64)
                y = np.concatenate([np.full(len(xs), lo), ys, [lo]]).astype(np.float64)
                g = np.full(len(x), level, dtype=np.int64)
                cells = cell_ids(x, y, g, bounds, cell_size)
                keys = quadtree_keys(x, y, g, bounds)
                n = len(xs)
                col_c, row_c, corner_c = cells[:n], cells[n:-1], cells[-1]
                col_k, row_k, corner_k = keys[:n], keys[n:-1], keys[-1]
                cmap[lo : h - lo, lo : w - lo] = row_c[:, None] + (col_c - corner_c)[None, :]
                kmap[lo : h - lo, lo : w - lo] = row_k[:, None] ^ (col_k ^ corner_k)[None, :]
                boxes_of.append(_cell_boxes(xs, ys, col_c, row_c, corner_c))
            cell_maps.append(cmap)
            key_maps.append(kmap)
        n_cells = max((int(c.max()) + 1 for c in cell_maps), default=0)
        big = np.iinfo(np.int64).max
        x0, y0 = np.full(n_cells, big, np.int64), np.full(n_cells, big, np.int64)
        x1, y1 = np.full(n_cells, -1, np.int64), np.full(n_cells, -1, np.int64)
        for ids, bx0, bx1, by0, by1 in boxes_of:
            x0[ids], x1[ids], y0[ids], y1[ids] = bx0, bx1, by0, by1
        level_cells = np.zeros(len(sizes) + 1, dtype=np.int64)
        for level, cmap in enumerate(cell_maps):
            level_cells[level + 1] = max(level_cells[level], int(cmap.max()) + 1)
        boxes = np.stack([x0, x1, y0, y1], axis=1)
        return cls(np.asarray(sizes, dtype=np.int64), bounds, cell_maps, key_maps, boxes, level_cells)


def _cell_boxes(
    xs: np.ndarray, ys: np.ndarray, col_cells: np.ndarray, row_cells: np.ndarray, corner: int
) -> tuple[np.ndarray, ...]:
    """The cells of one level and their boxes: (ids, x0, x1, y0, y1), each (R, C) for the
    level's R rows and C columns of cells. ``col_cells``: the cells along the first row
    (one per pixel column ``xs``), ``row_cells`` along the first column (pixel rows ``ys``),
    ``corner`` the cell of their first pixel; a cell's x range is its column's, its y range
    its row's."""
    big = np.iinfo(np.int64).max

    def ranges(values: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, ...]:
        unique, inverse = np.unique(values, return_inverse=True)
        first, last = np.full(len(unique), big, np.int64), np.full(len(unique), -1, np.int64)
        np.minimum.at(first, inverse, pixels)
        np.maximum.at(last, inverse, pixels + 1)
        return unique, first, last

    cols, bx0, bx1 = ranges(col_cells, xs)
    rows, by0, by1 = ranges(row_cells, ys)
    ids = rows[:, None] + (cols - corner)[None, :]
    shape = ids.shape
    return (ids, np.broadcast_to(bx0[None, :], shape), np.broadcast_to(bx1[None, :], shape),
            np.broadcast_to(by0[:, None], shape), np.broadcast_to(by1[:, None], shape))  # fmt: skip


@functools.lru_cache(maxsize=8)
def pyramid_maps(
    width: int, height: int, scale_factor: float, n_levels: int, edge: int, cell_size: float
) -> PyramidMaps:
    """The :class:`PyramidMaps` of one image size and pyramid, built once per process."""
    return PyramidMaps.create(width, height, scale_factor, n_levels, edge, cell_size)
