"""The HGCN vocabulary: words learned by a hyperbolic GCN over the descriptor graph.

Training (after "Semi-supervised Vector-Quantization in Visual SLAM using HGCN"):

1. ORB bits unpacked to 256-D and reduced to 20-D by PCA (:mod:`.graph`);
2. the symmetric, normalised 9-NN graph of the descriptors (faiss);
3. seed labels on a fraction of the nodes (default 10%): faiss k-means in PCA space with
   K = the word count, each seeded node labelled with its nearest k-means centre; with
   track ids (descriptors of one 3D point in several keyframes), all members of a track
   holding a seeded node share the label of the track's mean;
4. the 2-layer HGCN (:mod:`.hgcn`) trained on the seeds labels every node (argmax);
5. each word's centroid is the mean (in PCA space) of its nodes; a word no node chose
   keeps its k-means centre, so no word is empty.

Run time: descriptors are PCA-projected (a byte lookup table) and assigned to the nearest
word centroid by faiss: exactly (IndexFlatL2) for small vocabularies, or through an
inverted file over the centroids (IndexIVFFlat, ``nprobe`` lists) for large ones.
IDF weights are computed over the training images as for the tree.

The vocabulary is flat; its FeatureVector uses a coarse level: the word centroids are
clustered by k-means into ``n_coarse`` nodes and a feature's node is its word's coarse
node (``levels_up >= 1``; ``levels_up = 0`` indexes the words themselves).

Saved arrays: ``pca_mean`` (F,), ``pca_components`` (F, d), ``centroids`` (W, d),
``coarse_centroids`` (C, d), ``word_coarse`` (W,) int32, ``ivf_centroids`` (L, d) (L = 0:
exact search) and ``nprobe`` (scalar).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import faiss
import numpy as np

from orbslam_hgcn.config import HgcnTrainConfig
from orbslam_hgcn.vocabulary.base import Vocabulary, VocabularyMetadata, now_iso, require
from orbslam_hgcn.vocabulary.bow import idf_from_documents
from orbslam_hgcn.vocabulary.descriptors import BINARY, FLOAT, descriptor_kind
from orbslam_hgcn.vocabulary.graph import PCA, build_graph, configure_faiss, fit_pca

log = logging.getLogger(__name__)

FLAT_MAX_WORDS = 2048  # exact nearest-centroid search up to this many words, IVF above


def kmeans(x: np.ndarray, k: int, niter: int, seed: int, points_per_centroid: int = 256) -> np.ndarray:
    """(k, d) float32 faiss k-means centres of rows x (N, d); trains on at most
    ``points_per_centroid * k`` rows (faiss subsamples)."""
    configure_faiss()
    x = np.ascontiguousarray(x, dtype=np.float32)
    km = faiss.Kmeans(x.shape[1], k, niter=niter, seed=seed, max_points_per_centroid=points_per_centroid,
                      min_points_per_centroid=1, verbose=False)
    km.train(x)
    return np.ascontiguousarray(km.centroids, dtype=np.float32)


def nearest(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(N,) int64 index of the nearest centre of every row (exact, faiss flat)."""
    configure_faiss()
    index = faiss.IndexFlatL2(centres.shape[1])
    index.add(np.ascontiguousarray(centres, dtype=np.float32))
    return index.search(np.ascontiguousarray(x, dtype=np.float32), 1)[1][:, 0]


