"""Two-view initialisation, triangulation, PnP and Sim(3) solvers on known geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from orbslam_hgcn.config import InitializerConfig, load_camera
from orbslam_hgcn.features.orb import ORBExtractor
from orbslam_hgcn.geometry.epipolar import (
    decompose_essential,
    epipolar_sq_distances,
    fundamental_12_from_poses,
    fundamental_from_pose,
    relative_pose,
)
from orbslam_hgcn.geometry.pnp import solve_pnp_ransac
from orbslam_hgcn.geometry.se3 import angle_between_deg, inv_T, make_T, rotation_angle_deg
from orbslam_hgcn.geometry.sim3 import horn_similarity, sim3_ransac
from orbslam_hgcn.geometry.triangulation import projection_matrix, triangulate_checked, triangulate_dlt
from orbslam_hgcn.geometry.two_view import TwoViewInitializer, homography_motions
from orbslam_hgcn.match.matching import brute_force_match
from orbslam_hgcn.trajectory import read_tum

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def _project(T_cw, X):
    Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    return (Xc[:, :2] / Xc[:, 2:]) * [K[0, 0], K[1, 1]] + K[:2, 2], Xc[:, 2]


def _in_image(uv):
    return (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)


def _two_view_matches(rng, R21, t21, planar, n=300, noise=0.5, outliers=0.2):
    """Matched pixels of points seen by camera 1 (at the origin) and camera 2 = (R21, t21)."""
    uv = rng.uniform([0, 0], [640, 480], (4 * n, 2))
    rays = np.concatenate([(uv - K[:2, 2]) / K[0, 0], np.ones((len(uv), 1))], axis=1)
    if planar:  # a plane 4 m away tilted by 60 degrees about the x axis
        normal = Rotation.from_euler("x", 60, degrees=True).apply([0.0, 0.0, 1.0])
        depth = 4.0 / (rays @ normal)
    else:
        depth = rng.uniform(3.0, 8.0, len(uv))
    X = rays * depth[:, None]
    uv2, z2 = _project(make_T(R21, t21), X)
    ok = (depth > 0) & (depth < 30) & (z2 > 0) & _in_image(uv2)
    X, uv1, uv2 = X[ok][:n], uv[ok][:n], uv2[ok][:n]
    uv1 = uv1 + rng.normal(0, noise, uv1.shape)
    uv2 = uv2 + rng.normal(0, noise, uv2.shape)
    n_out = int(outliers * len(uv1))
    uv2[:n_out] = rng.uniform([0, 0], [640, 480], (n_out, 2))
    return X, uv1, uv2, n_out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_view_general_scene_chooses_f_and_recovers_motion(seed):
    rng = np.random.default_rng(seed)
    R21 = Rotation.from_rotvec(rng.normal(size=3) * 0.05).as_matrix()
    t21 = np.array([0.8, 0.1, 0.15])
    X, uv1, uv2, n_out = _two_view_matches(rng, R21, t21, planar=False)
    res = TwoViewInitializer().initialize(uv1, uv2, K)
    assert res is not None and res.model == "F"
    assert rotation_angle_deg(res.R21 @ R21.T) < 0.5
    assert angle_between_deg(res.t21, t21) < 2.0
    # The true matches are triangulated, the wrong ones are not; points lie in front.
    good = res.triangulated
    assert good[n_out:].mean() > 0.85 and good[:n_out].mean() < 0.1
    assert np.all(res.points[good, 2] > 0) and np.all(np.isnan(res.points[~res.inliers]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_view_planar_scene_chooses_h_and_recovers_motion(seed):
    rng = np.random.default_rng(seed)
    R21 = Rotation.from_rotvec(rng.normal(size=3) * 0.05).as_matrix()
    t21 = np.array([0.8, 0.0, 0.0])
    _, uv1, uv2, n_out = _two_view_matches(rng, R21, t21, planar=True)
    res = TwoViewInitializer().initialize(uv1, uv2, K)
    assert res is not None and res.model == "H"
    assert res.rh > 0.45
    assert rotation_angle_deg(res.R21 @ R21.T) < 0.5
    assert angle_between_deg(res.t21, t21) < 2.0
    assert res.triangulated[n_out:].mean() > 0.85


def test_two_view_rejects_pure_rotation():
    rng = np.random.default_rng(3)
    R21 = Rotation.from_rotvec([0.0, 0.08, 0.0]).as_matrix()
    _, uv1, uv2, _ = _two_view_matches(rng, R21, np.zeros(3), planar=False, outliers=0.0)
    assert TwoViewInitializer().initialize(uv1, uv2, K) is None


def test_homography_decomposition_contains_true_motion():
    R21 = Rotation.from_rotvec([0.02, -0.05, 0.03]).as_matrix()
    t21 = np.array([0.5, 0.1, -0.05])
    n, d = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0]), 4.0
    H = K @ (R21 + np.outer(t21, n) / d) @ np.linalg.inv(K)
    motions = homography_motions(H, K)
    assert len(motions) == 8
    errs = [rotation_angle_deg(R @ R21.T) + angle_between_deg(t, t21) for R, t in motions]
    assert min(errs) < 1e-6


def test_epipolar_helpers_agree_with_known_motion():
    rng = np.random.default_rng(4)
    T_1w = make_T(Rotation.random(random_state=5).as_matrix(), rng.normal(size=3))
    T_2w = make_T(Rotation.random(random_state=6).as_matrix(), rng.normal(size=3))
    T_21 = relative_pose(T_1w, T_2w)
    X = rng.normal(size=(50, 3)) * 2
    X_w = (X - T_1w[:3, 3]) @ T_1w[:3, :3]  # points in front of nothing in particular
    uv1, _ = _project(T_1w, X_w)
    uv2, _ = _project(T_2w, X_w)
    F21 = fundamental_from_pose(T_21[:3, :3], T_21[:3, 3], K, K)
    d2, d1 = epipolar_sq_distances(F21, uv1, uv2)
    assert d2.max() < 1e-12 * 1e6 and d1.max() < 1e-6
    np.testing.assert_allclose(fundamental_12_from_poses(T_1w, T_2w, K, K), F21.T, atol=1e-12)
    R1, R2, t = decompose_essential(K.T @ F21 @ K)
    rot_err = min(rotation_angle_deg(R @ T_21[:3, :3].T) for R in (R1, R2))
    assert rot_err < 1e-6 and min(angle_between_deg(s * t, T_21[:3, 3]) for s in (1, -1)) < 1e-6


def test_triangulation_exact_and_noisy():
    rng = np.random.default_rng(7)
    X = np.stack([rng.uniform(-2, 2, 500), rng.uniform(-2, 2, 500), rng.uniform(3, 9, 500)], axis=1)
    T_1w = np.eye(4)
    T_2w = make_T(Rotation.from_rotvec([0.0, -0.05, 0.0]).as_matrix(), [-0.6, 0.0, 0.0])
    uv1, _ = _project(T_1w, X)
    uv2, _ = _project(T_2w, X)
    P1, P2 = projection_matrix(K, T_1w), projection_matrix(K, T_2w)
    np.testing.assert_allclose(triangulate_dlt(P1, P2, uv1, uv2), X, atol=1e-8)
    noisy = triangulate_dlt(P1, P2, uv1 + rng.normal(0, 0.5, uv1.shape), uv2 + rng.normal(0, 0.5, uv2.shape))
    rel = np.linalg.norm(noisy - X, axis=1) / np.linalg.norm(X, axis=1)
    assert np.median(rel) < 0.02
    ones = np.ones(len(X))
    Xc, good = triangulate_checked(K, T_1w, uv1, ones, K, T_2w, uv2, ones, ones, ones)
    assert good.all()
    np.testing.assert_allclose(Xc, X, atol=1e-8)
    # Swapped observations (wrong matches) and rays without parallax are rejected.
    bad2 = uv2.copy()
    bad2[:100] = uv2[100:200]
    _, good_bad = triangulate_checked(K, T_1w, uv1, ones, K, T_2w, bad2, ones, ones, ones)
    assert good_bad[:100].mean() < 0.1 and good_bad[200:].all()
    _, good_same = triangulate_checked(K, T_1w, uv1, ones, K, T_1w, uv1, ones)
    assert not good_same.any()


def test_epnp_ransac_recovers_pose_with_outliers():
    rng = np.random.default_rng(8)
    n = 200
    uv = rng.uniform([0, 0], [640, 480], (n, 2))
    depth = rng.uniform(2, 10, n)
    X_c = np.concatenate([(uv - K[:2, 2]) / K[0, 0], np.ones((n, 1))], axis=1) * depth[:, None]
    T_cw = make_T(Rotation.random(random_state=9).as_matrix(), [0.5, 1.0, -2.0])
    X_w = (X_c - T_cw[:3, 3]) @ T_cw[:3, :3]
    octave = rng.integers(0, 4, n)
    sigma2 = 1.2 ** (2 * octave)
    obs = uv + rng.normal(0, 0.5, (n, 2)) * np.sqrt(sigma2)[:, None]
    n_out = int(0.3 * n)
    obs[:n_out] = rng.uniform([0, 0], [640, 480], (n_out, 2))
    res = solve_pnp_ransac(X_w, obs, K, sigma2)
    assert res is not None
    assert rotation_angle_deg(res.T_cw[:3, :3] @ T_cw[:3, :3].T) < 0.2
    assert np.linalg.norm(inv_T(res.T_cw)[:3, 3] - inv_T(T_cw)[:3, 3]) < 0.05
    assert res.inliers[n_out:].mean() > 0.9 and res.inliers[:n_out].mean() < 0.05
    # Too few inliers for the minimum count: no pose.
    assert solve_pnp_ransac(X_w[:12], rng.uniform(0, 480, (12, 2)), K) is None


def test_horn_similarity_exact():
    rng = np.random.default_rng(10)
    R = Rotation.random(random_state=11).as_matrix()
    P2 = rng.normal(size=(30, 3))
    P1 = 2.5 * P2 @ R.T + [1.0, -2.0, 0.5]
    s, R_est, t = horn_similarity(P1, P2)
    assert abs(s - 2.5) < 1e-12
    np.testing.assert_allclose(R_est, R, atol=1e-10)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-10)
    s_b, R_b, _ = horn_similarity(np.stack([P1[:3], P1[3:6]]), np.stack([P2[:3], P2[3:6]]))
    np.testing.assert_allclose(s_b, 2.5, atol=1e-10)


def test_sim3_ransac_recovers_similarity_with_outliers():
    rng = np.random.default_rng(12)
    n = 150
    # Points seen by keyframe 2; keyframe 1 sees the same points through S_12.
    uv2 = rng.uniform([0, 0], [640, 480], (n, 2))
    X2 = np.concatenate([(uv2 - K[:2, 2]) / K[0, 0], np.ones((n, 1))], axis=1) * rng.uniform(2, 6, n)[:, None]
    R12 = Rotation.from_rotvec([0.05, 0.2, -0.03]).as_matrix()
    s12, t12 = 1.8, np.array([0.3, -0.1, 0.4])
    X1 = s12 * X2 @ R12.T + t12
    # Each keyframe's points carry their own depth error (1%, along the viewing ray), as
    # monocular triangulation leaves them; 30% of the matches pair unrelated points.
    X1n = X1 * (1 + rng.normal(0, 0.01, (n, 1)))
    X2n = X2 * (1 + rng.normal(0, 0.01, (n, 1)))
    n_out = int(0.3 * n)
    X2n[:n_out] = X2n[rng.permutation(n_out)]
    # Observations: the points' own projections in each keyframe (as ORB-SLAM's Sim3Solver).
    obs1, z1 = _project(np.eye(4), X1n)
    obs2, _ = _project(np.eye(4), X2n)
    assert np.all(z1 > 0)
    res = sim3_ransac(X1n, X2n, obs1, obs2, K, K)
    assert res is not None
    assert abs(res.scale / s12 - 1.0) < 0.01
    assert rotation_angle_deg(res.S_12[:3, :3] / res.scale @ R12.T) < 0.5
    assert np.linalg.norm(res.S_12[:3, 3] - t12) < 0.05
    assert res.inliers[n_out:].mean() > 0.9 and res.inliers[:n_out].mean() < 0.1


def test_two_view_initialisation_on_real_tum_frames(tum_sample):
    """Frames 3.4 s apart (0.7 m, 10.8 degrees): brute-force matching with ratio test and
    cross check, then initialisation, against the TUM ground truth."""
    t1, t2 = 1341847980.722988, 1341847984.106759
    cam = load_camera("tum_fr3")
    ex = ORBExtractor()
    kps = [ex.extract(cv2.imread(str(tum_sample / f"rgb/{t:.6f}.png"), cv2.IMREAD_GRAYSCALE), cam) for t in (t1, t2)]
    pairs = brute_force_match(kps[0].desc, kps[1].desc, ratio=0.9, cross_check=True)
    res = TwoViewInitializer(InitializerConfig()).initialize(kps[0].uv[pairs[:, 0]], kps[1].uv[pairs[:, 1]], cam.K)
    assert res is not None
    gt = read_tum(tum_sample / "groundtruth.txt")
    T_w1 = gt.poses[gt.nearest(t1, 0.1)]  # first ground-truth pose is 67 ms after frame 1
    T_w2 = gt.poses[gt.nearest(t2, 0.1)]
    T_21 = inv_T(T_w2) @ T_w1
    assert rotation_angle_deg(res.R21 @ T_21[:3, :3].T) < 2.0
    assert angle_between_deg(res.t21, T_21[:3, 3]) < 5.0
    assert res.triangulated.sum() >= 50
