"""Feature tracks across consecutive training images, for the HGCN's shared labels.

The paper seeds one label on all descriptors of the same 3D point seen in several
keyframes. Without a map, tracks are built by matching each training image to the next
image of the same sequence: mutual nearest neighbours in Hamming distance (binary
descriptors; Euclidean for float ones such as SIFT) that pass Lowe's ratio test (IJCV 2004)
and, for binary descriptors, a distance bound, verified by a RANSAC fundamental
matrix (``cv2.findFundamentalMat``); matched descriptors are joined into tracks (connected
components of the match graph).
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from tqdm import tqdm

from orbslam_hgcn.match.hamming import hamming_matrix

log = logging.getLogger(__name__)


def match_pair(d1: np.ndarray, d2: np.ndarray, uv1: np.ndarray, uv2: np.ndarray, max_hamming: int = 64,
               ratio: float = 0.8, ransac_px: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Verified matches between two images: ((K,) indices into image 1, (K,) into image 2).

    d1, d2: (N1, 32), (N2, 32) uint8 descriptors (Hamming distance, at most
    ``max_hamming``) or (N, D) float ones (Euclidean distance, no bound); uv1, uv2: (N, 2)
    pixel positions.
    """
    empty = np.zeros(0, np.int64)
    if len(d1) < 8 or len(d2) < 8:
        return empty, empty
    if d1.dtype == np.uint8:
        dist = hamming_matrix(d1, d2)
        bound = max_hamming
    else:
        a, b = np.asarray(d1, np.float32), np.asarray(d2, np.float32)
        sq = np.einsum("nd,nd->n", a, a)[:, None] + np.einsum("nd,nd->n", b, b)[None, :] - 2.0 * a @ b.T
        dist, bound = np.sqrt(np.maximum(sq, 0.0)), np.inf
    nn12 = np.argmin(dist, axis=1)
    two = np.partition(dist, 1, axis=1)[:, :2]
    nn21 = np.argmin(dist, axis=0)
    i1 = np.flatnonzero((nn21[nn12] == np.arange(len(d1))) & (two[:, 0] <= bound)
                        & (two[:, 0] < ratio * two[:, 1]))
    i2 = nn12[i1]
    if len(i1) < 8:
        return empty, empty
    _, mask = cv2.findFundamentalMat(uv1[i1].astype(np.float64), uv2[i2].astype(np.float64), cv2.FM_RANSAC,
                                     ransac_px, 0.999)
    if mask is None:
        return empty, empty
    inl = mask.reshape(-1).astype(bool)
    return i1[inl], i2[inl]


def build_tracks(desc: list[np.ndarray], uv: list[np.ndarray], groups: np.ndarray, progress: bool = True,
                 **match_kw) -> np.ndarray:
    """Track id of every descriptor of a list of images (-1: seen once).

    desc, uv: per image, (N_i, 32) uint8 (or (N_i, D) float) descriptors and (N_i, 2) positions. groups: (I,)
    sequence of each image; images i and i+1 of the same group are matched.
    Returns (sum N_i,) int64 track ids; a track never holds two descriptors of one image.
    """
    sizes = np.array([len(d) for d in desc], np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    total = int(sizes.sum())
    rows, cols = [], []
    pairs = [i for i in range(len(desc) - 1) if groups[i] == groups[i + 1]]
    for i in tqdm(pairs, desc="matching for tracks", unit="pair", disable=not progress):
        a, b = match_pair(desc[i], desc[i + 1], uv[i], uv[i + 1], **match_kw)
        rows.append(offsets[i] + a)
        cols.append(offsets[i + 1] + b)
    track = np.full(total, -1, np.int64)
    if not rows or not sum(len(r) for r in rows):
        return track
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = sp.coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(total, total))
    _, comp = connected_components(graph, directed=False)
    size = np.bincount(comp)
    image = np.repeat(np.arange(len(desc)), sizes)
    # A component holding two descriptors of one image is a chain of mismatches: drop it.
    key = np.unique(comp * np.int64(len(desc)) + image)
    distinct_images = np.bincount(key // len(desc), minlength=len(size))
    good = (size >= 2) & (distinct_images == size)
    ok = good[comp]
    _, track[ok] = np.unique(comp[ok], return_inverse=True)
    n_tracks = int(good.sum())
    log.info("tracks: %d matches over %d image pairs, %d tracks covering %d descriptors (mean length %.1f)",
             len(r), len(pairs), n_tracks, int(ok.sum()), ok.sum() / max(n_tracks, 1))
    return track
