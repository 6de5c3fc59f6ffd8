"""Local mapping: triangulation, fusion and culling on scenes with known geometry, and map
invariants after a run on a synthetic sequence."""

import threading
from collections import Counter

import numpy as np
import pytest

from orbslam_hgcn.config import LocalMappingConfig
from orbslam_hgcn.datasets import open_sequence
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.epipolar import fundamental_12_from_poses
from orbslam_hgcn.geometry.se3 import make_T
from orbslam_hgcn.map import Frame, Map, check_invariants
from orbslam_hgcn.mapping import fuse as fuse_module
from orbslam_hgcn.mapping import triangulate as triangulate_module
from orbslam_hgcn.mapping.culling import cull_recent_points, redundant_keyframes
from orbslam_hgcn.mapping.fuse import search_in_neighbors
from orbslam_hgcn.mapping.triangulate import create_new_points, epipolar_candidate_pairs
from orbslam_hgcn.runtime.system import System

CAM = PinholeCamera(fx=520.0, fy=520.0, cx=320.0, cy=240.0, width=640, height=480)
SCALES = 1.2 ** np.arange(8)


def _world(rng, n=400):
    """(n, 3) points 2-4 m in front of the origin, (n, 32) descriptors (one per point)."""
    X = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.0, n), rng.uniform(2.0, 4.0, n)])
    return X, rng.integers(0, 256, (n, 32)).astype(np.uint8)


def _keyframe(m, i, T_cw, X, desc, rng, octave=0):
    """A keyframe seeing every point of X in front of it and inside the image; feature j of
    the keyframe shows point ``seen[j]`` (its slot order shuffled)."""
    Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    uv = CAM.project(Xc)[0]
    seen = np.flatnonzero((Xc[:, 2] > 0) & CAM.in_image(uv, 20))
    seen = rng.permutation(seen)
    n = len(seen)
    kps = KeypointSet(uv[seen].astype(np.float32), uv[seen], np.full(n, octave, np.int32), np.zeros(n, np.float32),
                      np.ones(n, np.float32), desc[seen], SCALES)  # fmt: skip
    kf = m.add_keyframe(Frame(i, float(i), CAM, kps, T_cw=T_cw))
    return kf, seen


def _link(m, kf, seen, truth_to_pid, which):
    """Link the keyframe's features showing points ``which`` (true indices) to their map points."""
    slot = {int(t): j for j, t in enumerate(seen)}
    for t in which:
        if int(t) in slot:
            m.add_observation(kf.id, truth_to_pid[int(t)], slot[int(t)])


def test_epipolar_candidates_hold_the_true_pairs():
    rng = np.random.default_rng(0)
    X, desc = _world(rng)
    m = Map()
    kf1, s1 = _keyframe(m, 0, np.eye(4), X, desc, rng)
    kf2, s2 = _keyframe(m, 1, make_T(np.eye(3), [-0.3, 0.05, 0.0]), X, desc, rng)
    F12 = fundamental_12_from_poses(kf1.T_cw, kf2.T_cw, CAM.K, CAM.K)
    a1 = np.ones(len(s1), bool)
    a2 = np.ones(len(s2), bool)
    i1, i2 = epipolar_candidate_pairs(kf1.keypoints.uv, kf2.keypoints.uv, np.ones(len(s2)), F12, a1, a2)
    pairs = set(zip(s1[i1].tolist(), s2[i2].tolist()))
    common = set(s1.tolist()) & set(s2.tolist())
    assert all((t, t) in pairs for t in common)  # every true correspondence is a candidate
    assert len(i1) < 0.05 * len(s1) * len(s2)  # and the constraint prunes most pairs


class _RecordingLock:
    """Re-entrant lock that counts how often it was released completely."""

    def __init__(self):
        self._lock = threading.RLock()
        self.depth = 0
        self.releases = 0

    def acquire(self, blocking=True, timeout=-1):
        ok = self._lock.acquire(blocking, timeout)
        self.depth += int(ok)
        return ok

    def release(self):
        self.depth -= 1
        self.releases += int(self.depth == 0)
        self._lock.release()

    __enter__ = acquire

    def __exit__(self, *exc):
        self.release()


def _record_calls(monkeypatch, module, name, lock):
    """Wrap module.name to log (lock depth, complete releases so far) at each call."""
    calls, inner = [], getattr(module, name)

    def wrapped(*args, **kwargs):
        calls.append((lock.depth, lock.releases))
        return inner(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapped)
    return calls


