"""The configurations of the commands beside a run's stages (YAML sections ``fabmap``,
``viz``, ``hgcn``, ``vocab_tree``, and the vocabulary's settings): FAB-MAP loop detection
(``orbslam-hgcn lcd``), the live rerun view, the run-time vocabulary and keyframe
database, and vocabulary training (``orbslam-hgcn vocab train``: the DBoW2 tree, HGCN and
k-means vocabularies). Frozen dataclasses, each with its defaults beside their meaning,
filled from a config file by :func:`~orbslam_hgcn.config_files.section_from_yaml`; every
name here is also importable from :mod:`orbslam_hgcn.config`.
"""

from __future__ import annotations

import dataclasses

from orbslam_hgcn.errors import ConfigError



@dataclasses.dataclass(frozen=True)
class FabmapConfig:
    """Appearance-based loop-closure detection (FAB-MAP 2.0, Cummins & Newman, IJRR 2011; the
    BoW detectors share ``min_gap``). Detector model, smoothing, new-place prior, motion bias
    and sample count are openFABMAP's defaults (Glover et al., ICRA 2012: samples/settings.yml
    PzGe 0.39, PzGne 0, NumSamples 1000; FabMap constructor Pnew 0.9, mBias 0.5; ChowLiuTree
    smoothing 0.98 f + 0.01); prior_spread 0.01 stands for its 1% posterior smoothing (sFactor 0.99)."""

    p_z_given_e: float = 0.39  # detector model p(z = 1 | e = 1): a present element is seen
    p_z_given_not_e: float = 0.0  # p(z = 1 | e = 0): an absent element is seen (false word)
    smoothing: float = 0.01  # Chow-Liu probabilities (1 - 2 s) * frequency + s, never 0 or 1
    new_place: str = "mean_field"  # new-place likelihood: "mean_field" or "sampled" (training)
    num_samples: int = 1000  # training images drawn for the "sampled" new-place model
    p_new: float = 0.9  # prior probability that a query shows a place not yet visited
    motion_model: bool = True  # prior favours the previous match's neighbours (else uniform)
    motion_bias: float = 0.5  # share of neighbour mass moved forward (1: all forward)
    prior_spread: float = 0.01  # share of the known-place prior always spread uniformly
    # A query is compared with images at least this many images earlier; 0: chosen from the
    # data (lcd: the ground truth's smallest loop separation, else 10 s of timestamps).
    min_gap: int = 0
    seed: int = 0  # seed of the training-image sample


