"""The default sampling of ``orbslam-hgcn lcd`` leaves enough revisits to measure, and its
AUC and recall at 100% precision come with bootstrap confidence intervals.

The trajectories are built here with numpy: a hand-held camera walking a circle at
30 frames/s looking outward, whose last part returns to where it started. Its loop ground
truth is synth's rule (camera centres within 0.5 m and optical axes within 30 deg), so it
also marks every pair of neighbouring frames, one continuous visit.
"""


import numpy as np
import pytest

from orbslam_hgcn.placerec.metrics import (
    bootstrap_ci,
    bootstrap_from_decisions,
    decisions,
    pr_curve,
    score_detector,
)
from orbslam_hgcn.placerec.window import (
    MIN_IMAGES,
    MIN_REVISITS,
    choose_window,
    revisit_pairs,
    revisiting_images,
    sample_by_motion,
    sample_for_loops,
    sample_indices,
)

FPS = 30.0


def circle_walk(n: int = 1000, turns: float = 1.25, radius: float = 1.0) -> np.ndarray:
    """(n, 4, 4) ``T_wc``: ``turns`` times round a circle, the optical axis pointing outward."""
    phi = 2 * np.pi * turns * np.arange(n) / n
    poses = np.tile(np.eye(4), (n, 1, 1))
    z = np.stack([np.cos(phi), np.zeros(n), np.sin(phi)], axis=1)
    y = np.tile([0.0, 1.0, 0.0], (n, 1))
    poses[:, :3, 0] = np.cross(y, z)
    poses[:, :3, 1] = y
    poses[:, :3, 2] = z
    poses[:, :3, 3] = radius * z
    return poses


