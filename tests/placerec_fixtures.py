"""Synthetic word-occurrence data: tree-structured samples and revisiting routes.

Used by the tests (recovering a known Chow-Liu tree) and by the benchmarks (FAB-MAP
inference at vocabulary scale, and loop-closure detection without images).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class TreeModel:
    """A tree-structured distribution over V binary variables.

    parent:       (V,) int64 parent of each variable, -1 at the root; parents precede
                  children in ``order``
    order:        (V,) int64 a topological order (root first)
    p_root:       p(z_root = 1)
    p1_given_1:   (V,) p(z_q = 1 | z_parent = 1)
    p1_given_0:   (V,) p(z_q = 1 | z_parent = 0)
    """

    parent: np.ndarray
    order: np.ndarray
    p_root: float
    p1_given_1: np.ndarray
    p1_given_0: np.ndarray


def random_tree(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A uniformly random recursive tree on n vertices.

    Returns (parent (n,) int64 with -1 at the root, order (n,) int64 topological order).
    """
    order = rng.permutation(n).astype(np.int64)
    parent = np.full(n, -1, dtype=np.int64)
    if n > 1:
        # vertex order[k] (k >= 1) hangs under a random earlier vertex
        pick = (rng.random(n - 1) * np.arange(1, n)).astype(np.int64)
        parent[order[1:]] = order[pick]
    return parent, order


def random_tree_model(
    n: int, rng: np.random.Generator, *, rate: float = 0.3, strength: float = 0.8
) -> TreeModel:
    """A random tree with dependencies of a given strength.

    Each child copies its parent's state with probability ``strength`` and otherwise is
    drawn independently with probability ``rate`` of being 1; the root is 1 with
    probability ``rate``. Stronger dependence means larger mutual information per edge.
    """
    parent, order = random_tree(n, rng)
    p1_given_1 = np.full(n, strength + (1 - strength) * rate)
    p1_given_0 = np.full(n, (1 - strength) * rate)
    return TreeModel(parent, order, rate, p1_given_1, p1_given_0)


def sample_tree(model: TreeModel, n_samples: int, rng: np.random.Generator) -> np.ndarray:
    """(n_samples, V) bool samples of a tree model, drawn root to leaves."""
    v = len(model.parent)
    z = np.zeros((n_samples, v), dtype=bool)
    u = rng.random((n_samples, v))
    for q in model.order:
        p = model.parent[q]
        if p < 0:
            z[:, q] = u[:, q] < model.p_root
        else:
            prob = np.where(z[:, p], model.p1_given_1[q], model.p1_given_0[q])
            z[:, q] = u[:, q] < prob
    return z


class WordWorld:
    """Places of a synthetic world, each owning a fixed set of words.

    Word popularity is Zipf-like (common words shared by many places, as in real
    vocabularies) and fixed for the world, so training and test routes through different
    places of one world share its word statistics.
    """

    def __init__(
        self, n_words: int, rng: np.random.Generator, *, words_per_place: int = 150, zipf: float = 1.1
    ) -> None:
        ranks = np.arange(1, n_words + 1, dtype=np.float64)
        popularity = ranks**-zipf
        self.popularity = popularity[rng.permutation(n_words)] / popularity.sum()
        self.n_words = n_words
        self.words_per_place = words_per_place
        self._rng = rng
        self._places: dict[int, np.ndarray] = {}

    def place_words(self, place: int) -> np.ndarray:
        """(words_per_place,) int64 word ids owned by ``place`` (drawn on first use)."""
        if place not in self._places:
            self._places[place] = self._rng.choice(
                self.n_words, size=self.words_per_place, replace=False, p=self.popularity
            )
        return self._places[place]


@dataclass(frozen=True, eq=False)
class RouteSequence:
    """Word observations along a route through discrete places.

    word_ids: per image, an (N_i,) int64 array of observed word ids
    place:    (n,) int64 the place each image was taken at
    truth:    (n, n) bool, True where images i and j show the same place (i != j)
    """

    word_ids: list[np.ndarray]
    place: np.ndarray
    truth: np.ndarray


def route_sequence(
    world: WordWorld, route: np.ndarray, rng: np.random.Generator, *, keep: float = 0.6, clutter: int = 40
) -> RouteSequence:
    """Images along ``route`` (a (n,) sequence of place ids; a repeated id is a revisit).

    An image sees each of its place's words with probability ``keep``, plus ``clutter``
    words drawn by popularity (moving objects, noise).
    """
    route = np.asarray(route, dtype=np.int64)
    word_ids = []
    for pl in route:
        own = world.place_words(int(pl))
        seen = own[rng.random(len(own)) < keep]
        noise = rng.choice(world.n_words, size=clutter, p=world.popularity)
        word_ids.append(np.unique(np.concatenate([seen, noise])))
    truth = (route[:, None] == route[None, :]) & ~np.eye(len(route), dtype=bool)
    return RouteSequence(word_ids, route, truth)


def dense_mutual_information_matrix(X, block_rows: int = 512) -> np.ndarray:
    """(V, V) float32 pairwise mutual information of the columns of ``X``, diagonal 0: the
    dense matrix the Chow-Liu tree was once built from, block by block of rows (row ``a``
    with ``a``'s count first), kept as the reference of the row-by-row computation."""
    from orbslam_hgcn.placerec.chow_liu import mutual_information_from_counts
    from orbslam_hgcn.placerec.words import as_binary_csr

    X = as_binary_csr(X)
    n, v = X.shape
    counts = np.asarray(X.sum(axis=0)).ravel()
    Xc = X.tocsc()
    mi = np.empty((v, v), dtype=np.float32)
    for a in range(0, v, block_rows):
        b = min(a + block_rows, v)
        co = (Xc[:, a:b].T @ Xc).toarray()
        mi[a:b] = mutual_information_from_counts(co, counts[a:b, None], counts[None, :], n)
        mi[np.arange(a, b), np.arange(a, b)] = 0.0
    return mi


def dense_chow_liu_tree(X, smoothing: float = 0.01, *, restrict: bool = True):
    """The Chow-Liu tree as built from the dense matrix: Prim's algorithm over the mutual
    information of the varying words (``restrict``) or of every word, rooted at the row of
    the matrix's ``argmax``; other words hang under the root, independent of it."""
    import scipy.sparse as sp

    from orbslam_hgcn.placerec.chow_liu import maximum_spanning_tree, tree_from_parents, varying_words

    X = sp.csr_matrix(X)
    v = X.shape[1]
    keep = varying_words(X) if restrict else np.arange(v)
    mi = dense_mutual_information_matrix(X[:, keep])
    root_k = int(np.unravel_index(np.argmax(mi), mi.shape)[0])
    parent_k = maximum_spanning_tree(lambda u: mi[u], len(keep), root=root_k)
    root = int(keep[root_k])
    parent = np.full(v, root, dtype=np.int64)
    inner = np.flatnonzero(parent_k >= 0)
    parent[keep[inner]] = keep[parent_k[inner]]
    parent[root] = -1
    mi_edge = np.zeros(v)
    mi_edge[keep[inner]] = mi[inner, parent_k[inner]]
    independent = np.ones(v, dtype=bool)
    independent[keep] = False
    return tree_from_parents(X, parent, mi_edge, smoothing, independent=independent)
