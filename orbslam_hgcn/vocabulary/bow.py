"""Bag-of-words vectors, direct-index feature vectors, TF-IDF weights and the L1 score.

Definitions follow DBoW2 (Galvez-Lopez & Tardos, "Bags of binary words for fast place
recognition in image sequences", T-RO 2012, section IV):

* the inverse document frequency of word ``w`` over a training corpus of ``N`` images is
  ``idf(w) = log(N / n_w)`` where ``n_w`` is the number of training images holding ``w``;
* the bag-of-words vector of an image with ``n`` features is ``v_w = (count_w / n) * idf(w)``,
  normalised to unit L1 norm (words with zero weight are left out);
* the similarity of two L1-normalised vectors is ``s(a, b) = 1 - 0.5 * |a - b|_1``, which
  for non-negative weights equals ``sum_w min(a_w, b_w)`` over the words they share.

The feature vector (direct index) maps a node of the vocabulary at a chosen level to the
indices of the image's features whose word lies under that node; ORB-SLAM matches features
only within the same node (Mur-Artal et al., T-RO 2015, section III-E).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

import numpy as np

log = logging.getLogger(__name__)


class BowVector:
    """A sparse bag-of-words vector: word id -> weight, kept as two sorted arrays.

    words: (M,) int32 strictly increasing word ids. weights: (M,) float32 weights.
    Behaves like a read-only mapping (``len``, ``in``, ``[]``, ``get``, ``keys``, ``values``,
    ``items``, iteration over word ids).
    """

    __slots__ = ("words", "weights")

    def __init__(self, words: np.ndarray | None = None, weights: np.ndarray | None = None) -> None:
        self.words = np.zeros(0, np.int32) if words is None else np.ascontiguousarray(words, dtype=np.int32)
        self.weights = (
            np.zeros(0, np.float32) if weights is None else np.ascontiguousarray(weights, dtype=np.float32)
        )
        if self.words.shape != self.weights.shape or self.words.ndim != 1:
            raise ValueError("words and weights must be 1-D arrays of equal length")

    @classmethod
    def from_dict(cls, mapping: dict[int, float]) -> BowVector:
        """A vector from ``{word: weight}`` (kept as given; not normalised)."""
        if not mapping:
            return cls()
        words = np.fromiter(mapping.keys(), dtype=np.int64, count=len(mapping))
        weights = np.fromiter(mapping.values(), dtype=np.float64, count=len(mapping))
        order = np.argsort(words)
        return cls(words[order], weights[order])

    @classmethod
    def from_words(cls, word_ids: np.ndarray, idf: np.ndarray) -> BowVector:
        """TF-IDF vector of one image from its features' words, L1-normalised.

        word_ids: (N,) int word of each feature (negative ids are ignored).
        idf: (W,) float inverse document frequency of every word.
        """
        w = np.asarray(word_ids).reshape(-1)
        w = w[w >= 0]
        if len(w) == 0:
            return cls()
        words, counts = np.unique(w, return_counts=True)
        weights = counts.astype(np.float64) * idf[words]
        keep = weights > 0
        words, weights = words[keep], weights[keep]
        total = weights.sum()
        if total <= 0:
            return cls()
        return cls(words, weights / total)

    # --- mapping API ---------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.words)

    def __iter__(self) -> Iterator[int]:
        return iter(self.words.tolist())

    def _find(self, word: int) -> int:
        i = int(np.searchsorted(self.words, word))
        return i if i < len(self.words) and self.words[i] == word else -1

    def __contains__(self, word: object) -> bool:
        return isinstance(word, (int, np.integer)) and self._find(int(word)) >= 0

    def __getitem__(self, word: int) -> float:
        i = self._find(int(word))
        if i < 0:
            raise KeyError(word)
        return float(self.weights[i])

    def get(self, word: int, default: float | None = None) -> float | None:
        i = self._find(int(word))
        return default if i < 0 else float(self.weights[i])

    def keys(self) -> list[int]:
        return self.words.tolist()

    def values(self) -> list[float]:
        return self.weights.tolist()

    def items(self) -> list[tuple[int, float]]:
        return list(zip(self.words.tolist(), self.weights.tolist()))

    def to_dict(self) -> dict[int, float]:
        return dict(self.items())

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, BowVector):
            return NotImplemented
        return np.array_equal(self.words, other.words) and np.array_equal(self.weights, other.weights)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"BowVector({len(self)} words, L1={float(self.weights.sum()):.3f})"

    def score(self, other: BowVector) -> float:
        """DBoW2's L1 score with ``other`` (see :func:`l1_score`)."""
        return l1_score(self, other)


