"""Chow-Liu tree over binary word occurrences (the dependency model of FAB-MAP).

Each visual word ``q`` is a binary variable ``z_q`` (seen / not seen in an image). The
Chow-Liu tree (Chow & Liu, IEEE Trans. Inf. Theory 1968) is the tree-structured
distribution closest in KL divergence to the empirical joint: the maximum spanning tree of
the pairwise mutual information graph. FAB-MAP (Cummins & Newman, IJRR 2008, sec. 3.2)
uses it so that the likelihood of an observation factorises as
``p(Z) = p(z_root) prod_q p(z_q | z_parent(q))``.

Only the words that vary across the training images (seen in some but not all of them)
enter the spanning tree: a word never seen, or seen in every image, has zero mutual
information with every other word, so the tree over all V words (as openFABMAP builds it)
hangs it under the root with a conditional equal to its marginal. That is what this module
stores for such words, without computing their rows. Mutual information among the
``V_occ`` varying words is computed exactly from co-occurrence counts (a sparse ``X^T X``
product, one block of rows at a time) into a dense ``(V_occ, V_occ)`` float32 matrix (400 MB
for 10k words; checked against the memory available first, see
:mod:`orbslam_hgcn.placerec.memory`), and the maximum spanning tree is grown by Prim's
algorithm, one vectorised ``O(V_occ)`` update per word. The stored conditionals are
smoothed as openFABMAP does (Glover et al., ICRA 2012): ``p = (1 - 2 s) * frequency + s``
with ``s = 0.01``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.special import xlogy
from tqdm import tqdm

from orbslam_hgcn.errors import OrbslamError
from orbslam_hgcn.placerec.memory import (
    MI_BLOCK_ELEMENTS,
    MI_BLOCK_ROWS,
    check_memory,
    chow_liu_bytes,
    format_bytes,
)
from orbslam_hgcn.placerec.words import as_binary_csr

log = logging.getLogger(__name__)

_BLOCK_ROWS = MI_BLOCK_ROWS  # rows of the MI matrix computed per sparse product (at most)


def _binary_entropy(p: np.ndarray) -> np.ndarray:
    return -(xlogy(p, p) + xlogy(1.0 - p, 1.0 - p))


def mutual_information_from_counts(n11: np.ndarray, ca: np.ndarray, cb: np.ndarray, n: int) -> np.ndarray:
    """Mutual information (nats) of binary pairs from counts, broadcasting over arrays.

    n11: images where both words occur; ca, cb: images where each occurs; n: images.
    Maximum-likelihood frequencies with ``0 log 0 = 0``, as ``H(A) + H(B) - H(A, B)``.
    """
    n11 = np.asarray(n11, dtype=np.float64)
    ca = np.asarray(ca, dtype=np.float64)
    cb = np.asarray(cb, dtype=np.float64)
    inv = 1.0 / n
    mi = _binary_entropy(ca * inv) + _binary_entropy(cb * inv)
    for joint in (n11, ca - n11, cb - n11, n - ca - cb + n11):
        pj = np.maximum(joint * inv, 0.0)
        mi = mi + xlogy(pj, pj)
    return np.maximum(mi, 0.0)


def mutual_information_matrix(X: sp.csr_matrix, *, block_rows: int = _BLOCK_ROWS, progress: bool = False) -> np.ndarray:
    """(V, V) float32 pairwise mutual information of the columns of ``X`` (diagonal 0).

    X: (N, V) binary occurrence matrix. Co-occurrences come from sparse products of one
    block of at most ``block_rows`` columns at a time (fewer for large V), so peak extra
    memory is O(min(block_rows * V, 2^21)) elements.
    """
    X = as_binary_csr(X)
    n, v = X.shape
    block_rows = max(1, min(block_rows, MI_BLOCK_ELEMENTS // max(v, 1)))
    counts = np.asarray(X.sum(axis=0)).ravel()
    Xc = X.tocsc()
    mi = np.empty((v, v), dtype=np.float32)
    starts = range(0, v, block_rows)
    for a in tqdm(starts, desc="mutual information", unit="block", disable=not progress):
        b = min(a + block_rows, v)
        co = (Xc[:, a:b].T @ Xc).toarray()  # (b - a, V) co-occurrence counts
        mi[a:b] = mutual_information_from_counts(co, counts[a:b, None], counts[None, :], n)
        mi[np.arange(a, b), np.arange(a, b)] = 0.0
    return mi


def maximum_spanning_tree(weights: np.ndarray, root: int = 0) -> np.ndarray:
    """Prim's algorithm on a dense symmetric (V, V) weight matrix.

    Returns (V,) int64 parents, -1 at ``root``: the maximum-weight spanning tree oriented
    away from ``root``. Ties break towards the lower vertex index.
    """
    v = weights.shape[0]
    parent = np.full(v, -1, dtype=np.int64)
    if v <= 1:
        return parent
    in_tree = np.zeros(v, dtype=bool)
    best = np.full(v, -np.inf)
    best_from = np.full(v, root, dtype=np.int64)
    u = root
    for _ in range(v - 1):
        in_tree[u] = True
        row = weights[u]
        better = (row > best) & ~in_tree
        best[better] = row[better]
        best_from[better] = u
        best[u] = -np.inf  # in-tree vertices keep -inf, so argmax picks outside the tree
        u = int(np.argmax(best))
        parent[u] = best_from[u]
    return parent


@dataclass(frozen=True, eq=False)
class ChowLiuTree:
    """A Chow-Liu tree over V binary words with smoothed conditionals.

    parent:          (V,) int64 parent word, -1 at the root
    p_z:             (V,) float64 smoothed marginal p(z_q = 1)
    p_z_given_p:     (V,) float64 p(z_q = 1 | z_parent = 1); the marginal at the root
    p_z_given_not_p: (V,) float64 p(z_q = 1 | z_parent = 0); the marginal at the root
    mi:              (V,) float64 mutual information of each word with its parent (0 at root)
    n_train:         number of training images
    """

    parent: np.ndarray
    p_z: np.ndarray
    p_z_given_p: np.ndarray
    p_z_given_not_p: np.ndarray
    mi: np.ndarray
    n_train: int

    @property
    def n_words(self) -> int:
        return len(self.parent)

    @property
    def root(self) -> int:
        return int(np.flatnonzero(self.parent < 0)[0])

    def edges(self) -> set[frozenset[int]]:
        """The undirected edge set {{q, parent(q)}}."""
        q = np.flatnonzero(self.parent >= 0)
        return {frozenset((int(a), int(b))) for a, b in zip(q, self.parent[q], strict=True)}

    def children(self) -> sp.csr_matrix:
        """(V, V) CSR matrix whose row p lists the children of word p (column indices)."""
        q = np.flatnonzero(self.parent >= 0)
        data = np.ones(len(q), dtype=np.int8)
        return sp.csr_matrix((data, (self.parent[q], q)), shape=(self.n_words, self.n_words))

    def save(self, path: str | Path) -> None:
        np.savez_compressed(
            path, parent=self.parent, p_z=self.p_z, p_z_given_p=self.p_z_given_p,
            p_z_given_not_p=self.p_z_given_not_p, mi=self.mi, n_train=self.n_train,
        )

    @classmethod
    def load(cls, path: str | Path) -> ChowLiuTree:
        try:
            with np.load(path) as d:
                tree = cls(
                    parent=d["parent"].astype(np.int64), p_z=d["p_z"], p_z_given_p=d["p_z_given_p"],
                    p_z_given_not_p=d["p_z_given_not_p"], mi=d["mi"], n_train=int(d["n_train"]),
                )
        except (OSError, KeyError, ValueError) as exc:
            raise OrbslamError(f"{path}: not a Chow-Liu tree file ({exc})") from None
        return tree


def _smoothed(count: np.ndarray, total: np.ndarray, s: float) -> np.ndarray:
    """(1 - 2s) count/total + s; s where total is 0 (openFABMAP's smoothing)."""
    count = np.asarray(count, dtype=np.float64)
    total = np.asarray(total, dtype=np.float64)
    freq = np.divide(count, total, out=np.zeros_like(count), where=total > 0)
    return (1.0 - 2.0 * s) * freq + s


def varying_words(X: sp.spmatrix) -> np.ndarray:
    """(V_occ,) int64 ids of the words seen in some but not all rows of ``X`` (N, V)."""
    X = as_binary_csr(X)
    counts = np.asarray(X.sum(axis=0)).ravel()
    return np.flatnonzero((counts > 0) & (counts < X.shape[0])).astype(np.int64)


def tree_from_parents(
    X: sp.csr_matrix, parent: np.ndarray, mi: np.ndarray | None = None, smoothing: float = 0.01,
    *, independent: np.ndarray | None = None,
) -> ChowLiuTree:
    """Fill a tree's smoothed probabilities from occurrence data ``X`` (N, V) and parents.

    mi: the (V, V) mutual information matrix, or (V,) the mutual information of each word
    with its parent. independent: (V,) bool, words whose conditionals are set to their
    marginal (no dependence on the parent).
    """
    X = as_binary_csr(X)
    n, v = X.shape
    counts = np.asarray(X.sum(axis=0)).ravel().astype(np.float64)
    dep = parent >= 0 if independent is None else (parent >= 0) & ~independent
    q = np.flatnonzero(dep)
    p = parent[q]
    Xc = X.tocsc()
    n11 = np.zeros(v)
    if len(q):
        n11[q] = np.asarray(Xc[:, q].multiply(Xc[:, p]).sum(axis=0)).ravel()
    p_z = _smoothed(counts, np.full(v, n), smoothing)
    p_given_p = p_z.copy()
    p_given_not_p = p_z.copy()
    p_given_p[q] = _smoothed(n11[q], counts[p], smoothing)
    p_given_not_p[q] = _smoothed(counts[q] - n11[q], n - counts[p], smoothing)
    mi_edge = np.zeros(v)
    if mi is not None and np.ndim(mi) == 1:
        mi_edge[q] = np.asarray(mi)[q]
    elif mi is not None:
        mi_edge[q] = mi[q, p]
    return ChowLiuTree(parent=parent.astype(np.int64), p_z=p_z, p_z_given_p=p_given_p,
                       p_z_given_not_p=p_given_not_p, mi=mi_edge, n_train=n)


CHOW_LIU_WAY_OUT = "use a smaller vocabulary or fewer training images"


def learn_chow_liu_tree(
    X: np.ndarray | sp.spmatrix, *, smoothing: float = 0.01, progress: bool = False,
    memory_limit_mb: float | None = None, way_out: str = CHOW_LIU_WAY_OUT,
) -> ChowLiuTree:
    """Learn the Chow-Liu tree of binary occurrence data.

    X: (N, V) occurrences (N training images, V words), dense or sparse; nonzero = seen.
    The spanning tree is grown over the words that vary in X (see :func:`varying_words`);
    every other word hangs under the root, independent of it. The root is an endpoint of
    the strongest edge (as openFABMAP builds it). Before the (V_occ, V_occ) mutual
    information is allocated, its size is checked against the memory available
    (``memory_limit_mb``, else :func:`orbslam_hgcn.placerec.memory.available_bytes`): an
    OrbslamError naming both and ``way_out`` when it does not fit.
    """
    X = as_binary_csr(X)
    n, v = X.shape
    if n == 0 or v == 0:
        raise OrbslamError("Chow-Liu tree: no training images or no words")
    keep = varying_words(X)
    vk = len(keep)
    need = chow_liu_bytes(vk)
    log.info("Chow-Liu tree: %d training images, %d words, %d of them varying (%s for mutual information)",
             n, v, vk, format_bytes(4 * vk * vk))
    check_memory(need, f"the Chow-Liu tree over the {vk} varying words (of {v})", way_out,
                 limit_mb=memory_limit_mb)
    root = 0
    parent = np.zeros(v, dtype=np.int64)
    mi_edge = np.zeros(v)
    if vk > 1:
        mi = mutual_information_matrix(X[:, keep], progress=progress)
        root_k = int(np.unravel_index(np.argmax(mi), mi.shape)[0])
        parent_k = maximum_spanning_tree(mi, root=root_k)
        root = int(keep[root_k])
        parent[:] = root
        inner = parent_k >= 0
        parent[keep[inner]] = keep[parent_k[inner]]
        mi_edge[keep[inner]] = mi[np.flatnonzero(inner), parent_k[inner]]
        del mi
    elif vk == 1:
        root = int(keep[0])
        parent[:] = root
    parent[root] = -1
    independent = np.ones(v, dtype=bool)
    independent[keep] = False
    return tree_from_parents(X, parent, mi_edge, smoothing, independent=independent)
