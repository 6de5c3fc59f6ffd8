"""Core helpers: SE3 algebra, the camera model, TUM trajectory files, camera YAML validation."""

import numpy as np
import pytest

from orbslam_hgcn.config import load_camera, save_camera
from orbslam_hgcn.errors import ConfigError, DatasetError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import R_to_quat, inv_T, make_T, quat_to_R, transform_points
from orbslam_hgcn.trajectory import Trajectory, read_tum, write_tum


def _random_T(rng):
    q = rng.normal(size=4)
    return make_T(quat_to_R(q / np.linalg.norm(q)), rng.normal(size=3))


def test_inverse_and_quaternion_round_trip():
    rng = np.random.default_rng(0)
    T = _random_T(rng)
    np.testing.assert_allclose(T @ inv_T(T), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(quat_to_R(R_to_quat(T[:3, :3])), T[:3, :3], atol=1e-12)
    X = rng.normal(size=(5, 3))
    np.testing.assert_allclose(transform_points(inv_T(T), transform_points(T, X)), X, atol=1e-12)


def test_quaternions_give_scipys_rotations():
    # The numpy conversion against scipy's, on unnormalised quaternions of both signs, one
    # and many at once; a zero or (3,) quaternion is refused.
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    q = rng.normal(size=(50, 4)) * rng.uniform(0.1, 10.0, size=(50, 1))
    np.testing.assert_allclose(quat_to_R(q), Rotation.from_quat(q).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(quat_to_R(q[3]), Rotation.from_quat(q[3]).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(quat_to_R([0.0, 0.0, 0.0, 1.0]), np.eye(3))
    for bad in ([0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0]):
        with pytest.raises(ValueError):
            quat_to_R(bad)


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    poses = np.stack([_random_T(rng) for _ in range(7)])
    stamps = 1000.0 + np.arange(7) * 0.033
    write_tum(tmp_path / "t.txt", Trajectory(stamps, poses))
    back = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(back.timestamps, stamps, atol=1e-6)
    np.testing.assert_allclose(back.poses, poses, atol=1e-8)


def test_tum_malformed_line_names_file_and_line(tmp_path):
    p = tmp_path / "bad.txt"
    p.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad.txt:3"):
        read_tum(p)


def test_camera_yaml_round_trip_and_validation(tmp_path):
    cam = PinholeCamera(500.0, 501.0, 320.0, 240.0, 640, 480, (0.1, -0.01, 0.0, 0.0, 0.0), 30.0, "x")
    save_camera(tmp_path / "c.yaml", cam)
    assert load_camera(tmp_path / "c.yaml") == cam
    (tmp_path / "bad.yaml").write_text("fx: -3\nfy: 500\ncx: 320\ncy: 240\nwidth: 640\nheight: 480\n")
    with pytest.raises(ConfigError, match=r"bad.yaml \[fx\].*positive"):
        load_camera(tmp_path / "bad.yaml")
    (tmp_path / "nofy.yaml").write_text("fx: 500\ncx: 320\ncy: 240\nwidth: 640\nheight: 480\n")
    with pytest.raises(ConfigError, match=r"nofy.yaml \[fy\].*missing"):
        load_camera(tmp_path / "nofy.yaml")


def test_undistort_inverts_distortion():
    import cv2

    cam = PinholeCamera(458.654, 457.296, 367.215, 248.375, 752, 480, (-0.2834, 0.07396, 0.000194, 1.76e-05))
    rng = np.random.default_rng(2)
    ideal = rng.uniform([50, 50], [700, 430], size=(50, 2))
    rays = cam.unproject(ideal)
    distorted, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    np.testing.assert_allclose(cam.undistort_points(distorted.reshape(-1, 2)), ideal, atol=1e-3)
