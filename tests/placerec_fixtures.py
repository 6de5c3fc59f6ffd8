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
