"""The vocabulary interface, its metadata and its one-file format.

Every vocabulary turns descriptors into words (``transform_words``), words into a TF-IDF
:class:`~orbslam_hgcn.vocabulary.bow.BowVector` and a
:class:`~orbslam_hgcn.vocabulary.bow.FeatureVector` (``transform``), scores two vectors
(``score``) and is saved as one versioned file (``save`` / :func:`~orbslam_hgcn.vocabulary.loading.load_vocabulary`). The
rest of the system never needs to know which kind it holds.

File format (version 2): one ``.npz`` (zip) archive holding

* ``_magic``: the string ``orbslam_hgcn-vocabulary``;
* ``_format_version``: int, :data:`FORMAT_VERSION`;
* ``_kind``: ``orb`` (DBoW2-style tree), ``hgcn`` or ``kmeans``;
* ``_metadata``: JSON text of :class:`VocabularyMetadata`;
* ``idf``: (W,) float32 inverse document frequency of every word;
* the arrays of the kind (see each class).

It is written to a temporary file beside the target and renamed into place, so an
interrupted save never leaves a partial file. Reading checks the header, every array's
CRC (zip) and the arrays' shapes; any problem is a :class:`VocabularyError` naming the file.
Version 2 added the ``kmeans`` kind and the HGCN vocabulary's network; version-1 files
(``orb`` and ``hgcn``, whose HGCN words are found by nearest centroid) still load.
"""

from __future__ import annotations

import abc
import dataclasses
import datetime
import json
import logging
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from orbslam_hgcn.errors import VocabularyError
from orbslam_hgcn.npzfile import atomic_save_npz
from orbslam_hgcn.vocabulary.bow import BowVector, FeatureVector, l1_score

log = logging.getLogger(__name__)

MAGIC = "orbslam_hgcn-vocabulary"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)


@dataclasses.dataclass
class VocabularyMetadata:
    """What a vocabulary is and what it was trained on.

    descriptor_type: ``binary`` (rows of packed bits, e.g. ORB's 32 bytes) or ``float``
    (e.g. 128-D SIFT). descriptor_dim: bytes per binary descriptor, or floats per float
    descriptor. trained_on: human-readable description of the training imagery.
    params: training parameters. stats: training figures (times, sizes).
    """

    kind: str
    n_words: int
    descriptor_type: str
    descriptor_dim: int
    trained_on: str = ""
    n_images: int = 0
    n_descriptors: int = 0
    created: str = ""
    params: dict[str, Any] = dataclasses.field(default_factory=dict)
    stats: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str, path: str | Path) -> VocabularyMetadata:
        try:
            data = json.loads(text)
            names = {f.name for f in dataclasses.fields(cls)}
            return cls(**{k: v for k, v in data.items() if k in names})
        except (ValueError, TypeError) as exc:
            raise VocabularyError(f"{path}: unreadable vocabulary metadata ({exc})") from None

    def describe(self) -> str:
        """Multi-line human-readable summary (``orbslam-hgcn vocab info``)."""
        lines = [
            f"kind:            {self.kind}",
            f"words:           {self.n_words}",
            f"descriptors:     {self.descriptor_type}, {self.descriptor_dim} "
            + ("bytes" if self.descriptor_type == "binary" else "floats"),
            f"trained on:      {self.trained_on or '(not recorded)'}",
            f"training images: {self.n_images}",
            f"training descr.: {self.n_descriptors}",
            f"created:         {self.created or '(not recorded)'}",
        ]
        for title, d in (("parameters", self.params), ("training stats", self.stats)):
            if d:
                lines.append(f"{title}:")
                lines.extend(f"  {k}: {v}" for k, v in sorted(d.items()))
        return "\n".join(lines)


def now_iso() -> str:
    return datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0).isoformat()


