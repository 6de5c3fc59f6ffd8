"""The ORB baseline vocabulary: a DBoW2 vocabulary tree with TF-IDF weights.

As ORB-SLAM's ``ORBvoc`` (DBoW2, Galvez-Lopez & Tardos, T-RO 2012): a hierarchical
k-medians tree over binary descriptors (k = 10 children per node, L levels), words at the
leaves, a descriptor's word found by descending from the root to the nearest child at every
level, IDF weights ``log(N / n_w)`` over the training images and TF-IDF BoW vectors. Float
descriptors (e.g. SIFT) are supported with k-means and the Euclidean distance.

Saved arrays (besides the common header and ``idf``): ``parent`` (M,) int32 node parents
(root -1, parents before children, siblings consecutive) and ``centres`` (M, B) uint8 or
(M, D) float32 node centres. The leaves, in node-id order, are words 0..W-1.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.compiled import descriptor_words
from orbslam_hgcn.vocabulary.base import Vocabulary, VocabularyMetadata, now_iso, require
from orbslam_hgcn.vocabulary.bow import idf_from_documents
from orbslam_hgcn.vocabulary.descriptors import BINARY, FLOAT, descriptor_kind, dist_to_candidates
from orbslam_hgcn.vocabulary.training.tree_build import build_tree

log = logging.getLogger(__name__)

_BIG = np.int32(1 << 30)


class TreeVocabulary(Vocabulary):
    """DBoW2-style vocabulary tree (kind ``orb``).

    parent: (M,) int32 parent of each node. centres: (M, B) uint8 or (M, D) float32.
    idf: (W,) float32, one per leaf. levels: the tree's nominal depth L (DBoW2's ``m_L``),
    which fixes the feature-vector level ``L - levels_up``.
    """

    kind = "orb"

    def __init__(self, parent: np.ndarray, centres: np.ndarray, idf: np.ndarray, metadata: VocabularyMetadata) -> None:
        super().__init__(idf, metadata)
        self.parent = np.ascontiguousarray(parent, dtype=np.int32)
        self.centres = np.ascontiguousarray(centres)
        M = len(self.parent)
        # Depth of every node: propagate from the root until stable (depth-many passes).
        depth = np.zeros(M, np.int32)
        has_parent = self.parent >= 0
        while True:
            new = np.where(has_parent, depth[np.maximum(self.parent, 0)] + 1, 0)
            if np.array_equal(new, depth):
                break
            depth = new
        self.depth = depth.astype(np.int32)
        self.levels = int(metadata.params.get("levels", int(depth.max()) if M else 0))
        # Children as a padded (M, kmax) table, -1 where absent.
        child = np.flatnonzero(has_parent)
        order = child[np.argsort(self.parent[child], kind="stable")]
        par = self.parent[order]
        n_children = np.bincount(par, minlength=M)
        kmax = max(1, int(n_children.max()) if len(par) else 1)
        first = np.concatenate([[0], np.cumsum(n_children)[:-1]])
        self.children = np.full((M, kmax), -1, np.int32)
        self.children[par, np.arange(len(order)) - first[par]] = order
        self.word_node = np.flatnonzero(n_children == 0).astype(np.int32)  # leaves = words
        self.node_word = np.full(M, -1, np.int32)
        self.node_word[self.word_node] = np.arange(len(self.word_node), dtype=np.int32)
        self._kind = BINARY if self.centres.dtype == np.uint8 else FLOAT
        self._cx = descriptor_words(self.centres) if self._kind == BINARY else self.centres.astype(np.float32)
        self._fv_cache: dict[int, np.ndarray] = {}

    # --- quantisation ---------------------------------------------------------------------
    def _words(self, desc: np.ndarray) -> np.ndarray:
        x = descriptor_words(desc) if self._kind == BINARY else desc
        cur = np.zeros(len(x), np.int32)
        rows = np.arange(len(x))
        for _ in range(int(self.depth.max())):
            ch = self.children[cur[rows]]
            inner = ch[:, 0] >= 0
            rows, ch = rows[inner], ch[inner]
            if len(rows) == 0:
                break
            d = dist_to_candidates(x[rows], self._cx[np.maximum(ch, 0)], self._kind)
            if self._kind == BINARY:
                d = np.where(ch >= 0, d, _BIG)
            else:
                d = np.where(ch >= 0, d, np.inf)
            cur[rows] = ch[np.arange(len(rows)), np.argmin(d, axis=1)]
        return self.node_word[cur]

    def word_nodes(self, words: np.ndarray, levels_up: int) -> np.ndarray:
        """Ancestor of each word at depth ``max(L - levels_up, 0)`` (or the word's leaf,
        when the leaf is shallower), as DBoW2's ``transform(..., levelsup)`` gives it."""
        table = self._fv_cache.get(levels_up)
        if table is None:
            target = max(self.levels - levels_up, 0)
            table = self.word_node.copy()
            while True:
                up = self.depth[table] > target
                if not up.any():
                    break
                table[up] = self.parent[table[up]]
            self._fv_cache[levels_up] = table
        return table[np.asarray(words, dtype=np.int64)]

    # --- persistence ----------------------------------------------------------------------
    def _state(self) -> dict[str, np.ndarray]:
        return {"parent": self.parent, "centres": self.centres}

    @classmethod
    def _from_state(cls, arrays: dict[str, np.ndarray], metadata: VocabularyMetadata, path: Path) -> TreeVocabulary:
        parent, centres, idf = arrays.get("parent"), arrays.get("centres"), arrays["idf"]
        require(parent is not None and centres is not None, path, "missing 'parent' or 'centres' array")
        require(parent.ndim == 1 and len(parent) >= 2 and parent.dtype.kind == "i", path, "bad 'parent' array")
        require(int(parent[0]) == -1 and bool(np.all(parent[1:] >= 0)), path, "root must be node 0 alone")
        require(bool(np.all(parent[1:] < np.arange(1, len(parent)))), path, "a node precedes its parent")
        require(centres.ndim == 2 and len(centres) == len(parent), path, "'centres' does not match 'parent'")
        want = np.uint8 if metadata.descriptor_type == BINARY else np.float32
        require(centres.dtype == want, path, f"'centres' should be {np.dtype(want).name}")
        require(centres.shape[1] == metadata.descriptor_dim, path, "'centres' width differs from the metadata")
        n_leaves = len(parent) - len(np.unique(parent[1:]))
        require(n_leaves == len(idf), path, f"{n_leaves} leaves but {len(idf)} IDF weights")
        return cls(parent, centres, idf, metadata)


