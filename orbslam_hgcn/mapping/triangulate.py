"""New map points by triangulation between a new keyframe and its covisible keyframes.

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. VI-C; LocalMapping::CreateNewMapPoints
of ORB-SLAM2, monocular): for each of the 20 best covisible keyframes whose baseline is at
least 1% of its median scene depth, the features without a point are matched under the
epipolar constraint (squared distance to the epipolar line below 3.84 sigma^2 of the
level, away from the epipole, Hamming distance at most 50), and each match is triangulated
and kept when the rays have parallax, the point lies in front of both cameras, reprojects
within the chi-square 95% gate (5.991 sigma^2) in both and its distances to the two
centres agree with the scales of its two keypoints.

Candidate pairs come from the vocabulary (features under one node, as ORB-SLAM) when the
keyframes carry feature vectors; otherwise every pair passing the epipolar test, found
with one (N1, N2) matrix product per neighbour.
"""

from __future__ import annotations

import logging

import numpy as np

from orbslam_hgcn.config import LocalMappingConfig
from orbslam_hgcn.geometry.epipolar import epipole, fundamental_12_from_poses
from orbslam_hgcn.geometry.triangulation import triangulate_checked
from orbslam_hgcn.map import KeyFrame, Map
from orbslam_hgcn.match.matching import bow_candidate_pairs, search_for_triangulation

log = logging.getLogger(__name__)

EPIPOLAR_CHI2 = 3.84  # chi-square 95% for 1 DoF: distance of a point to its epipolar line


def scene_median_depth(kf: KeyFrame, m: Map) -> float:
    """Median depth of the keyframe's points in its camera (ORB-SLAM ComputeSceneMedianDepth(2));
    nan without points."""
    _, pids = kf.observed_points()
    if len(pids) == 0:
        return float("nan")
    X = m.positions(pids)
    return float(np.median(X @ kf.T_cw[2, :3] + kf.T_cw[2, 3]))


def epipolar_candidate_pairs(
    uv1: np.ndarray,
    uv2: np.ndarray,
    sigma2_2: np.ndarray,
    F12: np.ndarray,
    avail1: np.ndarray,
    avail2: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """All (i1, i2) pairs of available features with x2 near the epipolar line of x1.

    uv1: (N1, 2), uv2: (N2, 2) undistorted pixels; sigma2_2: (N2,) level variances of image
    2; F12: (3, 3) with x1^T F12 x2 = 0; avail1/avail2: (N1,)/(N2,) bool.
    Returns ((K,) int64, (K,) int64) indices, squared line distance < 3.84 sigma2_2.
    """
    a1 = np.flatnonzero(avail1)
    a2 = np.flatnonzero(avail2)
    if len(a1) == 0 or len(a2) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lines = uv1[a1] @ F12[:2, :] + F12[2, :]  # (n1, 3): l2 = x1^T F12
    lines /= np.sqrt(np.maximum(lines[:, 0] ** 2 + lines[:, 1] ** 2, 1e-300))[:, None]
    lines32 = lines.astype(np.float32)
    dist = lines32[:, :2] @ uv2[a2].T.astype(np.float32)  # (n1, n2) signed distances
    dist += lines32[:, 2:3]
    np.abs(dist, out=dist)
    r, c = np.nonzero(dist < np.sqrt(EPIPOLAR_CHI2 * sigma2_2[a2]).astype(np.float32))
    return a1[r].astype(np.int64), a2[c].astype(np.int64)


def triangulate_with_neighbour(
    m: Map, kf1: KeyFrame, kf2: KeyFrame, config: LocalMappingConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Matches of kf1 with kf2 triangulated and checked, not yet in the map.

    Returns ((K, 3) world points, (K,) slots in kf1, (K,) slots in kf2); empty when the
    baseline is too short for kf2's depth.
    """
    empty = (np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64))
    baseline = float(np.linalg.norm(kf2.center - kf1.center))
    median = scene_median_depth(kf2, m)
    if not np.isfinite(median) or median <= 0 or baseline / median < config.min_baseline_ratio:
        return empty
    K1, K2 = kf1.camera.K, kf2.camera.K
    F12 = fundamental_12_from_poses(kf1.T_cw, kf2.T_cw, K1, K2)
    e2 = epipole(kf1.T_cw, kf2.T_cw, K2)
    kp1, kp2 = kf1.keypoints, kf2.keypoints
    avail1 = kf1.point_ids < 0
    avail2 = kf2.point_ids < 0
    if kf1.featvec is not None and kf2.featvec is not None:
        pairs = bow_candidate_pairs(kf1.featvec, kf2.featvec)
    else:
        pairs = epipolar_candidate_pairs(kp1.uv, kp2.uv, kp2.level_sigma2[kp2.octave], F12, avail1, avail2)
    matches = search_for_triangulation(
        kp1, kp2, F12, e2, pairs, avail1, avail2, check_orientation=config.triangulation_check_orientation
    )
    if len(matches) == 0:
        return empty
    i1, i2 = matches[:, 0], matches[:, 1]
    o1, o2 = kp1.octave[i1], kp2.octave[i2]
    X, good = triangulate_checked(
        K1, kf1.T_cw, kp1.uv[i1], kp1.level_sigma2[o1],
        K2, kf2.T_cw, kp2.uv[i2], kp2.level_sigma2[o2],
        kp1.scale_factors[o1], kp2.scale_factors[o2], float(kp1.scale_factors[1]),
    )  # fmt: skip
    return X[good], i1[good], i2[good]


def create_new_points(m: Map, kf: KeyFrame, config: LocalMappingConfig) -> np.ndarray:
    """Triangulate ``kf`` against its best covisible keyframes and add the points to the
    map (both observations, descriptor, viewing range). Returns (P,) new point ids.

    The map lock is held for one neighbour at a time, so the tracker waits for at most
    one neighbour's matching (threaded mode)."""
    with m.lock:
        neighbours = m.covisible_keyframes(kf.id, config.triangulation_neighbours)
    new_ids: list[np.ndarray] = []
    for k2 in neighbours:
        with m.lock:
            kf2 = m.keyframe(int(k2))
            if kf2.bad or kf.bad:
                continue
            X, s1, s2 = triangulate_with_neighbour(m, kf, kf2, config)
            if len(X) == 0:
                continue
            # Slots may have been taken by the points of an earlier neighbour.
            free = (kf.point_ids[s1] < 0) & (kf2.point_ids[s2] < 0)
            X, s1, s2 = X[free], s1[free], s2[free]
            pids = m.add_map_points(X, kf.id)
            m.add_observations(kf.id, pids, s1)
            m.add_observations(kf2.id, pids, s2)
            m.update_points(pids)
        new_ids.append(pids)
    return np.concatenate(new_ids) if new_ids else np.zeros(0, dtype=np.int64)
