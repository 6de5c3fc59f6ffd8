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
``V_occ`` varying words is computed exactly from co-occurrence counts, one row at a time as
Prim's algorithm asks for it (:class:`MutualInformationRows`), so no ``(V_occ, V_occ)``
matrix is ever stored: memory is the sparse occurrence data and O(V_occ) (checked against
the memory available first, see :mod:`orbslam_hgcn.placerec.memory`). The maximum spanning
tree is grown by Prim's algorithm, one vectorised ``O(V_occ)`` row and update per word,
from the root the dense matrix's ``argmax`` gives. The stored conditionals are smoothed as
openFABMAP does (Glover et al., ICRA 2012): ``p = (1 - 2 s) * frequency + s``
with ``s = 0.01``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.special import xlogy
from tqdm import tqdm

from orbslam_hgcn.errors import OrbslamError
from orbslam_hgcn.placerec.memory import check_memory, chow_liu_bytes, format_bytes
from orbslam_hgcn.placerec.words import as_binary_csr

log = logging.getLogger(__name__)


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


class MutualInformationRows:
    """Rows ``MI(u, .)`` of the pairwise mutual information of the columns of ``X``, on demand.

    X: (N, V) binary occurrence matrix. A row is computed from the co-occurrence counts of
    column ``u`` with every column (the sparse product of column ``u`` with ``X``, taken as
    the column indices of the images that contain ``u``): the words that never occur with
    ``u`` have a mutual information that depends only on their count, evaluated once per
    distinct count; the few that do are evaluated from their counts. Values are those of
    :func:`mutual_information_from_counts` with ``u``'s count first, as float32, diagonal 0:
    the same sum of the same terms, each term looked up in a table over the N + 1 possible
    counts (the entropies and ``p log p`` of ``count / N``), so the rows are bit for bit the
    rows of the dense matrix. Memory: the sparse matrix (CSR and CSC) and O(V) per row.
    """

    def __init__(self, X: sp.spmatrix):
        X = as_binary_csr(X)
        self.n_images, self.n_words = X.shape
        self._csr = X
        self._csc = X.tocsc()
        self.counts = np.asarray(X.sum(axis=0)).ravel().astype(np.int64)
        self._levels, self._level_of, self._level_size = np.unique(
            self.counts, return_inverse=True, return_counts=True)
        p = np.arange(self.n_images + 1, dtype=np.float64) * (1.0 / self.n_images)
        self._entropy_of = _binary_entropy(p)  # H(count / N), as in mutual_information_from_counts
        self._plogp_of = xlogy(p, p)  # p log p of a joint count's frequency, likewise

    def _mutual_information(self, n11: np.ndarray, ca: int, cb: np.ndarray) -> np.ndarray:
        """:func:`mutual_information_from_counts` of integer counts, by table, as float32."""
        t = self._plogp_of
        mi = self._entropy_of[ca] + self._entropy_of[cb]
        for joint in (n11, ca - n11, cb - n11, self.n_images - ca - cb + n11):
            mi += t[joint]
        return np.maximum(mi, 0.0).astype(np.float32)

    def entropy(self) -> np.ndarray:
        """(V,) float64 entropy (nats) of each word: an upper bound of its mutual information."""
        return self._entropy_of[self.counts]

    def cooccurrence(self, u: int) -> tuple[np.ndarray, np.ndarray]:
        """The columns that occur together with ``u`` (sorted, ``u`` included) and in how many images."""
        images = self._csc.indices[self._csc.indptr[u]:self._csc.indptr[u + 1]]
        starts, ends = self._csr.indptr[images], self._csr.indptr[images + 1]
        lens = ends - starts
        total = int(lens.sum())
        if total == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        offsets = np.repeat(starts - np.cumsum(lens) + lens, lens) + np.arange(total)
        cols = self._csr.indices[offsets]
        if total * 8 > self.n_words:  # long lists: a dense count beats sorting
            n11 = np.bincount(cols, minlength=self.n_words)
            j = np.flatnonzero(n11)
            return j, n11[j]
        return np.unique(cols, return_counts=True)

    def _values(self, u: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mutual information of ``u`` (float32) with a word of each distinct count that never
        occurs with it, and with the words ``j`` that do (with ``u`` among them), and ``j``."""
        j, n11 = self.cooccurrence(u)
        k = len(self._levels)
        cb = np.concatenate([self._levels, self.counts[j]])
        n11 = np.concatenate([np.zeros(k, dtype=np.int64), n11])
        mi = self._mutual_information(n11, int(self.counts[u]), cb)
        return mi[:k], mi[k:], j

    def row(self, u: int) -> np.ndarray:
        """(V,) float32 mutual information of word ``u`` with every word (0 at ``u``)."""
        apart, together, j = self._values(u)
        out = apart[self._level_of]
        out[j] = together
        out[u] = 0.0
        return out

    def row_max(self, u: int) -> float:
        """``row(u).max()`` in O(distinct counts + co-occurring words), without the row."""
        apart, together, j = self._values(u)
        together[j == u] = 0.0
        alone = self._level_size - np.bincount(self._level_of[j], minlength=len(apart))
        top = float(together.max(initial=0.0))
        return max(top, float(apart.max(where=alone > 0, initial=0.0)))


# Mutual information computed from counts exceeds the entropy bound of its words by rounding
# only (float64 sums, then float32): far less than this, which the root search allows for.
_MI_BOUND_SLACK = 1e-6


def strongest_edge_root(rows: MutualInformationRows) -> int:
    """The lowest word whose row holds the largest mutual information of all pairs.

    This is the row of ``np.argmax`` over the whole (V, V) matrix (the root openFABMAP
    takes: an endpoint of the strongest edge), found without the matrix: rows are computed
    in decreasing order of their word's entropy, which bounds every value of the row, and
    the search stops at the first word whose entropy is below the largest value found.
    """
    h = rows.entropy()
    best, root = -np.inf, 0
    for u in np.argsort(-h, kind="stable"):
        if h[u] + _MI_BOUND_SLACK < best:
            break
        top = rows.row_max(int(u))
        if top > best:
            best, root = top, int(u)
        elif top == best:
            root = min(root, int(u))
    return root


def maximum_spanning_tree(
    row: Callable[[int], np.ndarray], v: int, root: int = 0, *, progress: bool = False
) -> np.ndarray:
    """Prim's algorithm on a symmetric weight matrix given row by row.

    row(u): (v,) weights of vertex ``u`` to every vertex, asked once for each vertex as it
    joins the tree (all but the last), so the matrix need never be stored. Returns (v,)
    int64 parents, -1 at ``root``: the maximum-weight spanning tree oriented away from
    ``root``. Ties break towards the vertex that reached the weight first and, between
    vertices, towards the lower index.
    """
    parent = np.full(v, -1, dtype=np.int64)
    if v <= 1:
        return parent
    in_tree = np.zeros(v, dtype=bool)
    best = np.full(v, -np.inf)
    best_from = np.full(v, root, dtype=np.int64)
    u = root
    for _ in tqdm(range(v - 1), desc="Chow-Liu tree", unit="word", disable=not progress, mininterval=1.0):
        in_tree[u] = True
        w = row(u)
        better = (w > best) & ~in_tree
        best[better] = w[better]
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

    mi: (V,) the mutual information of each word with its parent. independent: (V,) bool,
    words whose conditionals are set to their marginal (no dependence on the parent).
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
    if mi is not None:
        mi_edge[q] = np.asarray(mi)[q]
    return ChowLiuTree(parent=parent.astype(np.int64), p_z=p_z, p_z_given_p=p_given_p,
                       p_z_given_not_p=p_given_not_p, mi=mi_edge, n_train=n)


CHOW_LIU_WAY_OUT = "use a smaller vocabulary or fewer training images"


def edge_mutual_information(X: sp.spmatrix, q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(E,) float64 of the float32 mutual information ``MI(q_e, p_e)`` of pairs of columns of
    ``X`` (N, V), with ``q``'s count first: the entries ``[q, p]`` of the matrix whose rows
    :class:`MutualInformationRows` gives."""
    Xc = as_binary_csr(X).tocsc()
    counts = np.asarray(Xc.sum(axis=0)).ravel()
    if len(q) == 0:
        return np.zeros(0)
    n11 = np.asarray(Xc[:, q].multiply(Xc[:, p]).sum(axis=0)).ravel()
    mi = mutual_information_from_counts(n11, counts[q], counts[p], Xc.shape[0])
    return mi.astype(np.float32).astype(np.float64)


def learn_chow_liu_tree(
    X: np.ndarray | sp.spmatrix, *, smoothing: float = 0.01, progress: bool = False,
    memory_limit_mb: float | None = None, way_out: str = CHOW_LIU_WAY_OUT,
) -> ChowLiuTree:
    """Learn the Chow-Liu tree of binary occurrence data.

    X: (N, V) occurrences (N training images, V words), dense or sparse; nonzero = seen.
    The spanning tree is grown over the words that vary in X (see :func:`varying_words`);
    every other word hangs under the root, independent of it. The root is an endpoint of
    the strongest edge (as openFABMAP builds it; :func:`strongest_edge_root`). Mutual
    information is computed one row at a time as Prim's algorithm needs it, so memory is
    O(V) beside the sparse data; that estimate is checked against the memory available
    (``memory_limit_mb``, else :func:`orbslam_hgcn.placerec.memory.available_bytes`) first:
    an OrbslamError naming both and ``way_out`` when it does not fit.
    """
    X = as_binary_csr(X)
    n, v = X.shape
    if n == 0 or v == 0:
        raise OrbslamError("Chow-Liu tree: no training images or no words")
    keep = varying_words(X)
    vk = len(keep)
    Xk = X[:, keep]
    need = chow_liu_bytes(vk, Xk.nnz)
    log.info("Chow-Liu tree: %d training images, %d words, %d of them varying (%s estimated)",
             n, v, vk, format_bytes(need))
    check_memory(need, f"the Chow-Liu tree over the {vk} varying words (of {v})", way_out,
                 limit_mb=memory_limit_mb)
    root = 0
    parent = np.zeros(v, dtype=np.int64)
    mi_edge = np.zeros(v)
    if vk > 1:
        rows = MutualInformationRows(Xk)
        root_k = strongest_edge_root(rows)
        parent_k = maximum_spanning_tree(rows.row, vk, root=root_k, progress=progress)
        del rows
        root = int(keep[root_k])
        parent[:] = root
        inner = np.flatnonzero(parent_k >= 0)
        parent[keep[inner]] = keep[parent_k[inner]]
        mi_edge[keep[inner]] = edge_mutual_information(Xk, inner, parent_k[inner])
    elif vk == 1:
        root = int(keep[0])
        parent[:] = root
    parent[root] = -1
    independent = np.ones(v, dtype=bool)
    independent[keep] = False
    return tree_from_parents(X, parent, mi_edge, smoothing, independent=independent)
