"""Descriptor matchers of ORB-SLAM's front end, as functions over arrays.

Each function reproduces one ORBmatcher search of ORB-SLAM (Mur-Artal, Montiel & Tardos,
T-RO 2015) on whole arrays: candidates are generated as (query, target) index pairs, their
Hamming distances computed at once, and the best candidate per query chosen by sorting.
ORB-SLAM processes queries one after the other, so when two queries want the same target
the later one wins or is skipped depending on the search; here the closer query wins,
which does not depend on the order of the queries.

The projection searches (tracking, fusion) live in
:mod:`orbslam_hgcn.match.projection_search` and are re-exported here.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping

import cv2
import numpy as np

from orbslam_hgcn.compiled import descriptor_words, jit, popcount64
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.match.hamming import (
    TH_HIGH,
    TH_LOW,
    apply_rotation_check,
    best_two_per_group,
    hamming_matrix,
    hamming_pairs,
    resolve_conflicts,
)
from orbslam_hgcn.match.projection_search import (
    fuse_candidates,
    predict_octave,
    radius_by_viewing_cos,
    scan_windows,
    search_by_projection,
    warm_problem,
)

log = logging.getLogger(__name__)

__all__ = [
    "TH_HIGH",
    "TH_LOW",
    "bow_candidate_pairs",
    "brute_force_match",
    "fuse_candidates",
    "hamming_matrix",
    "hamming_pairs",
    "predict_octave",
    "radius_by_viewing_cos",
    "search_by_bow",
    "search_by_projection",
    "search_for_initialization",
    "search_for_initialization_tracks",
    "search_for_triangulation",
]

FeatureVector = Mapping[int, np.ndarray]  # vocabulary node id -> (k,) feature indices


def search_for_initialization(
    kps1: KeypointSet,
    kps2: KeypointSet,
    grid2: FeatureGrid,
    prev_matched_uv: np.ndarray,
    window: float = 100.0,
    ratio: float = 0.9,
    check_orientation: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """ORB-SLAM's SearchForInitialization: level-0 features of image 1 searched in image 2.

    Each level-0 keypoint i of image 1 is searched among the level-0 keypoints of image 2
    within a square window of half side ``window`` around ``prev_matched_uv[i]`` (its
    position in the previous image, initially its own). A match needs distance <= TH_LOW
    and best < ratio * second best (ORB-SLAM uses 0.9 here), then the rotation check.
    prev_matched_uv: (N1, 2) float. Returns ((N1,) int64 index into image 2 or -1, the
    updated (N1, 2) prev_matched_uv: matched keypoints move to their image-2 position).
    """
    n1 = len(kps1)
    prev = np.asarray(prev_matched_uv, dtype=np.float64).reshape(n1, 2)
    match = np.full(n1, -1, dtype=np.int64)
    q_idx = np.flatnonzero(kps1.octave == 0)
    if len(q_idx) and len(kps2):
        m = len(q_idx)
        level = np.zeros(m, dtype=np.int64)
        best, bd, _, sd = scan_windows(
            kps2, grid2, prev[q_idx, 0], prev[q_idx, 1], np.full(m, float(window)), level, level,
            kps1.desc[q_idx], np.ones(len(kps2), dtype=bool), 0.0,
        )  # fmt: skip
        ok = (best >= 0) & (bd <= TH_LOW) & (bd < ratio * sd)
        match[q_idx[ok]] = best[ok]
        dist = np.full(n1, 1 << 30, dtype=np.int64)
        dist[q_idx[ok]] = bd[ok]
        match = resolve_conflicts(match, dist)
    if check_orientation:
        match = apply_rotation_check(match, kps1.angle, kps2.angle)
    out = prev.copy()
    ok = match >= 0
    out[ok] = kps2.uv[match[ok]]
    return match, out



def search_for_initialization_tracks(
    desc: np.ndarray,
    octave: np.ndarray,
    angle: np.ndarray,
    centre: np.ndarray,
    kps2: KeypointSet,
    grid2: FeatureGrid,
    window: float,
    ratio: float = 0.9,
    level_slack: int = 1,
    check_orientation: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """The initialiser's frame-to-frame step: features followed from the previous image
    searched in image 2 (a variant of ORB-SLAM's SearchForInitialization, which searches
    only level-0 features of the reference, always with the reference's descriptors).

    Feature i (its descriptor ``desc[i]`` (32,) uint8, level ``octave[i]`` and orientation
    ``angle[i]`` degrees as last seen) is searched among the keypoints of image 2 within
    ``level_slack`` levels of its own, inside a square window of half side ``window``
    around ``centre[i]`` (M, 2) (its predicted position). A match needs distance <= TH_LOW
    and best < ratio * second best; a keypoint wanted by several features goes to the
    closest; then the rotation check against ``angle``.
    Returns ((M,) int64 index into image 2 or -1, (M,) int64 distance, 1 << 30 where none).
    """
    m = len(desc)
    match = np.full(m, -1, dtype=np.int64)
    dist = np.full(m, 1 << 30, dtype=np.int64)
    if m == 0 or len(kps2) == 0:
        return match, dist
    octave = np.asarray(octave, dtype=np.int64).reshape(m)
    lo = np.maximum(octave - level_slack, 0)
    hi = octave + level_slack
    centre = np.asarray(centre, dtype=np.float64).reshape(m, 2)
    best, bd, _, sd = scan_windows(
        kps2, grid2, centre[:, 0], centre[:, 1], np.full(m, float(window)), lo, hi, desc,
        np.ones(len(kps2), dtype=bool), 0.0,
    )  # fmt: skip
    ok = (best >= 0) & (bd <= TH_LOW) & (bd < ratio * sd)
    match[ok] = best[ok]
    dist[ok] = bd[ok]
    match = resolve_conflicts(match, dist)
    if check_orientation:
        match = apply_rotation_check(match, np.asarray(angle), kps2.angle)
    dist[match < 0] = 1 << 30
    return match, dist

def bow_candidate_pairs(featvec1: FeatureVector, featvec2: FeatureVector) -> tuple[np.ndarray, np.ndarray]:
    """All (i1, i2) feature pairs that share a vocabulary node.

    featvec1, featvec2: node id -> (k,) int feature indices (a FeatureVector).
    Returns ((K,) int64, (K,) int64) indices into image 1 and image 2.
    """
    n1, f1 = featvec1.flat()
    n2, f2 = featvec2.flat()
    if len(n1) == 0 or len(n2) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    o2 = np.argsort(n2, kind="stable")
    n2, f2 = n2[o2], f2[o2]
    lo = np.searchsorted(n2, n1, side="left")
    cnt = np.searchsorted(n2, n1, side="right") - lo
    total = int(cnt.sum())
    i1 = np.repeat(f1, cnt)
    pos = np.repeat(lo - (np.cumsum(cnt) - cnt), cnt) + np.arange(total)
    return i1, f2[pos]


def search_by_bow(
    featvec1: FeatureVector,
    featvec2: FeatureVector,
    desc1: np.ndarray,
    desc2: np.ndarray,
    angle1: np.ndarray | None = None,
    angle2: np.ndarray | None = None,
    valid1: np.ndarray | None = None,
    valid2: np.ndarray | None = None,
    ratio: float = 0.75,
) -> np.ndarray:
    """ORB-SLAM's SearchByBoW: matches only between features under the same vocabulary node.

    desc1: (N1, 32), desc2: (N2, 32) uint8; valid1 / valid2: (N1,) / (N2,) bool features
    allowed to match (ORB-SLAM: those with a map point), None for all. A match needs
    distance < TH_LOW and best < ratio * second best (ORB-SLAM: 0.75 for relocalisation
    and loop closing, 0.7 for tracking the reference keyframe). With both angle arrays
    ((N1,), (N2,) degrees) the rotation check is applied.
    Returns (N1,) int64 index into image 2 or -1.
    """
    n1 = len(desc1)
    match = np.full(n1, -1, dtype=np.int64)
    i1, i2 = bow_candidate_pairs(featvec1, featvec2)
    keep = np.ones(len(i1), dtype=bool)
    if valid1 is not None:
        keep &= np.asarray(valid1, dtype=bool)[i1]
    if valid2 is not None:
        keep &= np.asarray(valid2, dtype=bool)[i2]
    i1, i2 = i1[keep], i2[keep]
    d = hamming_pairs(desc1[i1], desc2[i2])
    bp, bd, _, sd = best_two_per_group(i1, d, n1)
    ok = (bp >= 0) & (bd < TH_LOW) & (bd < ratio * sd)
    match[ok] = i2[bp[ok]]
    match = resolve_conflicts(match, bd)
    if angle1 is not None and angle2 is not None:
        match = apply_rotation_check(match, np.asarray(angle1), np.asarray(angle2))
    return match


@jit
def _triangulation_candidates(i1, i2, d1, d2, uv1, uv2, oct2, scale2, sigma2_2, F, e, avail1, avail2, n1, th_low):
    """The closest acceptable candidate of every image-1 feature for
    :func:`search_for_triangulation`: ((n1,) position in the candidate arrays or -1,
    (n1,) its Hamming distance, 1 << 30 where none). Ties keep the earliest candidate."""
    best_pos = np.full(n1, -1, dtype=np.int64)
    best = np.full(n1, 1 << 30, dtype=np.int64)
    for k in range(len(i1)):
        a, b = i1[k], i2[k]
        if not (avail1[a] and avail2[b]):
            continue
        d = 0
        for w in range(d1.shape[1]):
            d += popcount64(d1[a, w] ^ d2[b, w])
        if d > th_low or d >= best[a]:
            continue
        u2, v2 = uv2[b, 0], uv2[b, 1]
        o = oct2[b]
        if (u2 - e[0]) ** 2 + (v2 - e[1]) ** 2 < 100.0 * scale2[o]:
            continue  # too close to the epipole
        u1, v1 = uv1[a, 0], uv1[a, 1]
        l0 = u1 * F[0, 0] + v1 * F[1, 0] + F[2, 0]  # epipolar line of x1 in image 2: x1^T F12
        l1 = u1 * F[0, 1] + v1 * F[1, 1] + F[2, 1]
        l2 = u1 * F[0, 2] + v1 * F[1, 2] + F[2, 2]
        num = l0 * u2 + l1 * v2 + l2
        den = l0 * l0 + l1 * l1
        if not (den > 0.0 and num * num / den < 3.84 * sigma2_2[o]):
            continue
        best[a] = d
        best_pos[a] = k
    return best_pos, best


def search_for_triangulation(
    kps1: KeypointSet,
    kps2: KeypointSet,
    F12: np.ndarray,
    epipole2: np.ndarray,
    pairs: tuple[np.ndarray, np.ndarray] | None = None,
    avail1: np.ndarray | None = None,
    avail2: np.ndarray | None = None,
    check_orientation: bool = True,
) -> np.ndarray:
    """ORB-SLAM's SearchForTriangulation: unmatched features fulfilling the epipolar constraint.

    F12: (3, 3) fundamental matrix with ``x1^T F12 x2 = 0`` (undistorted pixels);
    epipole2: (2,) projection of camera 1's centre in image 2; pairs: candidate (i1, i2)
    arrays, typically :func:`bow_candidate_pairs` of the two feature vectors, or None for
    all pairs (brute force); avail1 / avail2: (N1,) / (N2,) bool features still without a
    map point, None for all. A candidate needs distance <= TH_LOW, image-2 keypoint farther
    than ``10 sqrt(scale)`` px from the epipole, and squared distance to the epipolar line
    below ``3.84 sigma2`` of its level; the closest candidate of each feature of image 1
    is kept, then each image-2 feature keeps its closest partner, then the rotation check.
    Returns (K, 2) int64 index pairs (i1, i2).
    """
    if pairs is None:
        i1 = np.repeat(np.arange(len(kps1)), len(kps2))
        i2 = np.tile(np.arange(len(kps2)), len(kps1))
    else:
        i1, i2 = (np.ascontiguousarray(p, dtype=np.int64) for p in pairs)
    n1, n2 = len(kps1), len(kps2)
    a1 = np.ones(n1, dtype=bool) if avail1 is None else np.ascontiguousarray(avail1, dtype=bool)
    a2 = np.ones(n2, dtype=bool) if avail2 is None else np.ascontiguousarray(avail2, dtype=bool)
    bp, bd = _triangulation_candidates(
        i1, i2, descriptor_words(kps1.desc), descriptor_words(kps2.desc), kps1.uv, kps2.uv,
        kps2.octave.astype(np.int64),
        np.asarray(kps2.scale_factors, dtype=np.float64), np.asarray(kps2.level_sigma2, dtype=np.float64),
        np.ascontiguousarray(F12, dtype=np.float64), np.asarray(epipole2, dtype=np.float64).reshape(2),
        a1, a2, n1, TH_LOW,
    )  # fmt: skip
    match = np.full(n1, -1, dtype=np.int64)
    ok = bp >= 0
    match[ok] = i2[bp[ok]]
    match = resolve_conflicts(match, bd)
    if check_orientation:
        match = apply_rotation_check(match, kps1.angle, kps2.angle)
    q = np.flatnonzero(match >= 0)
    return np.stack([q, match[q]], axis=1)


def brute_force_match(
    desc1: np.ndarray,
    desc2: np.ndarray,
    ratio: float = 0.8,
    cross_check: bool = True,
    max_dist: int = TH_HIGH,
) -> np.ndarray:
    """All-pairs matching with Lowe's ratio test and an optional mutual-best check.

    desc1: (N1, 32), desc2: (N2, 32) uint8. Returns (K, 2) int64 index pairs (i1, i2)
    with distance <= max_dist and best < ratio * second best (OpenCV's batchDistance
    finds the two nearest neighbours).
    """
    d1 = np.ascontiguousarray(desc1, dtype=np.uint8)
    d2 = np.ascontiguousarray(desc2, dtype=np.uint8)
    if len(d1) == 0 or len(d2) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    k = min(2, len(d2))
    dist, nidx = cv2.batchDistance(d1, d2, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=k)
    best = nidx[:, 0].astype(np.int64)
    bd = dist[:, 0].astype(np.int64)
    sd = dist[:, 1].astype(np.int64) if k == 2 else np.full(len(d1), 1 << 30)
    ok = (best >= 0) & (bd <= max_dist) & (bd < ratio * sd)
    if cross_check:
        _, back = cv2.batchDistance(d2, d1, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=1)
        ok &= back[np.clip(best, 0, len(d2) - 1), 0] == np.arange(len(d1))
    q = np.flatnonzero(ok)
    return np.stack([q, best[q]], axis=1).astype(np.int64)


def warm_up() -> float:
    """Compile (first use after an install) or load from numba's cache the kernels of
    :func:`search_for_triangulation`; returns the seconds it took."""
    t0 = time.perf_counter()
    _, kps, _, _ = warm_problem()
    pairs = (np.arange(len(kps), dtype=np.int64), np.arange(len(kps), dtype=np.int64))
    search_for_triangulation(kps, kps, np.eye(3), np.array([500.0, 500.0]), pairs)
    return time.perf_counter() - t0
