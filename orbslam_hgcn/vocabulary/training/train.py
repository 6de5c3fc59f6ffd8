"""Training a vocabulary from images: sources, descriptor extraction with a resumable
cache, and the ``orbslam-hgcn vocab train`` entry point.

Image sources are dataset folders (TUM RGB-D, EuRoC, KITTI: read through
:func:`orbslam_hgcn.datasets.open_sequence`), folders of image files (searched
recursively) or single image files. Descriptors are ORB-SLAM's
(:class:`orbslam_hgcn.features.orb.ORBExtractor`: 8 levels, factor 1.2, FAST 20/7).

Extracted descriptors are cached next to the output (``<out>.descriptors.npz``, written
atomically every few images and on Ctrl-C), so an interrupted run resumes where it
stopped; the vocabulary itself is written to a temporary file and renamed, so an
interrupted run never leaves a partial vocabulary.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from orbslam_hgcn.config import HgcnTrainConfig, ORBConfig, TreeTrainConfig
from orbslam_hgcn.datasets.base import IMAGE_SUFFIXES, read_image
from orbslam_hgcn.errors import ConfigError, DatasetError, OrbslamError, VocabularyError
from orbslam_hgcn.npzfile import atomic_save_npz, read_npz
from orbslam_hgcn.engine import Engine
from orbslam_hgcn.memory import check_memory
from orbslam_hgcn.outputs import check_output_file
from orbslam_hgcn.vocabulary.base import Vocabulary

log = logging.getLogger(__name__)

CACHE_EVERY = 50  # images between cache checkpoints
# Peak resident bytes per training descriptor, measured with tools/train_default_vocabs.py on
# 2.14 M descriptors of 2,153 photos (peak RSS over descriptors, rounded up): the ORB tree
# (k = 10, L = 6) about 700, the k-means words about 500, the HGCN (its 9-NN graph, the
# network's activations and the label propagation) about 2,000. Checked before extraction.
TRAIN_BYTES_PER_DESCRIPTOR = {"orb": 800, "kmeans": 600, "hgcn": 2400}
BASE_BYTES = 600 << 20  # the interpreter, torch, faiss and OpenCV


def training_memory_bytes(kind: str, n_images: int, n_features: int) -> int:
    """Peak memory (bytes) of training a ``kind`` vocabulary on ``n_images`` images with at
    most ``n_features`` descriptors each."""
    return BASE_BYTES + TRAIN_BYTES_PER_DESCRIPTOR.get(kind, max(TRAIN_BYTES_PER_DESCRIPTOR.values())) \
        * n_images * n_features


@dataclass(frozen=True)
class ImageSource:
    """``n`` images of one source; ``load(i)`` returns image i as (H, W) uint8 grayscale."""

    name: str
    n: int
    load: Callable[[int], np.ndarray]


def _file_source(name: str, files: list[Path]) -> ImageSource:
    return ImageSource(name, len(files), lambda i: read_image(files[i]))


def open_image_source(path: str | Path) -> ImageSource:
    """An image source from a dataset folder, a folder of images or an image file."""
    p = Path(path).expanduser()
    if not p.exists():
        raise DatasetError(f"{p}: no such image file or folder")
    if p.is_file():
        if p.suffix.lower() not in IMAGE_SUFFIXES:
            raise DatasetError(f"{p}: not an image file ({', '.join(IMAGE_SUFFIXES)})")
        return _file_source(str(p), [p])
    from orbslam_hgcn.datasets import detect_kind, open_sequence

    try:
        kind = detect_kind(p)
    except DatasetError:
        kind = "folder"
    if kind in ("tum", "euroc", "kitti"):
        seq = open_sequence(kind, p)
        return ImageSource(f"{p} ({kind})", len(seq), lambda i: seq[i].image)
    files = sorted(f for f in p.rglob("*") if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise DatasetError(f"{p}: no images found (looked for {', '.join(IMAGE_SUFFIXES)}, recursively)")
    return _file_source(str(p), files)


def select_images(sources: list[ImageSource], max_images: int | None) -> list[tuple[int, int]]:
    """(source, index) pairs of the images to use: all, or ``max_images`` evenly spread."""
    pairs = [(s, i) for s, src in enumerate(sources) for i in range(src.n)]
    if max_images is not None and 0 < max_images < len(pairs):
        pick = np.unique(np.round(np.linspace(0, len(pairs) - 1, max_images)).astype(int))
        pairs = [pairs[i] for i in pick]
    return pairs


def make_extractor(n_features: int) -> tuple[str, Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]]:
    """(name, image -> ((N, 32) uint8 descriptors, (N, 2) float32 keypoint positions)) with
    ORB-SLAM's ORB settings."""
    from orbslam_hgcn.features.orb import ORBExtractor

    extractor = ORBExtractor(dataclasses.replace(ORBConfig(), n_features=n_features))

    def extract(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kps = extractor.extract(img)
        return kps.desc, kps.uv_raw.astype(np.float32)

    return f"ORBExtractor(n_features={n_features})", extract


@dataclass
class TrainingData:
    """Descriptors of the training images.

    desc: (M, 32) uint8. uv: (M, 2) float32 keypoint positions. image_ids: (M,) int32
    image of each descriptor. groups: (I,) int32 source (sequence) of each image.
    """

    desc: np.ndarray
    uv: np.ndarray
    image_ids: np.ndarray
    groups: np.ndarray

    def per_image(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Descriptors and positions split by image."""
        cuts = np.cumsum(np.bincount(self.image_ids, minlength=len(self.groups)))[:-1]
        return np.split(self.desc, cuts), np.split(self.uv, cuts)


def _extract_shard(task: dict) -> list[tuple[np.ndarray, np.ndarray]]:
    """Descriptors of one shard of images, a task of the engine: the image sources are
    opened again from their paths (``images``), ``pairs`` index them."""
    sources = [open_image_source(p) for p in task["images"]]
    _, extract = make_extractor(task["n_features"])
    return [extract(sources[s].load(i)) for s, i in task["pairs"]]


def extract_descriptors(
    sources: list[ImageSource],
    pairs: list[tuple[int, int]],
    n_features: int,
    cache: Path | None = None,
    progress: bool = True,
    images: list[str | Path] | None = None,
    engine: Engine | None = None,
) -> TrainingData:
    """Descriptors (and keypoint positions) of the selected images.

    With ``cache``, images already there (same settings) are not extracted again, and the
    cache is updated every :data:`CACHE_EVERY` images and when interrupted. With an
    ``engine`` (and ``images``, the paths the sources were opened from) the images are
    extracted in shards of :data:`CACHE_EVERY` on it (Ray), the cache updated after each.
    """
    name, extract = make_extractor(n_features)
    keys = [f"{sources[s].name}#{i}" for s, i in pairs]
    settings = json.dumps({"extractor": name, "features": n_features, "format": 2})
    done: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if cache is not None and cache.is_file():
        try:
            arrays = read_npz(cache, "descriptor cache", VocabularyError)
            if str(arrays["settings"]) == settings:
                starts = np.concatenate([[0], np.cumsum(arrays["counts"])])
                for key, a, b in zip(arrays["keys"].tolist(), starts[:-1], starts[1:]):
                    done[key] = (arrays["desc"][a:b], arrays["uv"][a:b])
                log.info("%s: resuming with %d images already extracted", cache, len(done))
            else:
                log.info("%s: made with other settings; starting over", cache)
        except (VocabularyError, KeyError):
            log.warning("%s: unreadable descriptor cache; starting over", cache)

    def save_cache() -> None:
        if cache is None or not done:
            return
        ks = list(done)
        atomic_save_npz(cache, {
            "settings": np.array(settings), "keys": np.array(ks),
            "counts": np.array([len(done[k][0]) for k in ks], np.int64),
            "desc": np.concatenate([done[k][0] for k in ks]),
            "uv": np.concatenate([done[k][1] for k in ks]),
        }, compress=False)

    todo = [j for j, key in enumerate(keys) if key not in done]
    new = 0
    try:
        if engine is not None and images is not None:
            shards = [todo[a : a + CACHE_EVERY] for a in range(0, len(todo), CACHE_EVERY)]
            tasks = [{"images": [str(p) for p in images], "pairs": [pairs[j] for j in sh], "n_features": n_features}
                     for sh in shards]
            for k, result in tqdm(engine.imap_unordered(_extract_shard, tasks), total=len(tasks),
                                  desc=f"extracting ORB ({engine.name})", unit="shard", disable=not progress):
                if isinstance(result, Exception):
                    raise DatasetError(f"descriptor extraction failed: {result}")
                for j, r in zip(shards[k], result):
                    done[keys[j]] = r
                new += len(result)
                save_cache()
            todo = []
        for j in tqdm(todo, desc="extracting ORB", unit="image", disable=not progress):
            s, i = pairs[j]
            done[keys[j]] = extract(sources[s].load(i))
            new += 1
            if new % CACHE_EVERY == 0:
                save_cache()
    except KeyboardInterrupt:
        save_cache()
        raise
    if new:
        save_cache()
    parts = [done[k] for k in keys]
    if not parts:
        return TrainingData(np.zeros((0, 32), np.uint8), np.zeros((0, 2), np.float32), np.zeros(0, np.int32),
                            np.zeros(0, np.int32))
    return TrainingData(
        desc=np.concatenate([p[0] for p in parts]),
        uv=np.concatenate([p[1] for p in parts]),
        image_ids=np.repeat(np.arange(len(parts), dtype=np.int32), [len(p[0]) for p in parts]),
        groups=np.array([s for s, _ in pairs], np.int32),
    )


def train_vocabulary(
    kind: str,
    desc: np.ndarray,
    image_ids: np.ndarray,
    *,
    words: int | None = None,
    tree: TreeTrainConfig | None = None,
    hgcn: HgcnTrainConfig | None = None,
    track_ids: np.ndarray | None = None,
    trained_on: str = "",
    progress: bool = True,
    device: str | None = None,
) -> Vocabulary:
    """Train a vocabulary of ``kind`` (``orb``, ``hgcn`` or ``kmeans``) on descriptors.

    words: target word count; for ``orb`` it sets the depth ``L = round(log_k(words))``
    (a tree has up to k^L words), for ``hgcn`` and ``kmeans`` the number of words exactly.
    ``kmeans`` is trained with the ``hgcn`` settings (same PCA, k-means, search).
    device: the torch device of HGCN training (None or ``auto``: a GPU when torch sees one).
    """
    if kind == "orb":
        from orbslam_hgcn.vocabulary.orb_tree import train_tree_vocabulary

        tc = tree or TreeTrainConfig()
        if words is not None:
            tc = dataclasses.replace(tc, levels=max(1, int(round(np.log(words) / np.log(tc.k)))))
        return train_tree_vocabulary(desc, image_ids, k=tc.k, levels=tc.levels, max_iters=tc.max_iters,
                                     seed=tc.seed, trained_on=trained_on, progress=progress)
    if kind == "hgcn":
        from orbslam_hgcn.vocabulary.hgcn_vocab import train_hgcn_vocabulary

        hc = hgcn or HgcnTrainConfig()
        if words is not None:
            hc = dataclasses.replace(hc, n_words=int(words))
        return train_hgcn_vocabulary(desc, image_ids, hc, track_ids=track_ids, trained_on=trained_on,
                                     progress=progress, device=device)
    if kind == "kmeans":
        from orbslam_hgcn.vocabulary.flat import train_kmeans_vocabulary

        hc = hgcn or HgcnTrainConfig()
        if words is not None:
            hc = dataclasses.replace(hc, n_words=int(words))
        return train_kmeans_vocabulary(desc, image_ids, hc, trained_on=trained_on, progress=progress)
    raise OrbslamError(f"unknown vocabulary kind {kind!r}; use 'orb', 'hgcn' or 'kmeans'")


def train_from_images(
    kind: str,
    images: list[str | Path],
    out: str | Path,
    *,
    words: int | None = None,
    max_images: int | None = None,
    n_features: int = 1000,
    tree: TreeTrainConfig | None = None,
    hgcn: HgcnTrainConfig | None = None,
    trained_on: str | None = None,
    tracks: bool = False,
    keep_cache: bool = False,
    progress: bool = True,
    device: str | None = None,
    jobs: int = 1,
    address: str | None = None,
) -> Vocabulary:
    """Extract descriptors from image sources, train a vocabulary and save it to ``out``.

    tracks: (hgcn) match consecutive images of each source into feature tracks whose
    descriptors share their seed label (see :mod:`orbslam_hgcn.vocabulary.training.tracks`).
    device: the torch device of HGCN training (None or ``auto``: a GPU when torch sees one).
    jobs, address: extract the descriptors in shards on Ray (a local instance with ``jobs``
    CPUs, or the cluster at ``address``; :mod:`orbslam_hgcn.engine`), when
    ``jobs`` > 1 or ``address`` is given; else in this process.
    """
    if not images:
        raise OrbslamError("no image sources given (--images)")
    for name, value, least in (("--words", words, 1 if kind == "orb" else 2), ("--max-images", max_images, 1),
                               ("--n-features", n_features, 1), ("--jobs", jobs, 1)):
        if value is not None and value < least:
            raise ConfigError(f"{name} must be at least {least}, found {value}")
    out = check_output_file(out, "--out")
    t0 = time.perf_counter()
    sources = [open_image_source(p) for p in images]
    pairs = select_images(sources, max_images)
    check_memory(training_memory_bytes(kind, len(pairs), n_features),
                 f"training a {kind} vocabulary on {len(pairs)} images x {n_features} features",
                 "use fewer images (--max-images N) or fewer features per image (--n-features N)")
    cache = out.with_name(out.name + ".descriptors.npz")
    if jobs > 1 or address:
        with Engine(jobs, address) as engine:
            data = extract_descriptors(sources, pairs, n_features, cache, progress, images=list(images), engine=engine)
    else:
        data = extract_descriptors(sources, pairs, n_features, cache, progress)
    desc, image_ids = data.desc, data.image_ids
    if len(desc) < 2:
        raise DatasetError(f"only {len(desc)} descriptors found in {len(pairs)} images; nothing to train on")
    t_extract = time.perf_counter() - t0
    track_ids = None
    if tracks and kind == "hgcn":
        from orbslam_hgcn.vocabulary.training.tracks import build_tracks

        track_ids = build_tracks(*data.per_image(), data.groups, progress=progress)
    t_tracks = time.perf_counter() - t0 - t_extract
    if trained_on is None:
        trained_on = "; ".join(f"{s.name}: {sum(1 for p in pairs if p[0] == k)} of {s.n} images"
                               for k, s in enumerate(sources))
    log.info("training a %s vocabulary on %d descriptors of %d images", kind, len(desc), len(pairs))
    vocab = train_vocabulary(kind, desc, image_ids, words=words, tree=tree, hgcn=hgcn, track_ids=track_ids,
                             trained_on=trained_on, progress=progress, device=device)
    vocab.metadata.stats["extract_seconds"] = round(t_extract, 2)
    if track_ids is not None:
        vocab.metadata.stats["tracks_seconds"] = round(t_tracks, 2)
        vocab.metadata.stats["tracked_descriptors"] = int((track_ids >= 0).sum())
    vocab.metadata.params["n_features"] = n_features
    vocab.save(out)
    if not keep_cache and cache.exists():
        cache.unlink()
    log.info("wrote %s (%d words)", out, vocab.n_words)
    return vocab
