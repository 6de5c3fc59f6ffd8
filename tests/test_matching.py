"""Hamming distances, the feature grid and the descriptor matchers on synthetic keypoints."""

from __future__ import annotations

import cv2
import numpy as np

from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.epipolar import epipole, fundamental_12_from_poses
from orbslam_hgcn.geometry.se3 import make_T
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.match.hamming import hamming_matrix, hamming_pairs, rotation_consistency
from orbslam_hgcn.match.matching import (
    bow_candidate_pairs,
    brute_force_match,
    fuse_candidates,
    search_by_bow,
    search_by_projection,
    search_for_initialization,
    search_for_triangulation,
)
from orbslam_hgcn.vocabulary.bow import FeatureVector


# --- Hamming distances and the rotation check ------------------------------------------


def test_hamming_equals_bit_by_bit_reference():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (30, 32), dtype=np.uint8)
    ref = (np.unpackbits(a[:, None, :], axis=2) != np.unpackbits(b[None, :, :], axis=2)).sum(axis=2)
    np.testing.assert_array_equal(hamming_matrix(a, b), ref)
    i = rng.integers(0, 40, 100)
    j = rng.integers(0, 30, 100)
    np.testing.assert_array_equal(hamming_pairs(a[i], b[j]), ref[i, j])
    assert hamming_pairs(a[:5], a[:5]).tolist() == [0] * 5


def test_rotation_consistency_keeps_dominant_bins():
    rng = np.random.default_rng(1)
    diffs = np.concatenate([rng.normal(20.0, 2.0, 90), rng.uniform(60, 300, 10)])
    keep = rotation_consistency(diffs)
    assert keep[:90].mean() > 0.95
    assert keep[90:].mean() < 0.5


# --- Grid ----------------------------------------------------------------------------------


def _random_keypoints(rng, n, width=640, height=480, desc=None):
    uv = np.stack([rng.uniform(0, width, n), rng.uniform(0, height, n)], axis=1)
    return KeypointSet(
        uv_raw=uv.astype(np.float32),
        uv=uv,
        octave=rng.integers(0, 8, n).astype(np.int32),
        angle=rng.uniform(0, 360, n).astype(np.float32),
        response=rng.uniform(7, 100, n).astype(np.float32),
        desc=desc if desc is not None else rng.integers(0, 256, (n, 32), dtype=np.uint8),
        scale_factors=1.2 ** np.arange(8),
    )


CAM = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)


def test_feature_grid_equals_brute_force():
    rng = np.random.default_rng(4)
    kps = _random_keypoints(rng, 800)
    grid = FeatureGrid(kps, CAM)
    for _ in range(30):
        x, y = rng.uniform(-20, 660), rng.uniform(-20, 500)
        r = rng.uniform(1, 80)
        lo, hi = int(rng.integers(-1, 4)), int(rng.integers(-1, 8))
        got = grid.features_in_area(x, y, r, lo, hi)
        d = np.abs(kps.uv - [x, y])
        ok = (d[:, 0] < r) & (d[:, 1] < r)
        if lo >= 0:
            ok &= kps.octave >= lo
        if hi >= 0:
            ok &= kps.octave <= hi
        np.testing.assert_array_equal(got, np.flatnonzero(ok))


# --- Matchers ------------------------------------------------------------------------------


