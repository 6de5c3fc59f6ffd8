"""Relocalisation: a frame seen from a known pose is relocalised against a synthetic map
(pose within 1 cm / 0.5 deg, true correspondences), garbage fails cleanly, and the tracker
gets back to OK after a forced loss."""

import numpy as np
import pytest

from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.se3 import rotation_angle_deg
from orbslam_hgcn.map import Frame
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.tracking.relocalization import Relocalizer, relocalize
from orbslam_hgcn.tracking.tracker import Tracker, TrackingState
from orbslam_hgcn.vocabulary.bow import BowVector, FeatureVector
from orbslam_hgcn.map.database import KeyframeDatabase

from loop_fixtures import SCALE_FACTORS, RingScene, bow_of, build_ring_map, frame_at, ring_pose


@pytest.fixture(scope="module")
def ring():
    """20 keyframes over 0.9 of the ring, no drift (the map's frame is the true one)."""
    rm = build_ring_map(n_keyframes=20, turns=0.9, scale_rate=0.0, yaw_deg_rate=0.0, trans_rate=0.0, seed=2)
    db = KeyframeDatabase()
    for kf in rm.map.keyframes():
        db.add(kf.id, kf.bow)
    return rm, db


def _pose_between_keyframes() -> np.ndarray:
    T_wc = ring_pose(np.radians(5 * 0.9 * 360 / 19 + 7.0))  # between keyframes 5 and 6
    T_wc[:3, 3] += (0.04, -0.03, 0.05)
    return T_wc


def _garbage_frame(camera, n: int, seed: int) -> Frame:
    rng = np.random.default_rng(seed)
    kps = KeypointSet(
        uv_raw=rng.uniform(0, 480, (n, 2)).astype(np.float32), uv=rng.uniform(0, 480, (n, 2)),
        octave=rng.integers(0, 4, n).astype(np.int32), angle=rng.uniform(0, 360, n).astype(np.float32),
        response=np.ones(n, np.float32), desc=rng.integers(0, 256, (n, 32), dtype=np.uint8),
        scale_factors=SCALE_FACTORS.copy(),
    )  # fmt: skip
    f = Frame(900, 0.0, camera, kps)
    f.bow, f.featvec = bow_of(rng.integers(0, 2500, n), rng)  # words of real places, wrong features
    return f


def test_relocalisation_recovers_the_pose(ring):
    rm, db = ring
    T_wc = _pose_between_keyframes()
    f, ids = frame_at(rm.scene, T_wc, 100, seed=5)
    res = relocalize(f, FeatureGrid(f.keypoints, f.camera), rm.map, db)
    assert res.ok and res.n_inliers >= 50 and res.kf_id in (4, 5, 6, 7)
    D = res.T_cw @ T_wc
    assert np.linalg.norm(D[:3, 3]) < 0.01 and rotation_angle_deg(D[:3, :3]) < 0.5
    # Matches are true correspondences (the map point of the same scene point).
    slots = np.flatnonzero(res.point_ids >= 0)
    owner = {}
    for kf in rm.map.keyframes():
        for slot, pid in zip(*kf.observed_points()):
            owner[int(pid)] = int(rm.scene_ids[kf.id][slot])
    assert np.mean([owner[int(res.point_ids[s])] == ids[s] for s in slots]) > 0.98
    assert f.T_cw is None and (f.point_ids < 0).all()  # the frame itself is not changed


def test_relocalisation_fails_cleanly_on_garbage(ring):
    rm, db = ring
    m = rm.map
    g = _garbage_frame(rm.scene.camera, 600, 1)
    res = relocalize(g, FeatureGrid(g.keypoints, g.camera), m, db)
    assert not res.ok and res.T_cw is None and (res.point_ids == -1).all()
    # No BoW vector, no features, an empty database: failures, not exceptions.
    f, _ = frame_at(rm.scene, _pose_between_keyframes(), 101, seed=5)
    f.bow = f.featvec = None
    assert not relocalize(f, FeatureGrid(f.keypoints, f.camera), m, db).ok
    empty = Frame(102, 0.0, rm.scene.camera, _no_keypoints())
    empty.bow, empty.featvec = BowVector(), FeatureVector()
    assert not relocalize(empty, FeatureGrid(empty.keypoints, empty.camera), m, db).ok
    f, _ = frame_at(rm.scene, _pose_between_keyframes(), 103, seed=5)
    assert not relocalize(f, FeatureGrid(f.keypoints, f.camera), m, KeyframeDatabase()).ok
    # A frame of another place (same kind of scene, other points and descriptors).
    away, _ = frame_at(RingScene.make(seed=99), _pose_between_keyframes(), 104, seed=6)
    assert not relocalize(away, FeatureGrid(away.keypoints, away.camera), m, db).ok


def _no_keypoints() -> KeypointSet:
    return KeypointSet(
        uv_raw=np.zeros((0, 2), np.float32), uv=np.zeros((0, 2)), octave=np.zeros(0, np.int32),
        angle=np.zeros(0, np.float32), response=np.zeros(0, np.float32), desc=np.zeros((0, 32), np.uint8),
        scale_factors=SCALE_FACTORS.copy(),
    )  # fmt: skip


def test_tracker_resumes_after_a_forced_loss(ring):
    rm, db = ring
    m = rm.map
    reloc = Relocalizer(m, db)
    tracker = Tracker(m, relocalizer=reloc)
    tracker.state = TrackingState.LOST  # forced loss: no last frame, no velocity
    T_wc = _pose_between_keyframes()
    f, _ = frame_at(rm.scene, T_wc, 200, seed=5)
    result = tracker.track(f)
    assert reloc.attempts == 1 and reloc.successes == 1
    assert result.state == TrackingState.OK and result.n_inliers >= 50
    D = f.T_cw @ T_wc
    assert np.linalg.norm(D[:3, 3]) < 0.01 and rotation_angle_deg(D[:3, :3]) < 0.5
    # The next frame, a little further on, is tracked from the relocalised one.
    T2 = ring_pose(np.radians(5 * 0.9 * 360 / 19 + 8.0))
    T2[:3, 3] += (0.04, -0.03, 0.05)
    f2, _ = frame_at(rm.scene, T2, 201, seed=8)
    assert tracker.track(f2).state == TrackingState.OK
    D2 = f2.T_cw @ T2
    assert np.linalg.norm(D2[:3, 3]) < 0.01
    # Garbage while lost stays lost, without an exception.
    g = _garbage_frame(rm.scene.camera, 600, 3)
    tracker.state = TrackingState.LOST
    assert tracker.track(g).state == TrackingState.LOST
