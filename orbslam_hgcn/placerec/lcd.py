"""The loop-closure detection comparison of the HGCN paper (its Tables 1 and 2).

Four detectors, each trained on one sequence and tested on another:

=============  ==============================  ==================
method         detector                        default vocabulary
=============  ==============================  ==================
bow            TF-IDF cosine similarity        ORB tree (DBoW2)
hgcn-bow       TF-IDF cosine similarity        HGCN
fabmap2        FAB-MAP 2.0 (Chow-Liu tree)     ORB tree (DBoW2)
hgcn-fabmap    FAB-MAP 2.0 (Chow-Liu tree)     HGCN
=============  ==============================  ==================

Training supplies the IDF weights (BoW) or the Chow-Liu tree and the sampled new-place
model (FAB-MAP). Every method yields an (n, n) matrix over the test images, scored by
:mod:`orbslam_hgcn.placerec.metrics` against the ground-truth loop matrix.

``orbslam-hgcn lcd`` (:func:`lcd_command`) chooses by default which images it compares and
how: about one image per distinct view of each sequence (denser when that leaves fewer than
20 revisiting images or 80 images), the ground truth's revisits as the loops, an exclusion
window from the ground truth or the timestamps (:mod:`orbslam_hgcn.placerec.window`), and
the recall/accuracy threshold of each detector fitted on the training sequence
(:func:`fit_threshold`). AUC and recall at 100% precision come with 95% bootstrap
confidence intervals over the test queries (:func:`~orbslam_hgcn.placerec.metrics.bootstrap_ci`).

Before any detector runs, the memory each one needs is estimated (FAB-MAP's per-word tables
and Chow-Liu tree, the (n, n) matrices) and checked against the memory available (:mod:`orbslam_hgcn.placerec.memory`); one that does not fit
stops the comparison with an OrbslamError naming the way out: a smaller vocabulary, the ORB
tree's words taken at a coarser level (``levels``), or fewer images.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from orbslam_hgcn.config import FabmapConfig
from orbslam_hgcn.errors import OrbslamError, VocabularyError
from orbslam_hgcn.placerec.bow_detector import run_bow
from orbslam_hgcn.placerec.chow_liu import learn_chow_liu_tree
from orbslam_hgcn.placerec.describe import Describer, WordQuantizer, describe_images, words_of
from orbslam_hgcn.placerec.fabmap import FabMap2
from orbslam_hgcn.placerec.memory import bow_bytes, check_memory, fabmap_bytes
from orbslam_hgcn.placerec.metrics import (
    DetectorScore,
    PRCurve,
    best_matches,
    candidate_mask,
    full_precision_threshold,
    score_detector,
)
from orbslam_hgcn.placerec.sequence import PlaceMatches, run_fabmap
from orbslam_hgcn.placerec.window import NEAR_IMAGES, NEAR_SHARE, recent_past_share
from orbslam_hgcn.placerec.words import count_matrix, occurrence_matrix

log = logging.getLogger(__name__)

METHODS = ("bow", "hgcn-bow", "fabmap2", "hgcn-fabmap")
METHOD_VOCAB = {"bow": "orb", "hgcn-bow": "hgcn", "fabmap2": "orb", "hgcn-fabmap": "hgcn"}
# The baselines' vocabulary: the ORB tree at about the HGCN vocabulary's size (k = 10, L = 4,
# about 10k words against 8000), trained on the same photographs. The ORB-SLAM-shaped tree
# (``orb``, about 800k words) leaves FAB-MAP 2.0 a Chow-Liu tree over words that a few dozen
# training images cannot estimate (recall at 100% precision 0 on the rendered office loops
# of tests/test_placerec_lcd_defaults.py); ``--vocab-orb orb`` still selects it.
DEFAULT_ORB_VOCAB = "orb10k"
METHOD_LABEL = {"bow": "BoW", "hgcn-bow": "HGCN-BoW", "fabmap2": "FAB-MAP 2.0", "hgcn-fabmap": "HGCN-FABMAP"}
# Acceptance thresholds of the recall/accuracy columns when they cannot be fitted on the
# training sequence (it has no loop ground truth). FAB-MAP: posterior p(L_j | Z) of 0.99, the
# operating point of Cummins & Newman (IJRR 2008, sec. 6). BoW: cosine similarity.
DEFAULT_FABMAP_THRESHOLD = 0.99
DEFAULT_BOW_THRESHOLD = 0.3


def parse_methods(spec: str) -> list[str]:
    """``all`` or a comma-separated list of method names."""
    if spec.strip().lower() == "all":
        return list(METHODS)
    methods = [m.strip().lower() for m in spec.split(",") if m.strip()]
    for m in methods:
        if m not in METHODS:
            raise OrbslamError(f"unknown method {m!r}; use one of {', '.join(METHODS)} or all")
    return methods


def is_fabmap(method: str) -> bool:
    return method.endswith("fabmap") or method == "fabmap2"


def vocab_size(vocab: WordQuantizer) -> int:
    """Number of words of a vocabulary object (``n_words``, else ``len``)."""
    n = getattr(vocab, "n_words", None)
    if n is None:
        try:
            n = len(vocab)  # type: ignore[arg-type]
        except TypeError:
            raise VocabularyError(f"{vocab!r}: vocabulary does not tell its number of words") from None
    return int(n)


@dataclass(frozen=True, eq=False)
class WordData:
    """The words of the training and test images under one vocabulary.

    train, test: per image, (N_i,) int64 word ids; n_words: vocabulary size.
    """

    train: list[np.ndarray]
    test: list[np.ndarray]
    n_words: int


@dataclass(frozen=True, eq=False)
class LcdResult:
    """One detector's output and its scores.

    threshold_from: where the recall/accuracy threshold came from ("fitted on training",
    "given", "fixed"); train_score: the detector's scores on the training sequence at that
    threshold (when it was fitted there); recent_share: share of the test queries whose best
    match lies within a few images of the query (:func:`~orbslam_hgcn.placerec.window.recent_past_share`).
    """

    method: str
    matches: PlaceMatches
    score: DetectorScore
    curve: PRCurve
    threshold_from: str = "fixed"
    train_score: DetectorScore | None = None
    recent_share: float = 0.0


MEMORY_WAY_OUT = (
    "use a smaller vocabulary (--vocab-orb, --vocab-hgcn or --vocab), the ORB tree's words at a "
    "coarser level (--levels N: its nodes N levels below the root), or fewer images (--stride, --limit)"
)


class TreeLevelWords:
    """An ORB-tree vocabulary whose words are its nodes ``level`` levels below the root.

    A descriptor's word is the ancestor at that depth of its leaf (a leaf shallower than
    ``level`` stands for itself); the distinct such nodes are numbered 0..n_words-1 in
    node order.
    """

    def __init__(self, vocab, level: int) -> None:
        depth = getattr(vocab, "levels", None)
        if depth is None or not hasattr(vocab, "word_nodes"):
            raise VocabularyError(f"{vocab!r}: --levels needs an ORB-tree vocabulary")
        if not 1 <= level <= depth:
            raise VocabularyError(f"--levels {level}: the ORB tree has levels 1..{depth}")
        self.vocab = vocab
        self.level = level
        nodes = vocab.word_nodes(np.arange(vocab.n_words), depth - level)
        _, self.word_of_leaf = np.unique(nodes, return_inverse=True)
        self.n_words = int(self.word_of_leaf.max()) + 1
        self.descriptor_type = vocab.descriptor_type

    def transform_words(self, descriptors: np.ndarray) -> np.ndarray:
        return self.word_of_leaf[np.asarray(self.vocab.transform_words(descriptors), dtype=np.int64)]

    def __repr__(self) -> str:
        return f"{self.vocab!r} at level {self.level} ({self.n_words} words)"


def varying_word_count(word_ids: list[np.ndarray], n_words: int) -> tuple[int, int]:
    """How many words occur in some but not all of the images ``word_ids``, and how many
    (image, word) occurrences of them there are."""
    seen = [np.unique(np.asarray(w, dtype=np.int64)) for w in word_ids]
    counts = np.bincount(np.concatenate(seen), minlength=n_words) if seen else np.zeros(n_words, dtype=np.int64)
    varying = (counts > 0) & (counts < len(word_ids))
    return int(np.count_nonzero(varying)), int(counts[varying].sum())


def detector_memory(method: str, words: WordData) -> tuple[int, str]:
    """Estimated peak bytes of one detector on ``words`` (see :mod:`.memory`), and the
    detector and sizes the estimate is for, in words."""
    n_test = len(words.test)
    sizes = f"{len(words.train)} training and {n_test} test images"
    if is_fabmap(method):
        v_occ, nnz = varying_word_count(words.train, words.n_words)
        return (fabmap_bytes(v_occ, nnz, words.n_words, n_test),
                f"{METHOD_LABEL[method]} ({sizes}; a Chow-Liu tree over the {v_occ} of {words.n_words} "
                f"words that vary in training)")
    return bow_bytes(n_test), f"{METHOD_LABEL[method]} ({sizes}, {words.n_words} words)"


def detect(
    method: str, words: WordData, cfg: FabmapConfig, *, progress: bool = False, memory_limit_mb: float | None = None
) -> PlaceMatches:
    """Run one detector (trained on ``words.train``) over the test images."""
    if is_fabmap(method):
        Xtr = occurrence_matrix(words.train, words.n_words)
        tree = learn_chow_liu_tree(Xtr, smoothing=cfg.smoothing, progress=progress,
                                   memory_limit_mb=memory_limit_mb, way_out=MEMORY_WAY_OUT)
        fm = FabMap2(tree, cfg.p_z_given_e, cfg.p_z_given_not_e, train=Xtr, num_samples=cfg.num_samples, seed=cfg.seed)
        return run_fabmap(fm, occurrence_matrix(words.test, words.n_words), cfg, progress=progress)
    return run_bow(count_matrix(words.train, words.n_words), count_matrix(words.test, words.n_words), cfg.min_gap)


def _decision_scores(matches: PlaceMatches) -> tuple[np.ndarray, float]:
    """The matrix decisions are taken on (FAB-MAP: log posteriors) and its floor."""
    if matches.log_scores is not None:
        return matches.log_scores, -np.inf
    return matches.scores, 0.0


def fit_threshold(
    method: str, words: WordData, train_gt: np.ndarray, cfg: FabmapConfig, *, progress: bool = False,
    memory_limit_mb: float | None = None,
) -> tuple[float, DetectorScore]:
    """The detector run over its own training images (``cfg.min_gap`` their window): the
    threshold of the highest recall at 100% precision there, in the detector's decision
    space (FAB-MAP: log posterior), and its training scores at that threshold."""
    own = WordData(words.train, words.train, words.n_words)
    matches = detect(method, own, cfg, progress=progress, memory_limit_mb=memory_limit_mb)
    values, floor = _decision_scores(matches)
    thr = full_precision_threshold(values, train_gt, matches.min_gap, floor=floor)
    summary, _ = score_detector(METHOD_LABEL[method], matches.scores, train_gt, thr, matches.min_gap,
                                log_scores=matches.log_scores, threshold_is_log=matches.log_scores is not None,
                                resamples=0)
    return thr, summary


def evaluate_methods(
    methods: list[str],
    words_for: dict[str, WordData],
    gt: np.ndarray,
    cfg: FabmapConfig,
    *,
    fabmap_threshold: float | None = None,
    bow_threshold: float | None = None,
    train_gt: np.ndarray | None = None,
    train_gap: int | None = None,
    progress: bool = False,
    memory_limit_mb: float | None = None,
) -> list[LcdResult]:
    """Run and score ``methods``; ``words_for[method]`` holds each method's words.

    The recall/accuracy threshold of a method is ``fabmap_threshold`` / ``bow_threshold``
    when given; else, with ``train_gt`` (the training images' loop matrix), the one fitted on
    the training sequence (:func:`fit_threshold`, window ``train_gap``, default
    ``cfg.min_gap``); else the fixed defaults. Every method's memory is checked
    (:func:`detector_memory` against ``memory_limit_mb``, else the memory available) before
    the first one runs.
    """
    for method in methods:
        wd = words_for[method]
        if gt.shape != (len(wd.test), len(wd.test)):
            raise OrbslamError(f"ground truth is {gt.shape[0]}x{gt.shape[1]} but there are {len(wd.test)} test images")
        if train_gt is not None and train_gt.shape != (len(wd.train), len(wd.train)):
            raise OrbslamError(f"training ground truth is {train_gt.shape[0]}x{train_gt.shape[1]} but there are "
                               f"{len(wd.train)} training images")
        need, what = detector_memory(method, wd)
        check_memory(need, what, MEMORY_WAY_OUT, limit_mb=memory_limit_mb)
        if train_gt is not None:
            need, what = detector_memory(method, WordData(wd.train, wd.train, wd.n_words))
            check_memory(need, what, MEMORY_WAY_OUT, limit_mb=memory_limit_mb)
    train_cfg = dataclasses.replace(cfg, min_gap=train_gap if train_gap is not None else cfg.min_gap)
    results = []
    for method in methods:
        wd = words_for[method]
        log.info("%s: %d training and %d test images, %d words",
                 METHOD_LABEL[method], len(wd.train), len(wd.test), wd.n_words)
        given = fabmap_threshold if is_fabmap(method) else bow_threshold
        train_score = None
        if given is not None:
            thr, source, is_log = given, "given", False
        elif train_gt is not None:
            thr, train_score = fit_threshold(method, wd, train_gt, train_cfg, progress=progress,
                                             memory_limit_mb=memory_limit_mb)
            source, is_log = "fitted on training", is_fabmap(method)
        else:
            thr, source, is_log = (DEFAULT_FABMAP_THRESHOLD if is_fabmap(method) else DEFAULT_BOW_THRESHOLD), "fixed", False
        matches = detect(method, wd, cfg, progress=progress, memory_limit_mb=memory_limit_mb)
        summary, curve = score_detector(METHOD_LABEL[method], matches.scores, gt, thr, matches.min_gap,
                                        log_scores=matches.log_scores, threshold_is_log=is_log)
        best, _ = best_matches(_decision_scores(matches)[0], matches.min_gap)
        share = recent_past_share(best)
        if share > NEAR_SHARE:
            log.warning("%s: the best matches of %.0f%% of the test queries lie within %d images of the query "
                        "(exclusion window: %d images): it finds the recent past, not loops; widen the window "
                        "(--window-s, --min-gap)", METHOD_LABEL[method], 100 * share, NEAR_IMAGES, matches.min_gap)
        results.append(LcdResult(method, matches, summary, curve, source, train_score, share))
    return results


def format_table(results: list[LcdResult]) -> str:
    """The comparison as a text table (the paper's columns plus recall@100%P and AUC, each
    with its 95% bootstrap confidence interval)."""

    def pct(x: float) -> str:
        return "   n/a" if x != x else f"{100 * x:6.1f}"

    def ci(iv: tuple[float, float] | None) -> str:
        if iv is None or iv[0] != iv[0]:
            return f"{'':>13}"
        return f"[{100 * iv[0]:5.1f},{100 * iv[1]:5.1f}]"

    lines = [
        f"{'method':<13} {'thresh':>8} {'from':<8} {'recall%':>7} {'accuracy%':>9} {'TP':>5} {'FP':>5} {'FN':>5} "
        f"{'R@100P%':>7} {'[95% CI]':<13} {'AUC%':>6} {'[95% CI]':<13}"
    ]
    short = {"fitted on training": "training", "given": "given", "fixed": "fixed"}
    for r in results:
        s = r.score
        thr = f"{s.threshold:8.2f}" if 0.01 <= s.threshold or s.threshold == 0 else f"{s.threshold:8.1e}"
        lines.append(
            f"{s.method:<13} {thr} {short.get(r.threshold_from, r.threshold_from):<8} {pct(s.recall):>7} "
            f"{pct(s.accuracy):>9} {s.tp:5d} {s.fp:5d} {s.fn:5d} {pct(s.recall_at_100p):>7} "
            f"{ci(s.recall_at_100p_ci)} {pct(s.auc):>6} {ci(s.auc_ci)}".rstrip()
        )
    n_pos = results[0].score.n_positive if results else 0
    n_queries = len(results[0].matches.matched) if results else 0
    lines.append(f"({n_pos} test images have a true loop; accuracy = precision TP/(TP+FP))")
    resamples = max((r.score.ci_resamples for r in results), default=0)
    if resamples:
        gap = results[0].matches.min_gap if results else 1
        lines.append(f"([95% CI]: bootstrap over the {n_queries} test queries in blocks of {gap} consecutive ones "
                     f"(the exclusion window), {resamples} resamples with replacement, fixed seed; few true loops, "
                     f"or loops from one visit, make it wide)")
    if any(r.threshold_from == "fitted on training" for r in results):
        fits = ", ".join(f"{r.score.method} {pct(r.train_score.recall).strip()}%" for r in results
                         if r.train_score is not None)
        lines.append("(thresholds from training: the highest recall at 100% precision on the training sequence; "
                     f"training recall there: {fits})")
    return "\n".join(lines)


def write_outputs(
    results: list[LcdResult], gt: np.ndarray, out_dir: str | Path, extra: dict | None = None
) -> list[Path]:
    """confusion_<method>.npy/.png per method (and confusion_<method>_log.npy of log
    posteriors for FAB-MAP), pr_curves.png and lcd_results.json."""
    from orbslam_hgcn.placerec.plots import plot_confusion, plot_pr_curves, write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    record: dict = {"methods": {}, **(extra or {})}
    for r in results:
        npy = out / f"confusion_{r.method}.npy"
        np.save(npy, r.matches.scores)
        if r.matches.log_scores is not None:
            np.save(out / f"confusion_{r.method}_log.npy", r.matches.log_scores)
            paths.append(out / f"confusion_{r.method}_log.npy")
        png = plot_confusion(out / f"confusion_{r.method}.png", r.matches.scores, gt, r.score.method,
                             r.matches.min_gap, log_scores=r.matches.log_scores)
        paths += [npy, png]
        record["methods"][r.method] = {
            **r.score.as_dict(),
            "pr_curve": {"threshold": r.curve.thresholds, "recall": r.curve.recall, "precision": r.curve.precision},
            "matched": r.matches.matched,
            "p_new": r.matches.p_new,
            "min_gap": r.matches.min_gap,
            "threshold_from": r.threshold_from,
            "train_score": r.train_score.as_dict() if r.train_score is not None else None,
            "recent_past_share": r.recent_share,
        }
    curves = {r.score.method: (r.curve.recall, r.curve.precision) for r in results}
    paths.append(plot_pr_curves(out / "pr_curves.png", curves))
    paths.append(write_json(out / "lcd_results.json", record))
    return paths


def quantize_sequences(
    train_desc: list[np.ndarray], test_desc: list[np.ndarray], vocab: WordQuantizer
) -> WordData:
    """Word ids of the training and test descriptors under ``vocab``."""
    return WordData(words_of(train_desc, vocab), words_of(test_desc, vocab), vocab_size(vocab))


def check_vocabulary_features(vocab: WordQuantizer, describer: Describer, name: str) -> None:
    """A VocabularyError when a vocabulary's descriptor type does not fit the features."""
    kind = getattr(vocab, "descriptor_type", None)
    want = "binary" if describer.kind == "orb" else "float"
    if kind is not None and kind != want:
        raise VocabularyError(
            f"{name}: a {kind}-descriptor vocabulary cannot quantise {describer.kind} features "
            f"({want} descriptors); pass a vocabulary trained on {describer.kind}"
        )


def run_lcd(
    methods: list[str],
    train_images,
    test_images,
    gt: np.ndarray,
    vocabularies: dict[str, WordQuantizer],
    describer: Describer,
    cfg: FabmapConfig,
    *,
    fabmap_threshold: float | None = None,
    bow_threshold: float | None = None,
    train_gt: np.ndarray | None = None,
    train_gap: int | None = None,
    progress: bool = True,
    memory_limit_mb: float | None = None,
) -> list[LcdResult]:
    """Describe both sequences once, quantise per vocabulary, run and score ``methods``.

    train_images, test_images: sized iterables of grayscale images. vocabularies: for each
    method, the vocabulary object it uses (methods sharing one object share its words).
    Thresholds, ``train_gt`` and ``train_gap``: see :func:`evaluate_methods`.
    memory_limit_mb: the memory the detectors may use (default: what the machine has
    available, or ``$ORBSLAM_HGCN_MEMORY_LIMIT_MB``).
    """
    n_test = len(test_images)
    if gt.shape != (n_test, n_test):
        raise OrbslamError(f"ground truth is {gt.shape[0]}x{gt.shape[1]} but the test sequence has {n_test} images")
    train_desc = describe_images(train_images, describer, total=len(train_images), desc="train features")
    test_desc = describe_images(test_images, describer, total=n_test, desc="test features")
    cache: dict[int, WordData] = {}
    words_for = {}
    for m in methods:
        vocab = vocabularies[m]
        if id(vocab) not in cache:
            check_vocabulary_features(vocab, describer, repr(vocab))
            cache[id(vocab)] = quantize_sequences(train_desc, test_desc, vocab)
        words_for[m] = cache[id(vocab)]
    return evaluate_methods(methods, words_for, gt, cfg, fabmap_threshold=fabmap_threshold,
                            bow_threshold=bow_threshold, train_gt=train_gt, train_gap=train_gap,
                            progress=progress, memory_limit_mb=memory_limit_mb)


def load_vocabularies(
    methods: list[str], vocab: str | None = None, vocab_orb: str | None = None, vocab_hgcn: str | None = None,
    levels: int | None = None,
) -> dict[str, WordQuantizer]:
    """The vocabulary object of each method, each distinct file loaded once.

    ``vocab`` (a kind name ``orb``/``hgcn`` or a file) serves every method; otherwise ORB-tree
    methods use ``vocab_orb`` and HGCN methods ``vocab_hgcn`` (default: the shipped
    vocabulary of that kind). ``levels``: the words of every ORB-tree vocabulary are its
    nodes that many levels below the root (:class:`TreeLevelWords`); a VocabularyError
    when no method uses an ORB tree.
    """
    from orbslam_hgcn.vocabulary.loading import load_vocabulary

    loaded: dict[str, WordQuantizer] = {}
    out = {}
    for m in methods:
        if vocab is not None:
            spec = vocab
        else:
            spec = (vocab_orb or DEFAULT_ORB_VOCAB) if METHOD_VOCAB[m] == "orb" else (vocab_hgcn or "hgcn")
        if spec not in loaded:
            loaded[spec] = load_vocabulary(spec)
            if levels is not None and hasattr(loaded[spec], "levels"):
                loaded[spec] = TreeLevelWords(loaded[spec], levels)
        out[m] = loaded[spec]
    if levels is not None and not any(isinstance(v, TreeLevelWords) for v in out.values()):
        raise VocabularyError(f"--levels {levels}: none of the methods uses an ORB-tree vocabulary")
    return out


@dataclass(frozen=True, eq=False)
class LcdRun:
    """What ``orbslam-hgcn lcd`` did: results, files written, and the lines that say which
    images and windows it used (printed before the table)."""

    results: list[LcdResult]
    paths: list[Path]
    lines: list[str]


def lcd_command(
    *,
    method: str,
    train: str | Path,
    test: str | Path,
    gt: str | Path | None,
    out: str | Path,
    train_gt: str | Path | None = None,
    features: str = "orb",
    vocab: str | None = None,
    vocab_orb: str | None = None,
    vocab_hgcn: str | None = None,
    cfg: FabmapConfig | None = None,
    fabmap_threshold: float | None = None,
    bow_threshold: float | None = None,
    stride: int | None = None,
    every_s: float | None = None,
    window_s: float | None = None,
    limit: int | None = None,
    n_features: int = 1000,
    levels: int | None = None,
    memory_limit_mb: float | None = None,
) -> LcdRun:
    """``orbslam-hgcn lcd``: files in, comparison table and figures out.

    Both sequences are sampled to about one image per distinct view, denser where that
    leaves too few revisits to measure with, unless ``stride`` or ``every_s`` say
    otherwise, and each gets an exclusion window from its ground truth (or
    ``cfg.min_gap`` images when positive, or ``window_s`` seconds); see
    :mod:`orbslam_hgcn.placerec.window`. Thresholds not given are fitted on the training
    sequence when it has a loop ground truth (``train_gt``, default TRAIN/loop_gt.npy).
    Inputs are checked (sequences, ground truth and its size, method names) before any
    vocabulary is loaded or feature extracted.
    """
    from orbslam_hgcn.placerec.experiment import prepare_sequence, warn_hidden_loops, write_image_list
    from orbslam_hgcn.placerec.sequence import check_config

    cfg = check_config(cfg or FabmapConfig())
    methods = parse_methods(method)
    gt_path = Path(gt) if gt is not None else Path(test) / "loop_gt.npy"
    if gt is None and not gt_path.is_file():
        raise OrbslamError(f"{test}: no --gt given and no loop_gt.npy in the test folder")
    train_gt_path = Path(train_gt) if train_gt is not None else Path(train) / "loop_gt.npy"
    if train_gt is None and not train_gt_path.is_file():
        train_gt_path = None
    fixed_gap = cfg.min_gap if cfg.min_gap > 0 else None
    opts = dict(stride=stride, every_s=every_s, limit=limit, min_gap=fixed_gap, window_s=window_s)
    test_prep = prepare_sequence(test, gt_path, name="test", **opts)
    train_prep = prepare_sequence(train, train_gt_path, name="training", **opts)
    lines = []
    for name, prep in (("test", test_prep), ("train", train_prep)):
        lines.append(f"{name}: {len(prep.source)} of {prep.source.total} images ({prep.sampling.how}); "
                     f"images_{name}.txt lists them")
        if prep.gt is not None:
            lines.append(f"{name}: {int(prep.gt.any(axis=1).sum())} images revisit an earlier one "
                         f"({prep.visit_pairs} true pairs within one continuous visit are not loops)")
            if prep.sampling.revisiting is not None and prep.sampling.revisiting != int(prep.gt.any(axis=1).sum()):
                lines.append(f"{name}: {prep.sampling.revisiting} of them revisit one outside the exclusion window")
        if prep.window is not None:
            lines.append(f"{name}: exclusion window {prep.window.describe()}")
        for warning in (prep.sampling.warning, warn_hidden_loops(name, prep)):
            if warning:
                log.warning("%s", warning)
    train_gt_mat = train_prep.gt
    if train_gt_mat is not None and not (train_gt_mat & candidate_mask(len(train_gt_mat), train_prep.window.gap)).any():
        train_gt_mat = None  # no loop outside the window: nothing to fit a threshold on
    if train_gt_mat is None:
        why = "no loop ground truth" if train_prep.gt is None else "no ground-truth loop outside the window"
        lines.append(f"train: {why} ({Path(train) / 'loop_gt.npy'} or --train-gt): thresholds not "
                     "given are the fixed defaults")
    describer = Describer(features, n_features)
    vocabularies = load_vocabularies(methods, vocab, vocab_orb, vocab_hgcn, levels)
    run_cfg = dataclasses.replace(cfg, min_gap=test_prep.window.gap)
    results = run_lcd(methods, train_prep.source, test_prep.source, test_prep.gt, vocabularies, describer, run_cfg,
                      fabmap_threshold=fabmap_threshold, bow_threshold=bow_threshold,
                      train_gt=train_gt_mat, train_gap=train_prep.window.gap if train_prep.window else None,
                      memory_limit_mb=memory_limit_mb)
    extra = {
        "train": str(train), "test": str(test), "ground_truth": str(gt_path),
        "train_ground_truth": str(train_gt_path) if train_gt_path else None, "features": features,
        "stride": stride, "every_s": every_s, "levels": levels,
        "n_train": len(train_prep.source), "n_test": len(test_prep.source),
        "sampling": {"train": train_prep.sampling.how, "test": test_prep.sampling.how},
        "revisiting": {"train": train_prep.sampling.revisiting, "test": test_prep.sampling.revisiting},
        "sampling_warnings": [p.sampling.warning for p in (test_prep, train_prep) if p.sampling.warning],
        "window": {name: {"images": p.window.gap, "seconds": p.window.seconds, "source": p.window.source}
                   for name, p in (("train", train_prep), ("test", test_prep)) if p.window is not None},
        "images": {"train": train_prep.source.indices, "test": test_prep.source.indices},
        "vocabularies": {m: repr(v) for m, v in vocabularies.items()},
        "config": {k: getattr(run_cfg, k) for k in run_cfg.__dataclass_fields__},
    }
    paths = write_outputs(results, test_prep.gt, out, extra)
    paths += [write_image_list(Path(out) / f"images_{name}.txt", p)
              for name, p in (("test", test_prep), ("train", train_prep))]
    return LcdRun(results, paths, lines)