class FeatureVector(dict):
    """Direct index: vocabulary node id -> (K,) int32 indices of the features under it."""

    _flat: tuple[np.ndarray, np.ndarray] | None = None

    def __setitem__(self, node: int, idx: np.ndarray) -> None:
        self._flat = None
        super().__setitem__(node, idx)

    def flat(self) -> tuple[np.ndarray, np.ndarray]:
        """((K,) int64 node, (K,) int64 feature index): every indexed feature with its node,
        node after node in the index's order; made once (a keyframe's index is matched
        against each of its neighbours')."""
        if self._flat is None:
            if not self:
                self._flat = (np.zeros(0, np.int64), np.zeros(0, np.int64))
            else:
                idx = [np.asarray(v, dtype=np.int64).reshape(-1) for v in self.values()]
                nodes = np.repeat(np.fromiter(self.keys(), dtype=np.int64, count=len(self)), [len(i) for i in idx])
                self._flat = (nodes, np.concatenate(idx))
        return self._flat

    @classmethod
    def from_nodes(cls, nodes: np.ndarray, keep: np.ndarray | None = None) -> FeatureVector:
        """Group feature indices by node.

        nodes: (N,) int node of each feature. keep: optional (N,) bool, features to index
        (DBoW2 leaves out features whose word has zero weight).
        """
        nodes = np.asarray(nodes).reshape(-1)
        idx = np.arange(len(nodes), dtype=np.int32)
        if keep is not None:
            idx = idx[np.asarray(keep, dtype=bool)]
        fv = cls()
        if len(idx) == 0:
            return fv
        sel = nodes[idx]
        order = np.argsort(sel, kind="stable")
        sel, idx = sel[order], idx[order]
        bounds = [0, *(np.flatnonzero(sel[1:] != sel[:-1]) + 1).tolist(), len(sel)]  # runs of one node
        for node, a, b in zip(sel[bounds[:-1]].tolist(), bounds[:-1], bounds[1:]):
            fv[node] = idx[a:b]
        return fv

    def n_features(self) -> int:
        return int(sum(len(v) for v in self.values()))


def l1_score(a: BowVector, b: BowVector) -> float:
    """DBoW2's L1 similarity ``1 - 0.5 * |a - b|_1`` of two L1-normalised vectors.

    Computed over the shared words only, as DBoW2's L1Scoring does:
    ``0.5 * sum(|a_w| + |b_w| - |a_w - b_w|)``, in [0, 1] for normalised vectors.
    """
    if len(a) == 0 or len(b) == 0:
        return 0.0
    _, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
    if len(ia) == 0:
        return 0.0
    va = a.weights[ia].astype(np.float64)
    vb = b.weights[ib].astype(np.float64)
    return float(0.5 * np.sum(np.abs(va) + np.abs(vb) - np.abs(va - vb)))


def idf_from_documents(word_ids: np.ndarray, doc_ids: np.ndarray, n_words: int) -> np.ndarray:
    """Inverse document frequency ``log(N / n_w)`` of every word over a training corpus.

    word_ids: (M,) int word of every training feature. doc_ids: (M,) int image (document)
    of every feature. n_words: W. Returns (W,) float32. ``N`` counts the images with at
    least one feature. A word that no training image holds (possible in the HGCN
    vocabulary, whose empty words keep their seed centre) is given ``n_w = 1``, the weight
    of the rarest observed word.
    """
    word_ids = np.asarray(word_ids, dtype=np.int64).reshape(-1)
    doc_ids = np.asarray(doc_ids, dtype=np.int64).reshape(-1)
    if word_ids.shape != doc_ids.shape:
        raise ValueError("word_ids and doc_ids differ in length")
    if len(word_ids) == 0:
        return np.zeros(n_words, np.float32)
    _, docs = np.unique(doc_ids, return_inverse=True)
    n_docs = int(docs.max()) + 1
    pairs = np.unique(docs * np.int64(n_words) + word_ids)
    n_w = np.bincount(pairs % n_words, minlength=n_words)
    return np.log(n_docs / np.maximum(n_w, 1)).astype(np.float32)