def _locked_one_at_a_time(calls):
    """Each call ran under the lock, and the lock was let go between two calls (so a
    waiting tracker gets in)."""
    assert len(calls) >= 2
    assert all(depth >= 1 for depth, _ in calls)
    assert all(b[1] > a[1] for a, b in zip(calls, calls[1:]))


def test_triangulation_recovers_points_without_vocabulary(monkeypatch):
    rng = np.random.default_rng(1)
    X, desc = _world(rng)
    m = Map()
    kf1, s1 = _keyframe(m, 0, np.eye(4), X, desc, rng)
    kf2, s2 = _keyframe(m, 1, make_T(np.eye(3), [-0.3, 0.0, 0.0]), X, desc, rng)
    # 40 points already in the map make the two keyframes covisible.
    shared = np.intersect1d(s1, s2)[:40]
    pid = {int(t): m.add_map_point(X[t], kf1.id) for t in shared}
    _link(m, kf1, s1, pid, shared)
    _link(m, kf2, s2, pid, shared)
    m.update_points(np.array(list(pid.values())))
    m.update_connections(kf1.id)
    m.update_connections(kf2.id)
    m.lock = lock = _RecordingLock()
    calls = _record_calls(monkeypatch, triangulate_module, "triangulate_with_neighbour", lock)
    new = create_new_points(m, kf2, LocalMappingConfig())
    assert len(calls) == 1 and calls[0][0] >= 1  # one neighbour, matched under the lock
    expected = len(np.intersect1d(s1, s2)) - len(shared)
    assert len(new) >= 0.95 * expected
    truth2 = {int(j): int(t) for j, t in enumerate(s2)}
    for p in new:
        obs = m.point(int(p)).observations
        t = truth2[obs[kf2.id]]
        assert s1[obs[kf1.id]] == t  # matched the right feature
        assert np.linalg.norm(m.point(int(p)).position - X[t]) < 1e-6 * np.linalg.norm(X[t])
    assert check_invariants(m) == []


def _covisible_group(rng, n_kf=5, octaves=None):
    """n_kf keyframes a few cm apart all seeing the same points, every point linked.
    Returns (map, keyframes, X, descriptors, per-keyframe true indices, {true index: point id})."""
    X, desc = _world(rng, 150)
    m = Map()
    kfs, seens = [], []
    for i in range(n_kf):
        o = 0 if octaves is None else octaves[i]
        kf, seen = _keyframe(m, i, make_T(np.eye(3), [-0.05 * i, 0.0, 0.0]), X, desc, rng, octave=o)
        kfs.append(kf)
        seens.append(seen)
    common = seens[0]
    for s in seens[1:]:
        common = np.intersect1d(common, s)
    pid = {int(t): m.add_map_point(X[t], kfs[0].id) for t in common}
    for kf, s in zip(kfs, seens):
        _link(m, kf, s, pid, common)
    m.update_points(np.array(list(pid.values())))
    for kf in kfs:
        m.update_connections(kf.id)
    return m, kfs, X, desc, seens, pid


def test_keyframe_culling_keeps_enough_views():
    m, kfs, *_ = _covisible_group(np.random.default_rng(2))
    culled = redundant_keyframes(m, kfs[-1], LocalMappingConfig())
    # Keyframe 1: every point seen by 3+ others -> culled; then 2: by 0, 3, 4 -> culled;
    # then 3: only 0 and 4 remain -> kept. The first keyframe is never culled.
    assert culled == [1, 2]
    assert m.n_keyframes() == 3
    assert check_invariants(m) == []


def test_keyframe_culling_respects_scale():
    # The candidates see the points at level 0, the others only at level 3 (coarser):
    # they do not make the fine observations redundant.
    m, kfs, *_ = _covisible_group(np.random.default_rng(3), octaves=[3, 0, 3, 3, 3])
    culled = redundant_keyframes(m, kfs[-1], LocalMappingConfig())
    assert 1 not in culled


def test_recent_point_culling_rules():
    m, kfs, X, desc, seens, pid = _covisible_group(np.random.default_rng(4), n_kf=3)
    ids = np.array(sorted(pid.values()))
    a, b, c = int(ids[0]), int(ids[1]), int(ids[2])
    m.increase_visible(np.array([a]), 10)  # found 1 of 11: ratio < 0.25
    m.erase_observation(kfs[2].id, b)  # b keeps 2 observations: made bad by the map itself
    cfg = LocalMappingConfig()
    # Two keyframes after creation a point needs 3 observations; c has 3 and stays.
    kept, n = cull_recent_points(m, np.array([a, b, c]), kfs[0].id + 2, cfg)
    assert m.point(a).bad and m.point(b).bad and not m.point(c).bad
    assert kept.tolist() == [c] and n == 1
    # Three keyframes after creation the point leaves probation.
    kept, _ = cull_recent_points(m, np.array([c]), kfs[0].id + 3, cfg)
    assert kept.tolist() == []
    assert check_invariants(m) == []


