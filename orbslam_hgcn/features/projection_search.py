"""Guided matching of projected map points (ORB-SLAM's SearchByProjection and Fuse).

The caller projects its map points (it owns poses and points); these functions take the
projections as arrays and return, per point, the index of the matched keypoint or -1.
Rules follow ORB-SLAM's ORBmatcher (Mur-Artal, Montiel & Tardos, T-RO 2015).
"""

from __future__ import annotations

import logging

import numpy as np

from orbslam_hgcn.features.grid import FeatureGrid
from orbslam_hgcn.features.hamming import (
    TH_HIGH,
    TH_LOW,
    apply_rotation_check,
    best_two_per_group,
    hamming_pairs,
    resolve_conflicts,
)
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)

CHI2_MONO = 5.991  # chi-square 95% for 2 DoF: reprojection gate of Fuse (ORB-SLAM: 5.99)


def predict_octave(max_distance: np.ndarray, distance: np.ndarray, scale_factor: float, n_levels: int) -> np.ndarray:
    """(M,) int64 pyramid level at which a point should appear (ORB-SLAM MapPoint::PredictScale).

    max_distance: (M,) the point's scale-invariance upper distance; distance: (M,) its
    current distance to the camera. Level ``ceil(log(max_distance / distance) / log(s))``
    clamped to [0, n_levels - 1].
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.asarray(max_distance, dtype=np.float64) / np.asarray(distance, dtype=np.float64)
        lvl = np.ceil(np.log(ratio) / np.log(scale_factor))
    lvl = np.nan_to_num(lvl, nan=0.0, posinf=n_levels - 1, neginf=0.0)
    return np.clip(lvl, 0, n_levels - 1).astype(np.int64)


def radius_by_viewing_cos(view_cos: np.ndarray) -> np.ndarray:
    """(M,) search radius factor: 2.5 when viewed almost head-on (cos > 0.998), else 4.0."""
    return np.where(np.asarray(view_cos) > 0.998, 2.5, 4.0)


def search_by_projection(
    keypoints: KeypointSet,
    grid: FeatureGrid,
    uv: np.ndarray,
    octave: np.ndarray,
    desc: np.ndarray,
    radius_factor: np.ndarray | float = 1.0,
    *,
    level_range: tuple[int, int] = (-1, 0),
    max_dist: int = TH_HIGH,
    ratio: float | None = None,
    ref_angle: np.ndarray | None = None,
    available: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Match projected points to the keypoints around their projection.

    uv: (M, 2) undistorted projections; octave: (M,) predicted level (the observing
    keypoint's level for the motion model, PredictScale for the local map); desc: (M, 32)
    point descriptors; radius_factor: (M,) or scalar, the window half side is
    ``radius_factor * scale_factors[octave]`` (ORB-SLAM: th = 15 for the monocular motion
    model; th * radius_by_viewing_cos for the local map); level_range: keypoint levels
    allowed relative to ``octave`` (ORB-SLAM: (-1, 1) motion model, (-1, 0) local map);
    ratio: with a value (ORB-SLAM local map: 0.8), the best is rejected when the second
    best lies on the same level and ``best > ratio * second``; ref_angle: (M,) angles of
    the points' reference keypoints to apply the rotation check (motion model), None to
    skip it; available: (N,) bool keypoints that may be matched, None for all.
    A keypoint wanted by several points goes to the closest one.
    Returns ((M,) int64 keypoint index or -1, (M,) int64 distance, 1 << 30 where none).
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    m = len(uv)
    octave = np.asarray(octave, dtype=np.int64).reshape(m)
    scale = keypoints.scale_factors[np.clip(octave, 0, keypoints.n_levels - 1)]
    r = np.broadcast_to(np.asarray(radius_factor, dtype=np.float64), (m,)) * scale
    q, f = grid.candidate_pairs(
        uv[:, 0], uv[:, 1], r, np.maximum(octave + level_range[0], 0), octave + level_range[1]
    )
    if available is not None:
        keep = np.asarray(available, dtype=bool)[f]
        q, f = q[keep], f[keep]
    d = hamming_pairs(np.asarray(desc)[q], keypoints.desc[f])
    bp, bd, sp, sd = best_two_per_group(q, d, m)
    ok = (bp >= 0) & (bd <= max_dist)
    if ratio is not None:
        has2 = sp >= 0
        same_level = np.zeros(m, dtype=bool)
        same_level[has2] = keypoints.octave[f[bp[has2]]] == keypoints.octave[f[sp[has2]]]
        ok &= ~(same_level & (bd > ratio * sd))
    match = np.full(m, -1, dtype=np.int64)
    match[ok] = f[bp[ok]]
    match = resolve_conflicts(match, bd)
    if ref_angle is not None:
        match = apply_rotation_check(match, np.asarray(ref_angle), keypoints.angle)
    dist = np.where(match >= 0, bd, 1 << 30)
    return match, dist


def fuse_candidates(
    keypoints: KeypointSet,
    grid: FeatureGrid,
    camera: PinholeCamera,
    T_cw: np.ndarray,
    points_w: np.ndarray,
    desc: np.ndarray,
    normals: np.ndarray,
    min_distance: np.ndarray,
    max_distance: np.ndarray,
    th: float = 3.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints of a keyframe onto which map points should be fused (ORB-SLAM Fuse).

    T_cw: (4, 4) keyframe pose; points_w: (M, 3) world points; desc: (M, 32); normals:
    (M, 3) unit mean viewing directions; min_distance / max_distance: (M,) scale
    invariance range. A point is searched when it projects in front of the camera inside
    the image, its distance lies in its range and it is seen within 60 degrees of its
    normal; the window is ``th * scale_factors[predicted level]``; a keypoint must lie on
    the predicted level or the one below, within the 95% reprojection gate of its level,
    and have distance <= TH_LOW. Several points may pick the same keypoint (the map merges
    them). Returns ((M,) int64 keypoint index or -1, (M,) int64 distance, 1 << 30 where none).
    """
    X = np.asarray(points_w, dtype=np.float64).reshape(-1, 3)
    m = len(X)
    T_cw = np.asarray(T_cw, dtype=np.float64)
    X_c = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    uv, z = camera.project(X_c)
    center = -T_cw[:3, :3].T @ T_cw[:3, 3]
    PO = X - center
    dist3 = np.linalg.norm(PO, axis=1)
    with np.errstate(invalid="ignore"):
        ok = (
            (z > 0)
            & (uv[:, 0] >= grid.min_x)
            & (uv[:, 0] < grid.max_x)
            & (uv[:, 1] >= grid.min_y)
            & (uv[:, 1] < grid.max_y)
            & (dist3 >= min_distance)
            & (dist3 <= max_distance)
            & (np.sum(PO * normals, axis=1) >= 0.5 * dist3)
        )
    match = np.full(m, -1, dtype=np.int64)
    out_dist = np.full(m, 1 << 30, dtype=np.int64)
    cand = np.flatnonzero(ok)
    if len(cand) == 0 or len(keypoints) == 0:
        return match, out_dist
    sf = float(keypoints.scale_factors[1]) if keypoints.n_levels > 1 else 1.2
    lvl = predict_octave(np.asarray(max_distance)[cand], dist3[cand], sf, keypoints.n_levels)
    r = th * keypoints.scale_factors[lvl]
    q, f = grid.candidate_pairs(uv[cand, 0], uv[cand, 1], r)
    ko = keypoints.octave[f]
    e2 = np.sum((keypoints.uv[f] - uv[cand[q]]) ** 2, axis=1)
    keep = (ko >= lvl[q] - 1) & (ko <= lvl[q]) & (e2 * keypoints.inv_level_sigma2[ko] <= CHI2_MONO)
    q, f = q[keep], f[keep]
    d = hamming_pairs(np.asarray(desc)[cand[q]], keypoints.desc[f])
    bp, bd, _, _ = best_two_per_group(q, d, len(cand))
    good = (bp >= 0) & (bd <= TH_LOW)
    match[cand[good]] = f[bp[good]]
    out_dist[cand[good]] = bd[good]
    return match, out_dist
