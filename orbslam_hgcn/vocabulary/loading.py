"""Opening vocabulary files of any kind: the shipped defaults, ``.npz`` files dispatched on
their kind, and DBoW2 text files (ORB-SLAM's ``ORBvoc.txt``) read as an ORB tree.

Apart from :mod:`.base` because it needs every kind: :mod:`.dbow2` and the kinds' modules
import :mod:`.base`, and this module imports them (the kinds' modules when a file of that
kind is opened).
"""

from __future__ import annotations

import importlib
import logging
from pathlib import Path

import numpy as np

from orbslam_hgcn.errors import VocabularyError
from orbslam_hgcn.npzfile import read_versioned_npz
from orbslam_hgcn.vocabulary import dbow2
from orbslam_hgcn.vocabulary.base import MAGIC, READABLE_VERSIONS, Vocabulary, VocabularyMetadata

log = logging.getLogger(__name__)

# Kind -> module defining its class (imported when a file of that kind is loaded).
KIND_MODULES = {
    "orb": "orbslam_hgcn.vocabulary.orb_tree",
    "hgcn": "orbslam_hgcn.vocabulary.hgcn_vocab",
    "kmeans": "orbslam_hgcn.vocabulary.flat",
}
DATA_DIR = Path(__file__).resolve().parent.parent / "data"
DEFAULT_FILES = {"orb": DATA_DIR / "vocab_orb_default.npz", "hgcn": DATA_DIR / "vocab_hgcn_default.npz",
                 "kmeans": DATA_DIR / "vocab_kmeans_default.npz"}
# Names load_vocabulary takes besides files: the default of each kind, the ORB tree of
# the flat vocabularies' size (k = 10, L = 4) for comparisons at equal size, and the
# k-means words with the graph network over feature tracks, with attention and with mean
# aggregation (tools/train_graph_vocab.py).
SHIPPED = {**DEFAULT_FILES, "orb10k": DATA_DIR / "vocab_orb10k.npz", "hgcn_graph": DATA_DIR / "vocab_hgcn_graph.npz",
           "hgcn_graph_mean": DATA_DIR / "vocab_hgcn_graph_mean.npz"}


def load_vocabulary(path: str | Path, expected_kind: str | None = None) -> Vocabulary:
    """Load any vocabulary file, dispatching on its kind.

    path: a vocabulary file (``.npz``, or a DBoW2 text file such as ORB-SLAM's ``ORBvoc.txt``,
    told by a ``.txt`` name or a first line of four integers), or the name of a shipped one:
    ``orb`` / ``hgcn`` / ``kmeans`` (the default of that kind) or ``orb10k``.
    expected_kind: if given, a file of another kind is a VocabularyError.
    """
    path = Path(path)
    if not path.exists() and str(path) in SHIPPED:
        path = SHIPPED[str(path)]
    if dbow2.is_dbow2_text(path):  # a DBoW2 text vocabulary (ORB-SLAM's ORBvoc.txt): an ORB tree
        if expected_kind not in (None, "orb"):
            raise VocabularyError(f"{path}: is a DBoW2 text ('orb') vocabulary, expected {expected_kind!r}")
        return dbow2.read_dbow2_text(path)
    arrays = read_versioned_npz(path, "vocabulary", MAGIC, READABLE_VERSIONS, VocabularyError,
                                "retrain it with 'orbslam-hgcn vocab train'")
    kind = str(arrays.get("_kind", ""))
    if kind not in KIND_MODULES:
        raise VocabularyError(f"{path}: unknown vocabulary kind {kind!r} (known: {', '.join(KIND_MODULES)})")
    if expected_kind is not None and kind != expected_kind:
        raise VocabularyError(f"{path}: is a {kind!r} vocabulary, expected {expected_kind!r}")
    meta_text = arrays.get("_metadata")
    if meta_text is None:
        raise VocabularyError(f"{path}: vocabulary metadata missing")
    metadata = VocabularyMetadata.from_json(str(meta_text), path)
    cls = vocabulary_class(kind)
    idf = arrays.get("idf")
    if idf is None or idf.ndim != 1 or len(idf) == 0 or not np.all(np.isfinite(idf)):
        raise VocabularyError(f"{path}: vocabulary has no (or a damaged) 'idf' array; it is empty or corrupt")
    if metadata.n_words != len(idf):
        raise VocabularyError(f"{path}: metadata says {metadata.n_words} words but 'idf' holds {len(idf)}")
    state = {k: v for k, v in arrays.items() if not k.startswith("_")}
    vocab = cls._from_state(state, metadata, path)
    log.info("loaded %r from %s", vocab, path)
    return vocab


def vocabulary_class(kind: str) -> type[Vocabulary]:
    """The Vocabulary subclass of ``kind`` (``orb``, ``hgcn`` or ``kmeans``)."""
    module = importlib.import_module(KIND_MODULES[kind])
    for obj in vars(module).values():
        if isinstance(obj, type) and issubclass(obj, Vocabulary) and getattr(obj, "kind", None) == kind:
            return obj
    raise VocabularyError(f"no vocabulary class of kind {kind!r}")


def default_vocabulary_path(kind: str) -> Path:
    """The shipped default vocabulary file of ``kind`` (``orb``, ``hgcn`` or ``kmeans``)."""
    if kind not in DEFAULT_FILES:
        raise VocabularyError(f"unknown vocabulary kind {kind!r}; use one of {', '.join(DEFAULT_FILES)}")
    return DEFAULT_FILES[kind]


def open_vocabulary(config) -> Vocabulary:
    """The vocabulary a :class:`~orbslam_hgcn.config.VocabularyConfig` names: its ``path``,
    or the shipped default of its ``kind`` when the path is empty."""
    return load_vocabulary(config.path or default_vocabulary_path(config.kind), expected_kind=config.kind)


def which_vocabulary() -> str:
    """Which shipped vocabulary is best for relocalisation, loop detection and tracking on
    real data, with the recorded figures (``data/WHICH_VOCABULARY.md``, its figures kept
    equal to bench/results by ``bench/figures.py``), as ``vocab info`` prints it."""
    import re
    import textwrap

    text = re.sub(r"<!--.*?-->", "", (DATA_DIR / "WHICH_VOCABULARY.md").read_text(encoding="utf-8"))
    out = ""
    for block in re.split(r"\n(?=- )|\n\s*\n", text.strip()):  # paragraphs and bullets, wrapped again
        words = " ".join(block.split())
        bullet = words.startswith("- ")
        if out:
            out += "\n" if bullet and out.splitlines()[-1].startswith(("- ", "  ")) else "\n\n"
        out += textwrap.fill(words, 92, subsequent_indent="  " if bullet else "")
    return out
