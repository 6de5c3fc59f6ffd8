"""Recall / accuracy (precision) / PR-curve metrics on a hand-made confusion matrix."""

import numpy as np
import pytest

from orbslam_hgcn.placerec.metrics import confusion_counts, pr_curve, score_detector


def _example():
    """6 images; true loops (3,0), (4,1), (5,2) given in the upper triangle (symmetrised).

    Best earlier match per query: 1 -> 0 (0.7, no loop exists: FP), 2 -> 0 (0.3, FP),
    3 -> 0 (0.9, TP), 4 -> 2 (0.8, wrong: its true loop 1 scores 0.5), 5 -> 2 (0.6, TP).
    """
    s = np.zeros((6, 6))
    s[1, 0] = 0.7
    s[2, 0], s[2, 1] = 0.3, 0.1
    s[3, 0], s[3, 2] = 0.9, 0.2
    s[4, 1], s[4, 2] = 0.5, 0.8
    s[5, 2], s[5, 4] = 0.6, 0.05
    s[0, 5] = 0.99  # upper triangle: never a candidate
    gt = np.zeros((6, 6), dtype=bool)
    gt[0, 3] = gt[1, 4] = gt[2, 5] = True
    return s, gt


def test_counts_at_threshold_match_hand_count():
    s, gt = _example()
    c = confusion_counts(s, gt, 0.65)
    # accepted: 3 (TP), 4 (FP, and its loop missed), 1 (FP); 5 below threshold (FN)
    assert (c.tp, c.fp, c.fn, c.tn) == (1, 2, 2, 2)
    assert c.recall == pytest.approx(1 / 3)
    assert c.precision == pytest.approx(1 / 3)
    c = confusion_counts(s, gt, 0.55)
    assert (c.tp, c.fp, c.fn) == (2, 2, 1)
    assert c.recall == pytest.approx(2 / 3) and c.precision == pytest.approx(0.5)
    c = confusion_counts(s, gt, 0.95)
    assert (c.tp, c.fp, c.fn, c.tn) == (0, 0, 3, 3)
    assert np.isnan(c.precision) and c.recall == 0.0


def test_pr_curve_auc_and_recall_at_full_precision():
    s, gt = _example()
    curve = pr_curve(s, gt)
    np.testing.assert_allclose(curve.thresholds, [0.9, 0.8, 0.7, 0.6, 0.3])
    np.testing.assert_allclose(curve.recall, [1 / 3, 1 / 3, 1 / 3, 2 / 3, 2 / 3])
    np.testing.assert_allclose(curve.precision, [1, 1 / 2, 1 / 3, 1 / 2, 2 / 5])
    # step-wise area: 1/3 * 1 + 1/3 * 1/2
    assert curve.auc == pytest.approx(0.5)
    assert curve.recall_at_100p == pytest.approx(1 / 3)
    assert curve.n_positive == 3


def test_min_gap_hides_recent_images_and_their_loops():
    s, gt = _example()
    # with min_gap 3, query 4 may only match 0 or 1 and query 5 only 0..2
    c = confusion_counts(s, gt, 0.4, min_gap=3)
    # query 3 -> 0 (TP), 4 -> 1 (0.5, TP), 5 -> 2 (0.6, TP); queries 1, 2 have no candidate
    assert (c.tp, c.fp, c.fn) == (3, 0, 0)
    summary, curve = score_detector("x", s, gt, 0.4, min_gap=3)
    assert summary.recall == 1.0 and summary.accuracy == 1.0
    assert curve.recall_at_100p == 1.0 and curve.auc == pytest.approx(1.0)


def test_ties_are_one_threshold_and_first_error_gives_zero_r100():
    s = np.zeros((4, 4))
    s[1, 0] = 0.5  # FP (no loop)
    s[2, 0] = 0.5  # TP
    s[3, 1] = 0.2  # TP
    gt = np.zeros((4, 4), bool)
    gt[2, 0] = gt[3, 1] = True
    curve = pr_curve(s, gt)
    np.testing.assert_allclose(curve.thresholds, [0.5, 0.2])
    np.testing.assert_allclose(curve.precision, [0.5, 2 / 3])
    assert curve.recall_at_100p == 0.0
    assert curve.auc == pytest.approx(0.5 * 0.5 + 0.5 * 2 / 3)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="differ in shape"):
        confusion_counts(np.zeros((3, 3)), np.zeros((4, 4)), 0.5)


def test_log_scores_rank_posteriors_that_underflow():
    s, gt = _example()
    with np.errstate(divide="ignore"):
        log_s = np.where(s > 0, -1000.0 + 100.0 * s, -np.inf)  # exp() of these is 0.0
    assert np.all(np.exp(log_s) == 0.0)
    plain, plain_curve = score_detector("x", np.exp(log_s), gt, 1e-300)
    assert plain.tp == 0 and len(plain_curve.recall) == 0
    summary, curve = score_detector("x", np.exp(log_s), gt, 0.0, log_scores=log_s)
    assert curve.auc == pytest.approx(0.5)  # the same ranking as the hand example
    assert curve.recall_at_100p == pytest.approx(1 / 3)
    assert (summary.tp, summary.fp, summary.fn) == (2, 3, 1)  # everything accepted at p >= 0
