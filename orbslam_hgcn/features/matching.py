"""Descriptor matchers of ORB-SLAM's front end, as functions over arrays.

Each function reproduces one ORBmatcher search of ORB-SLAM (Mur-Artal, Montiel & Tardos,
T-RO 2015) on whole arrays: candidates are generated as (query, target) index pairs, their
Hamming distances computed at once, and the best candidate per query chosen by sorting.
ORB-SLAM processes queries one after the other, so when two queries want the same target
the later one wins or is skipped depending on the search; here the closer query wins,
which does not depend on the order of the queries.

The projection searches (tracking, fusion) live in
:mod:`orbslam_hgcn.features.projection_search` and are re-exported here.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import cv2
import numpy as np

from orbslam_hgcn.features.grid import FeatureGrid
from orbslam_hgcn.features.hamming import (
    TH_HIGH,
    TH_LOW,
    apply_rotation_check,
    best_two_per_group,
    hamming_matrix,
    hamming_pairs,
    resolve_conflicts,
)
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.features.projection_search import (
    fuse_candidates,
    predict_octave,
    radius_by_viewing_cos,
    scan_windows,
    search_by_projection,
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


def bow_candidate_pairs(featvec1: FeatureVector, featvec2: FeatureVector) -> tuple[np.ndarray, np.ndarray]:
    """All (i1, i2) feature pairs that share a vocabulary node.

    featvec1, featvec2: node id -> (k,) int feature indices (a FeatureVector).
    Returns ((K,) int64, (K,) int64) indices into image 1 and image 2.
    """

    def flat(fv: FeatureVector) -> tuple[np.ndarray, np.ndarray]:
        if not fv:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        idx = [np.asarray(v, dtype=np.int64).reshape(-1) for v in fv.values()]
        nodes = np.repeat(np.fromiter(fv.keys(), dtype=np.int64, count=len(fv)), [len(i) for i in idx])
        return nodes, np.concatenate(idx)

    n1, f1 = flat(featvec1)
    n2, f2 = flat(featvec2)
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
        i1, i2 = (np.asarray(p, dtype=np.int64) for p in pairs)
    keep = np.ones(len(i1), dtype=bool)
    if avail1 is not None:
        keep &= np.asarray(avail1, dtype=bool)[i1]
    if avail2 is not None:
        keep &= np.asarray(avail2, dtype=bool)[i2]
    i1, i2 = i1[keep], i2[keep]
    d = hamming_pairs(kps1.desc[i1], kps2.desc[i2])
    keep = d <= TH_LOW
    i1, i2, d = i1[keep], i2[keep], d[keep]
    uv1 = kps1.uv[i1]
    uv2 = kps2.uv[i2]
    oct2 = kps2.octave[i2]
    e = np.asarray(epipole2, dtype=np.float64).reshape(2)
    far = np.sum((uv2 - e) ** 2, axis=1) >= 100.0 * kps2.scale_factors[oct2]
    # Epipolar line in image 2 of x1: l2 = x1^T F12.
    F = np.asarray(F12, dtype=np.float64)
    line = uv1 @ F[:2, :] + F[2, :]
    num = line[:, 0] * uv2[:, 0] + line[:, 1] * uv2[:, 1] + line[:, 2]
    den = line[:, 0] ** 2 + line[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        on_line = (den > 0) & (num * num / den < 3.84 * kps2.level_sigma2[oct2])
    keep = far & on_line
    i1, i2, d = i1[keep], i2[keep], d[keep]
    n1 = len(kps1)
    bp, bd, _, _ = best_two_per_group(i1, d, n1)
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