class Vocabulary(abc.ABC):
    """A visual vocabulary: descriptors -> words -> BoW vectors, with IDF weights.

    idf: (W,) float32 inverse document frequency of each word. metadata: see
    :class:`VocabularyMetadata`.
    """

    kind: ClassVar[str]

    def __init__(self, idf: np.ndarray, metadata: VocabularyMetadata) -> None:
        self.idf = np.ascontiguousarray(idf, dtype=np.float32)
        self.metadata = metadata

    # --- to implement ---------------------------------------------------------------------
    @abc.abstractmethod
    def _words(self, desc: np.ndarray) -> np.ndarray:
        """(N,) int32 word of each of N validated descriptors."""

    @abc.abstractmethod
    def word_nodes(self, words: np.ndarray, levels_up: int) -> np.ndarray:
        """(N,) int32 feature-vector node of each word, ``levels_up`` levels above it."""

    @abc.abstractmethod
    def _state(self) -> dict[str, np.ndarray]:
        """The arrays that define the vocabulary (saved beside the header and ``idf``)."""

    @classmethod
    @abc.abstractmethod
    def _from_state(cls, arrays: dict[str, np.ndarray], metadata: VocabularyMetadata, path: Path) -> Vocabulary:
        """Rebuild from saved arrays; shape problems are VocabularyErrors naming ``path``."""

    # --- shared behaviour -----------------------------------------------------------------
    @property
    def n_words(self) -> int:
        return len(self.idf)

    @property
    def descriptor_type(self) -> str:
        return self.metadata.descriptor_type

    def check_descriptors(self, desc: np.ndarray) -> np.ndarray:
        """Validate descriptors: (N, B) uint8 for binary, (N, D) float32 for float vocabularies."""
        desc = np.asarray(desc)
        dim = self.metadata.descriptor_dim
        if self.descriptor_type == "binary":
            if desc.dtype != np.uint8 or desc.ndim != 2 or desc.shape[1] != dim:
                if desc.size == 0:
                    return np.zeros((0, dim), np.uint8)
                raise ValueError(f"expected (N, {dim}) uint8 binary descriptors, got {desc.shape} {desc.dtype}")
            return np.ascontiguousarray(desc)
        if desc.size == 0:
            return np.zeros((0, dim), np.float32)
        if desc.ndim != 2 or desc.shape[1] != dim or not np.issubdtype(desc.dtype, np.floating):
            raise ValueError(f"expected (N, {dim}) float descriptors, got {desc.shape} {desc.dtype}")
        return np.ascontiguousarray(desc, dtype=np.float32)

    def transform_words(self, desc: np.ndarray) -> np.ndarray:
        """(N,) int32 word id of each descriptor. desc: (N, 32) uint8 or (N, D) float32."""
        desc = self.check_descriptors(desc)
        if len(desc) == 0:
            return np.zeros(0, np.int32)
        return self._words(desc)

    def bow_from_words(self, words: np.ndarray) -> BowVector:
        """TF-IDF BowVector (L1-normalised) of one image from its features' words."""
        return BowVector.from_words(words, self.idf)

    def transform(self, desc: np.ndarray, levels_up: int = 4) -> tuple[BowVector, FeatureVector]:
        """BoW vector and feature vector of one image's descriptors.

        desc: (N, 32) uint8 (or (N, D) float32 for a float vocabulary). levels_up: the
        feature vector indexes nodes this many levels above the words (ORB-SLAM: 4).
        Features whose word has zero IDF weight are left out of both (as DBoW2 does).
        """
        return self.vectors(self.transform_words(desc), levels_up)

    def vectors(self, words: np.ndarray, levels_up: int = 4) -> tuple[BowVector, FeatureVector]:
        """BoW vector and feature vector of one image from its features' (N,) words (see
        :meth:`transform`)."""
        words = np.asarray(words, dtype=np.int32)
        bow = self.bow_from_words(words)
        keep = self.idf[words] > 0 if len(words) else np.zeros(0, bool)
        fv = FeatureVector.from_nodes(self.word_nodes(words, levels_up), keep)
        return bow, fv

    def bow(self, desc: np.ndarray) -> BowVector:
        """TF-IDF BowVector of one image's descriptors."""
        return self.bow_from_words(self.transform_words(desc))

    @staticmethod
    def score(a: BowVector, b: BowVector) -> float:
        """DBoW2's L1 score ``1 - 0.5 |a - b|_1`` (1: identical, 0: no shared word)."""
        return l1_score(a, b)

    def save(self, path: str | Path) -> Path:
        """Write the vocabulary to one file (atomically: temporary file, then rename)."""
        arrays = {
            "_magic": np.array(MAGIC),
            "_format_version": np.array(FORMAT_VERSION, np.int64),
            "_kind": np.array(self.kind),
            "_metadata": np.array(self.metadata.to_json()),
            "idf": self.idf,
        }
        for key, val in self._state().items():
            arrays[key] = np.asarray(val)
        return atomic_save_npz(path, arrays)

    def __repr__(self) -> str:
        m = self.metadata
        return f"{type(self).__name__}({m.n_words} words, {m.descriptor_type}x{m.descriptor_dim}, {m.trained_on!r})"


def require(cond: bool, path: Path, message: str) -> None:
    """Raise a VocabularyError naming ``path`` unless ``cond`` holds (used by ``_from_state``)."""
    if not cond:
        raise VocabularyError(f"{path}: corrupt vocabulary: {message}")
