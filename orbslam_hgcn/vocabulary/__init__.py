"""Visual vocabularies: the DBoW2-style ORB tree (baseline) and the HGCN vocabulary, BoW
and feature vectors, and the keyframe database (inverted index) used for loop closing and
relocalisation. Works on descriptors and ids, never on the map.

``load_vocabulary(path)`` opens either kind; ``load_vocabulary("orb")`` or
``load_vocabulary("hgcn")`` opens the shipped default.
"""

from orbslam_hgcn.vocabulary.base import (
    Vocabulary,
    VocabularyMetadata,
    default_vocabulary_path,
    load_vocabulary,
    open_vocabulary,
)
from orbslam_hgcn.vocabulary.bow import BowVector, FeatureVector, l1_score
from orbslam_hgcn.vocabulary.database import Candidate, KeyframeDatabase

__all__ = [
    "BowVector",
    "Candidate",
    "FeatureVector",
    "KeyframeDatabase",
    "Vocabulary",
    "VocabularyMetadata",
    "default_vocabulary_path",
    "l1_score",
    "load_vocabulary",
    "open_vocabulary",
]
