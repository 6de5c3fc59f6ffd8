"""Flat vocabularies over PCA-projected descriptors, and the k-means vocabulary.

What the HGCN vocabulary and its ablation share: descriptors are projected to ``d``
dimensions by PCA (ORB: the 256 bits, through a nibble lookup table), words are
points found, up to :data:`FLAT_MAX_WORDS` words, by the coarse-to-fine search of
:mod:`.probe` (the 28 nearest of round(2 sqrt(W)) lists probed; lists built at load time)
and, above, through faiss's inverted file over the words (IndexIVFFlat with ``4 sqrt(W)``
lists saved in the file and ``nprobe`` probed). The FeatureVector uses coarse nodes: the
words' centres clustered by k-means into ``n_coarse`` nodes (``levels_up >= 1``;
``levels_up = 0`` indexes the words).

The k-means vocabulary (kind ``kmeans``) is the HGCN vocabulary without the graph and the
network: its words are the seed k-means centres the HGCN is trained from (same PCA, same
k-means, same word count, search and weights), so comparing the two measures what the
network adds.

Saved arrays (kind ``kmeans``): ``pca_mean`` (F,), ``pca_components`` (F, d),
``centroids`` (W, d), ``coarse_centroids`` (C, d), ``word_coarse`` (W,) int32,
``ivf_centroids`` (L, d) (L = 0: the coarse-to-fine search of :mod:`.probe`, whose lists are
built at load time) and ``nprobe`` (scalar).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.config import HgcnTrainConfig
from orbslam_hgcn.vocabulary.base import Vocabulary, VocabularyMetadata, now_iso, require
from orbslam_hgcn.vocabulary.bow import idf_from_documents
from orbslam_hgcn.vocabulary.descriptors import BINARY, FLOAT, descriptor_kind
from orbslam_hgcn.vocabulary.graph import PCA, configure_faiss, faiss_threads, fit_pca
from orbslam_hgcn.vocabulary.probe import ProbedSearch

log = logging.getLogger(__name__)

# The coarse-to-fine search (:mod:`.probe`) up to this many words, faiss's inverted file
# above. For 2000-feature KITTI keyframes against the shipped 8000 words (20-D), one thread,
# same process, machine load 8-11: faiss's exhaustive flat search took 18-19 ms CPU per
# keyframe (the 2 ms per 1000 descriptors noted here before was not reproduced), the probed
# search about 8 ms, with the exact word for 99.5% of the descriptors.
FLAT_MAX_WORDS = 16384


def kmeans(x: np.ndarray, k: int, niter: int, seed: int, points_per_centroid: int = 256) -> np.ndarray:
    """(k, d) float32 faiss k-means centres of rows x (N, d); trains on at most
    ``points_per_centroid * k`` rows (faiss subsamples)."""
    configure_faiss()
    x = np.ascontiguousarray(x, dtype=np.float32)
    import faiss
    km = faiss.Kmeans(x.shape[1], k, niter=niter, seed=seed, max_points_per_centroid=points_per_centroid,
                      min_points_per_centroid=1, verbose=False)
    km.train(x)
    return np.ascontiguousarray(km.centroids, dtype=np.float32)


def nearest(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(N,) int64 index of the nearest centre of every row (exact, faiss flat)."""
    configure_faiss()
    import faiss
    index = faiss.IndexFlatL2(centres.shape[1])
    index.add(np.ascontiguousarray(centres, dtype=np.float32))
    return index.search(np.ascontiguousarray(x, dtype=np.float32), 1)[1][:, 0]


