"""The HGCN vocabulary: words learned by a hyperbolic GCN over the descriptor graph.

Training (after "Semi-supervised Vector-Quantization in Visual SLAM using HGCN"):

1. ORB bits unpacked to 256-D and reduced to 20-D by PCA (:mod:`.graph`);
2. the symmetric, normalised 9-NN graph of the descriptors (faiss);
3. seed labels on a fraction of the nodes (default 10%): faiss k-means in PCA space with
   K = the word count, each seeded node labelled with its nearest k-means centre; with
   track ids (descriptors of one 3D point in several images), all members of a track
   holding a seeded node share the label of the track's mean;
4. the 2-layer HGCN (:mod:`.training.hgcn`) trained on the seeds, with early stopping on held-out
   seeds, labels every node: a word is a class, and its prototype the network's embedding
   of the class's seed centre, a point of the Poincare ball.

Run time (``assignment = "network"``): a descriptor is PCA-projected (a nibble lookup table),
passed through the trained layers as a graph of its own (:class:`~.ball.BallNetwork`,
compiled), and its word is the nearest prototype in the hyperbolic distance, found by the
coarse-to-fine search of :mod:`.probe` over lifted prototypes (:class:`~.ball.PrototypeSearch`;
the exact nearest for about 99% of real descriptors). Training measures how often this
gives the word the network gave the training descriptor inside its graph
(``runtime_word_agreement``). ``assignment = "centroid"`` instead takes the nearest
class-mean centroid (in PCA space) of the network's labels: the decoder of version-1 files,
which load that way, and a comparison for benchmarks (``centroid_word_agreement``: 94.9%
on the shipped file's training descriptors against 100% for the network); trained files
use the network.

IDF weights are computed over the training images as for the tree; the FeatureVector uses
coarse nodes (k-means of the class-mean centroids), see :mod:`.flat`.

Saved arrays: those of :class:`~.flat.KMeansVocabulary` (``centroids`` are the class means
of the network's labels) and, for the network, ``prototypes`` (W, h) points of the output
ball, ``assignment`` (a scalar) and the ``net_*`` arrays of :class:`~.ball.BallNetwork`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.config import HgcnTrainConfig
from orbslam_hgcn.vocabulary.ball import BallNetwork, PrototypeSearch
from orbslam_hgcn.vocabulary.base import VocabularyMetadata, now_iso, require
from orbslam_hgcn.vocabulary.bow import idf_from_documents
from orbslam_hgcn.vocabulary.flat import (
    KMeansVocabulary,
    check_training_input,
    coarse_nodes,
    ivf_lists,
    kmeans,
    nearest,
)
from orbslam_hgcn.vocabulary.graph import PCA, build_graph, fit_pca
from orbslam_hgcn.vocabulary.track_network import TrackNetwork

log = logging.getLogger(__name__)

ASSIGNMENTS = ("network", "centroid")


class HGCNVocabulary(KMeansVocabulary):
    """Flat vocabulary of HGCN-learned words (kind ``hgcn``): the centroid search of
    :class:`~.flat.KMeansVocabulary` over the class means of the network's labels, and the
    network.

    pca: descriptor projection. centroids: (W, d) class-mean centroids in PCA space.
    coarse_centroids: (C, d). word_coarse: (W,) coarse node of every word. ivf_centroids:
    (L, d) inverted-list centres of the centroid search (L = 0: exact). nprobe: lists probed
    per query (centroids and prototypes). network: the trained layers (None: a version-1 file, centroids only).
    prototypes: (W, h) output-ball points of the words. assignment: ``network`` or
    ``centroid``.
    """

    kind = "hgcn"
    # The graph network over causal feature tracks (:mod:`.track_network`), when the file
    # holds one: the keyframe words of ``local_mapping.track_words_by: network``.
    track_network: TrackNetwork | None = None

    def __init__(self, pca: PCA, centroids: np.ndarray, coarse_centroids: np.ndarray, word_coarse: np.ndarray,
                 ivf_centroids: np.ndarray, nprobe: int, idf: np.ndarray, metadata: VocabularyMetadata, *,
                 network: BallNetwork | None = None, prototypes: np.ndarray | None = None,
                 assignment: str = "network") -> None:
        super().__init__(pca, centroids, coarse_centroids, word_coarse, ivf_centroids, nprobe, idf, metadata)
        self.network = network
        if network is not None:
            self.prototypes = np.ascontiguousarray(prototypes, dtype=np.float32)
            self._proto_search = PrototypeSearch(self.prototypes, float(network.curvatures[-1]))
            network.embed_isolated(np.zeros((1, network.weights[0].shape[1]), np.float32))  # compile or load the kernel
        self.assignment = assignment

    @property
    def assignment(self) -> str:
        return self._assignment

    @assignment.setter
    def assignment(self, value: str) -> None:
        if value not in ASSIGNMENTS:
            raise ValueError(f"assignment must be one of {ASSIGNMENTS}, found {value!r}")
        if value == "network" and self.network is None:
            raise ValueError("this vocabulary holds no network (a version-1 file): only 'centroid' assignment")
        self._assignment = value

    def embed(self, x: np.ndarray) -> np.ndarray:
        """(N, h) output-ball points of PCA coordinates x (N, d), each a graph of its own."""
        return self.network.embed_isolated(x)

    def nearest_prototype(self, h: np.ndarray, exact: bool = False) -> np.ndarray:
        """(N,) int32 hyperbolically nearest prototype of ball points h (N, h): the run-time
        search, or the exhaustive one (``exact``)."""
        return self._proto_search.search(h, exact)

    def words_of_points(self, x: np.ndarray, exact: bool = False) -> np.ndarray:
        if self._assignment == "centroid":
            return super().words_of_points(x, exact)
        return self.nearest_prototype(self.embed(x), exact)

    def graph_words(self, x: np.ndarray, adj) -> np.ndarray:
        """(N,) int32 the network's words of nodes x (N, d) inside the graph with normalised
        propagation matrix adj (the labels training gives; for held-out descriptors, build
        the graph over them and the training descriptors)."""
        return self.nearest_prototype(self.network.embed_graph(x, adj))

    def _state(self) -> dict[str, np.ndarray]:
        out = super()._state()
        if self.network is not None:
            out.update(self.network.arrays())
            out.update({"prototypes": self.prototypes, "assignment": np.array(self._assignment)})
        if self.track_network is not None:
            out.update(self.track_network.arrays())
        return out

    @classmethod
    def _from_state(cls, arrays: dict[str, np.ndarray], metadata: VocabularyMetadata, path: Path) -> HGCNVocabulary:
        args = cls._centroid_args(arrays, metadata, path)
        pca, n = args[0], len(arrays["idf"])
        kw: dict = {"assignment": "centroid"}
        if "prototypes" in arrays:
            try:
                net = BallNetwork.from_arrays(arrays)
            except (KeyError, ValueError) as exc:
                require(False, path, f"bad network arrays ({exc})")
            require(net.weights[0].shape[1] == pca.dim, path, "network input size differs from the PCA size")
            cls._check_points(arrays, path, "prototypes", net.out_dim, n)
            protos = arrays["prototypes"]
            require(bool(np.all(net.curvatures[-1] * np.einsum("kd,kd->k", protos, protos) < 1.0)), path,
                    "'prototypes' outside the ball")
            assignment = str(arrays.get("assignment", "network"))
            require(assignment in ASSIGNMENTS, path, f"unknown assignment {assignment!r}")
            kw = {"network": net, "prototypes": protos, "assignment": assignment}
        else:
            log.info("%s: a vocabulary without the network: words by nearest centroid", path)
        vocab = cls(*args, **kw)
        if "tracknet_weight" in arrays:
            try:
                vocab.track_network = TrackNetwork.from_arrays(arrays)
            except (KeyError, ValueError) as exc:
                require(False, path, f"bad track network arrays ({exc})")
            require(vocab.track_network.dim == pca.dim, path, "track network size differs from the PCA size")
        return vocab


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


def class_means(x: np.ndarray, pred: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """(K, d) mean of each class's points; a class without points keeps its fallback row."""
    k = len(fallback)
    counts = np.bincount(pred, minlength=k)
    sums = np.zeros((k, x.shape[1]), np.float64)
    np.add.at(sums, pred, x)
    return np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], fallback).astype(np.float32)


