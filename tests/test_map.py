"""Map model: links kept at both ends, covisibility weights, fuse, culling, tree, invariants."""

from collections import Counter

import numpy as np
import pytest

from orbslam_hgcn.config import MapConfig
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import make_T
from orbslam_hgcn.map import Frame, Map, MapSnapshot, check_invariants, essential_graph, predict_scale, snapshot
from orbslam_hgcn.map.graph import COVISIBILITY, LOOP, TREE
from orbslam_hgcn.map.mappoint import distinctive_descriptor, distinctive_descriptors, normal_and_depth
from orbslam_hgcn.map.window import apply_window, local_window
from orbslam_hgcn.match.hamming import hamming_matrix

CAM = PinholeCamera(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
SCALES = 1.2 ** np.arange(8)
N_FEAT = 300


def _keypoints(rng, n=N_FEAT):
    uv = rng.uniform([0, 0], [640, 480], size=(n, 2))
    return KeypointSet(
        uv_raw=uv.astype(np.float32),
        uv=uv,
        octave=rng.integers(0, 8, n).astype(np.int32),
        angle=np.zeros(n, np.float32),
        response=np.ones(n, np.float32),
        desc=rng.integers(0, 256, (n, 32)).astype(np.uint8),
        scale_factors=SCALES,
    )


def _frame(i, rng):
    return Frame(id=i, timestamp=0.1 * i, camera=CAM, keypoints=_keypoints(rng), T_cw=make_T(np.eye(3), [-0.2 * i, 0, 0]))


def _build(rng, n_kf=6, n_pts=400, span=(2, 4)):
    """A map whose points are each seen by a run of consecutive keyframes; returns (map,
    {pid: {kf: idx}}) with the intended observations."""
    m = Map()
    kfs = [m.add_keyframe(_frame(i, rng)) for i in range(n_kf)]
    next_slot = [0] * n_kf
    truth = {}
    for _ in range(n_pts):
        length = int(rng.integers(span[0], span[1] + 1))
        start = int(rng.integers(0, n_kf - length + 1))
        seen = [k for k in range(start, start + length) if next_slot[k] < N_FEAT]
        if len(seen) < 2:
            continue
        pid = m.add_map_point(rng.normal(size=3) + [0, 0, 5], seen[0])
        truth[pid] = {}
        for k in seen:
            m.add_observation(kfs[k].id, pid, next_slot[k])
            truth[pid][k] = next_slot[k]
            next_slot[k] += 1
    for kf in kfs:
        m.update_connections(kf.id)
    return m, truth


def _shared_counts(truth):
    c = Counter()
    for obs in truth.values():
        for a in obs:
            for b in obs:
                if a != b:
                    c[(a, b)] += 1
    return c


def test_observations_linked_at_both_ends_and_weights_equal_shared_counts():
    rng = np.random.default_rng(0)
    m, truth = _build(rng)
    assert check_invariants(m) == []
    for pid, obs in truth.items():
        assert m.point(pid).observations == obs
        for k, idx in obs.items():
            assert m.keyframe(k).point_ids[idx] == pid
    counts = _shared_counts(truth)
    for (a, b), c in counts.items():
        assert m.covisibility_weight(a, b) == c
    # Ordered neighbours: weights >= 15, descending.
    ids = m.covisible_keyframes(2)
    w = [m.covisibility_weight(2, int(k)) for k in ids]
    assert w == sorted(w, reverse=True) and min(w) >= 15
    assert set(ids) == {b for (a, b), c in counts.items() if a == 2 and c >= 15}


def test_erase_observation_unlinks_both_ends_and_drops_weak_points():
    rng = np.random.default_rng(1)
    m, truth = _build(rng, span=(3, 4))
    pid = next(p for p, o in truth.items() if len(o) == 4)
    kf_a, kf_b = list(truth[pid])[:2]
    w_before = m.covisibility_weight(kf_a, kf_b)
    m.erase_observation(kf_a, pid)
    assert kf_a not in m.point(pid).observations and pid not in m.keyframe(kf_a).point_ids
    assert m.covisibility_weight(kf_a, kf_b) == w_before - 1
    assert not m.point(pid).bad and check_invariants(m) == []
    # The threshold is configurable: with 1, a point survives on a single observation.
    lenient = Map(MapConfig(min_observations_after_erase=1))
    a, b = lenient.add_keyframe(_frame(0, rng)), lenient.add_keyframe(_frame(1, rng))
    q = lenient.add_map_point([0, 0, 5], a.id)
    lenient.add_observation(a.id, q, 0)
    lenient.add_observation(b.id, q, 0)
    lenient.erase_observation(b.id, q)
    assert not lenient.point(q).bad and lenient.point(q).observations == {a.id: 0}
    # Left with 2 observations after the next erase: discarded as in ORB-SLAM (nObs <= 2).
    m.erase_observation(kf_b, pid)
    assert m.point(pid).bad and m.point(pid).n_obs == 0
    others = [p for p in truth if p != pid][:5]
    np.testing.assert_array_equal(m.bad_points(np.array([pid, *others])), [True] + [False] * len(others))
    assert not np.isin(pid, np.concatenate([m.keyframe(k).point_ids for k in truth[pid]]))
    assert check_invariants(m) == []


def test_add_observation_refuses_conflicting_links():
    rng = np.random.default_rng(2)
    m, truth = _build(rng)
    pid, obs = next(iter(truth.items()))
    k, idx = next(iter(obs.items()))
    assert m.add_observation(k, pid, idx) is False  # same link again: no-op
    other = next(p for p in truth if p != pid and k not in truth[p])
    with pytest.raises(ValueError):
        m.add_observation(k, other, idx)  # slot taken
    with pytest.raises(ValueError):
        m.add_observation(k, pid, N_FEAT - 1)  # point already in this keyframe
    assert check_invariants(m) == []


def test_add_observations_equals_one_by_one_and_stops_at_a_conflict():
    # A keyframe's links added in one call: the same links, shared counts and the same
    # order of neighbours (ties in covisibility keep it) as one add_observation per link.
    rng = np.random.default_rng(5)
    ref, truth = _build(rng)
    batch = Map()
    for k in range(len(ref.keyframes())):
        batch.add_keyframe(_frame(k, np.random.default_rng(k)))
    for pid in sorted(truth):
        assert batch.add_map_point(ref.point(pid).position, next(iter(truth[pid]))) == pid
    by_kf: dict[int, list[tuple[int, int]]] = {}
    for pid, obs in truth.items():
        for k, idx in obs.items():
            by_kf.setdefault(k, []).append((pid, idx))
    one = Map()
    for k in range(len(ref.keyframes())):
        one.add_keyframe(_frame(k, np.random.default_rng(k)))
    for pid in sorted(truth):
        one.add_map_point(ref.point(pid).position, next(iter(truth[pid])))
    for k in sorted(by_kf):
        pids, idxs = np.array(by_kf[k]).T
        assert batch.add_observations(k, pids, idxs) == len(pids)
        assert batch.add_observations(k, pids[:3], idxs[:3]) == 0  # present already: skipped
        for p, i in zip(pids, idxs):
            one.add_observation(k, int(p), int(i))
    for k in by_kf:
        assert list(batch.keyframe(k).shared.items()) == list(one.keyframe(k).shared.items())
        np.testing.assert_array_equal(batch.keyframe(k).point_ids, one.keyframe(k).point_ids)
    assert check_invariants(batch) == []
    # Keyframes observing a set of points, counted.
    pids = np.array(sorted(truth)[:40])
    want = Counter(k for p in pids for k in truth[int(p)])
    kf_ids, counts = batch.observer_counts(pids)
    assert dict(zip(kf_ids.tolist(), counts.tolist())) == want and list(kf_ids) == sorted(want)
    # A conflicting pair raises; the pairs before it are linked, with their shared counts.
    k = 0
    free = [i for i in range(N_FEAT) if batch.keyframe(k).point_ids[i] < 0]
    new = [batch.add_map_point([0.0, 0.0, 5.0], 1) for _ in range(3)]
    for p in new:
        batch.add_observation(1, p, int(np.flatnonzero(batch.keyframe(1).point_ids < 0)[0]))
    taken = int(np.flatnonzero(batch.keyframe(k).point_ids >= 0)[0])
    before = batch.covisibility_weight(k, 1)
    with pytest.raises(ValueError, match="already holds"):
        batch.add_observations(k, np.array(new), np.array([free[0], free[1], taken]))
    assert batch.covisibility_weight(k, 1) == before + 2
    assert batch.point(new[2]).observations.keys() == {1}
    assert check_invariants(batch) == []


def test_best_neighbour_kept_when_none_reaches_threshold():
    rng = np.random.default_rng(3)
    m = Map()
    a, b, c = (m.add_keyframe(_frame(i, rng)) for i in range(3))
    for j in range(5):  # a-b share 5, a-c share 3: both below 15
        p = m.add_map_point([0, 0, 5], a.id)
        m.add_observation(a.id, p, j)
        m.add_observation(b.id, p, j)
    for j in range(5, 8):
        p = m.add_map_point([0, 0, 5], a.id)
        m.add_observation(a.id, p, j)
        m.add_observation(c.id, p, j)
    assert list(m.covisible_keyframes(a.id)) == [b.id]
    m.update_connections(c.id)
    assert m.keyframe(c.id).parent == a.id


def test_replace_point_merges_observations():
    rng = np.random.default_rng(4)
    m, truth = _build(rng, span=(3, 3))
    # Two points sharing exactly one keyframe: the survivor keeps its own slot there.
    pairs = [(p, q) for p in truth for q in truth if p < q and len(set(truth[p]) & set(truth[q])) == 1]
    old, new = pairs[0]
    common = (set(truth[old]) & set(truth[new])).pop()
    found = m.point(old).found + m.point(new).found
    m.replace_point(old, new)
    obs = m.point(new).observations
    expected = dict(truth[new])
    expected.update({k: i for k, i in truth[old].items() if k != common})
    assert obs == expected
    assert m.point(old).bad and m.point(old).replaced_by == new
    assert m.keyframe(common).point_ids[truth[old][common]] == -1
    assert m.point(new).found == found
    assert check_invariants(m) == []
    after = {p: (expected if p == new else o) for p, o in truth.items() if p != old}
    for (a, b), c in _shared_counts(after).items():
        assert m.covisibility_weight(a, b) == c


def _fuse_one_by_one(m, kf_id, pids, idxs):
    """Map.fuse_points written out with add_observation and replace_point, one match at a
    time (the reference)."""
    kf, merged, added = m.keyframe(kf_id), 0, 0
    for pid, idx in zip(pids, idxs):
        p = m.point(pid)
        if p.bad or kf_id in p.observations:
            continue
        other = int(kf.point_ids[idx])
        if other < 0:
            m.add_observation(kf_id, pid, idx)
            added += 1
        elif other != pid and not m.point(other).bad:
            if m.point(other).n_obs > p.n_obs:
                m.replace_point(pid, other, refresh=False)
            else:
                m.replace_point(other, pid, refresh=False)
            merged += 1
    return merged, added


def test_fuse_points_equals_adding_and_merging_one_match_at_a_time():
    """Fusion's write step batches the covisibility counts of the observations it adds;
    the links, counts and merges are those of one match at a time, including a point
    landing on a slot that an earlier match of the same call filled."""
    (a, truth), (b, _) = (_build(np.random.default_rng(6), n_kf=6, n_pts=500) for _ in range(2))
    k = 5
    kf = a.keyframe(k)
    free = np.flatnonzero(kf.point_ids < 0)
    held = np.flatnonzero(kf.point_ids >= 0)
    others = [p for p, o in truth.items() if k not in o]
    seen = [p for p, o in truth.items() if k in o]
    # A point seen only by keyframes 0 and 1 (which share no point with keyframe 5) lands
    # on a free slot, then a point with more observations lands on the same slot and
    # absorbs it: the count between 5 and 0 passes through zero on the way.
    lone = next(p for p, o in truth.items() if set(o) == {0, 1})
    big = next(p for p, o in truth.items() if len(o) == 4 and not {0, 5} & set(o))
    assert a.covisibility_weight(5, 0) == 0
    pids = [lone, big, others[1], others[2], others[3], seen[0], others[4], others[0], others[5]]
    idxs = [free[3], free[3], free[0], held[0], free[1], held[1], held[2], free[2], free[0]]
    got = a.fuse_points(k, np.array(pids), np.array(idxs))[:2]
    want = _fuse_one_by_one(b, k, pids, idxs)
    assert check_invariants(a) == [] and check_invariants(b) == []
    assert got == want and got[0] >= 3 and got[1] >= 2
    assert b.covisibility_weight(5, 0) > 0  # the absorbed point's observation in 0 moved over
    for p in truth:
        assert a.point(p).bad == b.point(p).bad
        assert a.point(p).observations == b.point(p).observations
    for x in range(6):
        for y in range(6):
            assert a.covisibility_weight(x, y) == b.covisibility_weight(x, y)
        np.testing.assert_array_equal(a.covisible_keyframes(x), b.covisible_keyframes(x))


def test_set_bad_keyframe_keeps_spanning_tree_connected():
    rng = np.random.default_rng(5)
    m, _ = _build(rng, n_kf=8, n_pts=900, span=(2, 5))
    # Cull inner keyframes with children; the tree must stay connected each time.
    assert m.set_bad_keyframe(m.origin_id) is False
    for k in (3, 1, 5):
        kf = m.keyframe(k)
        children = set(kf.children)
        assert m.set_bad_keyframe(k)
        assert check_invariants(m) == [], k
        for c in children:
            assert m.keyframe(c).parent not in (-1, k)
        assert kf.bad and kf.n_points() == 0 and not kf.shared
    good = set(m.keyframe_ids().tolist())
    assert good == {0, 2, 4, 6, 7}
    # Protected keyframes are culled only once released.
    m.set_not_erase(6)
    assert m.set_bad_keyframe(6) is False and not m.keyframe(6).bad
    m.set_erase(6)
    assert m.keyframe(6).bad and check_invariants(m) == []


def test_check_invariants_catches_broken_maps():
    rng = np.random.default_rng(6)
    m, truth = _build(rng)
    assert check_invariants(m) == []
    pid, obs = next(iter(truth.items()))
    k, idx = next(iter(obs.items()))
    m.keyframe(k)._point_ids[idx] = -1  # one end of a link cut behind the Map's back
    problems = check_invariants(m)
    assert any(f"point {pid}" in p for p in problems)
    assert any("covisibility weights" in p for p in problems)

    m2, _ = _build(np.random.default_rng(7))
    kf = m2.keyframe(1)
    other = next(iter(kf.shared))
    kf.shared[other] += 3  # a stale weight
    assert any("not symmetric" in p for p in check_invariants(m2))

    m3, _ = _build(np.random.default_rng(8))
    leaf = m3.keyframe(5)
    m3.keyframe(leaf.parent).children.discard(5)
    leaf.parent = -1  # detached from the spanning tree
    assert any("not reachable" in p for p in check_invariants(m3))


def test_essential_graph_and_snapshot(tmp_path):
    rng = np.random.default_rng(9)
    m, truth = _build(rng, n_kf=6, n_pts=900, span=(2, 3))
    m.add_loop_edge(0, 5)
    g = essential_graph(m, min_weight=100)
    pairs = {(int(g.kf_ids[i]), int(g.kf_ids[j])): int(kd) for (i, j), kd in zip(g.edges, g.kind)}
    for kf in m.keyframes():
        if kf.parent >= 0:
            assert pairs[tuple(sorted((kf.id, kf.parent)))] == TREE
    assert pairs[(0, 5)] == LOOP
    counts = _shared_counts(truth)
    strong = {tuple(sorted(p)) for p, c in counts.items() if c >= 100}
    assert {p for p, kd in pairs.items() if kd == COVISIBILITY} == strong - {p for p, kd in pairs.items() if kd != COVISIBILITY}
    snap = snapshot(m)
    assert len(snap.kf_ids) == 6 and len(snap.point_ids) == len(truth)
    for (a, b), w in zip(snap.covis_edges, snap.covis_weights):
        assert counts[(a, b)] == w >= 15
    snap.save(tmp_path / "map.npz")
    back = MapSnapshot.load(tmp_path / "map.npz")
    np.testing.assert_array_equal(back.points, snap.points)
    np.testing.assert_array_equal(back.covis_edges, snap.covis_edges)


def test_point_descriptor_viewing_range_and_scale_prediction():
    rng = np.random.default_rng(10)
    desc = rng.integers(0, 256, (6, 32)).astype(np.uint8)
    ref = np.unpackbits(desc[:, None, :] ^ desc[None, :, :], axis=2).sum(axis=2)
    np.testing.assert_array_equal(hamming_matrix(desc, desc), ref)
    base = rng.integers(0, 256, 32).astype(np.uint8)
    bits = np.unpackbits(base)
    noisy = []
    for _ in range(7):
        b = bits.copy()
        b[rng.choice(256, 20, replace=False)] ^= 1
        noisy.append(np.packbits(b))
    stack = np.array(noisy[:3] + [base] + noisy[3:])
    np.testing.assert_array_equal(distinctive_descriptor(stack), base)
    # Many points at once (sizes 1 to 8, the centre placed at different rows) give what
    # the one-point form gives.
    blocks = [stack[:k] for k in (1, 2, 3)] + [np.roll(stack, r, axis=0) for r in range(5)]
    batched = distinctive_descriptors(np.concatenate(blocks), np.array([len(b) for b in blocks]))
    np.testing.assert_array_equal(batched, np.stack([distinctive_descriptor(b) for b in blocks]))
    np.testing.assert_array_equal(batched[3:], np.tile(base, (5, 1)))

    P = np.array([0.0, 0.0, 4.0])
    normal, dmin, dmax = normal_and_depth(P, np.array([[-1.0, 0, 0], [1.0, 0, 0]]), np.array([-1.0, 0, 0]), 2, SCALES)
    np.testing.assert_allclose(normal, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(dmax, np.sqrt(17) * 1.2**2)
    np.testing.assert_allclose(dmin, dmax / 1.2**7)

    dist = 10.0 / 1.2 ** np.array([0.0, 2.5, 3.0, 20.0, -1.0])
    np.testing.assert_array_equal(predict_scale(dist, np.full(5, 10.0), SCALES), [0, 3, 3, 7, 0])


def test_local_window_round_trip():
    rng = np.random.default_rng(11)
    m, truth = _build(rng, n_kf=6, n_pts=900, span=(2, 4))
    w = local_window(m, 3)
    assert w.kf_ids[0] == 3
    assert set(w.kf_ids[~w.fixed].tolist()) == {3} | set(m.covisible_keyframes(3).tolist()) - {m.origin_id}
    local = set(w.kf_ids[: len(m.covisible_keyframes(3)) + 1].tolist())
    expected_pts = {p for p, o in truth.items() if set(o) & local}
    assert set(w.point_ids.tolist()) == expected_pts
    for o in range(0, w.n_observations, 97):
        kf = m.keyframe(int(w.kf_ids[w.obs_kf[o]]))
        assert kf.point_ids[w.obs_feat[o]] == w.point_ids[w.obs_pt[o]]
        np.testing.assert_array_equal(w.uv[o], kf.keypoints.uv[w.obs_feat[o]])
    outlier = np.zeros(w.n_observations, dtype=bool)
    outlier[:5] = True
    new_pts = w.points + 1.0
    apply_window(m, w, w.T_cw, new_pts, outlier)
    for o in range(5):
        kf_id, pid = int(w.kf_ids[w.obs_kf[o]]), int(w.point_ids[w.obs_pt[o]])
        assert kf_id not in m.point(pid).observations
        assert m.keyframe(kf_id).point_ids[w.obs_feat[o]] == -1
    assert check_invariants(m) == []
    alive = ~m._pts.bad[w.point_ids]
    np.testing.assert_allclose(m.positions(w.point_ids[alive]), new_pts[alive])


def test_update_points_matches_single_point_formulas():
    rng = np.random.default_rng(12)
    m, truth = _build(rng, n_kf=5, n_pts=200, span=(2, 5))
    pids = np.array(sorted(truth))
    for pid in pids[::14]:  # a reference keyframe that is not the first observer
        m._pts.ref_kf[pid] = list(truth[pid])[-1]
    m.update_points(pids)
    for pid in pids[::7]:
        obs = truth[pid]
        kfs = [m.keyframe(k) for k in obs]
        ref = m.keyframe(m.point(pid).ref_kf)
        normal, dmin, dmax = normal_and_depth(
            m.point(pid).position, np.array([kf.center for kf in kfs]), ref.center,
            int(ref.keypoints.octave[obs[ref.id]]), SCALES,
        )  # fmt: skip
        np.testing.assert_allclose(m.point(pid).normal, normal, atol=1e-12)
        assert m.point(pid).max_dist == pytest.approx(dmax) and m.point(pid).min_dist == pytest.approx(dmin)
        desc = np.stack([kf.keypoints.desc[obs[kf.id]] for kf in kfs])
        np.testing.assert_array_equal(m.point(pid).descriptor, distinctive_descriptor(desc))
