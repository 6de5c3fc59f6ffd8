"""Recall and precision of a loop-closure detector against a ground-truth loop matrix.

Counting (one decision per test image, as in FAB-MAP's and the HGCN paper's evaluations):
for query image ``i`` only earlier images ``j <= i - min_gap`` are candidates. Its best
candidate ``j* = argmax_j scores[i, j]`` is *accepted* when ``scores[i, j*] >= threshold``.

- TP: accepted and ``gt[i, j*]`` is a true loop;
- FP: accepted and ``gt[i, j*]`` is not a loop;
- FN: image i has a true loop among its candidates and no correct match was accepted
  (nothing accepted, or a wrong image accepted: such a row counts both FP and FN);
- TN: no true loop among its candidates and nothing accepted.

The HGCN paper's equations (9) and (10): ``recall = TP / (TP + FN)`` and ``accuracy`` (its
name for precision) ``= TP / (TP + FP)``. ``TP + FN`` is the number of images with a true
loop, whatever the threshold. The ground truth is used symmetrised (``gt | gt.T``), so a
matrix marking each loop in either triangle works.

The precision-recall curve sweeps the threshold over every distinct positive best score;
``auc`` is the area under it as the step-wise average precision
``sum_k (R_k - R_{k-1}) P_k`` (R_0 = 0); ``recall_at_100p`` is the largest recall reached
with no false positive.

Both rest on the few queries with a true loop, so each comes with a 95% confidence interval
(:func:`bootstrap_ci`): the percentile interval of the figure over ``BOOTSTRAP_RESAMPLES``
resamples of the query images drawn with replacement (each query keeps its best match and
whether it has a true loop), from a fixed seed so that a run is reproducible. Queries closer
than the exclusion window see the same place and are not independent, so the resamples are
drawn in blocks of that many consecutive queries (a moving-block bootstrap, Kunsch, Annals of
Statistics 1989): a figure that rests on one visit gets the wide interval it deserves.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np

log = logging.getLogger(__name__)


BOOTSTRAP_RESAMPLES = 1000
BOOTSTRAP_SEED = 0
CI_LEVEL = 0.95
_BOOTSTRAP_CHUNK = 2_000_000  # resamples x queries held at once


def candidate_mask(n: int, min_gap: int) -> np.ndarray:
    """(n, n) bool: True where image j may match query i (``j <= i - min_gap``)."""
    return np.tri(n, n, -max(1, min_gap), dtype=bool)


def best_matches(scores: np.ndarray, min_gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Per query: (best candidate (n,) int64, -1 when none; its score (n,) float64, -inf when none)."""
    n = scores.shape[0]
    mask = candidate_mask(n, min_gap)
    masked = np.where(mask, scores, -np.inf)
    best = masked.argmax(axis=1) if n else np.zeros(0, dtype=np.int64)
    score = masked[np.arange(n), best] if n else np.zeros(0)
    has = mask.any(axis=1)
    return np.where(has, best, -1).astype(np.int64), np.where(has, score, -np.inf)


