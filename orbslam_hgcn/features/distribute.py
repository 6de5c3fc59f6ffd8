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
  every corner at every depth without building the tree, for all pyramid levels at once,
  in one compiled pass over the corners sorted by code.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from orbslam_hgcn.compiled import jit

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
    key = np.ascontiguousarray(key, dtype=np.int64)
    response = np.ascontiguousarray(response, dtype=np.float64)
    n_wanted = np.ascontiguousarray(n_wanted, dtype=np.int64)
    if len(key) == 0:
        return np.zeros(0, dtype=np.int64)
    if key.min() < 0 or int(key.max() >> _GROUP_SHIFT) >= len(n_wanted):
        raise ValueError("quadtree keys must be non-negative and name a level of n_wanted")
    return _distribute(key, response, n_wanted, int(key.max()).bit_length(), len(key).bit_length())


@jit
def _radix_argsort(key, bits):  # pragma: no cover - compiled
    """Stable argsort of non-negative int64 keys below 2**bits (least significant digit
    first, 11-bit digits)."""
    n = len(key)
    idx = np.arange(n)
    tmp = np.empty(n, np.int64)
    shift = 0
    while shift < bits:
        count = np.zeros(2049, np.int64)
        for i in range(n):
            count[((key[idx[i]] >> shift) & 2047) + 1] += 1
        for d in range(2048):
            count[d + 1] += count[d]
        for i in range(n):
            j = idx[i]
            d = (key[j] >> shift) & 2047
            tmp[count[d]] = j
            count[d] += 1
        idx, tmp = tmp, idx
        shift += 11
    return idx


@jit
def _merge_argsort(values):  # pragma: no cover - compiled
    """Stable argsort of (N,) float64 values (bottom-up merge sort)."""
    n = len(values)
    idx = np.arange(n)
    tmp = np.empty(n, np.int64)
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid, hi = min(lo + width, n), min(lo + 2 * width, n)
            i, j = lo, mid
            for k in range(lo, hi):
                if i < mid and (j >= hi or values[idx[i]] <= values[idx[j]]):
                    tmp[k] = idx[i]
                    i += 1
                else:
                    tmp[k] = idx[j]
                    j += 1
        idx, tmp = tmp, idx
        width *= 2
    return idx


@jit
def _distribute(key, response, n_wanted, key_bits, index_bits):  # pragma: no cover - compiled
    """:func:`distribute_quadtree` on checked arrays: keys below 2**key_bits, N below
    2**index_bits (the bits the radix sorts look at)."""
    n = len(key)
    n_groups = len(n_wanted)
    order = _radix_argsort(key, key_bits)
    k = key[order]
    gs = k >> _GROUP_SHIFT
    # Depth at which neighbours in Morton order fall into different nodes: keys share their
    # node at depth d while their highest differing bit is below 2 (D - d). Different roots
    # or levels differ already at depth 0; identical positions never separate (D + 1). The
    # highest bit is read off the float64 exponent.
    n_bins = _MAX_DEPTH + 2
    sep = np.empty(n, np.int64)
    hist = np.zeros(n_groups * n_bins, np.int64)
    for i in range(1, n):
        d = k[i] ^ k[i - 1]
        if d > 0:
            sep[i] = max(_MAX_DEPTH - (math.frexp(float(d))[1] - 1) // 2, 0)
        else:
            sep[i] = _MAX_DEPTH + 1
        if gs[i] == gs[i - 1]:
            hist[gs[i] * n_bins + sep[i]] += 1
    # First depth with enough nodes per level; a level with too few corners keeps them all.
    depth = np.full(n_groups, _MAX_DEPTH + 1, np.int64)
    for g in range(n_groups):
        n_nodes = 1
        for b in range(n_bins):
            n_nodes += hist[g * n_bins + b]
            if n_nodes >= n_wanted[g]:
                depth[g] = b
                break
    # The parent (node at depth - 1) of each corner, and whether it starts a child node.
    p_id = np.empty(n, np.int64)
    c_new = np.empty(n, np.bool_)
    n_parent = 0
    for i in range(n):
        p_new = True
        c_new[i] = True
        if i > 0:
            p_new = sep[i] <= max(depth[gs[i]] - 1, 0)
            c_new[i] = sep[i] <= depth[gs[i]]
        n_parent += p_new
        p_id[i] = n_parent - 1
    p_group = np.empty(n_parent, np.int64)
    n_points = np.zeros(n_parent, np.int64)
    n_children = np.zeros(n_parent, np.int64)
    for i in range(n):
        p = p_id[i]
        p_group[p] = gs[i]
        n_points[p] += 1
        n_children[p] += c_new[i]
    # Per level, split the most populated parents first (ORB-SLAM sorts nodes by size; ties
    # in Morton order) while the node count is still below n_wanted.
    split = np.zeros(n_parent, np.bool_)
    a = 0
    while a < n_parent:
        b = a
        while b < n_parent and p_group[b] == p_group[a]:
            b += 1
        need = n_wanted[p_group[a]] - (b - a)
        before = 0
        for p in _radix_argsort(n - n_points[a:b], index_bits) + a:
            split[p] = before < need
            before += n_children[p] - 1
        a = b
    # The strongest corner of each leaf (the first on ties, in Morton order).
    resp = response[order]
    weak = resp.max() - resp
    best = np.empty(n, np.int64)
    n_best = 0
    for i in range(n):
        if i == 0 or p_id[i] != p_id[i - 1] or (c_new[i] and split[p_id[i]]):
            best[n_best] = i
            n_best += 1
        elif weak[i] < weak[best[n_best - 1]]:
            best[n_best - 1] = i
    # At most n_wanted leaves per level, the strongest.
    kept = np.empty(n_best, np.int64)
    n_kept = 0
    a = 0
    while a < n_best:
        b = a
        while b < n_best and gs[best[b]] == gs[best[a]]:
            b += 1
        leaves = best[a:b]
        ranked = leaves[_merge_argsort(weak[leaves])]
        for j in range(min(len(ranked), n_wanted[gs[leaves[0]]])):
            kept[n_kept] = order[ranked[j]]
            n_kept += 1
        a = b
    kept = kept[:n_kept]
    return kept[_radix_argsort(kept, index_bits)]
