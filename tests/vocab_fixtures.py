"""Shared, cached test data for the vocabulary tests: ORB descriptors of sample images and
small vocabularies trained on them (trained once per test session).

The images are the real samples beside the repository (TUM fr3, EuRoC) when they are there;
without them, the synthetic stand-ins of tests/conftest.py (``stand_in``): the fr3 camera
path replayed in the synthetic office for "tum", a drive down the synthetic street for
"euroc", so that these tests run on any checkout."""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np

from orbslam_hgcn.config import HgcnTrainConfig

from conftest import REPLAY_GT, SHARED_DATA as SHARED, stand_in  # noqa: F401 - REPLAY_GT re-exported (vf.REPLAY_GT)
REAL_TUM_RGB = SHARED / "tum_fr3_long_office_household_sample" / "rgb"
REAL_EUROC_RGB = SHARED / "euroc_V1_01_easy_first95" / "mav0" / "cam0" / "data"


def tum_rgb() -> Path:
    """The folder of "tum" images: the real TUM sample's rgb/, else its synthetic stand-in."""
    return REAL_TUM_RGB if REAL_TUM_RGB.is_dir() else stand_in("tum") / "rgb"


def euroc_rgb() -> Path:
    """The folder of "euroc" images: the real EuRoC sample's cam0/data, else a stand-in."""
    return REAL_EUROC_RGB if REAL_EUROC_RGB.is_dir() else stand_in("euroc") / "rgb"


@functools.lru_cache(maxsize=None)
def keypoints(which: str, index: int):
    """ORB-SLAM keypoints (KeypointSet) of frame ``index`` of ``tum`` or ``euroc``."""
    from orbslam_hgcn.features.orb import ORBExtractor

    folder = tum_rgb() if which == "tum" else euroc_rgb()
    path = sorted(folder.glob("*.png"))[index]
    return ORBExtractor().extract(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))


def descriptors(which: str, index: int) -> np.ndarray:
    """(N, 32) uint8 ORB-SLAM descriptors of frame ``index`` of ``tum`` or ``euroc``."""
    return keypoints(which, index).desc


def training_set() -> tuple[np.ndarray, np.ndarray]:
    """Descriptors of TUM frames 4..9 and EuRoC frames 20, 40, 60, 80 (not the query
    frames TUM 0, 1 and EuRoC 0), with the image of each."""
    frames = [("tum", i) for i in range(4, 10)] + [("euroc", i) for i in range(20, 81, 20)]
    parts = [descriptors(w, i) for w, i in frames]
    return np.concatenate(parts), np.repeat(np.arange(len(parts)), [len(p) for p in parts])


@functools.lru_cache(maxsize=None)
def small_orb_vocab():
    from orbslam_hgcn.vocabulary.orb_tree import train_tree_vocabulary

    desc, img = training_set()
    return train_tree_vocabulary(desc, img, k=10, levels=3, trained_on="test frames", progress=False)


SMALL_HGCN = HgcnTrainConfig(n_words=150, hidden_dim=16, epochs=6, eval_every=2, n_coarse=20, kmeans_iters=10)


@functools.lru_cache(maxsize=None)
def small_hgcn_vocab():
    from orbslam_hgcn.vocabulary.hgcn_vocab import train_hgcn_vocabulary

    desc, img = training_set()
    return train_hgcn_vocabulary(desc, img, SMALL_HGCN, trained_on="test frames", progress=False)


@functools.lru_cache(maxsize=None)
def small_kmeans_vocab():
    from orbslam_hgcn.vocabulary.flat import train_kmeans_vocabulary

    desc, img = training_set()
    return train_kmeans_vocabulary(desc, img, SMALL_HGCN, trained_on="test frames", progress=False)