def _check(scores: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    scores = np.asarray(scores, dtype=np.float64)
    gt = np.asarray(gt).astype(bool)
    if scores.ndim != 2 or scores.shape[0] != scores.shape[1]:
        raise ValueError(f"scores must be a square matrix, found shape {scores.shape}")
    if gt.shape != scores.shape:
        raise ValueError(f"ground truth {gt.shape} and scores {scores.shape} differ in shape")
    return scores, gt | gt.T


def decisions(scores: np.ndarray, gt: np.ndarray, min_gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per query: (best score (n,), best is a true loop (n,) bool, has a true loop (n,) bool)."""
    scores, gt = _check(scores, gt)
    n = scores.shape[0]
    best, score = best_matches(scores, min_gap)
    correct = np.zeros(n, dtype=bool)
    ok = best >= 0
    correct[ok] = gt[np.flatnonzero(ok), best[ok]]
    positive = (gt & candidate_mask(n, min_gap)).any(axis=1)
    return score, correct, positive


@dataclass(frozen=True)
class Counts:
    """Confusion counts at one threshold, with the paper's recall and accuracy (precision)."""

    threshold: float
    tp: int
    fp: int
    fn: int
    tn: int

    @property
    def recall(self) -> float:
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else float("nan")

    @property
    def precision(self) -> float:
        return self.tp / (self.tp + self.fp) if self.tp + self.fp else float("nan")


def confusion_counts(scores: np.ndarray, gt: np.ndarray, threshold: float, min_gap: int = 1) -> Counts:
    """TP/FP/FN/TN of the best-match decisions at ``threshold`` (see the module docstring)."""
    score, correct, positive = decisions(scores, gt, min_gap)
    has_candidate = candidate_mask(len(score), min_gap).any(axis=1)
    accepted = has_candidate & (score >= threshold)
    tp = int(np.sum(accepted & correct))
    fp = int(np.sum(accepted & ~correct))
    fn = int(np.sum(positive & ~(accepted & correct)))
    tn = int(np.sum(~positive & ~accepted))
    return Counts(float(threshold), tp, fp, fn, tn)


@dataclass(frozen=True, eq=False)
class PRCurve:
    """thresholds (K,) descending; precision, recall (K,) at each; n_positive images with a loop."""

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    n_positive: int

    @property
    def auc(self) -> float:
        """Step-wise area under the curve (average precision); NaN without positives."""
        if self.n_positive == 0:
            return float("nan")
        if len(self.recall) == 0:
            return 0.0
        dr = np.diff(np.concatenate(([0.0], self.recall)))
        return float(np.sum(dr * self.precision))

    @property
    def recall_at_100p(self) -> float:
        """The largest recall with precision 1 (0 when the first acceptance is wrong)."""
        if self.n_positive == 0:
            return float("nan")
        full = self.precision >= 1.0
        return float(self.recall[full].max()) if full.any() else 0.0


def pr_curve(scores: np.ndarray, gt: np.ndarray, min_gap: int = 1, *, floor: float = 0.0) -> PRCurve:
    """Sweep the threshold over every distinct best-match score above ``floor``.

    floor: scores at or below it never count as a match (0 for similarities and
    probabilities; ``-inf`` for log-probabilities).
    """
    score, correct, positive = decisions(scores, gt, min_gap)
    n_pos = int(positive.sum())
    thr, tp, fp = _sweep(score, correct, np.ones((1, len(score))), floor)
    tp, fp = tp[0], fp[0]
    precision = tp / np.maximum(tp + fp, 1)
    recall = tp / n_pos if n_pos else np.full(len(tp), np.nan)
    if n_pos == 0:
        log.warning("ground truth has no loop among the candidate pairs: recall is undefined")
    return PRCurve(thr, precision.astype(np.float64), np.asarray(recall, dtype=np.float64), n_pos)


def _sweep(
    score: np.ndarray, correct: np.ndarray, weights: np.ndarray, floor: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The threshold sweep of :func:`pr_curve` over weighted query sets: the distinct best
    scores above ``floor``, descending, (K,), and the weighted true and false acceptances at
    each, (B, K), for ``weights`` (B, n) (how many times each query counts in each set)."""
    keep = np.isfinite(score) & (score > floor)
    s = np.asarray(score)[keep]
    order = np.argsort(-s, kind="stable")
    s, c = s[order], np.asarray(correct, dtype=bool)[keep][order]
    wk = np.asarray(weights, dtype=np.float64)[:, keep][:, order]
    last = np.flatnonzero(np.r_[s[1:] != s[:-1], True]) if len(s) else np.zeros(0, dtype=np.int64)
    return s[last], np.cumsum(wk * c, axis=1)[:, last], np.cumsum(wk * ~c, axis=1)[:, last]


def curve_figures(
    score: np.ndarray, correct: np.ndarray, positive: np.ndarray, weights: np.ndarray, *, floor: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """AUC and recall at 100% precision (as :class:`PRCurve` has them) of weighted query sets.

    score, correct, positive: (n,) per query, as :func:`decisions` gives them; weights: (B, n)
    how many times each query counts in each of B sets (a bootstrap resample: counts
    summing to n; all ones: the queries as they are). Returns ((B,) AUC, (B,) recall at 100%
    precision), NaN for a set without a query that has a true loop.
    """
    w = np.atleast_2d(np.asarray(weights, dtype=np.float64))
    n_pos = w @ np.asarray(positive, dtype=np.float64)
    _, tp, fp = _sweep(score, correct, w, floor)
    nan = np.full(len(w), np.nan)
    if tp.shape[1] == 0:
        zero = np.where(n_pos > 0, 0.0, nan)
        return zero, zero
    precision = tp / np.maximum(tp + fp, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        recall = tp / n_pos[:, None]
    dr = np.diff(recall, axis=1, prepend=0.0)
    auc = np.sum(dr * precision, axis=1)
    r100 = np.max(np.where(precision >= 1.0, recall, 0.0), axis=1)
    return np.where(n_pos > 0, auc, nan), np.where(n_pos > 0, r100, nan)


@dataclass(frozen=True)
class BootstrapCI:
    """95% confidence intervals (low, high) of AUC and recall at 100% precision, from
    ``resamples`` resamples of the ``queries`` query images (``valid`` of them with a query
    that has a true loop; the others leave the figures undefined and are not counted)."""

    auc: tuple[float, float]
    recall_at_100p: tuple[float, float]
    resamples: int
    valid: int
    queries: int
    level: float = CI_LEVEL


def bootstrap_from_decisions(
    score: np.ndarray, correct: np.ndarray, positive: np.ndarray, *, floor: float = 0.0,
    resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED, level: float = CI_LEVEL, block: int = 1,
) -> BootstrapCI:
    """:func:`bootstrap_ci` on the per-query decisions of :func:`decisions`; ``block``: queries
    are drawn in runs of this many consecutive ones (wrapping round), 1 for single queries."""
    n = len(score)
    rng = np.random.default_rng(seed)
    aucs, r100s = [], []
    chunk = max(1, _BOOTSTRAP_CHUNK // max(n, 1))
    block = int(min(max(block, 1), max(n, 1)))
    n_blocks = -(-n // block) if n else 0
    for start in range(0, resamples if n else 0, chunk):
        b = min(chunk, resamples - start)
        starts = rng.integers(0, n, size=(b, n_blocks))
        draw = ((starts[:, :, None] + np.arange(block)) % n).reshape(b, n_blocks * block)[:, :n]
        weights = np.bincount((np.arange(b)[:, None] * n + draw).ravel(), minlength=b * n).reshape(b, n)
        a, r = curve_figures(score, correct, positive, weights, floor=floor)
        aucs.append(a)
        r100s.append(r)
    aucs = np.concatenate(aucs) if aucs else np.zeros(0)
    r100s = np.concatenate(r100s) if r100s else np.zeros(0)
    ok = np.isfinite(aucs)
    q = [50 * (1 - level), 50 * (1 + level)]

    def interval(x: np.ndarray) -> tuple[float, float]:
        if not ok.any():
            return (float("nan"), float("nan"))
        lo, hi = np.percentile(x[ok], q)
        return (float(lo), float(hi))

    return BootstrapCI(interval(aucs), interval(r100s), int(resamples if n else 0), int(ok.sum()), n, level)


def bootstrap_ci(
    scores: np.ndarray, gt: np.ndarray, min_gap: int = 1, *, floor: float = 0.0,
    resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED, level: float = CI_LEVEL,
) -> BootstrapCI:
    """Percentile bootstrap confidence intervals of AUC and recall at 100% precision.

    The query images (rows of ``scores``) are resampled with replacement ``resamples``
    times from ``seed``, in blocks of ``min_gap`` consecutive queries (the exclusion window:
    queries closer than that see the same place); each resample's curve is
    :func:`pr_curve`'s over the queries drawn (each keeping its best match, whether that is
    a true loop, and whether it has one).
    """
    score, correct, positive = decisions(scores, gt, min_gap)
    return bootstrap_from_decisions(score, correct, positive, floor=floor, resamples=resamples, seed=seed,
                                    level=level, block=min_gap)


def full_precision_threshold(scores: np.ndarray, gt: np.ndarray, min_gap: int = 1, *, floor: float = 0.0) -> float:
    """The acceptance threshold with the highest recall at 100% precision on ``scores``.

    It is the lowest best-match score of a correct match that ranks above every wrong best
    match (scores at or below ``floor`` are never accepted, as in :func:`pr_curve`), so every
    match it accepts on these scores is right. When no correct match outranks the wrong
    ones, it lies just above the highest best-match score: nothing is accepted.
    """
    score, correct, _ = decisions(scores, gt, min_gap)
    keep = np.isfinite(score) & (score > floor)
    s, c = score[keep], correct[keep]
    wrong = s[~c].max() if (~c).any() else -np.inf
    good = s[c & (s > wrong)]
    if len(good):
        return float(good.min())
    top = s.max() if len(s) else floor
    return float(np.nextafter(max(top, floor), np.inf))


@dataclass(frozen=True)
class DetectorScore:
    """Summary of one detector: recall/accuracy at a threshold, recall@100%P and AUC."""

    method: str
    threshold: float
    recall: float
    accuracy: float
    tp: int
    fp: int
    fn: int
    tn: int
    recall_at_100p: float
    auc: float
    n_positive: int
    recall_at_100p_ci: tuple[float, float] | None = None  # 95% bootstrap interval over the queries
    auc_ci: tuple[float, float] | None = None
    ci_resamples: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


def score_detector(
    method: str,
    scores: np.ndarray,
    gt: np.ndarray,
    threshold: float,
    min_gap: int = 1,
    *,
    log_scores: np.ndarray | None = None,
    threshold_is_log: bool = False,
    resamples: int = BOOTSTRAP_RESAMPLES,
) -> tuple[DetectorScore, PRCurve]:
    """Everything the comparison table and plots need for one detector.

    log_scores: (n, n) log of ``scores`` where the detector has it (FAB-MAP's log
    posteriors); decisions are then taken on it, so that posteriors too small for float64
    (below about 1e-308) still rank. The curve's thresholds are given as probabilities.
    threshold_is_log: ``threshold`` is a log-probability (with ``log_scores``), as
    :func:`full_precision_threshold` finds it on them. resamples: of the bootstrap
    confidence intervals of AUC and recall at 100% precision (:func:`bootstrap_ci`); 0 for none.
    """
    if log_scores is not None:
        if threshold_is_log:
            log_thr, threshold = float(threshold), float(np.exp(threshold))
        else:
            log_thr = float(np.log(threshold)) if threshold > 0 else -np.inf
        counts = confusion_counts(log_scores, gt, log_thr, min_gap)
        counts = Counts(float(threshold), counts.tp, counts.fp, counts.fn, counts.tn)
        curve = pr_curve(log_scores, gt, min_gap, floor=-np.inf)
        curve = PRCurve(np.exp(curve.thresholds), curve.precision, curve.recall, curve.n_positive)
        values, floor = log_scores, -np.inf
    else:
        counts = confusion_counts(scores, gt, threshold, min_gap)
        curve = pr_curve(scores, gt, min_gap)
        values, floor = scores, 0.0
    ci = bootstrap_ci(values, gt, min_gap, floor=floor, resamples=resamples) if resamples > 0 else None
    summary = DetectorScore(
        method=method, threshold=float(threshold), recall=counts.recall, accuracy=counts.precision,
        tp=counts.tp, fp=counts.fp, fn=counts.fn, tn=counts.tn,
        recall_at_100p=curve.recall_at_100p, auc=curve.auc, n_positive=curve.n_positive,
        recall_at_100p_ci=ci.recall_at_100p if ci is not None else None,
        auc_ci=ci.auc if ci is not None else None, ci_resamples=ci.resamples if ci is not None else 0,
    )
    return summary, curve
