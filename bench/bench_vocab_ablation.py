"""Vocabulary ablation for loop-closure detection: HGCN against k-means and the vocabulary tree.

Does the HGCN vocabulary earn its place? Each repetition builds a strip world of
``bench_lcd.py`` (a camera along a procedural mural, the test route revisiting its first
part; training images from another mural), extracts the features of both sequences and
trains, on the training sequence only:

* the HGCN vocabulary (``train_hgcn_vocabulary``), with the seed labels shared along
  feature tracks (``tracks on``) and without (``tracks off``);
* the k-means vocabulary (``train_kmeans_vocabulary``): the same PCA, the same seed
  k-means (same settings and seed) and the same word count, with no graph and no network;
* the vocabulary tree (``train_tree_vocabulary``, DBoW2-style; k-means on float
  descriptors) at k=10, L=``--levels`` (up to 10^L words) and, when the flat vocabularies
  are much smaller, also at the depth whose 10^L is nearest their word count (say k=10,
  L=3 for about 1000 words).

``--track-mean`` adds the k-means vocabulary with each test descriptor's word taken from its
causal track mean over the last ``--min-gap`` test images (arm B0 of
``bench_track_words.py``, here also for SIFT, the paper's float-descriptor case).

Every vocabulary's words feed the TF-IDF cosine BoW detector (``--fabmap``: FAB-MAP 2.0
as well; ``--centroid``: also each HGCN vocabulary with the words of its class-mean
centroids instead of its network), scored on the test sequence by recall at 100%
precision and the area under the precision-recall curve. Repetitions use different worlds and training seeds; the table
gives the median and the per-seed values. Axes: ``--features orb sift`` (SIFT stands in
for SURF), ``--tracks on off``, ``--words`` (default: the largest multiple of 100 that
leaves at least ``--per-word`` training descriptors per word).

Tracks join the descriptors matched between consecutive training images (mutual nearest
neighbours, ratio test, RANSAC fundamental matrix): ``build_tracks``, by Hamming distance
for ORB and Euclidean distance for SIFT. Consecutive training images overlap by
``1 - step / 640`` of their width; the share of descriptors in tracks is printed.

The HGCN's training figures are printed too (seed accuracy on the training, validation
and held-out seeds, the validation accuracy of the untrained network, the best epoch,
run-time word agreement and agreement with the seed k-means), to show whether the network
learned anything beyond its seeds.

    python bench/bench_vocab_ablation.py                      # defaults: about 10-15 min on 2 cores
    python bench/bench_vocab_ablation.py --features orb --tracks off --words 500 --repeats 5
    python bench/bench_vocab_ablation.py --train-frames 60 --n-features 1000 --fabmap --json out.json
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import shlex
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from bench_lcd import WIN, strip_world
from orbslam_hgcn.config import FabmapConfig, HgcnTrainConfig, ORBConfig
from orbslam_hgcn.placerec.lcd import WordData, detect, quantize_sequences
from orbslam_hgcn.vocabulary.training.tracks import build_tracks
from orbslam_hgcn.placerec.metrics import score_detector

log = logging.getLogger("bench_vocab_ablation")

TRACK_MEAN = "k-means track mean"
HGCN_FIGURES = (
    ("labelled_accuracy", "train"),
    ("validation_accuracy", "val"),
    ("heldout_accuracy", "held"),
    ("validation_accuracy_untrained", "val@0"),
    ("runtime_word_agreement", "runtime"),
    ("agreement_with_seed_kmeans", "=kmeans"),
)


# --------------------------------------------------------------------------- features


class Extractor:
    """Descriptors and keypoint positions, as ``placerec.describe.Describer`` extracts them."""

    def __init__(self, kind: str, n_features: int) -> None:
        self.kind = kind
        if kind == "orb":
            from orbslam_hgcn.features.orb import ORBExtractor

            self._orb = ORBExtractor(ORBConfig(n_features=n_features))
        else:
            self._sift = cv2.SIFT_create(nfeatures=n_features)

    def __call__(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.kind == "orb":
            kps = self._orb.extract(image)
            return np.ascontiguousarray(kps.desc, np.uint8), np.asarray(kps.uv_raw, np.float32).reshape(-1, 2)
        kps, desc = self._sift.detectAndCompute(image, None)
        if desc is None:
            return np.zeros((0, 128), np.float32), np.zeros((0, 2), np.float32)
        return np.ascontiguousarray(desc, np.float32), np.array([k.pt for k in kps], np.float32).reshape(-1, 2)


def sequence_tracks(desc: list[np.ndarray], uv: list[np.ndarray]) -> np.ndarray:
    """Track id of every descriptor of one sequence (``tracks.build_tracks``: binary
    descriptors by Hamming distance, float ones by Euclidean distance)."""
    return build_tracks(desc, uv, np.zeros(len(desc), np.int64), progress=False)


def causal_track_mean_words(vocab, desc: list[np.ndarray], lone_words: list[np.ndarray], tracks: np.ndarray,
                            window: int) -> list[np.ndarray]:
    """Per image, the word of each descriptor's causal track mean (arm B0 of
    ``bench_track_words.py``): the mean, in the vocabulary's PCA space, of its track's members
    in this image and the ``window - 1`` images before it. A descriptor without a track, or
    whose track has no other member in the window, keeps its own word.

    desc: per image, the descriptors; lone_words: per image, their own words under ``vocab``;
    tracks: (sum N_i,) track ids (-1: none), a track holding at most one descriptor of an image. With ``window`` at most the detector's minimum gap, a
    query and the images it is compared with never share a member."""
    x = [np.asarray(vocab.project(d), np.float64) for d in desc]
    start = np.concatenate([[0], np.cumsum([len(d) for d in desc])])
    out = []
    for k in range(len(desc)):
        own = tracks[start[k]:start[k + 1]]
        words = lone_words[k]
        has = np.flatnonzero(own >= 0)
        if len(has):
            lo = max(0, k - window + 1)
            tw = tracks[start[lo]:start[k + 1]]
            keep = np.isin(tw, own[has])
            ids, inv = np.unique(tw[keep], return_inverse=True)
            sums = np.zeros((len(ids), x[k].shape[1]))
            np.add.at(sums, inv, np.concatenate(x[lo:k + 1])[keep])
            count = np.bincount(inv, minlength=len(ids))
            pos = np.searchsorted(ids, own[has])
            mates = has[count[pos] > 1]
            if len(mates):
                pos = np.searchsorted(ids, own[mates])
                words = np.array(words, copy=True)
                words[mates] = vocab.words_of_points((sums[pos] / count[pos][:, None]).astype(np.float32))
        out.append(words)
    return out


# --------------------------------------------------------------------------- vocabularies


def tree_depths(words: int, levels: int) -> list[int]:
    """Depths of the k=10 trees: ``levels``, and the one whose 10^L is nearest ``words`` in
    ratio when the flat vocabularies have under half of 10^levels words."""
    out = [levels]
    if words < 10**levels / 2:
        near = max(1, int(round(np.log10(words))))
        if near != levels:
            out.append(near)
    return out


def train_all(kind: str, desc: np.ndarray, ids: np.ndarray, tracks: np.ndarray | None, args, words: int,
              seed: int) -> tuple[dict, dict]:
    """{label: vocabulary} and {label: seconds} for one training set."""
    from orbslam_hgcn.vocabulary.flat import train_kmeans_vocabulary
    from orbslam_hgcn.vocabulary.hgcn_vocab import train_hgcn_vocabulary
    from orbslam_hgcn.vocabulary.orb_tree import train_tree_vocabulary

    cfg = dataclasses.replace(HgcnTrainConfig(), **args.hgcn_overrides, n_words=words, seed=seed)
    vocabs, secs = {}, {}
    for mode in args.tracks:
        label = f"HGCN tracks {mode}"
        t0 = time.perf_counter()
        vocabs[label] = train_hgcn_vocabulary(desc, ids, cfg, track_ids=tracks if mode == "on" else None,
                                              trained_on="bench", progress=False)
        secs[label] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vocabs["k-means"] = train_kmeans_vocabulary(desc, ids, cfg, trained_on="bench", progress=False)
    secs["k-means"] = time.perf_counter() - t0
    for L in tree_depths(words, args.levels):
        label = f"tree k=10 L={L}"
        t0 = time.perf_counter()
        vocabs[label] = train_tree_vocabulary(desc, ids, k=10, levels=L, seed=seed, trained_on="bench",
                                              progress=False)
        secs[label] = time.perf_counter() - t0
    return vocabs, secs


def score_words(wd: WordData, gt: np.ndarray, args) -> dict:
    """{detector: {"r100p", "auc"}} of the BoW detector (and FAB-MAP 2.0) on one set of words."""
    out = {}
    cfg = FabmapConfig(min_gap=args.min_gap)
    for method, name in (("bow", "BoW"), ("fabmap2", "FAB-MAP")):
        if method == "fabmap2" and not args.fabmap:
            continue
        m = detect(method, wd, cfg)
        s, _ = score_detector(name, m.scores, gt, 0.5, m.min_gap, log_scores=m.log_scores)
        out[name] = {"r100p": float(s.recall_at_100p), "auc": float(s.auc), "n_positive": int(s.n_positive)}
    return out


# --------------------------------------------------------------------------- report


def pct(x: float) -> str:
    return "  n/a" if x != x else f"{100 * x:5.1f}"


def spread(values: list[float]) -> str:
    v = np.array(values, np.float64)
    return f"{pct(float(np.median(v)))} [{' '.join(pct(x).strip() for x in v)}]"


def paired(diffs: list[float], resamples: int = 10000) -> str:
    """Mean of paired differences (points) with a bootstrap 95% interval over the seeds
    (fixed resampling seed) and wins/losses."""
    d = 100 * np.asarray(diffs, np.float64)
    boot = d[np.random.default_rng(0).integers(0, len(d), (resamples, len(d)))].mean(axis=1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return f"mean {d.mean():+.1f} [{lo:+.1f}, {hi:+.1f}] {int((d > 0).sum())}/{int((d < 0).sum())}"


def summary_table(runs: list[dict], detectors: list[str]) -> str:
    lines = []
    for det in detectors:
        lines.append(f"{det} detector: median over {len(runs) // max(1, len({r['features'] for r in runs}))} "
                     f"repetitions [per-seed values], percent")
        lines.append(f"{'features':<8} {'vocabulary':<24} {'words':>11} {'R@100P median [seeds]':<30} "
                     f"{'AUC median [seeds]':<30}")
        for feat in dict.fromkeys(r["features"] for r in runs):
            rs = [r for r in runs if r["features"] == feat]
            for label in rs[0]["scores"]:
                words = [r["n_words"][label] for r in rs]
                wtxt = str(words[0]) if len(set(words)) == 1 else f"{min(words)}-{max(words)}"
                r100 = [r["scores"][label][det]["r100p"] for r in rs]
                auc = [r["scores"][label][det]["auc"] for r in rs]
                lines.append(f"{feat:<8} {label:<24} {wtxt:>11} {spread(r100):<30} {spread(auc):<30}")
            for label in rs[0]["scores"]:
                if not (label.startswith("HGCN") or label == TRACK_MEAN):
                    continue
                d100 = [r["scores"][label][det]["r100p"] - r["scores"]["k-means"][det]["r100p"] for r in rs]
                dauc = [r["scores"][label][det]["auc"] - r["scores"]["k-means"][det]["auc"] for r in rs]
                lines.append(f"{feat:<8} {label + ' - k-means':<36} R@100P {' '.join(f'{100 * d:+.1f}' for d in d100)}"
                             f"   AUC {' '.join(f'{100 * d:+.1f}' for d in dauc)}  (per seed, points)")
                lines.append(f"{'':<8} {'':<36} R@100P {paired(d100)}   AUC {paired(dauc)}")
        lines.append("")
    return "\n".join(lines)


def training_table(runs: list[dict]) -> str:
    head = " ".join(f"{short:>7}" for _, short in HGCN_FIGURES)
    lines = ["HGCN training figures (seed accuracy: train / validation / held-out seeds; val@0: validation "
             "accuracy of the untrained network; runtime: run-time words = the network's training labels; "
             "=kmeans: training labels = nearest seed k-means centre)",
             f"{'features':<8} {'seed':>4} {'tracks':>6} {'in tracks':>9} {'seeds':>6} {head} {'epochs':>7} "
             f"{'best':>4} {'loss first->last':>17} {'train s':>7}"]
    for r in runs:
        for label, st in r["hgcn_stats"].items():
            figs = " ".join(f"{'n/a' if st.get(k) is None else format(st[k], '.4f'):>7}" for k, _ in HGCN_FIGURES)
            mode = label.split()[-1]
            share = f"{100 * r['track_share']:8.1f}%" if mode == "on" else f"{'-':>9}"
            loss = f"{st.get('loss_first')}->{st.get('loss_last')}"
            lines.append(f"{r['features']:<8} {r['seed']:>4} {mode:>6} {share} {st.get('labelled_nodes', 0):>6} {figs} "
                         f"{st.get('hgcn_epochs', 0):>7} {st.get('hgcn_best_epoch', 0):>4} {loss:>17} "
                         f"{st.get('train_seconds', 0):>7.1f}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- main


def parse_overrides(ap: argparse.ArgumentParser, items: list[str]) -> dict:
    """{field: value} of ``--hgcn FIELD=VALUE`` items, each value of its field's type."""
    fields = {f.name: type(getattr(HgcnTrainConfig(), f.name)) for f in dataclasses.fields(HgcnTrainConfig)}
    out = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in fields or name in ("n_words", "seed") or not value:
            ap.error(f"--hgcn {item}: expected FIELD=VALUE with FIELD one of "
                     f"{', '.join(n for n in fields if n not in ('n_words', 'seed'))} (use --words, --seed)")
        kind = fields[name]
        try:
            out[name] = value.lower() in ("1", "true", "yes", "on") if kind is bool else kind(value)
        except ValueError:
            ap.error(f"--hgcn {item}: {value!r} is not a {kind.__name__}")
    try:
        HgcnTrainConfig(**out)
    except Exception as exc:  # ConfigError
        ap.error(f"--hgcn: {exc}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--features", nargs="+", choices=("orb", "sift"), default=["orb", "sift"])
    ap.add_argument("--tracks", nargs="+", choices=("on", "off"), default=["on", "off"],
                    help="HGCN seed labels shared along feature tracks, or not")
    ap.add_argument("--words", type=int, default=None,
                    help="words of the HGCN and k-means vocabularies (default: from --per-word)")
    ap.add_argument("--per-word", type=int, default=20,
                    help="default word count: at least this many training descriptors per word")
    ap.add_argument("--repeats", type=int, default=3, help="repetitions (world and training seed 0, 1, ...)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the first repetition")
    ap.add_argument("--train-frames", type=int, default=32, help="training images per world")
    ap.add_argument("--frames", type=int, default=48, help="test images of the first pass")
    ap.add_argument("--revisit", type=int, default=20, help="test images revisiting the first part")
    ap.add_argument("--step", type=int, default=256, help="pixels between consecutive images (window 640)")
    ap.add_argument("--n-features", type=int, default=800, help="features per image")
    ap.add_argument("--levels", type=int, default=4, help="depth of the k=10 tree (10^L words at most)")
    ap.add_argument("--fabmap", action="store_true", help="also score FAB-MAP 2.0 (mean-field new place)")
    ap.add_argument("--centroid", action="store_true",
                    help="also score each HGCN vocabulary with centroid words (nearest class mean in PCA "
                         "space, Euclidean) instead of the network's run-time words")
    ap.add_argument("--min-gap", type=int, default=3, help="compare only with images this many frames back")
    ap.add_argument("--track-mean", action="store_true",
                    help="also score the k-means vocabulary with each test descriptor's word taken from its "
                         "causal track mean over the last --min-gap test images (tracks matched between "
                         "consecutive test images of a pass)")
    ap.add_argument("--hgcn", action="append", default=[], metavar="FIELD=VALUE",
                    help="override an HgcnTrainConfig field of the HGCN and k-means training, e.g. "
                         "--hgcn patience=30 --hgcn epochs=60 (repeatable)")
    ap.add_argument("--json", default=None, help="write every figure to this JSON file")
    args = ap.parse_args()
    args.hgcn_overrides = parse_overrides(ap, args.hgcn)
    logging.basicConfig(level=logging.WARNING)

    t_start = time.perf_counter()
    load = os.getloadavg()
    print(f"command: {' '.join(shlex.quote(a) for a in [sys.executable] + sys.argv)}")
    print(f"load average at start: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} ({os.cpu_count()} CPUs)")
    if args.hgcn_overrides:
        print(f"HGCN training settings changed from the defaults: {args.hgcn_overrides}")
    print(f"consecutive training images overlap by {max(0.0, 1 - args.step / WIN):.0%} of their width "
          f"(step {args.step} px, window {WIN} px)")

    # Worlds and features first: the default word count needs the training-set sizes.
    data = []
    extractors = {kind: Extractor(kind, args.n_features) for kind in args.features}
    need_tracks = "on" in args.tracks
    for rep in range(args.repeats):
        seed = args.seed + rep
        ns = argparse.Namespace(seed=seed, frames=args.frames, revisit=args.revisit,
                                train_frames=args.train_frames, step=args.step)
        train, test, gt = strip_world(ns)
        for kind in args.features:
            t0 = time.perf_counter()
            tr = [extractors[kind](im) for im in train]
            te_uv = [extractors[kind](im) for im in test]
            te = [d for d, _ in te_uv]
            t_feat = time.perf_counter() - t0
            t0 = time.perf_counter()
            tracks = sequence_tracks([d for d, _ in tr], [u for _, u in tr]) if need_tracks else None
            t_tracks = time.perf_counter() - t0
            n_desc = sum(len(d) for d, _ in tr)
            share = float(np.mean(tracks >= 0)) if tracks is not None else float("nan")
            n_tr = int(tracks.max()) + 1 if tracks is not None else 0
            print(f"  seed {seed} {kind}: {n_desc} training descriptors ({n_desc / len(tr):.0f} per image), "
                  f"{np.mean([len(d) for d in te]):.0f} per test image, features {t_feat:.1f} s"
                  + (f"; {n_tr} tracks hold {100 * share:.1f}% of the training descriptors "
                     f"(mean length {np.sum(tracks >= 0) / max(n_tr, 1):.2f}), {t_tracks:.1f} s" if need_tracks else ""))
            test_tracks = None
            if args.track_mean:  # the two passes are matched within each, not across the jump
                passes = np.repeat([0, 1], [args.frames, len(te) - args.frames])
                test_tracks = build_tracks(te, [u for _, u in te_uv], passes, progress=False)
            data.append({"seed": seed, "features": kind, "train": tr, "test": te, "gt": gt, "tracks": tracks,
                         "test_tracks": test_tracks,
                         "track_share": share, "n_desc": n_desc, "n_tracks": n_tr})
    words = args.words or max(100, min(d["n_desc"] for d in data) // args.per_word // 100 * 100)
    print(f"HGCN and k-means vocabularies: {words} words "
          f"({min(d['n_desc'] for d in data) / words:.1f}-{max(d['n_desc'] for d in data) / words:.1f} "
          f"training descriptors per word{'' if args.words else f', default from --per-word {args.per_word}'})")
    depths = tree_depths(words, args.levels)
    if len(depths) > 1:
        print(f"trees: k=10 at L={args.levels} (up to {10 ** args.levels} words) and, nearer the flat "
              f"vocabularies' size, L={depths[1]} (up to {10 ** depths[1]} words)")
    detectors = ["BoW"] + (["FAB-MAP"] if args.fabmap else [])

    runs = []
    for d in data:
        desc_list = [x for x, _ in d["train"]]
        desc = np.vstack(desc_list)
        ids = np.repeat(np.arange(len(desc_list)), [len(x) for x in desc_list])
        vocabs, secs = train_all(d["features"], desc, ids, d["tracks"], args, words, d["seed"])
        run = {"seed": d["seed"], "features": d["features"], "track_share": d["track_share"],
               "n_tracks": d["n_tracks"], "n_train_descriptors": d["n_desc"], "scores": {}, "n_words": {},
               "train_seconds": {k: round(v, 2) for k, v in secs.items()}, "hgcn_stats": {}}
        for label, v in vocabs.items():
            wd = quantize_sequences(desc_list, d["test"], v)
            run["scores"][label] = score_words(wd, d["gt"], args)
            run["n_words"][label] = int(v.n_words)
            if label == "k-means" and d["test_tracks"] is not None:
                test_words = causal_track_mean_words(v, d["test"], wd.test, d["test_tracks"], args.min_gap)
                run["scores"][TRACK_MEAN] = score_words(WordData(wd.train, test_words, wd.n_words), d["gt"], args)
                run["n_words"][TRACK_MEAN] = int(v.n_words)
            if label.startswith("HGCN"):
                run["hgcn_stats"][label] = dict(v.metadata.stats)
                if args.centroid:
                    v.assignment = "centroid"
                    wd = quantize_sequences(desc_list, d["test"], v)
                    run["scores"][f"{label} centroid"] = score_words(wd, d["gt"], args)
                    run["n_words"][f"{label} centroid"] = int(v.n_words)
                    v.assignment = "network"
        runs.append(run)
        txt = "  ".join(f"{label} {pct(s['BoW']['r100p']).strip()}/{pct(s['BoW']['auc']).strip()}"
                        for label, s in run["scores"].items())
        print(f"  seed {d['seed']} {d['features']} (BoW R@100P/AUC %): {txt}; training "
              + ", ".join(f"{k} {v:.0f} s" for k, v in secs.items()), flush=True)

    n_pos = runs[0]["scores"]["k-means"]["BoW"]["n_positive"] if runs else 0
    print()
    print(f"Loop-closure detection, trained on one strip world and tested on another: {args.train_frames} "
          f"training and {args.frames}+{args.revisit} test images per world ({n_pos} with a true loop), "
          f"{args.n_features} features per image, min gap {args.min_gap}")
    print(summary_table(runs, detectors))
    print(training_table(runs))
    total = time.perf_counter() - t_start
    print(f"\ntotal {total:.0f} s; load average at the end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if args.json:
        from orbslam_hgcn.placerec.plots import write_json

        record = {"command": sys.argv, "load_at_start": load, "args": vars(args), "words": words,
                  "tree_depths": depths, "seconds": round(total, 1), "runs": runs}
        print(f"wrote {write_json(Path(args.json), record)}")


if __name__ == "__main__":
    main()
