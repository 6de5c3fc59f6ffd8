"""Saved maps in a running system: write a System's map with its vocabulary reference, read
one back under the same vocabulary (``System.install_map`` then installs it, for
localisation or to extend it).

The file itself is :mod:`orbslam_hgcn.map.io`. Keyframe BoW vectors are only meaningful
under the vocabulary that computed them, so the file records that vocabulary (kind, the
name or path it was opened by, word count, SHA-256 of its IDF weights and metadata) and
reading it under another one is a :class:`~orbslam_hgcn.errors.VocabularyError`.

Localisation only (ORB-SLAM2's localisation mode): the loaded map is installed, the tracker
starts LOST so the first frame is relocalised from the keyframe database (rebuilt from the
saved BoW vectors), and then tracks against the map without making keyframes or resetting
it. Only the points' found/visible counters change, as in ORB-SLAM2.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from orbslam_hgcn.errors import VocabularyError
from orbslam_hgcn.map import Map
from orbslam_hgcn.map.io import MapFile, MapFileError, read_header, read_map, save_map
from orbslam_hgcn.vocabulary.loading import SHIPPED
from orbslam_hgcn.vocabulary.bow import BowVector, FeatureVector

def vocabulary_reference(vocabulary: Any, name: str | None = None) -> dict[str, Any]:
    """What identifies a vocabulary in a map file: kind, name (``orb``, ``hgcn``, ... for the
    shipped ones, else a resolved path), word count, training description and a SHA-256
    over its (W,) IDF weights and its metadata JSON."""
    h = hashlib.sha256(np.ascontiguousarray(vocabulary.idf, dtype=np.float32).tobytes())
    h.update(vocabulary.metadata.to_json().encode("utf-8"))
    name = name or vocabulary.kind
    if name not in SHIPPED and Path(name).exists():
        name = str(Path(name).resolve())
    return {
        "kind": vocabulary.kind,
        "name": name,
        "n_words": int(vocabulary.n_words),
        "trained_on": vocabulary.metadata.trained_on,
        "sha256": h.hexdigest(),
    }


def map_vocabulary_name(path: str | Path) -> str | None:
    """The vocabulary name or path recorded in a map file (None if it had none)."""
    _, meta = read_header(path)
    ref = meta.get("vocabulary")
    return ref.get("name") if isinstance(ref, dict) else None


def check_vocabulary(mf: MapFile, vocabulary: Any) -> None:
    """VocabularyError unless ``vocabulary`` is the one the map's BoW vectors were made with."""
    ref = mf.meta.get("vocabulary")
    if not isinstance(ref, dict):
        if mf.bow:
            raise MapFileError(f"{mf.path}: the map holds BoW vectors but no vocabulary reference")
        return
    if vocabulary is None:
        raise VocabularyError(f"{mf.path}: the map was built with the {ref['kind']} vocabulary {ref['name']!r}; "
                              f"open it with that vocabulary (--vocab {ref['name']})")
    mine = vocabulary_reference(vocabulary)
    if mine["sha256"] != ref.get("sha256"):
        raise VocabularyError(
            f"{mf.path}: the map was built with the {ref['kind']} vocabulary {ref['name']!r} ({ref['n_words']} words, "
            f"sha256 {str(ref.get('sha256'))[:12]}), but the vocabulary given is a {mine['kind']} one with "
            f"{mine['n_words']} words (sha256 {mine['sha256'][:12]}); use --vocab {ref['name']}"
        )


def load_map(path: str | Path, vocabulary: Any) -> MapFile:
    """Read a map file (an atlas) and give its keyframes their BoW and feature vectors,
    after checking that ``vocabulary`` is the one they were computed with."""
    mf = read_map(path)
    check_vocabulary(mf, vocabulary)
    for kf_id, (words, weights) in mf.bow.items():
        mf.atlas.keyframe(kf_id).bow = BowVector(words, weights)
    for kf_id, nodes in mf.nodes.items():
        mf.atlas.keyframe(kf_id).featvec = FeatureVector.from_nodes(nodes, nodes >= 0)
    return mf


def save_system_map(path: str | Path, system: Any, vocab_name: str | None = None) -> Path:
    """Write ``system``'s atlas (every map) with a reference to ``system.vocabulary``
    (opened as ``vocab_name``)."""
    meta: dict[str, Any] = {}
    if system.vocabulary is not None:
        meta["vocabulary"] = vocabulary_reference(system.vocabulary, vocab_name)
    return save_map(path, system.atlas, meta)