def train_tree_vocabulary(
    desc: np.ndarray,
    image_ids: np.ndarray,
    *,
    k: int = 10,
    levels: int = 5,
    max_iters: int = 10,
    seed: int = 0,
    trained_on: str = "",
    progress: bool = True,
) -> TreeVocabulary:
    """Train a DBoW2 vocabulary tree and its IDF weights.

    desc: (N, B) uint8 binary or (N, D) float descriptors. image_ids: (N,) int image each
    descriptor came from (the documents of the IDF). k, levels: branching factor and depth.
    max_iters: Lloyd iterations per level. trained_on: description kept in the metadata.
    """
    desc = np.asarray(desc)
    image_ids = np.asarray(image_ids).reshape(-1)
    if len(desc) != len(image_ids):
        raise ValueError("desc and image_ids differ in length")
    if len(desc) < 2:
        raise ValueError("need at least two descriptors to train a vocabulary")
    kind = descriptor_kind(desc)
    if kind == FLOAT:
        desc = desc.astype(np.float32)
    t0 = time.perf_counter()
    parent, centres = build_tree(desc, k, levels, max_iters, seed, progress)
    t_tree = time.perf_counter() - t0
    n_images = int(len(np.unique(image_ids)))
    meta = VocabularyMetadata(
        kind="orb",
        n_words=0,
        descriptor_type=kind,
        descriptor_dim=int(desc.shape[1]),
        trained_on=trained_on,
        n_images=n_images,
        n_descriptors=int(len(desc)),
        created=now_iso(),
        params={"k": k, "levels": levels, "max_iters": max_iters, "seed": seed, "weighting": "tf-idf",
                "scoring": "L1"},
    )
    n_leaves = len(parent) - len(np.unique(parent[1:]))
    vocab = TreeVocabulary(parent, centres, np.ones(n_leaves, np.float32), meta)
    words = vocab.transform_words(desc)
    vocab.idf = idf_from_documents(words, image_ids, vocab.n_words)
    meta.n_words = vocab.n_words
    meta.stats = {"train_seconds": round(time.perf_counter() - t0, 2), "tree_seconds": round(t_tree, 2),
                  "nodes": int(len(parent))}
    log.info("trained a %d-word tree (k=%d, L=%d) on %d descriptors of %d images in %.1f s",
             vocab.n_words, k, levels, len(desc), n_images, time.perf_counter() - t0)
    return vocab
