"""Which images the loop-closure experiment compares: sampling, the exclusion window, and
the threshold fitted on the training sequence, on hand-made inputs with known answers."""

import numpy as np
import pytest

from orbslam_hgcn.errors import OrbslamError
from orbslam_hgcn.placerec.metrics import confusion_counts, decisions, full_precision_threshold, pr_curve
from orbslam_hgcn.placerec.window import (
    SAMPLE_EVERY_S,
    WINDOW_S,
    choose_window,
    hidden_revisits,
    recent_past_share,
    revisit_pairs,
    sample_by_motion,
    sample_indices,
    window_from_ground_truth,
    window_from_timestamps,
)


def _band_and_loops(n: int, band: int, loops: list[tuple[int, int]]) -> np.ndarray:
    """A loop matrix: every pair closer than ``band`` frames is one visit (diagonal
    included, as synth's loop_gt.npy has it), plus the given revisit blocks (3x3 each)."""
    i, j = np.indices((n, n))
    gt = np.abs(i - j) < band
    for a, b in loops:
        gt[a - 1:a + 2, b - 1:b + 2] = True
        gt[b - 1:b + 2, a - 1:a + 2] = True
    return gt


def test_revisits_leave_out_the_visit_joined_to_the_diagonal():
    gt = _band_and_loops(100, band=6, loops=[(60, 20), (90, 30)])
    rev = revisit_pairs(gt)
    i, j = np.nonzero(rev)
    assert len(i) == 18  # the two 3x3 blocks, lower triangle only
    assert set(zip(i.tolist(), j.tolist())) >= {(60, 20), (90, 30), (61, 21), (59, 19)}
    assert not np.any(np.triu(rev))
    # a matrix of loop closures only (no band) is all revisits
    loops_only = np.zeros((10, 10), bool)
    loops_only[8, 2] = loops_only[9, 7] = True  # even a pair 2 apart, not touching j = i - 1
    np.testing.assert_array_equal(revisit_pairs(loops_only), loops_only)


def test_window_from_ground_truth_is_its_smallest_loop_separation():
    gt = _band_and_loops(100, band=6, loops=[(60, 20), (90, 30)])
    t = np.arange(100) / 30.0
    w = window_from_ground_truth(revisit_pairs(gt), t)
    assert w.gap == 38  # the block round (60, 20) spans rows 59-61, columns 19-21: 59 - 21
    assert w.seconds == pytest.approx(38 / 30.0)
    assert "smallest loop separation" in w.describe()
    assert window_from_ground_truth(revisit_pairs(_band_and_loops(50, 6, []))) is None
    # the default: ground truth first, timestamps when it has no loop
    assert choose_window(revisit_pairs(gt), t).gap == 38
    t600 = np.arange(600) / 30.0
    no_loop = choose_window(revisit_pairs(_band_and_loops(600, 6, [])), t600)
    assert no_loop.gap == int(WINDOW_S * 30)  # j <= i - 300: at least 10 s back
    assert no_loop.seconds == pytest.approx(WINDOW_S) and "no loop" in no_loop.source


def test_window_from_timestamps_covers_the_seconds_for_every_query():
    # 10 images per second, then a gap of 5 s, then 2 per second
    t = np.r_[np.arange(30) / 10.0, 8.0 + np.arange(10) / 2.0]
    w = window_from_timestamps(t, 2.0)
    # every candidate j <= i - gap lies at least 2 s back, and gap - 1 would not do
    i = np.arange(w.gap, len(t))
    assert np.all(t[i] - t[i - w.gap] >= 2.0 - 1e-9)
    assert np.any(t[w.gap - 1:] - t[:len(t) - w.gap + 1] < 2.0)
    assert w.gap == 20 and w.seconds == pytest.approx(2.0)
    # a 30 frames/s sequence: never one frame
    assert window_from_timestamps(np.arange(600) / 30.0, 0.5).gap == 15
    with pytest.raises(OrbslamError, match="no timestamps"):
        window_from_timestamps(None)
    with pytest.raises(OrbslamError, match="both set the exclusion window"):
        choose_window(None, t, min_gap=3, window_s=2.0)
    assert choose_window(None, t, min_gap=3).gap == 3


