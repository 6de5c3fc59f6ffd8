"""Hierarchical k-medians (binary) / k-means (float) tree, built level by level.

DBoW2 (Galvez-Lopez & Tardos, T-RO 2012, section IV) builds its vocabulary tree by running
k-means with k-means++ seeding on the descriptors of every node, recursively, ``L`` levels
deep; for binary descriptors the distance is the Hamming distance and the centre the
bitwise majority ("k-medians"). This module builds the same tree, but processes all nodes
of one level at once: seeding, assignment and centre updates are vectorised over the whole
level (each row only compares against its own node's ``k`` centres), so the cost is a few
numpy passes per level instead of one Python call per node.

Details (as DBoW2 unless said otherwise):

* a node holding at most ``k`` descriptors gets one child per descriptor;
* seeding is k-means++ (Arthur & Vassilvitskii, SODA 2007) with probability proportional
  to the squared distance to the nearest chosen centre (DBoW2 uses the plain distance);
* Lloyd iterations stop when no assignment changes or after ``max_iters``;
* a node with a single descriptor is a leaf (DBoW2 continues it as a chain of one-child
  nodes down to level ``L``; the words and their descriptors are the same) and clusters
  left empty are dropped, so a node may have fewer than ``k`` children.
"""

from __future__ import annotations

import logging

import numpy as np
from tqdm import tqdm

from orbslam_hgcn.compiled import descriptor_words
from orbslam_hgcn.vocabulary.descriptors import (
    BINARY,
    descriptor_kind,
    dist_to_candidates,
    segment_centres,
)

log = logging.getLogger(__name__)

_CHUNK = 32768  # rows per chunk when gathering (rows, k, W) candidate centres


def _dist_rows(xs: np.ndarray, cs: np.ndarray, kind: str) -> np.ndarray:
    """(N,) distance of each row of xs to the same row of cs (Hamming or squared L2)."""
    if kind == BINARY:
        return np.bitwise_count(xs ^ cs).sum(axis=1, dtype=np.int32).astype(np.float64)
    d = xs - cs
    return np.einsum("nd,nd->n", d, d).astype(np.float64)


def _assign(xs: np.ndarray, centres: np.ndarray, gid: np.ndarray, kind: str) -> np.ndarray:
    """(N,) index in [0, k) of the nearest of each row's own group centres (G, k, W)."""
    out = np.empty(len(xs), np.int64)
    for s in range(0, len(xs), _CHUNK):
        d = dist_to_candidates(xs[s : s + _CHUNK], centres[gid[s : s + _CHUNK]], kind)
        out[s : s + _CHUNK] = np.argmin(d, axis=1)
    return out


def batched_kmedians(
    xs: np.ndarray, sizes: np.ndarray, k: int, max_iters: int, rng: np.random.Generator, kind: str
) -> np.ndarray:
    """Cluster G groups of rows into k clusters each, all groups at once.

    xs: (N, W) rows sorted by group (uint64 words or float32). sizes: (G,) rows per group,
    each > k. Returns (N,) int64 cluster of each row within its group, in [0, k).
    """
    G = len(sizes)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    gid = np.repeat(np.arange(G), sizes)
    centres = np.empty((G, k) + xs.shape[1:], xs.dtype)
    # k-means++ seeding, one new centre per group and step.
    first = starts + (rng.random(G) * sizes).astype(np.int64)
    centres[:, 0] = xs[first]
    dmin = _dist_rows(xs, centres[gid, 0], kind)
    for j in range(1, k):
        w = dmin * dmin if kind == BINARY else dmin  # D^2 (float distances are squared already)
        cs = np.cumsum(w)
        before = np.concatenate([[0.0], cs])
        total = before[starts + sizes] - before[starts]
        pick = np.searchsorted(cs, before[starts] + rng.random(G) * total, side="right")
        flat = total <= 0  # all rows equal their centres: pick uniformly
        pick[flat] = starts[flat] + (rng.random(int(flat.sum())) * sizes[flat]).astype(np.int64)
        pick = np.clip(pick, starts, starts + sizes - 1)
        centres[:, j] = xs[pick]
        dmin = np.minimum(dmin, _dist_rows(xs, centres[gid, j], kind))
    labels = np.full(len(xs), -1, np.int64)
    for _ in range(max(1, max_iters)):
        new = _assign(xs, centres, gid, kind)
        if np.array_equal(new, labels):
            break
        labels = new
        key = gid * k + labels
        order = np.argsort(key, kind="stable")
        uniq, first_row = np.unique(key[order], return_index=True)
        centres[uniq // k, uniq % k] = segment_centres(xs[order], first_row, kind)
    return labels


def build_tree(
    desc: np.ndarray, k: int, levels: int, max_iters: int = 10, seed: int = 0, progress: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Build the vocabulary tree.

    desc: (N, B) uint8 binary or (N, D) float descriptors. k: branching factor.
    levels: depth L of the tree (root at depth 0, deepest words at depth L).
    Returns ``parent`` (M,) int32 (root 0 has parent -1; every node's parent has a smaller
    id; siblings have consecutive ids) and ``centres`` (M, B) uint8 / (M, D) float32 (the
    root's centre is zero). The leaves are the words.
    """
    if k < 2 or levels < 1:
        raise ValueError("the tree needs k >= 2 and levels >= 1")
    kind = descriptor_kind(desc)
    x = descriptor_words(desc) if kind == BINARY else np.ascontiguousarray(desc, dtype=np.float32)
    rng = np.random.default_rng(seed)
    n = len(x)
    parents = [np.array([-1], np.int64)]
    centres = [np.zeros((1,) + x.shape[1:], x.dtype)]
    n_nodes = 1
    node_of = np.zeros(n, np.int64)  # node of every descriptor at the current depth
    level_first = 0  # first node id of the current depth
    bar = tqdm(range(levels), desc="vocabulary tree levels", unit="level", disable=not progress)
    for depth in bar:
        counts = np.bincount(node_of, minlength=n_nodes)
        splittable = counts >= 2
        splittable[:level_first] = False
        rows = np.flatnonzero(splittable[node_of])
        if len(rows) == 0:
            break
        rows = rows[np.argsort(node_of[rows], kind="stable")]
        g_node, g_start, g_size = np.unique(node_of[rows], return_index=True, return_counts=True)
        G = len(g_node)
        labels = np.arange(len(rows)) - np.repeat(g_start, g_size)  # small groups: one child each
        big = g_size > k
        if big.any():
            in_big = np.repeat(big, g_size)
            labels[in_big] = batched_kmedians(x[rows[in_big]], g_size[big], k, max_iters, rng, kind)
        key = np.repeat(np.arange(G), g_size) * k + labels
        order = np.argsort(key, kind="stable")
        uniq, first_row, inverse = np.unique(key[order], return_index=True, return_inverse=True)
        parents.append(g_node[uniq // k])
        centres.append(segment_centres(x[rows[order]], first_row, kind))
        node_of[rows[order]] = n_nodes + inverse.reshape(-1)
        level_first = n_nodes
        n_nodes += len(uniq)
        bar.set_postfix(nodes=n_nodes, split=G)
        log.debug("tree depth %d: %d nodes split into %d children", depth + 1, G, len(uniq))
    parent = np.concatenate(parents).astype(np.int32)
    c = np.concatenate(centres)
    if kind == BINARY:
        c = np.ascontiguousarray(c).view(np.uint8)[:, : desc.shape[1]]
    return parent, np.ascontiguousarray(c)