class HGCNVocabulary(Vocabulary):
    """Flat vocabulary of HGCN-learned word centroids in PCA space (kind ``hgcn``).

    pca: descriptor projection. centroids: (W, d) word centroids. coarse_centroids: (C, d).
    word_coarse: (W,) coarse node of every word. ivf_centroids: (L, d) inverted-list
    centres of the run-time search (L = 0: exact). nprobe: lists probed per query.
    """

    kind = "hgcn"

    def __init__(self, pca: PCA, centroids: np.ndarray, coarse_centroids: np.ndarray, word_coarse: np.ndarray,
                 ivf_centroids: np.ndarray, nprobe: int, idf: np.ndarray, metadata: VocabularyMetadata) -> None:
        super().__init__(idf, metadata)
        self.pca = pca
        self.centroids = np.ascontiguousarray(centroids, dtype=np.float32)
        self.coarse_centroids = np.ascontiguousarray(coarse_centroids, dtype=np.float32)
        self.word_coarse = np.ascontiguousarray(word_coarse, dtype=np.int32)
        self.ivf_centroids = np.ascontiguousarray(ivf_centroids, dtype=np.float32).reshape(-1, self.centroids.shape[1])
        configure_faiss()
        d = self.centroids.shape[1]
        if len(self.ivf_centroids) == 0:
            self._index = faiss.IndexFlatL2(d)
        else:
            quantizer = faiss.IndexFlatL2(d)
            quantizer.add(self.ivf_centroids)
            self._index = faiss.IndexIVFFlat(quantizer, d, len(self.ivf_centroids))
            self._index.is_trained = True
            self._quantizer = quantizer  # keep alive: the IVF index does not own it
        self._index.add(self.centroids)
        self.nprobe = nprobe

    @property
    def nprobe(self) -> int:
        return self._nprobe

    @nprobe.setter
    def nprobe(self, value: int) -> None:
        self._nprobe = int(value)
        if isinstance(self._index, faiss.IndexIVF):
            self._index.nprobe = max(1, min(self._nprobe, self._index.nlist))

    def project(self, desc: np.ndarray) -> np.ndarray:
        """(N, d) PCA coordinates of (N, B) uint8 or (N, D) float descriptors."""
        return self.pca.transform(self.check_descriptors(desc))

    def _words(self, desc: np.ndarray) -> np.ndarray:
        return self.words_of_points(self.pca.transform(desc))

    def words_of_points(self, x: np.ndarray) -> np.ndarray:
        """(N,) int32 nearest word of points x (N, d) in PCA space (the run-time search)."""
        _, idx = self._index.search(np.ascontiguousarray(x, dtype=np.float32), 1)
        return idx[:, 0].astype(np.int32)

    def word_nodes(self, words: np.ndarray, levels_up: int) -> np.ndarray:
        words = np.asarray(words, dtype=np.int64)
        return words.astype(np.int32) if levels_up <= 0 else self.word_coarse[words]

    def _state(self) -> dict[str, np.ndarray]:
        return {
            "pca_mean": self.pca.mean,
            "pca_components": self.pca.components,
            "centroids": self.centroids,
            "coarse_centroids": self.coarse_centroids,
            "word_coarse": self.word_coarse,
            "ivf_centroids": self.ivf_centroids,
            "nprobe": np.array(self.nprobe, np.int64),
        }

    @classmethod
    def _from_state(cls, arrays: dict[str, np.ndarray], metadata: VocabularyMetadata, path: Path) -> HGCNVocabulary:
        names = ("pca_mean", "pca_components", "centroids", "coarse_centroids", "word_coarse", "ivf_centroids",
                 "nprobe")
        missing = [n for n in names if n not in arrays]
        require(not missing, path, f"missing arrays {missing}")
        mean, comp, cent = arrays["pca_mean"], arrays["pca_components"], arrays["centroids"]
        coarse, wc, ivf = arrays["coarse_centroids"], arrays["word_coarse"], arrays["ivf_centroids"]
        require(mean.ndim == 1 and comp.ndim == 2 and comp.shape[0] == len(mean), path, "bad PCA arrays")
        d = comp.shape[1]
        binary = metadata.descriptor_type == BINARY
        require(len(mean) == (8 * metadata.descriptor_dim if binary else metadata.descriptor_dim), path,
                "PCA input size differs from the descriptor size")
        require(cent.ndim == 2 and cent.shape[1] == d and len(cent) == len(arrays["idf"]), path,
                "'centroids' does not match the PCA size or the word count")
        require(coarse.ndim == 2 and coarse.shape[1] == d and len(coarse) >= 1, path, "bad 'coarse_centroids'")
        require(wc.shape == (len(cent),) and wc.dtype.kind == "i", path, "bad 'word_coarse'")
        require(bool(np.all((wc >= 0) & (wc < len(coarse)))), path, "'word_coarse' out of range")
        require(ivf.ndim == 2 and ivf.shape[1] == d, path, "bad 'ivf_centroids'")
        for name in ("pca_mean", "pca_components", "centroids", "coarse_centroids", "ivf_centroids"):
            require(bool(np.all(np.isfinite(arrays[name]))), path, f"non-finite values in '{name}'")
        pca = PCA(mean, comp, binary=binary)
        return cls(pca, cent, coarse, wc, ivf, int(arrays["nprobe"]), arrays["idf"], metadata)


def seed_labels(x: np.ndarray, cfg: HgcnTrainConfig, track_ids: np.ndarray | None, rng: np.random.Generator):
    """Seed labels: (N,) int64 with -1 on unlabelled nodes, and the (K, d) k-means centres."""
    n = len(x)
    centres = kmeans(x, cfg.n_words, cfg.kmeans_iters, cfg.seed, cfg.kmeans_points_per_word)
    labels = np.full(n, -1, np.int64)
    chosen = rng.choice(n, max(1, int(round(cfg.label_fraction * n))), replace=False)
    labels[chosen] = nearest(x[chosen], centres)
    if track_ids is not None:
        track_ids = np.asarray(track_ids, dtype=np.int64).reshape(-1)
        if len(track_ids) != n:
            raise ValueError("track_ids must give one id per descriptor (-1: no track)")
        in_track = track_ids >= 0
        seeded_tracks = np.unique(track_ids[chosen][track_ids[chosen] >= 0])
        members = np.flatnonzero(in_track & np.isin(track_ids, seeded_tracks))
        if len(members):
            tids, inv = np.unique(track_ids[members], return_inverse=True)
            sums = np.zeros((len(tids), x.shape[1]), np.float64)
            np.add.at(sums, inv, x[members])
            means = sums / np.bincount(inv, minlength=len(tids))[:, None]
            labels[members] = nearest(means.astype(np.float32), centres)[inv]
    return labels, centres