@dataclasses.dataclass(frozen=True)
class VizConfig:
    """Rerun visualisation (``orbslam_hgcn.viz``): what is logged and how often."""

    # Frames between two map logs; the map is also logged on every loop closure (the
    # corrected map replaces the old one) and, with map_on_keyframe, on a keyframe insert
    # at least map_min_interval frames after the previous map log. A map log costs about
    # 2.7 ms at 10k points / 200 keyframes, a frame about 2 ms (bench/bench_viz.py): with
    # these defaults logging stays under 10% of a 30 fps frame budget.
    log_every_map: int = 20
    map_on_keyframe: bool = True
    map_min_interval: int = 10
    # Map point colour: "observations" (observing keyframes, viridis up to obs_colour_max),
    # "height" (above the first camera, i.e. along world -y), or "none".
    point_colour: str = "observations"
    obs_colour_max: int = 15
    # Camera image: "jpeg" (about 10x smaller files), "raw" (lossless) or "none";
    # logged every image_every frames (keypoints, pose and plots are logged every frame).
    image_format: str = "jpeg"
    jpeg_quality: int = 80
    image_every: int = 1
    # Distance of the drawn image plane of keyframe frustums, in world (map) units.
    frustum_depth: float = 0.1

    def __post_init__(self) -> None:
        choices = {"point_colour": ("observations", "height", "none"),
                   "image_format": ("jpeg", "raw", "none")}
        for key, allowed in choices.items():
            if getattr(self, key) not in allowed:
                raise ConfigError(
                    f"viz.{key}: {getattr(self, key)!r} is not one of {', '.join(allowed)}"
                )
        for key in ("log_every_map", "map_min_interval", "image_every", "obs_colour_max"):
            if int(getattr(self, key)) < 1:
                raise ConfigError(f"viz.{key}: must be at least 1, found {getattr(self, key)!r}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"viz.jpeg_quality: must be in 1..100, found {self.jpeg_quality!r}")
        if not self.frustum_depth > 0:
            raise ConfigError(f"viz.frustum_depth: must be positive, found {self.frustum_depth!r}")


@dataclasses.dataclass(frozen=True)
class VocabularyConfig:
    """Visual vocabulary and keyframe database at run time (ORB-SLAM, Mur-Artal et al., T-RO
    2015, sections III-E and VI: DBoW2 vectors, FeatureVector 4 levels above the words, loop
    candidates sharing > 0.8 x the most common words, kept above 0.75 x the best group score)."""

    kind: str = "kmeans"  # "kmeans" (flat k-means, the default run vocabulary), "hgcn" (the paper's) or "orb" (DBoW2 tree)
    path: str = ""  # vocabulary file; "" = the shipped default of `kind`
    levels_up: int = 4  # FeatureVector nodes this many levels above the words (HGCN: coarse nodes)
    min_common_words_ratio: float = 0.8  # candidates share more than this x the most common words
    retain_score_ratio: float = 0.75  # keep groups scoring above this x the best group score
    n_covisible: int = 10  # best covisible keyframes whose scores form a candidate's group

    def __post_init__(self) -> None:
        if self.kind not in ("hgcn", "orb", "kmeans"):
            raise ConfigError(f"vocabulary.kind: must be 'hgcn', 'orb' or 'kmeans', found {self.kind!r}")
        if self.levels_up < 0:
            raise ConfigError(f"vocabulary.levels_up: must be >= 0, found {self.levels_up!r}")
        for key in ("min_common_words_ratio", "retain_score_ratio"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise ConfigError(f"vocabulary.{key}: must be in [0, 1], found {getattr(self, key)!r}")


@dataclasses.dataclass(frozen=True)
class TreeTrainConfig:
    """Training of the DBoW2 vocabulary tree (Galvez-Lopez & Tardos, T-RO 2012; ORB-SLAM's
    ORBvoc uses k = 10, L = 6)."""

    k: int = 10  # children per node
    levels: int = 6  # depth L: up to k^L words (ORBvoc: 6)
    max_iters: int = 10  # Lloyd iterations of k-medians per level
    seed: int = 0  # k-means++ seeding

    def __post_init__(self) -> None:
        if self.k < 2 or self.levels < 1 or self.max_iters < 1:
            raise ConfigError(f"vocab_tree: k >= 2, levels >= 1 and max_iters >= 1 are required, found k = {self.k}, "
                              f"levels = {self.levels}, max_iters = {self.max_iters}")


@dataclasses.dataclass(frozen=True)
class HgcnTrainConfig:
    """Training of the HGCN vocabulary ("Semi-supervised Vector-Quantization in Visual SLAM
    using HGCN": 20-D PCA of the 256 ORB bits, 9-NN graph, 2-layer HGCN of Chami et al.,
    NeurIPS 2019, labels seeded on a fraction of the nodes by k-means). The k-means
    vocabulary (the ablation without the graph and the network) uses the same PCA, seed
    k-means, word count, coarse nodes and search settings."""

    n_words: int = 8000  # K: words = seed clusters = output classes
    pca_dim: int = 20  # PCA dimensions of the descriptor features
    knn: int = 9  # neighbours per node before symmetrisation
    knn_exact_max: int = 60000  # exact kNN (faiss flat) up to this many nodes, IVF above
    knn_nprobe: int = 16  # IVF lists probed by the approximate kNN search
    label_fraction: float = 0.1  # fraction of nodes given a seed label
    kmeans_iters: int = 20  # faiss k-means iterations of the label seeding
    kmeans_points_per_word: int = 64  # k-means trains on at most this many points per word
    hidden_dim: int = 20  # width of both HGCN layers (with 20 the run-time prototype search stays in faiss's fused kernel)
    activation: str = "tanh"  # tangent-space activation: relu, leaky_relu, elu, tanh
    residual: bool = True  # layers add their aggregate to an identity-initialised self path
    dropout: float = 0.0  # dropout on the layer weights (as HGCN's HypLinear)
    input_radius: float = 0.5  # mean tangent norm of the input features on the first ball
    epochs: int = 60  # full-batch epochs at most (early stopping usually ends sooner)
    eval_every: int = 2  # epochs between two validation passes
    patience: int = 5  # validation passes without improvement before training stops
    holdout: float = 0.1  # share of the seed groups held out for validation, and again for test
    candidate_classes: int = 16  # hard negatives per seed in the loss: the nearest prototypes
    lr: float = 5e-4  # Adam learning rate of the layers
    scale_lr: float = 0.01  # Adam learning rate of the logit scale
    weight_decay: float = 0.0  # Adam weight decay
    init_curvature: float = 1.0  # initial c of every ball (trainable, c = softplus(raw))
    n_coarse: int = 100  # coarse nodes (k-means of the word centres) for the FeatureVector
    nprobe: int = 4  # inverted lists probed at run time (IVF over the words; above 16384 words only)
    seed: int = 0  # sampling, initialisation and k-means seeds

    def __post_init__(self) -> None:
        if self.n_words < 2 or self.pca_dim < 1 or self.knn < 1 or self.hidden_dim < 1 or self.epochs < 1:
            raise ConfigError("hgcn: n_words >= 2, pca_dim >= 1, knn >= 1, hidden_dim >= 1 and epochs >= 1 are "
                              f"required, found {self.n_words}, {self.pca_dim}, {self.knn}, {self.hidden_dim}, "
                              f"{self.epochs}")
        if not 0.0 < self.label_fraction <= 1.0:
            raise ConfigError(f"hgcn.label_fraction: must be in (0, 1], found {self.label_fraction!r}")
        if self.activation not in ("relu", "leaky_relu", "elu", "tanh"):
            raise ConfigError(f"hgcn.activation: unknown activation {self.activation!r}")
        if not 0.0 <= self.holdout < 0.5:
            raise ConfigError(f"hgcn.holdout: must be in [0, 0.5), found {self.holdout!r}")
        if self.epochs < 0 or self.eval_every < 1 or self.candidate_classes < 1:
            raise ConfigError("hgcn: epochs >= 0, eval_every >= 1 and candidate_classes >= 1 are required")