class PointIndex:
    """Nearest-point search over W points (W, d): the coarse-to-fine search of
    :class:`~.probe.ProbedSearch` (no lists given), or faiss's inverted file over
    ``lists`` (L, d) list centres with ``nprobe`` lists probed."""

    def __init__(self, points: np.ndarray, lists: np.ndarray, nprobe: int) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float32)
        d = self.points.shape[1]
        self.lists = np.ascontiguousarray(lists, dtype=np.float32).reshape(-1, d)
        if len(self.lists) == 0:
            self.index = None
            self.probed = ProbedSearch(self.points)
        else:
            import faiss

            configure_faiss()
            self._quantizer = faiss.IndexFlatL2(d)  # kept alive: the IVF index does not own it
            self._quantizer.add(self.lists)
            self.index = faiss.IndexIVFFlat(self._quantizer, d, len(self.lists))
            self.index.is_trained = True
            self.index.add(self.points)
        self.nprobe = nprobe

    @property
    def nprobe(self) -> int:
        return self._nprobe

    @nprobe.setter
    def nprobe(self, value: int) -> None:
        self._nprobe = int(value)
        if self.index is not None:
            self.index.nprobe = max(1, min(self._nprobe, self.index.nlist))

    def search(self, x: np.ndarray, exact: bool = False) -> np.ndarray:
        """(N,) int32 nearest point of every row of x (N, d) (exact: faiss's exhaustive
        search, for comparisons)."""
        x = np.ascontiguousarray(x, dtype=np.float32)
        if exact:
            return nearest(x, self.points).astype(np.int32)
        if self.index is None:
            return self.probed.search(x)
        with faiss_threads(len(x)):
            return self.index.search(x, 1)[1][:, 0].astype(np.int32)


def ivf_lists(points: np.ndarray, seed: int) -> np.ndarray:
    """List centres of the inverted file over W points: none (the search of :mod:`.probe`) up to
    :data:`FLAT_MAX_WORDS` points, else ``4 sqrt(W)`` k-means centres."""
    if len(points) <= FLAT_MAX_WORDS:
        return np.zeros((0, points.shape[1]), np.float32)
    return kmeans(points, int(4 * np.sqrt(len(points))), 20, seed)


