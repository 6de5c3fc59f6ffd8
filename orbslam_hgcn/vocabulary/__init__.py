"""Visual vocabularies: the DBoW2-style ORB tree (baseline) and the HGCN vocabulary, BoW
and feature vectors. Works on descriptors and ids, never on the map (the keyframe database
over BoW vectors is :mod:`orbslam_hgcn.map.database`; training is :mod:`.training`).

``load_vocabulary(path)`` opens either kind; ``load_vocabulary("orb")`` or
``load_vocabulary("hgcn")`` opens the shipped default.
"""

from orbslam_hgcn.vocabulary.base import Vocabulary, VocabularyMetadata
from orbslam_hgcn.vocabulary.bow import BowVector, FeatureVector, l1_score
from orbslam_hgcn.vocabulary.loading import default_vocabulary_path, load_vocabulary, open_vocabulary

__all__ = [
    "BowVector",
    "FeatureVector",
    "Vocabulary",
    "VocabularyMetadata",
    "default_vocabulary_path",
    "l1_score",
    "load_vocabulary",
    "open_vocabulary",
]
