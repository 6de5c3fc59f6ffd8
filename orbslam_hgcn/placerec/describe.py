"""Local descriptors of images for place recognition, and their visual words.

``orb``: the package's ORB-SLAM-style extractor ((N, 32) uint8 binary descriptors).
``sift``: OpenCV's SIFT ((N, 128) float32), standing in for the SURF features of the
FAB-MAP papers, which OpenCV's PyPI builds do not include. Vocabularies are expected to
accept either kind (binary descriptors as uint8, float descriptors as float32).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Protocol

import cv2
import numpy as np
from tqdm import tqdm

from orbslam_hgcn.errors import OrbslamError

log = logging.getLogger(__name__)

FEATURE_KINDS = ("orb", "sift")


class WordQuantizer(Protocol):
    """What this package needs of a vocabulary: descriptors in, one word id per descriptor."""

    def transform_words(self, descriptors: np.ndarray) -> np.ndarray: ...


class Describer:
    """Extract (N, D) descriptors from a grayscale image with the chosen feature kind."""

    def __init__(self, kind: str = "orb", n_features: int = 1000) -> None:
        kind = kind.lower()
        if kind not in FEATURE_KINDS:
            raise OrbslamError(f"unknown feature kind {kind!r}; use one of {', '.join(FEATURE_KINDS)}")
        self.kind = kind
        if kind == "orb":
            from orbslam_hgcn.config import ORBConfig
            from orbslam_hgcn.features.orb import ORBExtractor

            self._orb = ORBExtractor(ORBConfig(n_features=n_features))
        else:
            self._sift = cv2.SIFT_create(nfeatures=n_features)

    @property
    def dim(self) -> int:
        return 32 if self.kind == "orb" else 128

    @property
    def dtype(self) -> type:
        return np.uint8 if self.kind == "orb" else np.float32

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(N, 32) uint8 ORB or (N, 128) float32 SIFT descriptors of one image."""
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if self.kind == "orb":
            desc = self._orb.extract(image).desc
        else:
            _, desc = self._sift.detectAndCompute(image, None)
        if desc is None:
            return np.zeros((0, self.dim), dtype=self.dtype)
        return np.ascontiguousarray(desc, dtype=self.dtype)


def describe_images(
    images: Iterable[np.ndarray], describer: Describer, *, total: int | None = None, desc: str = "features"
) -> list[np.ndarray]:
    """Per image, its (N_i, D) descriptors."""
    return [describer(im) for im in tqdm(images, total=total, desc=desc, unit="img")]


def words_of(descriptors: list[np.ndarray], vocab: WordQuantizer) -> list[np.ndarray]:
    """Per image, the (N_i,) int64 word ids of its descriptors under ``vocab``."""
    out = []
    for d in descriptors:
        if len(d) == 0:
            out.append(np.zeros(0, dtype=np.int64))
        else:
            out.append(np.asarray(vocab.transform_words(d), dtype=np.int64).reshape(-1))
    return out
