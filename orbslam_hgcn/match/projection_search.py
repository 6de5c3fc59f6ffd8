"""Guided matching of projected map points (ORB-SLAM's SearchByProjection and Fuse).

The caller projects its map points (it owns poses and points); these functions take the
projections as arrays and return, per point, the index of the matched keypoint or -1.
Rules follow ORB-SLAM's ORBmatcher (Mur-Artal, Montiel & Tardos, T-RO 2015).

:func:`search_by_projection` runs twice on every tracked frame and :func:`fuse_candidates`
for every neighbour of a new keyframe, with 10-100 candidate keypoints per point, so their
window scan (grid cells, window, level and reprojection tests, Hamming distance, best two
per point) is one compiled loop (:func:`_best_two_in_windows`, see
:mod:`orbslam_hgcn.compiled`) rather than numpy over the candidate pairs: 0.9 against 2.6 ms
for 400 points in a window of 4 px per level. It visits candidates in the order of
:meth:`FeatureGrid.candidate_pairs` and keeps the earliest on ties, as
:func:`~orbslam_hgcn.match.hamming.best_two_per_group` does, so the matches are the same.
The initialiser's search (:func:`~orbslam_hgcn.match.matching.search_for_initialization`,
2000 features in windows of 200 px) uses the same loop (:func:`scan_windows`): 1.7 against
16.9 ms per call.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from orbslam_hgcn.compiled import descriptor_words, jit, popcount64
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.match.hamming import (
    TH_HIGH,
    TH_LOW,
    apply_rotation_check,
    resolve_conflicts,
)

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


@jit
def _best_two_in_windows(
    x, y, r, lo, hi, qdesc, kdesc, kuv, koctave, order, start, available,
    min_x, min_y, inv_w, inv_h, cols, rows, inv_sigma2, chi2_gate,
):  # fmt: skip
    """Per query: the closest and second-closest (Hamming) keypoint inside its square
    window of half side r whose octave lies in [lo, hi] (a limit < 0: none), that is
    available and, when chi2_gate > 0, whose squared distance to (x, y) times the
    information of its level (inv_sigma2 by octave) is at most chi2_gate. Returns (best
    keypoint, best distance, second keypoint, second distance), each (M,) int64, -1 and
    1 << 30 where absent. qdesc (M, W), kdesc (N, W): uint64 words."""
    m = len(x)
    big = 1 << 30
    best_f = np.full(m, -1, np.int64)
    second_f = np.full(m, -1, np.int64)
    best_d = np.full(m, big, np.int64)
    second_d = np.full(m, big, np.int64)
    n_words = qdesc.shape[1]
    for i in range(m):
        c0f = math.floor((x[i] - min_x - r[i]) * inv_w)
        c1f = math.floor((x[i] - min_x + r[i]) * inv_w)
        r0f = math.floor((y[i] - min_y - r[i]) * inv_h)
        r1f = math.floor((y[i] - min_y + r[i]) * inv_h)
        if not (math.isfinite(c0f + c1f + r0f + r1f) and c1f >= 0 and c0f < cols and r1f >= 0 and r0f < rows):
            continue
        c0, c1 = int(max(c0f, 0.0)), int(min(c1f, cols - 1.0))
        r0, r1 = int(max(r0f, 0.0)), int(min(r1f, rows - 1.0))
        for row in range(r0, r1 + 1):
            for pos in range(start[row * cols + c0], start[row * cols + c1 + 1]):
                f = order[pos]
                if not (abs(kuv[f, 0] - x[i]) < r[i] and abs(kuv[f, 1] - y[i]) < r[i]):
                    continue
                oc = koctave[f]
                if (lo[i] >= 0 and oc < lo[i]) or (hi[i] >= 0 and oc > hi[i]) or not available[f]:
                    continue
                if chi2_gate > 0.0:
                    du, dv = kuv[f, 0] - x[i], kuv[f, 1] - y[i]
                    if (du * du + dv * dv) * inv_sigma2[oc] > chi2_gate:
                        continue
                d = 0
                for w in range(n_words):
                    d += popcount64(qdesc[i, w] ^ kdesc[f, w])
                if d < best_d[i]:
                    second_f[i], second_d[i] = best_f[i], best_d[i]
                    best_f[i], best_d[i] = f, d
                elif d < second_d[i]:
                    second_f[i], second_d[i] = f, d
    return best_f, best_d, second_f, second_d


def scan_windows(keypoints: KeypointSet, grid: FeatureGrid, x, y, r, lo, hi, desc, available, chi2_gate: float):
    """The two closest keypoints of ``grid`` (over ``keypoints``) to each query descriptor
    inside its window (:func:`_best_two_in_windows`): x, y, r: (M,) float window centres
    and half sides; lo, hi: (M,) int64 octave limits (-1: none); desc: (M, 32) uint8;
    available: (N,) bool; chi2_gate: 0 for none. Returns (best, best distance, second,
    second distance), each (M,) int64, -1 and 1 << 30 where absent."""
    return _best_two_in_windows(
        np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(y, dtype=np.float64),
        np.ascontiguousarray(r, dtype=np.float64), lo, hi, descriptor_words(desc), descriptor_words(keypoints.desc),
        grid.uv, grid.octave, grid.order, grid.start, available,
        grid.min_x, grid.min_y, grid.inv_w, grid.inv_h, grid.cols, grid.rows, keypoints.inv_level_sigma2, chi2_gate,
    )  # fmt: skip


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
    if m == 0 or len(keypoints) == 0:
        return np.full(m, -1, dtype=np.int64), np.full(m, 1 << 30, dtype=np.int64)
    lo = np.maximum(octave + level_range[0], 0)
    hi = octave + level_range[1]
    avail = np.ones(len(keypoints), dtype=bool) if available is None else np.asarray(available, dtype=bool)
    best, bd, second, sd = scan_windows(keypoints, grid, uv[:, 0], uv[:, 1], r, lo, hi, desc, avail, 0.0)
    ok = (best >= 0) & (bd <= max_dist)
    if ratio is not None:
        has2 = second >= 0
        same_level = np.zeros(m, dtype=bool)
        same_level[has2] = keypoints.octave[best[has2]] == keypoints.octave[second[has2]]
        ok &= ~(same_level & (bd > ratio * sd))
    match = np.where(ok, best, -1)
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
    everywhere = np.ones(len(keypoints), dtype=bool)
    best, bd, _, _ = scan_windows(
        keypoints, grid, uv[cand, 0], uv[cand, 1], r, lvl - 1, lvl, np.asarray(desc)[cand], everywhere, CHI2_MONO
    )
    good = (best >= 0) & (bd <= TH_LOW)
    match[cand[good]] = best[good]
    out_dist[cand[good]] = bd[good]
    return match, out_dist


def warm_problem() -> tuple[PinholeCamera, KeypointSet, FeatureGrid, np.ndarray]:
    """A tiny matching problem with the argument types of a real one (for the warm-ups):
    (camera, 4 keypoints, their grid, (4, 3) points in front of the camera that project
    onto them)."""
    camera = PinholeCamera(100.0, 100.0, 50.0, 50.0, 100, 100)
    uv = np.array([[20.0, 30.0], [60.0, 40.0], [45.0, 70.0], [75.0, 75.0]])
    X = np.column_stack([(uv - 50.0) / 100.0 * 2.0, np.full(len(uv), 2.0)])
    n = len(uv)
    kps = KeypointSet(
        uv_raw=uv.astype(np.float32), uv=uv, octave=np.zeros(n, np.int32), angle=np.zeros(n, np.float32),
        response=np.ones(n, np.float32), desc=np.zeros((n, 32), np.uint8), scale_factors=np.array([1.0, 1.2]),
    )  # fmt: skip
    return camera, kps, FeatureGrid(kps, camera), X


def warm_up() -> float:
    """Compile (first use after an install) or load from numba's cache the window scan of
    :func:`search_by_projection` and :func:`fuse_candidates`; returns the seconds it took."""
    t0 = time.perf_counter()
    camera, kps, grid, X = warm_problem()
    n = len(kps)
    search_by_projection(kps, grid, kps.uv, kps.octave, kps.desc, 2.0, ratio=0.8, available=np.ones(n, bool))
    fuse_candidates(
        kps, grid, camera, np.eye(4), X, kps.desc, X / np.linalg.norm(X, axis=1, keepdims=True),
        np.zeros(n), np.full(n, 10.0),
    )  # fmt: skip
    return time.perf_counter() - t0