def _flip_bits(rng, desc, n_bits):
    out = desc.copy()
    for row in out:
        bits = rng.choice(256, n_bits, replace=False)
        row[bits // 8] ^= (1 << (bits % 8)).astype(np.uint8)
    return out


def test_search_by_projection_finds_known_correspondences():
    rng = np.random.default_rng(5)
    kps = _random_keypoints(rng, 1000)
    grid = FeatureGrid(kps, CAM)
    truth = rng.choice(1000, 300, replace=False)
    uv = kps.uv[truth] + rng.normal(0, 2.0, (300, 2))
    desc = _flip_bits(rng, kps.desc[truth], 20)
    match, dist = search_by_projection(kps, grid, uv, kps.octave[truth], desc, 15.0, level_range=(-1, 1))
    assert np.mean(match == truth) > 0.98
    assert np.all(dist[match >= 0] <= 100)
    # Points whose true keypoint is taken by another point find nothing else close enough.
    avail = np.ones(1000, bool)
    avail[truth[:50]] = False
    match2, _ = search_by_projection(kps, grid, uv, kps.octave[truth], desc, 15.0, level_range=(-1, 1), available=avail)
    assert np.all(match2[:50] == -1) and np.mean(match2[50:] == truth[50:]) > 0.98
    # A level window that excludes the true keypoint's level finds nothing for most points.
    wrong = (kps.octave[truth] + 4) % 8
    match3, _ = search_by_projection(kps, grid, uv, wrong, desc, 15.0, level_range=(0, 0))
    assert np.mean(match3 == truth) == 0.0


def test_search_by_projection_ratio_test_on_same_level_only():
    rng = np.random.default_rng(12)
    desc = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    twin = _flip_bits(rng, desc, 1)  # a near-identical distractor for every keypoint
    uv = np.array([[100.0, 100.0], [103.0, 100.0], [300.0, 300.0], [303.0, 300.0]])
    kps = KeypointSet(
        uv.astype(np.float32), uv, np.array([2, 2, 2, 3], np.int32), np.zeros(4, np.float32),
        np.ones(4, np.float32), np.stack([desc[0], twin[0], desc[2], twin[2]]), 1.2 ** np.arange(8),
    )
    grid = FeatureGrid(kps, CAM)
    # Queries far (20 bits) from both twins: best and second best are nearly equal.
    query = _flip_bits(rng, np.stack([desc[0], desc[2]]), 20)
    args = (kps, grid, np.array([[101.0, 100.0], [301.0, 300.0]]), np.array([3, 3]), query, 4.0)
    plain, _ = search_by_projection(*args, level_range=(-1, 0))
    ratio, _ = search_by_projection(*args, level_range=(-1, 0), ratio=0.8)
    assert plain[0] in (0, 1) and plain[1] in (2, 3)
    assert ratio[0] == -1  # ambiguous between two keypoints of one level: dropped
    assert ratio[1] == plain[1]  # ambiguous across levels: kept (ORB-SLAM's rule)


def test_search_by_projection_rotation_check_removes_inconsistent():
    rng = np.random.default_rng(6)
    kps = _random_keypoints(rng, 600)
    grid = FeatureGrid(kps, CAM)
    truth = rng.choice(600, 200, replace=False)
    ref_angle = kps.angle[truth] + 10.0 + rng.normal(0, 1.0, 200)
    ref_angle[:20] += rng.uniform(90, 270, 20)  # inconsistent orientation change
    match, _ = search_by_projection(
        kps, grid, kps.uv[truth], kps.octave[truth], kps.desc[truth], 5.0, ref_angle=ref_angle
    )
    assert np.all(match[:20] == -1)
    assert np.mean(match[20:] == truth[20:]) > 0.97


def test_search_for_initialization_on_shifted_keypoints():
    rng = np.random.default_rng(7)
    kps1 = _random_keypoints(rng, 500)
    kps1 = KeypointSet(
        kps1.uv_raw, kps1.uv, np.zeros(500, np.int32), kps1.angle, kps1.response, kps1.desc, kps1.scale_factors
    )
    shift = np.array([12.0, -7.0])
    perm = rng.permutation(500)
    uv2 = kps1.uv[perm] + shift + rng.normal(0, 0.5, (500, 2))
    kps2 = KeypointSet(
        uv2.astype(np.float32), uv2, np.zeros(500, np.int32), kps1.angle[perm] - 5.0, kps1.response[perm],
        _flip_bits(rng, kps1.desc[perm], 10), kps1.scale_factors,
    )
    m12, prev = search_for_initialization(kps1, kps2, FeatureGrid(kps2, CAM), kps1.uv, window=100)
    inv = np.argsort(perm)
    ok = m12 >= 0
    assert ok.mean() > 0.9
    np.testing.assert_array_equal(m12[ok], inv[ok])
    np.testing.assert_allclose(prev[ok], kps2.uv[m12[ok]])


def test_search_by_bow_only_matches_within_nodes():
    rng = np.random.default_rng(8)
    d1 = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    perm = rng.permutation(200)
    d2 = _flip_bits(rng, d1[perm], 8)
    inv = np.argsort(perm)  # feature i of image 1 is feature inv[i] of image 2
    node1 = rng.integers(0, 20, 200)
    node2 = node1[perm].copy()
    node2[inv[:30]] = (node2[inv[:30]] + 1) % 20  # these true partners sit under another node
    fv1 = FeatureVector.from_nodes(node1)
    fv2 = FeatureVector.from_nodes(node2)
    i1, i2 = bow_candidate_pairs(fv1, fv2)
    assert np.all(node1[i1] == node2[i2]) and len(i1) == sum(len(fv1[n]) * len(fv2.get(n, [])) for n in fv1)
    match = search_by_bow(fv1, fv2, d1, d2)
    assert np.all(match[:30] == -1)
    assert np.mean(match[30:] == inv[30:]) > 0.95


def _two_view_scene(rng, n=300):
    X = np.stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(4, 10, n)], axis=1)
    T_1w = np.eye(4)
    T_2w = make_T(cv2.Rodrigues(np.array([0.02, -0.08, 0.01]))[0], np.array([-0.8, 0.05, 0.1]))
    uv1, z1 = CAM.project(X)
    uv2, z2 = CAM.project(X @ T_2w[:3, :3].T + T_2w[:3, 3])
    ok = CAM.in_image(uv1, 20) & CAM.in_image(uv2, 20)
    return X[ok], uv1[ok], uv2[ok], T_1w, T_2w