def test_fusion_merges_duplicated_points(monkeypatch):
    rng = np.random.default_rng(5)
    m, kfs, X, desc, seens, pid = _covisible_group(rng, n_kf=3)
    # Two more keyframes whose features were given duplicates of the same points.
    kf3, s3 = _keyframe(m, 3, make_T(np.eye(3), [-0.15, 0.0, 0.0]), X, desc, rng)
    kf4, s4 = _keyframe(m, 4, make_T(np.eye(3), [-0.20, 0.0, 0.0]), X, desc, rng)
    common = np.array(sorted(set(pid) & set(s3.tolist()) & set(s4.tolist())))
    dup = {int(t): m.add_map_point(X[t] + 1e-4, kf3.id) for t in common}
    _link(m, kf3, s3, dup, common)
    _link(m, kf4, s4, dup, common)
    m.update_points(np.array(list(dup.values())))
    # 20 duplicates are merged up front, so the two groups are covisible.
    bridge = common[:20]
    for t in bridge:
        m.replace_point(dup[int(t)], pid[int(t)])
    m.update_connections(kf3.id)
    m.update_connections(kf4.id)
    n_before = m.n_points()
    m.lock = lock = _RecordingLock()
    calls = _record_calls(monkeypatch, fuse_module, "fuse_into", lock)
    stats = search_in_neighbors(m, kf3, LocalMappingConfig())
    assert len(calls) == stats["targets"] + 1
    _locked_one_at_a_time(calls)
    n_dup = len(common) - len(bridge)
    assert stats["merged"] >= 0.9 * n_dup
    assert m.n_points() <= n_before - 0.9 * n_dup
    # The slots showing one true point now hold one shared id, in every keyframe.
    for t in common:
        ids = {int(kf.point_ids[np.flatnonzero(s == t)[0]]) for kf, s in zip(kfs + [kf3, kf4], seens + [s3, s4])}
        assert len(ids) == 1
    assert check_invariants(m) == []


@pytest.fixture(scope="session")
def synth_run(synth_replay_100):
    """The system run over the first 45 frames of the replayed fr3 camera path."""
    seq = open_sequence("tum", synth_replay_100)
    system = System(seq.camera, sequential=True)
    system.run(seq, 45, progress=False)
    return system


def test_map_invariants_after_a_run(synth_run):
    m = synth_run.map
    assert m.n_keyframes() >= 3 and m.n_points() > 300
    assert check_invariants(m) == []
    # Covisibility weights equal the points two keyframes share, recounted from the slots.
    kfs = m.keyframes()
    sets = {kf.id: set(kf.observed_points()[1].tolist()) for kf in kfs}
    for kf in kfs:
        recount = Counter({o: len(sets[kf.id] & sets[o]) for o in sets if o != kf.id})
        assert kf.shared == {o: c for o, c in recount.items() if c > 0}
    # Every good point is seen by at least two keyframes, and lies in front of them.
    for pid in m.point_ids()[:500]:
        p = m.point(int(pid))
        assert p.n_obs >= 2
        for k in p.observations:
            T = m.keyframe(k).T_cw
            assert (T[:3, :3] @ p.position + T[:3, 3])[2] > 0


def test_compiled_kernels_have_one_signature_after_a_run(synth_run):
    """System() compiled (or loaded) the kernels with the argument types of a real run, so
    the run (pose-only optimisation, projection search, fusion, FAST, quadtree, ORB description) compiled
    nothing more; with the kernels built ahead of time, none of them needed numba."""
    from orbslam_hgcn import aot
    from orbslam_hgcn.backend.pose_only import _optimize
    from orbslam_hgcn.features.distribute import _distribute
    from orbslam_hgcn.features.fast import detect_level
    from orbslam_hgcn.features.rbrief import ic_moments, rbrief
    from orbslam_hgcn.match.projection_search import _best_two_in_windows

    assert synth_run.mapper.timings["fuse"], "the run fused points"
    for kernel in (_optimize, _best_two_in_windows, ic_moments, rbrief, detect_level, _distribute):
        if isinstance(kernel, aot.Kernel):
            assert kernel.exports and not kernel.numba_used, kernel.qualname
        else:
            assert len(kernel.signatures) == 1, kernel