def straight_walk(n: int = 1000, length: float = 3.0) -> np.ndarray:
    """(n, 4, 4) ``T_wc``: a walk along x looking along it (no place seen twice)."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # optical axis along +x
    poses[:, 0, 3] = np.linspace(0.0, length, n)
    return poses


def loop_gt(poses: np.ndarray, dist: float = 0.5, angle_deg: float = 30.0) -> np.ndarray:
    c, z = poses[:, :3, 3], poses[:, :3, 2]
    near = np.linalg.norm(c[:, None] - c[None], axis=2) < dist
    return near & (z @ z.T > np.cos(np.radians(angle_deg)))


def test_a_slow_hand_held_revisit_is_sampled_densely_enough_to_measure():
    n = 1000
    poses, t = circle_walk(n), np.arange(n) / FPS
    rev = revisit_pairs(loop_gt(poses))
    # one image per distinct view leaves few images and a handful of revisits (the problem)
    base = sample_indices(n, t, poses).indices
    base_rev = rev[np.ix_(base, base)]
    base_window = choose_window(base_rev, t[base])
    assert len(base) < 40 and revisiting_images(base_rev, base_window.gap) < 12
    s = sample_for_loops(n, t, poses, rev)
    assert len(s.indices) >= 80 and s.revisiting >= 20, (len(s.indices), s.revisiting)
    assert s.warning is None and "denser than 0.25 m / 15 deg" in s.how
    # the sparsest spacing that does it: every frame would be 1000 images
    assert len(s.indices) <= 2 * MIN_IMAGES
    # the window is found anew on the images used: more images, about the same time back
    sub = rev[np.ix_(s.indices, s.indices)]
    window = choose_window(sub, t[s.indices])
    assert window.gap > 2 * base_window.gap
    assert window.seconds > 20.0 and base_window.seconds > 20.0
    assert revisiting_images(sub, window.gap) == s.revisiting
    # no pair of one continuous visit counts as a loop, however dense: neighbours never
    i, j = np.nonzero(sub)
    assert len(i) and np.all(t[s.indices[i]] - t[s.indices[j]] > 20.0)


def test_no_densification_without_revisits_or_when_the_spacing_suffices():
    n = 1000
    t = np.arange(n) / FPS
    straight = straight_walk(n)
    s = sample_for_loops(n, t, straight, revisit_pairs(loop_gt(straight)))
    np.testing.assert_array_equal(s.indices, sample_by_motion(straight))
    assert s.revisiting is None and s.warning is None and "denser" not in s.how
    # no ground truth at all: as before
    np.testing.assert_array_equal(sample_for_loops(n, t, straight, None).indices, sample_by_motion(straight))
    # four fast laps: the distinct views already hold plenty of revisits
    laps = circle_walk(n, turns=4.0)
    s = sample_for_loops(n, t, laps, revisit_pairs(loop_gt(laps)))
    np.testing.assert_array_equal(s.indices, sample_by_motion(laps))
    assert len(s.indices) >= MIN_IMAGES and s.revisiting >= MIN_REVISITS and s.warning is None


def test_a_warning_when_even_every_frame_has_too_few_revisits(caplog):
    n = 90  # three seconds that barely come back to the start
    poses, t = circle_walk(n, turns=1.1), np.arange(n) / FPS
    rev = revisit_pairs(loop_gt(poses))
    s = sample_for_loops(n, t, poses, rev, name="test")
    assert len(s.indices) == n  # the sequence is exhausted: every frame
    assert 0 < s.revisiting < MIN_REVISITS
    assert s.warning.startswith(f"test: only {s.revisiting} images revisit an earlier one")
    assert "which keeps every frame" in s.warning and f"fewer than the {MIN_REVISITS}" in s.warning
    assert "confidence intervals" in s.warning
    # a sampling given by hand is kept as it is, with the warning
    given = sample_for_loops(n, t, poses, rev, stride=10)
    np.testing.assert_array_equal(given.indices, np.arange(0, n, 10))
    assert given.revisiting < MIN_REVISITS and "every 10th image (--stride), as given:" in given.warning


def test_lcd_prepares_a_dense_enough_sequence_from_its_files(tmp_path, caplog):
    """prepare_sequence reads the ground truth over every frame before choosing the images
    (a TUM-layout folder; the images themselves are not read)."""
    from pathlib import Path

    from orbslam_hgcn.placerec.experiment import prepare_sequence, write_image_list
    from scipy.spatial.transform import Rotation

    n = 1000
    poses, t = circle_walk(n), np.arange(n) / FPS
    (tmp_path / "camera.yaml").write_text(
        "name: test\nmodel: pinhole\nwidth: 640\nheight: 480\nfps: 30.0\nfx: 535.4\nfy: 539.2\ncx: 320.1\n"
        "cy: 247.6\ndistortion: [0.0, 0.0, 0.0, 0.0, 0.0]\n", encoding="utf-8")
    (tmp_path / "rgb.txt").write_text("".join(f"{s:.6f} rgb/{s:.6f}.png\n" for s in t), encoding="utf-8")
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    (tmp_path / "groundtruth.txt").write_text(
        "".join(f"{s:.6f} {p[0, 3]:.9f} {p[1, 3]:.9f} {p[2, 3]:.9f} {a[0]:.9f} {a[1]:.9f} {a[2]:.9f} {a[3]:.9f}\n"
                for s, p, a in zip(t, poses, q)), encoding="utf-8")
    np.save(tmp_path / "loop_gt.npy", loop_gt(poses))
    prep = prepare_sequence(tmp_path, tmp_path / "loop_gt.npy", stride=None, every_s=None, limit=None,
                            min_gap=None, window_s=None)
    assert len(prep.source) >= 80 and prep.sampling.revisiting >= 20
    assert int(prep.gt.any(axis=1).sum()) == prep.sampling.revisiting
    assert prep.window.seconds > 20.0 and prep.sampling.warning is None
    listed = write_image_list(tmp_path / "images_test.txt", prep).read_text().splitlines()
    assert "denser than 0.25 m / 15 deg" in listed[0] and len(listed) == 2 + len(prep.source)
    # --min-gap counts images of one per distinct view: rescaled to the denser sampling
    base_n = len(sample_by_motion(poses))
    gapped = prepare_sequence(tmp_path, tmp_path / "loop_gt.npy", stride=None, every_s=None, limit=None,
                              min_gap=3, window_s=None)
    np.testing.assert_array_equal(gapped.source.indices, prep.source.indices)
    assert gapped.window.gap == int(np.ceil(3 * len(prep.source) / base_n)) > 3
    assert gapped.window.source == "--min-gap 3, rescaled to the denser sampling"
    # --stride and --min-gap as given: 100 images, 15 apart
    fixed = prepare_sequence(Path(tmp_path), tmp_path / "loop_gt.npy", stride=10, every_s=None, limit=None,
                             min_gap=15, window_s=None)
    assert len(fixed.source) == 100 and fixed.window.gap == 15 and "--stride" in fixed.sampling.how


# ---- bootstrap confidence intervals ----------------------------------------------------


def _queries(n: int, seed: int, share: float = 0.3):
    """Per-query decisions of an imperfect detector: a share of queries with a true loop,
    correct best matches scoring higher on the whole than wrong ones."""
    rng = np.random.default_rng(seed)
    positive = rng.random(n) < share
    correct = positive & (rng.random(n) < 0.8)
    score = np.where(correct, rng.normal(0.7, 0.15, n), rng.normal(0.45, 0.15, n)).clip(0.01, 1.0)
    return score, correct, positive


def _matrix(score, correct, positive):
    """(n, n) scores and ground truth whose decisions (min_gap 1) are the given ones."""
    n = len(score) + 1
    s = np.zeros((n, n))
    gt = np.zeros((n, n), bool)
    for k in range(1, n):
        s[k, 0] = score[k - 1]  # the best match of query k is image 0 ...
        s[k, 1:k] = score[k - 1] / 10
        gt[k, 0] = correct[k - 1]  # ... a true loop when correct
        if positive[k - 1] and not correct[k - 1] and k > 1:
            gt[k, k - 1] = True  # a true loop it missed
    return s, gt


def test_bootstrap_ci_holds_the_estimate_narrows_and_is_reproducible():
    score, correct, positive = _queries(200, seed=1)
    s, gt = _matrix(score, correct, positive)
    d = decisions(s, gt, 1)
    assert np.array_equal(d[1][1:], correct) and np.array_equal(d[2][1:], positive & (np.arange(200) > 0))
    curve = pr_curve(s, gt, 1)
    ci = bootstrap_ci(s, gt, 1)
    assert ci.resamples == 1000 and ci.queries == 201
    assert ci.auc[0] <= curve.auc <= ci.auc[1] and ci.auc[0] < ci.auc[1]
    assert ci.recall_at_100p[0] <= curve.recall_at_100p <= ci.recall_at_100p[1]
    assert 0.0 <= ci.auc[0] and ci.auc[1] <= 1.0
    # fixed seed: the same intervals every time; another seed: other ones
    assert bootstrap_ci(s, gt, 1) == ci
    assert bootstrap_ci(s, gt, 1, seed=5).auc != ci.auc
    # more queries of the same detector: a narrower interval
    widths = []
    for n in (60, 600, 3000):
        sc, co, po = _queries(n, seed=2)
        iv = bootstrap_from_decisions(sc, co, po).auc
        widths.append(iv[1] - iv[0])
    assert widths[0] > 1.8 * widths[1] > 1.8 ** 2 * widths[2], widths


def test_a_figure_from_six_positives_has_a_wide_interval_in_the_detector_score():
    score, correct, positive = _queries(29, seed=3, share=0.0)
    positive[[4, 9, 14, 19, 24, 28]] = True
    correct[[4, 9, 14, 24]] = True
    score[[4, 9, 14, 24]] += 0.3
    s, gt = _matrix(score, correct, positive)
    summary, curve = score_detector("x", s, gt, 0.5, 1)
    assert summary.n_positive == 6 and summary.ci_resamples == 1000
    lo, hi = summary.auc_ci
    assert lo <= summary.auc <= hi and hi - lo > 0.3
    assert summary.recall_at_100p_ci[0] <= summary.recall_at_100p <= summary.recall_at_100p_ci[1]
    assert summary.as_dict()["auc_ci"] == summary.auc_ci
    # log posteriors (FAB-MAP) give the same intervals as the posteriors they rank by
    with np.errstate(divide="ignore"):
        log_summary, _ = score_detector("x", s, gt, 0.5, 1, log_scores=np.log(s))
    assert log_summary.auc_ci == pytest.approx(summary.auc_ci)
    assert score_detector("x", s, gt, 0.5, 1, resamples=0)[0].auc_ci is None


def test_the_table_prints_the_intervals():
    from types import SimpleNamespace

    from orbslam_hgcn.placerec.lcd import format_table

    score, correct, positive = _queries(100, seed=4)
    s, gt = _matrix(score, correct, positive)
    summary, curve = score_detector("BoW", s, gt, 0.5, 1)
    r = SimpleNamespace(score=summary, threshold_from="given", train_score=None,
                        matches=SimpleNamespace(matched=np.zeros(101), min_gap=1))
    table = format_table([r])
    lo, hi = summary.auc_ci
    assert f"{100 * summary.auc:6.1f} [{100 * lo:5.1f},{100 * hi:5.1f}]" in table
    assert "bootstrap over the 101 test queries in blocks of 1 consecutive ones" in table and "1000 resamples" in table


def test_blocks_of_consecutive_queries_widen_the_interval_of_a_figure_from_one_visit():
    """Queries inside the exclusion window see the same place: a figure whose positives all
    sit in one run of consecutive queries must not read as certain. Resampled in blocks of
    the window, the interval is wider than with single queries; block 1 is the plain
    bootstrap, and a block longer than the queries is the whole set, wrapped."""
    score, correct, positive = _queries(300, seed=4, share=0.0)
    positive[200:240] = True
    correct[200:230] = True
    score[200:230] += 0.5
    single = bootstrap_from_decisions(score, correct, positive)
    assert bootstrap_from_decisions(score, correct, positive, block=1) == single
    blocked = bootstrap_from_decisions(score, correct, positive, block=60)
    w1 = single.recall_at_100p[1] - single.recall_at_100p[0]
    w60 = blocked.recall_at_100p[1] - blocked.recall_at_100p[0]
    assert w60 > 1.3 * w1, (w1, w60)
    whole = bootstrap_from_decisions(score, correct, positive, block=10_000)
    assert whole.queries == 300 and whole.valid > 0
    s, gt = _matrix(score, correct, positive)
    assert bootstrap_ci(s, gt, 60) == bootstrap_from_decisions(*decisions(s, gt, 60), block=60)