def _kps_from(uv, desc, rng):
    n = len(uv)
    return KeypointSet(
        uv.astype(np.float32), uv, np.zeros(n, np.int32), rng.uniform(0, 1, n).astype(np.float32),
        np.ones(n, np.float32), desc, 1.2 ** np.arange(8),
    )


def test_search_for_triangulation_respects_epipolar_constraint():
    rng = np.random.default_rng(9)
    X, uv1, uv2, T_1w, T_2w = _two_view_scene(rng)
    n = len(X)
    d1 = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    d2 = _flip_bits(rng, d1, 10)
    # Swap the image-2 positions of 20 pairs of features: same descriptors, wrong geometry.
    uv2_bad = uv2.copy()
    uv2_bad[:20], uv2_bad[20:40] = uv2[20:40].copy(), uv2[:20].copy()
    kps1 = _kps_from(uv1, d1, rng)
    kps2 = _kps_from(uv2_bad, d2, rng)
    F12 = fundamental_12_from_poses(T_1w, T_2w, CAM.K, CAM.K)
    e2 = epipole(T_1w, T_2w, CAM.K)
    pairs = search_for_triangulation(kps1, kps2, F12, e2, pairs=None)
    got = dict(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist()))
    assert all(got.get(i, -1) == -1 for i in range(40))
    correct = [got.get(i, -1) == i for i in range(40, n)]
    assert np.mean(correct) > 0.95
    # Restricting to BoW candidate pairs (each feature alone under its own node) agrees.
    fv = FeatureVector.from_nodes(np.arange(n))
    pairs_bow = search_for_triangulation(kps1, kps2, F12, e2, pairs=bow_candidate_pairs(fv, fv))
    assert set(map(tuple, pairs_bow.tolist())) <= set(map(tuple, pairs.tolist()))
    assert len(pairs_bow) >= 0.95 * (n - 40)


def test_fuse_candidates_finds_projected_keypoints():
    rng = np.random.default_rng(10)
    X, uv1, _, T_1w, _ = _two_view_scene(rng)
    n = len(X)
    kps = _kps_from(uv1 + rng.normal(0, 0.5, uv1.shape), rng.integers(0, 256, (n, 32), dtype=np.uint8), rng)
    grid = FeatureGrid(kps, CAM)
    desc = _flip_bits(rng, kps.desc, 10)
    normals = X / np.linalg.norm(X, axis=1, keepdims=True)
    dist = np.linalg.norm(X, axis=1)
    match, _ = fuse_candidates(kps, grid, CAM, T_1w, X, desc, normals, dist / 2, dist * 1.1, th=3.0)
    assert np.mean(match == np.arange(n)) > 0.95
    # Points seen from behind (normals reversed) or out of their distance range are skipped.
    match_back, _ = fuse_candidates(kps, grid, CAM, T_1w, X, desc, -normals, dist / 2, dist * 1.1)
    assert np.all(match_back == -1)
    match_far, _ = fuse_candidates(kps, grid, CAM, T_1w, X, desc, normals, dist * 2, dist * 3)
    assert np.all(match_far == -1)


def test_brute_force_match_ratio_and_cross_check():
    rng = np.random.default_rng(11)
    d1 = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    perm = rng.permutation(300)
    d2 = _flip_bits(rng, d1[perm], 15)
    pairs = brute_force_match(d1, d2, ratio=0.8)
    assert len(pairs) > 280
    np.testing.assert_array_equal(perm[pairs[:, 1]], pairs[:, 0])