def test_hidden_revisits_and_recent_past():
    gt = _band_and_loops(100, band=6, loops=[(60, 20), (90, 30)])
    rev = revisit_pairs(gt)
    assert hidden_revisits(rev, 38) == (0, 0)
    lost, pairs = hidden_revisits(rev, 50)  # the block at (60, 20) lies 38-42 back: hidden
    assert pairs == 9 and lost == 3
    best = np.r_[-1, np.arange(0, 9)]  # every query's best match is the image before it
    assert recent_past_share(best) == 1.0
    assert recent_past_share(np.r_[-1, -1, 0, 0, 0, 0, 0, 0, 0, 0]) == pytest.approx(2 / 8)


def test_sampling_by_motion_time_and_overrides():
    # a camera moving 1.1 cm per frame along x, still for 50 frames, then turning 0.7 deg per frame
    n = 200
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:100, 0, 3] = np.arange(100) * 0.011
    poses[100:, 0, 3] = 99 * 0.011
    for k in range(150, n):
        a = np.radians(0.7 * (k - 149))
        poses[k, :3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    keep = sample_by_motion(poses, 0.25, 15.0)
    # 23 frames make 0.253 m; from frame 92 the camera stops 0.077 m on, then turns:
    # 22 frames make 15.4 deg (frame 171), 22 more 15.4 deg again (frame 193)
    np.testing.assert_array_equal(keep, [0, 23, 46, 69, 92, 171, 193])
    t = np.arange(n) / 30.0
    s = sample_indices(n, t, poses)
    np.testing.assert_array_equal(s.indices, keep)
    assert "camera motion" in s.how
    s = sample_indices(n, t, None)
    assert np.allclose(np.diff(t[s.indices]), SAMPLE_EVERY_S, atol=1 / 30.0) and "per 0.5 s" in s.how
    assert len(sample_indices(n, None, None).indices) == n  # an image folder: every image
    np.testing.assert_array_equal(sample_indices(n, t, poses, stride=50).indices, [0, 50, 100, 150])
    np.testing.assert_array_equal(sample_indices(n, t, poses, every_s=2.0).indices, [0, 60, 120, 180])
    with pytest.raises(OrbslamError, match="needs timestamps"):
        sample_indices(n, None, None, every_s=1.0)


@pytest.mark.parametrize("floor", [0.0, -np.inf])
def test_fitted_threshold_reproduces_full_precision_on_training(floor):
    rng = np.random.default_rng(3)
    n = 60
    route = np.r_[np.arange(30), rng.permutation(30)]
    gt = (route[:, None] == route[None, :]) & ~np.eye(n, dtype=bool)
    scores = np.tril(rng.uniform(0.1, 0.6, (n, n)), -1)
    scores[np.tril(gt, -1)] += rng.uniform(0.0, 0.5, np.count_nonzero(np.tril(gt, -1)))
    if floor == -np.inf:
        scores = np.log(np.maximum(scores, 1e-300))
    thr = full_precision_threshold(scores, gt, 1, floor=floor)
    counts = confusion_counts(scores, gt, thr, 1)
    curve = pr_curve(scores, gt, 1, floor=floor)
    assert counts.fp == 0 and counts.tp > 0
    assert counts.recall == pytest.approx(curve.recall_at_100p)  # the highest recall at 100% precision
    # the next best-match score below it is a wrong match: a lower threshold loses 100% precision
    best, correct, _ = decisions(scores, gt, 1)
    below = np.flatnonzero((best < thr) & (best > floor))
    nxt = below[np.argmax(best[below])]
    assert not correct[nxt]
    assert confusion_counts(scores, gt, best[nxt], 1).fp > 0
    # the first acceptance wrong: nothing is accepted
    scores2 = np.where(np.tril(gt, -1), 0.2, np.tril(np.full((n, n), 0.1), -1))
    wrong = int(np.flatnonzero(~gt[40, :30])[0])
    scores2[40, wrong] = 0.9
    thr2 = full_precision_threshold(scores2, gt, 1)
    assert confusion_counts(scores2, gt, thr2, 1).tp + confusion_counts(scores2, gt, thr2, 1).fp == 0