def train_hgcn_vocabulary(
    desc: np.ndarray,
    image_ids: np.ndarray,
    cfg: HgcnTrainConfig | None = None,
    *,
    track_ids: np.ndarray | None = None,
    trained_on: str = "",
    progress: bool = True,
    device: str | None = None,
) -> HGCNVocabulary:
    """Train an HGCN vocabulary (see the module docstring).

    desc: (N, 32) uint8 ORB or (N, D) float descriptors. image_ids: (N,) image of every
    descriptor (the IDF documents). track_ids: optional (N,) 3D point of every descriptor
    (-1: none). device: where the network trains (None: a GPU when torch sees one, else
    the CPU; see :func:`~orbslam_hgcn.vocabulary.training.hgcn.train_hgcn`). Returns the vocabulary; ``metadata.stats`` holds the stage timings, the
    seed accuracies and the run-time agreement.
    """
    from orbslam_hgcn.vocabulary.training.hgcn import train_hgcn  # torch: imported for training only

    cfg = cfg or HgcnTrainConfig()
    desc, image_ids, kind = check_training_input(desc, image_ids, cfg.n_words)
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
    adj = build_graph(x, cfg.knn, cfg.knn_exact_max, cfg.knn_nprobe, cfg.seed)
    stats["graph_edges"] = int(adj.nnz - adj.shape[0])
    lap("graph")
    labels, seeds = seed_labels(x, cfg, track_ids, rng)
    stats["labelled_nodes"] = int((labels >= 0).sum())
    lap("seed_kmeans")
    model, pred, hstats = train_hgcn(x, adj, labels, seeds, cfg, groups=track_ids, progress=progress,
                                   device=device)
    stats.update(hstats)
    t = time.perf_counter()
    network = model.to_numpy(model.input_scale)
    prototypes = network.embed_isolated(seeds)
    centroids = class_means(x, pred, seeds)
    stats["empty_words"] = int((np.bincount(pred, minlength=cfg.n_words) == 0).sum())
    stats["agreement_with_seed_kmeans"] = round(float(np.mean(pred == nearest(x, seeds))), 4)
    coarse, word_coarse = coarse_nodes(centroids, cfg.n_coarse, cfg.seed)
    meta = VocabularyMetadata(
        kind="hgcn",
        n_words=cfg.n_words,
        descriptor_type=kind,
        descriptor_dim=int(desc.shape[1]),
        trained_on=trained_on,
        n_images=int(len(np.unique(image_ids))),
        n_descriptors=int(len(desc)),
        created=now_iso(),
        params={**dataclasses.asdict(cfg), "tracks": track_ids is not None,
                "decoder": "hyperbolic prototypes of the seed centres", "weighting": "tf-idf", "scoring": "L1"},
        stats=stats,
    )
    vocab = HGCNVocabulary(pca, centroids, coarse, word_coarse, ivf_lists(centroids, cfg.seed + 1), cfg.nprobe,
                           np.ones(cfg.n_words, np.float32), meta, network=network, prototypes=prototypes,
                           assignment="network")
    params = meta.params
    params["ivf_lists"] = len(vocab.ivf_centroids)
    lap("prototypes")
    words = vocab.words_of_points(x)
    stats["runtime_word_agreement"] = round(float(np.mean(words == pred)), 4)
    vocab.assignment = "centroid"  # measured for comparison; files use the network
    stats["centroid_word_agreement"] = round(float(np.mean(vocab.words_of_points(x) == pred)), 4)
    vocab.assignment = "network"
    lap("agreement")
    vocab.idf = idf_from_documents(words, image_ids, vocab.n_words)
    stats["train_seconds"] = round(time.perf_counter() - t0, 2)
    log.info("trained a %d-word HGCN vocabulary on %d descriptors of %d images in %.1f s (run-time agreement %.3f)",
             cfg.n_words, len(desc), meta.n_images, stats["train_seconds"], stats["runtime_word_agreement"])
    return vocab