def train_hgcn_vocabulary(
    desc: np.ndarray,
    image_ids: np.ndarray,
    cfg: HgcnTrainConfig | None = None,
    *,
    track_ids: np.ndarray | None = None,
    trained_on: str = "",
    progress: bool = True,
    kmeans_only: bool = False,
) -> HGCNVocabulary:
    """Train an HGCN vocabulary (see the module docstring).

    desc: (N, 32) uint8 ORB or (N, D) float descriptors. image_ids: (N,) image of every
    descriptor (the IDF documents). track_ids: optional (N,) 3D point of every descriptor
    (-1: none). kmeans_only: ablation baseline: skip the graph and the HGCN and use the
    seed k-means centres as the words (same PCA, word count, search and weights).
    Returns the vocabulary; ``metadata.stats`` holds the stage timings.
    """
    from orbslam_hgcn.vocabulary.hgcn import train_hgcn  # torch: imported for training only

    cfg = cfg or HgcnTrainConfig()
    desc = np.asarray(desc)
    kind = descriptor_kind(desc)
    image_ids = np.asarray(image_ids).reshape(-1)
    if len(desc) != len(image_ids):
        raise ValueError("desc and image_ids differ in length")
    if len(desc) < 2 * cfg.n_words:
        raise ValueError(f"{len(desc)} descriptors are too few for {cfg.n_words} words (need at least twice as many)")
    if kind == FLOAT:
        desc = desc.astype(np.float32)
    rng = np.random.default_rng(cfg.seed)
    stats: dict = {}
    t0 = t = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t
        now = time.perf_counter()
        stats[f"{name}_seconds"] = round(now - t, 2)
        t = now

    pca = fit_pca(desc, cfg.pca_dim, seed=cfg.seed)
    x = pca.transform(desc)
    lap("pca")
    if not kmeans_only:
        adj = build_graph(x, cfg.knn, cfg.knn_exact_max, cfg.knn_nprobe, cfg.seed)
        stats["graph_edges"] = int(adj.nnz - adj.shape[0])
        lap("graph")
    labels, seeds = seed_labels(x, cfg, track_ids, rng)
    stats["labelled_nodes"] = int((labels >= 0).sum())
    lap("seed_kmeans")
    if kmeans_only:
        pred = nearest(x, seeds)
    else:
        _, pred, hstats = train_hgcn(x, adj, labels, cfg.n_words, cfg, progress)
        stats.update(hstats)
    t = time.perf_counter()
    counts = np.bincount(pred, minlength=cfg.n_words)
    sums = np.zeros((cfg.n_words, x.shape[1]), np.float64)
    np.add.at(sums, pred, x)
    centroids = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], seeds).astype(np.float32)
    stats["empty_words"] = int((counts == 0).sum())
    stats["agreement_with_seed_kmeans"] = round(float(np.mean(pred == nearest(x, seeds))), 4)
    n_coarse = min(cfg.n_coarse, cfg.n_words)
    coarse = kmeans(centroids, n_coarse, 20, cfg.seed)
    word_coarse = nearest(centroids, coarse).astype(np.int32)
    ivf = np.zeros((0, x.shape[1]), np.float32)
    if cfg.n_words > FLAT_MAX_WORDS:
        ivf = kmeans(centroids, int(4 * np.sqrt(cfg.n_words)), 20, cfg.seed + 1)
    lap("centroids")
    meta = VocabularyMetadata(
        kind="hgcn",
        n_words=cfg.n_words,
        descriptor_type=kind,
        descriptor_dim=int(desc.shape[1]),
        trained_on=trained_on,
        n_images=int(len(np.unique(image_ids))),
        n_descriptors=int(len(desc)),
        created=now_iso(),
        params={**dataclasses.asdict(cfg), "tracks": track_ids is not None, "ivf_lists": len(ivf),
                "decoder": "none: k-means centres (ablation)" if kmeans_only else "hyperbolic prototypes",
                "weighting": "tf-idf", "scoring": "L1"},
        stats=stats,
    )
    vocab = HGCNVocabulary(pca, centroids, coarse, word_coarse, ivf, cfg.nprobe, np.ones(cfg.n_words, np.float32), meta)
    words = vocab.words_of_points(x)
    stats["runtime_word_agreement"] = round(float(np.mean(words == pred)), 4)
    vocab.idf = idf_from_documents(words, image_ids, vocab.n_words)
    lap("idf")
    stats["train_seconds"] = round(time.perf_counter() - t0, 2)
    log.info("trained a %d-word HGCN vocabulary on %d descriptors of %d images in %.1f s",
             cfg.n_words, len(desc), meta.n_images, stats["train_seconds"])
    return vocab
