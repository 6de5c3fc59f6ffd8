"""Geometry for drawing: keyframe frustums, graph edges and point colours, as whole arrays."""

from __future__ import annotations

import logging

import numpy as np

from orbslam_hgcn.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)

# Matplotlib's viridis sampled at five stops (0, .25, .5, .75, 1), linearly interpolated:
# perceptually ordered and readable on the viewer's dark background.
_VIRIDIS_STOPS = np.array(
    [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=np.float64
)
_LUT_SIZE = 256
_LUT = np.stack(
    [np.interp(np.linspace(0, 1, _LUT_SIZE), np.linspace(0, 1, 5), _VIRIDIS_STOPS[:, c]) for c in range(3)],
    axis=1,
).round().astype(np.uint8)

# Vertex order of one frustum drawn as a single strip of 10 vertices: the four image
# corners (0-3) and the centre (C). Image rectangle 0-1-2-3-0, then 0-C-1, 1-2 (drawn
# twice), 2-C-3: every one of the eight edges with a single strip, so all keyframes fit in
# one (K, 10, 3) array.
_FRUSTUM_ORDER = np.array([0, 1, 2, 3, 0, 4, 1, 2, 4, 3])


# The same table packed as 0xRRGGBBAA, the form rerun stores colours in (no conversion).
_LUT_PACKED = (
    (_LUT[:, 0].astype(np.uint32) << 24) | (_LUT[:, 1].astype(np.uint32) << 16)
    | (_LUT[:, 2].astype(np.uint32) << 8) | np.uint32(0xFF)
)


def colormap(values: np.ndarray, lo: float, hi: float, packed: bool = False) -> np.ndarray:
    """Viridis colours of ``values`` scaled from [lo, hi] (clipped; NaN as lo).

    (N,) -> (N, 3) uint8 RGB, or (N,) uint32 0xRRGGBBAA with ``packed``.
    """
    values = np.asarray(values, dtype=np.float64)
    span = hi - lo if hi > lo else 1.0
    idx = np.clip((values - lo) / span, 0.0, 1.0) * (_LUT_SIZE - 1)
    idx = np.nan_to_num(idx, nan=0.0).astype(np.intp)
    return _LUT_PACKED[idx] if packed else _LUT[idx]


def frustum_strips(T_wc: np.ndarray, camera: PinholeCamera, depth: float) -> np.ndarray:
    """Wire frustums of cameras, one strip each.

    T_wc:  (K, 4, 4) camera-to-world poses.
    depth: distance of the drawn image plane from the centre, world units.
    Returns (K, 10, 3) float32 strip vertices in the world frame.
    """
    T_wc = np.asarray(T_wc, dtype=np.float64).reshape(-1, 4, 4)
    w, h = float(camera.width), float(camera.height)
    corners_uv = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    rays = camera.unproject(corners_uv) * depth  # (4, 3) camera frame
    verts_c = np.vstack([rays, np.zeros((1, 3))])  # (5, 3): corners then centre
    verts_w = np.matmul(T_wc[:, :3, :3], verts_c.T).transpose(0, 2, 1) + T_wc[:, None, :3, 3]
    return verts_w[:, _FRUSTUM_ORDER].astype(np.float32)


def edge_segments(node_ids: np.ndarray, node_pos: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Line segments joining graph nodes given by id.

    node_ids: (K,) int ids, node_pos: (K, 3) positions, edges: (E, 2) id pairs.
    Edges naming an unknown id are dropped (a keyframe culled since the edge was read).
    Returns (E', 2, 3) float32 segment end points.
    """
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    node_ids = np.asarray(node_ids, dtype=np.int64).reshape(-1)
    if len(edges) == 0 or len(node_ids) == 0:
        return np.zeros((0, 2, 3), dtype=np.float32)
    order = np.argsort(node_ids, kind="stable")
    sorted_ids = node_ids[order]
    slot = np.clip(np.searchsorted(sorted_ids, edges), 0, len(sorted_ids) - 1)
    known = np.all(sorted_ids[slot] == edges, axis=1)
    if not known.all():
        log.debug("dropped %d of %d edges naming unknown nodes", int((~known).sum()), len(edges))
    idx = order[slot[known]]  # (E', 2) rows of node_pos
    return np.asarray(node_pos, dtype=np.float32)[idx]


def unique_edges(*edge_sets: np.ndarray) -> np.ndarray:
    """Union of undirected edge lists, each (E_i, 2) int: (E, 2) with a < b, sorted."""
    edges = np.vstack([np.asarray(e, dtype=np.int64).reshape(-1, 2) for e in edge_sets])
    if len(edges) == 0:
        return edges
    return np.unique(np.sort(edges, axis=1), axis=0)


def point_colours(
    points_w: np.ndarray, obs_count: np.ndarray, mode: str, obs_range: tuple[float, float]
) -> np.ndarray | None:
    """Colours of map points: (P,) uint32 0xRRGGBBAA, or None for the viewer's default colour.

    mode "observations": by observing-keyframe count over ``obs_range`` (dark: few).
    mode "height": by height above the first camera (world -y, as the first camera's image
    y axis points down), scaled over the 2nd-98th percentiles of the snapshot.
    mode "none": None.
    """
    if mode == "none" or len(points_w) == 0:
        return None
    if mode == "observations":
        return colormap(obs_count, *obs_range, packed=True)
    if mode == "height":
        height = -np.asarray(points_w, dtype=np.float64)[:, 1]
        lo, hi = np.percentile(height, [2.0, 98.0])
        return colormap(height, float(lo), float(hi), packed=True)
    raise ValueError(f"unknown point colour mode {mode!r}")
