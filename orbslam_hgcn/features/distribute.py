"""Spreading of detected corners over an image: ORB-SLAM's cell thresholds and quadtree.

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, section III-A; ORBextractor.cc) detects
FAST corners per cell of about 30 px with threshold 20, falls back to threshold 7 in cells
where none is found, and then keeps the requested number of corners with a quadtree
(``DistributeOctTree``): nodes are split into four until there are as many nodes as wanted
features, splitting the most populated nodes first at the last step, and the strongest
corner of each node survives. Here:

* the per-cell thresholds are applied by :class:`~orbslam_hgcn.features.orb.ORBExtractor`
  (one high-threshold pass per level, then the low threshold on the cells left empty);
  :func:`cell_ids` gives the cell of every corner;
* the quadtree is evaluated on Morton codes of the corner positions, which give the node of
  every corner at every depth without building the tree, for all pyramid levels at once.
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

# Depth of the Morton codes: 2**12 subdivisions of a root node are finer than a pixel for
# any image side below 4096 pixels.
_MAX_DEPTH = 12
_GROUP_SHIFT = 2 * _MAX_DEPTH + 8  # key bits: level | 8 bits of root node | Morton code


def features_per_level(n_features: int, scale_factor: float, n_levels: int) -> np.ndarray:
    """(L,) int number of features wanted at each pyramid level.

    ORB-SLAM's geometric series: level ``l`` gets ``n * (1 - f) / (1 - f**L) * f**l`` with
    ``f = 1 / scale_factor`` (rounded), the last level takes the remainder. (The ratio
    between levels is the linear scale, as in ORB-SLAM's code, not the area ratio f**2.)
    """
    f = 1.0 / scale_factor
    per = n_features * (1.0 - f) / (1.0 - f**n_levels)
    out = np.zeros(n_levels, dtype=np.int64)
    total = 0
    for level in range(n_levels - 1):
        out[level] = int(round(per))
        total += out[level]
        per *= f
    out[-1] = max(n_features - total, 0)
    return out


def _bounds_columns(bounds: np.ndarray) -> tuple[np.ndarray, ...]:
    b = np.asarray(bounds, dtype=np.float64).reshape(-1, 4)
    return b[:, 0], b[:, 1], b[:, 2], b[:, 3]


def cell_ids(x: np.ndarray, y: np.ndarray, group: np.ndarray, bounds: np.ndarray, cell_size: float) -> np.ndarray:
    """(N,) int64 index of ORB-SLAM's detection cell of each corner, unique over all levels.

    x, y: (N,) corner positions in pixels of their level; group: (N,) int level; bounds:
    (G, 4) (min_x, max_x, min_y, max_y) detection area of each level. A level is cut into
    ``int(width / cell_size)`` x ``int(height / cell_size)`` cells of ``ceil`` sizes.
    """
    min_x, max_x, min_y, max_y = _bounds_columns(bounds)
    width, height = max_x - min_x, max_y - min_y
    n_cols = np.maximum((width / cell_size).astype(np.int64), 1)
    n_rows = np.maximum((height / cell_size).astype(np.int64), 1)
    w_cell = np.ceil(width / n_cols)
    h_cell = np.ceil(height / n_rows)
    first_cell = np.concatenate([[0], np.cumsum(n_cols * n_rows)])
    g = np.asarray(group, dtype=np.int64)
    # ORB-SLAM runs FAST on windows [ini, ini + cell + 6) whose 3 px margin FAST skips, so a
    # cell owns the corners in [ini + 3, ini + 3 + cell).
    cx = np.clip(((x - min_x[g] - 3) // w_cell[g]).astype(np.int64), 0, n_cols[g] - 1)
    cy = np.clip(((y - min_y[g] - 3) // h_cell[g]).astype(np.int64), 0, n_rows[g] - 1)
    return first_cell[g] + cy * n_cols[g] + cx


def _spread_table() -> np.ndarray:
    """(2**_MAX_DEPTH,) int64: the bits of each index moved to the even bit positions."""
    i = np.arange(1 << _MAX_DEPTH, dtype=np.int64)
    out = np.zeros_like(i)
    for b in range(_MAX_DEPTH):
        out |= ((i >> b) & 1) << (2 * b)
    return out


_SPREAD = _spread_table()


def _first_of_runs(values: np.ndarray) -> np.ndarray:
    """(K,) bool: True where a sorted array starts a new run of equal values."""
    return np.concatenate([np.ones(min(len(values), 1), dtype=bool), values[1:] != values[:-1]])


def quadtree_keys(x: np.ndarray, y: np.ndarray, group: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """(N,) int64 quadtree keys: level, root node and Morton code of each corner.

    x, y: (N,) corner positions; group: (N,) int level; bounds: (G, 4) (min_x, max_x, min_y,
    max_y) of each level's area. Each level has ``round(width / height)`` root nodes side by
    side (ORB-SLAM); two corners share their node at quadtree depth d exactly when their
    keys agree above bit ``2 (_MAX_DEPTH - d)``.
    """
    g = np.asarray(group, dtype=np.int64)
    min_x, max_x, min_y, max_y = _bounds_columns(bounds)
    n_roots = np.maximum(np.round((max_x - min_x) / (max_y - min_y)), 1.0)
    root_w = (max_x - min_x) / n_roots
    side = 1 << _MAX_DEPTH
    u = np.clip((x - min_x[g]) / root_w[g], 0.0, n_roots[g] - 1e-9)
    v = np.clip((y - min_y[g]) / (max_y - min_y)[g], 0.0, 1.0 - 1e-9)
    root = u.astype(np.int64)
    qx = ((u - root) * side).astype(np.int64)
    qy = (v * side).astype(np.int64)
    return (g << _GROUP_SHIFT) | (root << (2 * _MAX_DEPTH)) | _SPREAD[qx] | (_SPREAD[qy] << 1)


def distribute_quadtree(key: np.ndarray, response: np.ndarray, n_wanted: np.ndarray) -> np.ndarray:
    """Indices of the corners kept by ORB-SLAM's quadtree, for several levels at once.

    key: (N,) quadtree keys (:func:`quadtree_keys`, which hold the level); response: (N,)
    corner scores; n_wanted: (G,) corners wanted per level.
    Per level, ORB-SLAM (``DistributeOctTree``) splits every node holding more than one
    corner into four, and when a full round would pass ``n_wanted`` nodes splits only the
    most populated nodes, largest first, until there are enough. The strongest corner of
    each final node is kept. ORB-SLAM may end with up to three nodes too many; the weakest
    of those are dropped here so exactly ``min(N_g, n_wanted_g)`` corners remain per level.
    Returns (K,) int64 sorted indices into the inputs.
    """
    n = len(key)
    n_wanted = np.asarray(n_wanted, dtype=np.int64)
    n_groups = len(n_wanted)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    key = np.asarray(key, dtype=np.int64)
    order = np.argsort(key, kind="stable")
    key = key[order]
    gs = key >> _GROUP_SHIFT
    # Depth at which neighbours in Morton order fall into different nodes: keys share their
    # node at depth d while their highest differing bit is below 2 (D - d). Different roots
    # or levels differ already at depth 0; identical positions never separate (D + 1).
    diff = key[1:] ^ key[:-1]
    top_bit = np.frexp(diff.astype(np.float64))[1] - 1
    sep = np.where(diff > 0, np.maximum(_MAX_DEPTH - top_bit // 2, 0), _MAX_DEPTH + 1)
    n_bins = _MAX_DEPTH + 2
    same = gs[1:] == gs[:-1]
    hist = np.bincount(gs[1:][same] * n_bins + sep[same], minlength=n_groups * n_bins)
    n_nodes = 1 + np.cumsum(hist.reshape(n_groups, n_bins), axis=1)  # (G, D + 2) per depth
    enough = n_nodes >= n_wanted[:, None]
    # First depth with enough nodes per level; a level with too few corners keeps them all.
    depth = np.where(enough.any(axis=1), enough.argmax(axis=1), _MAX_DEPTH + 1)
    pair_g = gs[1:]
    first = np.ones(1, dtype=bool)
    p_new = np.concatenate([first, sep <= np.maximum(depth - 1, 0)[pair_g]])
    c_new = np.concatenate([first, sep <= depth[pair_g]])
    p_id = np.cumsum(p_new) - 1
    n_parent = int(p_id[-1]) + 1
    p_group = gs[p_new]
    n_points = np.bincount(p_id, minlength=n_parent)
    n_children = np.bincount(p_id[c_new], minlength=n_parent)
    need = n_wanted - np.bincount(p_group, minlength=n_groups)
    # Split the most populated parents of each level first (ORB-SLAM sorts nodes by size)
    # while the node count is still below n_wanted.
    by_size = np.argsort(p_group * (n + 1) + (n - n_points), kind="stable")
    gain = n_children[by_size] - 1
    before = np.cumsum(gain) - gain
    grp_sorted = p_group[by_size]
    before -= before[np.searchsorted(grp_sorted, grp_sorted)]
    split = np.zeros(n_parent, dtype=bool)
    split[by_size] = before < need[grp_sorted]
    leaf_id = np.cumsum(p_new | (c_new & split[p_id])) - 1
    # Strongest corner of each leaf: one sort on leaf id (scaled past the response range)
    # plus the corner's weakness.
    resp = np.asarray(response, dtype=np.float64)[order]
    weak = resp.max() - resp  # >= 0, smallest for the strongest corner
    span = float(weak.max()) + 1.0
    pick = np.argsort(leaf_id * span + weak, kind="stable")
    best = pick[_first_of_runs(leaf_id[pick])]
    # Keep at most n_wanted leaves per level, the strongest.
    ranked = best[np.argsort(gs[best] * span + weak[best], kind="stable")]
    rg = gs[ranked]
    rank = np.arange(len(ranked)) - np.searchsorted(rg, rg)
    kept = ranked[rank < n_wanted[rg]]
    return np.sort(order[kept])