def coarse_nodes(centres: np.ndarray, n_coarse: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """((C, d) coarse node centres, (W,) int32 coarse node of every word) by k-means."""
    coarse = kmeans(centres, min(n_coarse, len(centres)), 20, seed)
    return coarse, nearest(centres, coarse).astype(np.int32)


class PCAVocabulary(Vocabulary):
    """What flat vocabularies in PCA space share: the projection and the coarse nodes.

    pca: descriptor projection. coarse_centroids: (C, d). word_coarse: (W,) coarse node of
    every word.
    """

    def __init__(self, pca: PCA, coarse_centroids: np.ndarray, word_coarse: np.ndarray, idf: np.ndarray,
                 metadata: VocabularyMetadata) -> None:
        super().__init__(idf, metadata)
        self.pca = pca
        self.coarse_centroids = np.ascontiguousarray(coarse_centroids, dtype=np.float32)
        self.word_coarse = np.ascontiguousarray(word_coarse, dtype=np.int32)

    def project(self, desc: np.ndarray) -> np.ndarray:
        """(N, d) PCA coordinates of (N, B) uint8 or (N, D) float descriptors."""
        return self.pca.transform(self.check_descriptors(desc))

    def _words(self, desc: np.ndarray) -> np.ndarray:
        return self.words_of_points(self.pca.transform(desc))

    def words_of_points(self, x: np.ndarray, exact: bool = False) -> np.ndarray:
        """(N,) int32 word of points x (N, d) in PCA space: the run-time search, or the
        exhaustive one (``exact``, for comparisons)."""
        raise NotImplementedError

    def word_nodes(self, words: np.ndarray, levels_up: int) -> np.ndarray:
        words = np.asarray(words, dtype=np.int64)
        return words.astype(np.int32) if levels_up <= 0 else self.word_coarse[words]

    def _pca_state(self) -> dict[str, np.ndarray]:
        return {"pca_mean": self.pca.mean, "pca_components": self.pca.components,
                "coarse_centroids": self.coarse_centroids, "word_coarse": self.word_coarse}

    @staticmethod
    def _check_pca_state(arrays: dict[str, np.ndarray], metadata: VocabularyMetadata, path: Path,
                         names: tuple[str, ...]) -> PCA:
        """Check the shared arrays (and that ``names`` exist); returns the PCA."""
        missing = [n for n in ("pca_mean", "pca_components", "coarse_centroids", "word_coarse", *names)
                   if n not in arrays]
        require(not missing, path, f"missing arrays {missing}")
        mean, comp, coarse, wc = (arrays[k] for k in ("pca_mean", "pca_components", "coarse_centroids", "word_coarse"))
        require(mean.ndim == 1 and comp.ndim == 2 and comp.shape[0] == len(mean), path, "bad PCA arrays")
        binary = metadata.descriptor_type == BINARY
        require(len(mean) == (8 * metadata.descriptor_dim if binary else metadata.descriptor_dim), path,
                "PCA input size differs from the descriptor size")
        require(coarse.ndim == 2 and coarse.shape[1] == comp.shape[1] and len(coarse) >= 1, path,
                "bad 'coarse_centroids'")
        require(wc.shape == (len(arrays["idf"]),) and wc.dtype.kind == "i", path, "bad 'word_coarse'")
        require(bool(np.all((wc >= 0) & (wc < len(coarse)))), path, "'word_coarse' out of range")
        for name in ("pca_mean", "pca_components", "coarse_centroids"):
            require(bool(np.all(np.isfinite(arrays[name]))), path, f"non-finite values in '{name}'")
        return PCA(mean, comp, binary=binary)

    @staticmethod
    def _check_points(arrays: dict[str, np.ndarray], path: Path, points: str, dim: int, n: int,
                      lists: str | None = None) -> None:
        """Check the (n, dim) array ``points`` and, if named, its (L, dim) search lists."""
        p = arrays[points]
        require(p.ndim == 2 and p.shape == (n, dim), path, f"'{points}' does not match the word count or size")
        if lists is None:
            require(bool(np.all(np.isfinite(p))), path, f"non-finite values in '{points}'")
            return
        lst = arrays[lists]
        require(lst.ndim == 2 and lst.shape[1] == dim, path, f"bad '{lists}'")
        require(bool(np.all(np.isfinite(p))) and bool(np.all(np.isfinite(lst))), path,
                f"non-finite values in '{points}' or '{lists}'")


class KMeansVocabulary(PCAVocabulary):
    """Flat vocabulary of k-means centres in PCA space (kind ``kmeans``): a descriptor's
    word is its nearest centre.

    centroids: (W, d). ivf_centroids: (L, d) inverted-list centres of the search (L = 0:
    :class:`~.probe.ProbedSearch`). nprobe: inverted lists probed per query.
    """

    kind = "kmeans"

    def __init__(self, pca: PCA, centroids: np.ndarray, coarse_centroids: np.ndarray, word_coarse: np.ndarray,
                 ivf_centroids: np.ndarray, nprobe: int, idf: np.ndarray, metadata: VocabularyMetadata) -> None:
        super().__init__(pca, coarse_centroids, word_coarse, idf, metadata)
        self.centroids = np.ascontiguousarray(centroids, dtype=np.float32)
        self._search = PointIndex(self.centroids, ivf_centroids, nprobe)

    @property
    def ivf_centroids(self) -> np.ndarray:
        return self._search.lists

    @property
    def nprobe(self) -> int:
        return self._search.nprobe

    @nprobe.setter
    def nprobe(self, value: int) -> None:
        self._search.nprobe = value

    def words_of_points(self, x: np.ndarray, exact: bool = False) -> np.ndarray:
        return self._search.search(x, exact)

    def _state(self) -> dict[str, np.ndarray]:
        return {**self._pca_state(), "centroids": self.centroids, "ivf_centroids": self.ivf_centroids,
                "nprobe": np.array(self.nprobe, np.int64)}

    @classmethod
    def _centroid_args(cls, arrays: dict[str, np.ndarray], metadata: VocabularyMetadata, path: Path) -> tuple:
        """The constructor's positional arguments, from checked arrays."""
        pca = cls._check_pca_state(arrays, metadata, path, ("centroids", "ivf_centroids", "nprobe"))
        cls._check_points(arrays, path, "centroids", pca.dim, len(arrays["idf"]), lists="ivf_centroids")
        return (pca, arrays["centroids"], arrays["coarse_centroids"], arrays["word_coarse"],
                arrays["ivf_centroids"], int(arrays["nprobe"]), arrays["idf"], metadata)

    @classmethod
    def _from_state(cls, arrays: dict[str, np.ndarray], metadata: VocabularyMetadata, path: Path) -> KMeansVocabulary:
        return cls(*cls._centroid_args(arrays, metadata, path))


def check_training_input(desc: np.ndarray, image_ids: np.ndarray, n_words: int) -> tuple[np.ndarray, np.ndarray, str]:
    """Validated (descriptors, image ids, descriptor kind) of a flat vocabulary's training."""
    desc = np.asarray(desc)
    kind = descriptor_kind(desc)
    image_ids = np.asarray(image_ids).reshape(-1)
    if len(desc) != len(image_ids):
        raise ValueError("desc and image_ids differ in length")
    if len(desc) < 2 * n_words:
        raise ValueError(f"{len(desc)} descriptors are too few for {n_words} words (need at least twice as many)")
    return (desc.astype(np.float32) if kind == FLOAT else desc), image_ids, kind


def train_kmeans_vocabulary(
    desc: np.ndarray,
    image_ids: np.ndarray,
    cfg: HgcnTrainConfig | None = None,
    *,
    trained_on: str = "",
    progress: bool = True,
) -> KMeansVocabulary:
    """Train a k-means vocabulary: the PCA, k-means (the HGCN's seed k-means: same
    settings and seed), coarse nodes, search lists and IDF of :func:`train_hgcn_vocabulary
    <orbslam_hgcn.vocabulary.hgcn_vocab.train_hgcn_vocabulary>` with the same ``cfg``.

    desc: (N, 32) uint8 ORB or (N, D) float descriptors. image_ids: (N,) image of every
    descriptor (the IDF documents).
    """
    cfg = cfg or HgcnTrainConfig()
    desc, image_ids, kind = check_training_input(desc, image_ids, cfg.n_words)
    t0 = time.perf_counter()
    pca = fit_pca(desc, cfg.pca_dim, seed=cfg.seed)
    x = pca.transform(desc)
    t_pca = time.perf_counter() - t0
    centres = kmeans(x, cfg.n_words, cfg.kmeans_iters, cfg.seed, cfg.kmeans_points_per_word)
    t_km = time.perf_counter() - t0 - t_pca
    coarse, word_coarse = coarse_nodes(centres, cfg.n_coarse, cfg.seed)
    ivf = ivf_lists(centres, cfg.seed + 1)
    meta = VocabularyMetadata(
        kind="kmeans", n_words=cfg.n_words, descriptor_type=kind, descriptor_dim=int(desc.shape[1]),
        trained_on=trained_on, n_images=int(len(np.unique(image_ids))), n_descriptors=int(len(desc)),
        created=now_iso(),
        params={k: v for k, v in dataclasses.asdict(cfg).items()
                if k in ("n_words", "pca_dim", "kmeans_iters", "kmeans_points_per_word", "n_coarse", "nprobe", "seed")}
        | {"ivf_lists": len(ivf), "weighting": "tf-idf", "scoring": "L1"},
    )
    vocab = KMeansVocabulary(pca, centres, coarse, word_coarse, ivf, cfg.nprobe, np.ones(cfg.n_words, np.float32),
                             meta)
    words = vocab.words_of_points(x)
    vocab.idf = idf_from_documents(words, image_ids, vocab.n_words)
    exact = nearest(x[:: max(1, len(x) // 100_000)], centres)
    meta.stats = {
        "pca_seconds": round(t_pca, 2), "kmeans_seconds": round(t_km, 2),
        "train_seconds": round(time.perf_counter() - t0, 2),
        "empty_words": int((np.bincount(words, minlength=cfg.n_words) == 0).sum()),
        "search_exactness": round(float(np.mean(words[:: max(1, len(x) // 100_000)] == exact)), 4),
    }
    log.info("trained a %d-word k-means vocabulary on %d descriptors in %.1f s", cfg.n_words, len(desc),
             meta.stats["train_seconds"])
    return vocab
