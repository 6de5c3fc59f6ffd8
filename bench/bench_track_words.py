"""Track words against lone words in place recognition: the ablation that picks the keyframe BoW.

Arms (same sequences, keyframes, tracks and database protocol; :data:`ARMS`):

* ``A0``  k-means words of lone descriptors;
* ``A1``  the HGCN's words of lone descriptors (its network on one descriptor);
* ``B0``  k-means word of each feature's causal track mean (no network);
* ``B1``  k-means word of the track's distinctive descriptor (ORB-SLAM's rule: the causal
  member whose median Hamming distance to the members, itself included, is least; ties to
  the oldest);
* ``C``   the track network of ``hgcn_graph_mean`` over each feature's causal track mates
  (mean aggregation in the centre's tangent space; its k-means words), ``C-att`` the same
  network with attention (``hgcn_graph``): :mod:`orbslam_hgcn.vocabulary.track_network`
  (8000 words only: no 1000-word track network is trained);
* ``orb`` the ORB tree on lone descriptors.

Each arm runs at two word counts (``--sizes``): the shipped vocabularies (k-means and HGCN
8000 words, the ORB tree ``orb10k`` with 10 000) and 1000 words (k-means and HGCN with 1000
words, the ORB tree with k = 10, L = 3), trained on the shipped vocabularies' imagery by
``tools/train_default_vocabs.py --kinds kmeans orb hgcn --hgcn-words 1000 --orb-levels 3
--out-dir DIR`` (``--vocab-1000 DIR``, default ``CACHE/vocab1000``).

An arm is a vocabulary kind and a function ``(vocabulary, Keyframes) -> per keyframe (N,)
words``; another arm is one more entry in :data:`ARMS` (and its contrasts in
:data:`CONTRASTS`, which are left out while an arm is missing).

Sequences: place-recognition offices (two laps round a desk, the second 0.3 m further out
and 0.15 m lower; scene seeds outside the vocabularies' training seeds 1001..), rendered
with depth at the keyframe rate (``--fps`` / ``--kf-every``; only the keyframes are
rendered). Tracks: features matched between consecutive keyframes
(:func:`orbslam_hgcn.vocabulary.training.tracks.build_tracks`: mutual nearest neighbours,
ratio test, RANSAC fundamental matrix), standing in for the map's point observations. A
keyframe's track uses the members in itself and the keyframes before it that are less
than ``--min-gap`` frames older (causal, and never reaching the keyframes a query is
allowed to match, so a query and its true match never share a track member); a feature
whose track has no such earlier member keeps its lone word. Each keyframe queries a
database of the keyframes at least ``--min-gap`` frames older; its best match is a
detection, true when the two cameras are within ``--dist`` m and ``--angle`` degrees.

Per sequence and arm: average precision (PR curve over the detections' scores), recall@1
(true top-1 detections / queries with a true loop in the database), recall at 100%
precision; and two mechanism figures: cross-visit repeatability (features of a query and of
its nearest true match in the database whose depth-map 3D points are mutual nearest
neighbours within ``--point-tol`` m are the same surface point; the share of those pairs
with the same word) and the effective vocabulary size (exp of the entropy of the words the
sequence's keyframes use). Paired contrasts over sequences (units) per word count: mean
difference, bootstrap 95% CI (10 000 resamples of the units), Wilcoxon signed-rank p,
Holm-corrected over every contrast, metric and word count.

Other families of sequences (``--family``; each its own arm table and contrasts, the
sequences of a family its units):

* ``street``: rendered street drives (KITTI 00's camera, 1241x376, noise and exposure
  drift), each street driven twice from the same start (:func:`street_passes`: the second
  pass 1 m left of the first and 0.2 m lower, its own jitter and noise), the second pass's
  keyframes after the first's; a loop is within 4 m and 30 degrees (keyframes are 2.5 m
  apart at 8.5 m/s); same surface point within 5 cm; scene seeds 10..17 (the vocabularies
  saw no street);
* ``replay``: the ``fr3_replay_hard`` preset (the real fr3 long-office camera path round a
  desk and back to its start, motion blur, exposure steps, vignetting, JPEG) in synthetic
  rooms 10..15, loop truth as for the offices;
* ``map`` (the saved-map protocol): the keyframes of maps saved by ``orbslam-hgcn run
  --vocab orb --save-map`` (``--maps MAP.npz=SEQ_DIR``), each feature's track its map
  point; the track window keeps every member less than ``--min-gap`` frames older
  (:func:`map_window`), loop truth from the sequence's ground truth at the keyframes'
  times. The map holds its final observations: an earlier keyframe's link to a point may
  have been made after the query was inserted (point fusion), so this is causal in
  keyframe order only;
* ``kitti``: the real KITTI 00 frames 0-159 (117 m of street, no revisit; database gap 30
  frames, loop within 4 m: the test suite checks that the stretch has none). A
  false-positive check, not AP: per arm, the threshold that gives 90% precision on the
  pooled top-1 detections of the validation offices (``--calib-seeds``, default 0 1 2)
  and how many of the stretch's queries score at least that, and its highest score;
* ``photos``: real photographs no vocabulary trains on, the held-out images of
  ``shared/data/real_photos`` (``--photo-dir``;
  :func:`orbslam_hgcn.vocabulary.training.photos.photo_files` ``heldout``: CamVid
  ``camvid_0560``..``0700``, street driving, video frames about 1 s apart). Units
  (:func:`photo_units`): the 141 held-out CamVid images in order, cut into 6 blocks of 23-24
  consecutive images (``round(n / 24)`` near-equal blocks), each block a sequence whose
  images are its keyframes, one frame apart. Loop truth by geometric verification, not by
  pose (there is none): two images of a unit are the same place when
  :func:`~orbslam_hgcn.vocabulary.training.tracks.match_pair` (mutual nearest neighbours,
  ratio test, RANSAC fundamental matrix) finds at least 40 inliers between their ORB-SLAM
  extractor features (``--min-inliers``; unrelated images get about 9). Database gap 2
  images (the next image is too easy; the track window is then the image and the one
  before it); tracks from consecutive images as for the other families. No depth: the
  same-point repeatability is n/a. The held-out ICDAR 2015 images
  (``icdar2015_0400``..``0499``) are not units: their consecutive images share no geometry
  (at most 10 inliers between any two consecutive ones: separate views, not a walk), so a
  unit of them would hold no true pair. At gap 2, 97 of the 129 queries have a true pair in
  their database (3, 9, 22, 21, 21, 21 per unit; gap 2 kept). The last four units are a slow
  stretch behind cyclists: 227-236 of their 231-253 image pairs are true, so nearly every
  detection there is right whatever the words, and the first two units carry the contrasts.

The street, replay, KITTI and photos settings were set before their first run and not tuned.

Settings were frozen on validation scene seeds 0, 1, 2 (``--scene-seeds 0 1 2``) before the
test run on the default seeds 10..29, by a rule fixed beforehand and blind to the arms'
differences: keep the defaults (keyframe every 3 frames at 10 fps, database gap 100 frames,
loop within 0.5 m and 30 degrees) unless a validation sequence has fewer than 50 queries
with a true loop or A0's AP is above 0.95 or below 0.3. They passed (139 queries with a
loop per sequence, A0 AP 0.70-0.84); no other setting was tried. Renders, and each sequence's features, tracks and
depth points, are kept in ``--cache-dir``; ``--prepare-only`` makes them (run a few at once
on disjoint seeds), after which a run only computes the arms. ``--json`` writes everything;
``--record NAME`` the README's figures (``bench/figures.py``).

    python bench/bench_track_words.py [--family office|street|replay|kitti|map|photos] [--scene-seeds 10 11 ...]
        [--sizes 8000 1000] [--jobs 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import multiprocessing
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import faiss
import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import wilcoxon

sys.path.insert(0, str(Path(__file__).resolve().parent))
import figures  # noqa: E402
from bench_place_recognition import loop_truth, pr_curve, two_lap_trajectory  # noqa: E402

from orbslam_hgcn.datasets import open_sequence  # noqa: E402
from orbslam_hgcn.features.orb import ORBExtractor  # noqa: E402
from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence, street_options, synth_options  # noqa: E402
from orbslam_hgcn.vocabulary import load_vocabulary  # noqa: E402
from orbslam_hgcn.vocabulary.loading import SHIPPED  # noqa: E402
from orbslam_hgcn.vocabulary.track_network import window_words  # noqa: E402
from orbslam_hgcn.vocabulary.training.tracks import build_tracks, match_pair  # noqa: E402

METRICS = ("AP", "recall@1")
TEST_SEEDS = list(range(10, 30))
FEATURE_CACHE_VERSION = 1  # bump when describe() or build_tracks() change what they give


@dataclasses.dataclass
class Keyframes:
    """One sequence's keyframes: what every arm gets.

    frames: (K,) frame numbers at ``--fps``; desc, uv: per keyframe (N, 32) uint8 descriptors
    and (N, 2) positions; tracks: per keyframe (N,) track ids (-1: none); window: keyframes a
    track reaches back (itself included); gt: (K, K) bool loop truth; centres: (K, 3) camera
    centres; points: per keyframe (N, 3) world points of the features from the depth map (NaN
    where there is no depth).
    """

    name: str
    frames: np.ndarray
    desc: list[np.ndarray]
    uv: list[np.ndarray]
    tracks: list[np.ndarray]
    window: int
    gt: np.ndarray
    centres: np.ndarray
    points: list[np.ndarray]
    _members: list | None = None

    def members(self) -> list[Members]:
        """Per keyframe k: (rows: its features with at least two causal track members,
        offsets (R + 1,), member keyframes, member feature indices); members of row r are
        ``[offsets[r]:offsets[r + 1]]``, in keyframe order (k itself last)."""
        if self._members is None:
            self._members = causal_members(self.tracks, self.window)
        return self._members


Members = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def causal_members(tracks: list[np.ndarray], window: int) -> list[Members]:
    """See :meth:`Keyframes.members`: members in keyframes k - window + 1 .. k."""
    out = []
    for k in range(len(tracks)):
        lo = max(0, k - window + 1)
        ids = np.concatenate(tracks[lo:k + 1])
        kf = np.concatenate([np.full(len(tracks[j]), j, np.int64) for j in range(lo, k + 1)])
        ix = np.concatenate([np.arange(len(tracks[j])) for j in range(lo, k + 1)])
        valid = ids >= 0
        ids, kf, ix = ids[valid], kf[valid], ix[valid]
        order = np.lexsort((kf, ids))  # by track, then keyframe
        ids, kf, ix = ids[order], kf[order], ix[order]
        uid, start, cnt = np.unique(ids, return_index=True, return_counts=True)
        t = tracks[k]
        pos = np.searchsorted(uid, t)
        has = (t >= 0) & (pos < len(uid))
        has[has] &= uid[pos[has]] == t[has]
        rows = np.flatnonzero(has)
        rows = rows[cnt[pos[rows]] >= 2]
        sel = [np.arange(start[p], start[p] + cnt[p]) for p in pos[rows]]
        take = np.concatenate(sel) if sel else np.zeros(0, np.int64)
        offsets = np.concatenate([[0], np.cumsum([len(s) for s in sel], dtype=np.int64)])
        out.append((rows, offsets, kf[take], ix[take]))
    return out


# --- arms: (vocabulary, Keyframes) -> per keyframe (N,) words ---------------------------

def lone_words(vocab, kfs: Keyframes) -> list[np.ndarray]:
    return [vocab.transform_words(d) for d in kfs.desc]


def _member_rows(kfs: Keyframes, mkf: np.ndarray, mix: np.ndarray) -> np.ndarray:
    """Rows of members (keyframe, feature) in the keyframes' concatenated features."""
    start = np.concatenate([[0], np.cumsum([len(d) for d in kfs.desc])[:-1]])
    return start[mkf] + mix


def track_mean_words(vocab, kfs: Keyframes) -> list[np.ndarray]:
    """Word of the mean of the causal members' reduced descriptors (B0)."""
    x = [vocab.project(d) for d in kfs.desc]
    allx = np.concatenate(x).astype(np.float64)
    out = []
    for k, (rows, offsets, mkf, mix) in enumerate(kfs.members()):
        w = vocab.words_of_points(x[k])
        if len(rows):
            means = np.add.reduceat(allx[_member_rows(kfs, mkf, mix)], offsets[:-1], axis=0) / np.diff(offsets)[:, None]
            w[rows] = vocab.words_of_points(means.astype(np.float32))
        out.append(w)
    return out


POPCOUNT = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(1).astype(np.int32)


def distinctive_batch(groups: np.ndarray) -> np.ndarray:
    """:func:`distinctive` of each of (G, M, 32) uint8 groups of M descriptors: (G,) indices."""
    d = POPCOUNT[groups[:, :, None, :] ^ groups[:, None, :, :]].sum(-1)
    med = np.sort(d, axis=2)[:, :, (groups.shape[1] - 1) // 2]
    return np.argmin(med, axis=1)


def distinctive(desc: np.ndarray) -> int:
    """Index of ORB-SLAM's distinctive descriptor among (M, 32) uint8 descriptors: least
    median Hamming distance to all of them (itself included, median = sorted[(M - 1) // 2]);
    ties to the first."""
    return int(distinctive_batch(desc[None])[0])


def distinctive_words(vocab, kfs: Keyframes) -> list[np.ndarray]:
    """Word of the track's distinctive descriptor among its causal members (B1)."""
    alld = np.concatenate(kfs.desc)
    out = []
    for k, (rows, offsets, mkf, mix) in enumerate(kfs.members()):
        w = vocab.transform_words(kfs.desc[k])
        if len(rows):
            members = alld[_member_rows(kfs, mkf, mix)]
            size = np.diff(offsets)
            picked = np.empty((len(rows), alld.shape[1]), np.uint8)
            for m in np.unique(size):  # groups of one size at a time, in chunks
                g = np.flatnonzero(size == m)
                for c in range(0, len(g), 512):
                    gc = g[c:c + 512]
                    block = members[offsets[gc][:, None] + np.arange(m)]
                    picked[gc] = block[np.arange(len(gc)), distinctive_batch(block)]
            w[rows] = vocab.transform_words(picked)
        out.append(w)
    return out


ArmFn = Callable[[object, Keyframes], list]
def network_words(vocab, kfs: Keyframes) -> list[np.ndarray]:
    """Words of the vocabulary's track network over each feature's causal track mates (C, C-att)."""
    return window_words(vocab, kfs.desc, kfs.tracks, kfs.window)


# name -> (vocabulary kind, words function)
ARMS: dict[str, tuple[str, ArmFn]] = {
    "A0": ("kmeans", lone_words),
    "A1": ("hgcn", lone_words),
    "B0": ("kmeans", track_mean_words),
    "B1": ("kmeans", distinctive_words),
    "C": ("graph_mean", network_words),
    "C-att": ("graph", network_words),
    "orb": ("orb", lone_words),
}
CONTRASTS = (("B0", "A0"), ("B1", "A0"), ("A1", "A0"), ("B1", "B0"), ("orb", "A0"), ("C", "A0"), ("C", "B0"),
             ("C-att", "A0"), ("C-att", "B0"))
# vocabulary kind -> (shipped name at the default size, file name in --vocab-1000)
VOCAB_FILES = {"kmeans": ("kmeans", SHIPPED["kmeans"].name), "hgcn": ("hgcn", SHIPPED["hgcn"].name),
               "orb": ("orb10k", SHIPPED["orb"].name),
               "graph": ("hgcn_graph", "vocab_hgcn_graph.npz"), "graph_mean": ("hgcn_graph_mean", "vocab_hgcn_graph_mean.npz")}


def vocab_files(size: int, vocab_1000: Path) -> dict[str, str | Path]:
    """Vocabulary kind -> shipped name or file at a word count (the kinds whose file exists)."""
    if size == 8000:
        return {kind: shipped for kind, (shipped, _) in VOCAB_FILES.items()}
    out = {kind: vocab_1000 / file for kind, (_, file) in VOCAB_FILES.items()}
    return {kind: p for kind, p in out.items() if p.exists()}


def arms_by_size(sizes: list[int], arms: list[str], vocab_1000: Path) -> dict[int, list[str]]:
    """The arms run at each word count: those whose vocabulary exists there (the others are
    named on stderr; no arm at all at a word count exits with status 2)."""
    out = {}
    for size in sizes:
        have = vocab_files(size, vocab_1000)
        out[size] = [a for a in arms if ARMS[a][0] in have]
        left = [a for a in arms if a not in out[size]]
        if left:
            kinds = sorted({ARMS[a][0] for a in left})
            print(f"bench_track_words: no {size}-word {', '.join(kinds)} vocabulary in {vocab_1000} (make them with "
                  f"tools/train_default_vocabs.py --kinds kmeans orb hgcn --hgcn-words 1000 --orb-levels 3 "
                  f"--out-dir {vocab_1000}): arm(s) {', '.join(left)} left out at {size} words", file=sys.stderr)
        if not out[size]:
            raise SystemExit(2)
    return out


# --- figures of one sequence -------------------------------------------------------------

def detections(bows: list, frames: np.ndarray, gt: np.ndarray, min_gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Top-1 detections of one sequence: per query keyframe (one with a keyframe at least
    ``min_gap`` frames older) its best score, whether that match is a true loop, and whether
    its database holds a true loop (arrays of equal length).

    Keyframe i queries the keyframes at least ``min_gap`` frames older, as the keyframe
    database does (:meth:`KeyframeDatabase.query`: L1 score ``sum_w min(q_w, v_w)``, ties to
    the lowest id, no detection when no keyframe shares a word), on dense vectors."""
    n_words = 1 + max((int(b.words.max()) for b in bows if len(b.words)), default=0)
    v = np.zeros((len(bows), n_words), np.float32)
    for i, b in enumerate(bows):
        v[i, b.words] = b.weights
    s, correct, eligible = [], [], []
    for i in range(len(bows)):
        added = int(np.searchsorted(frames, frames[i] - min_gap, side="right"))
        if added == 0:
            continue
        nz = np.flatnonzero(v[i])
        sc = np.minimum(v[:added, nz], v[i, nz]).sum(1, dtype=np.float64)
        j = int(np.argmax(sc))
        s.append(float(sc[j]))
        correct.append(sc[j] > 0 and bool(gt[i, j]))
        eligible.append(bool(gt[i, :added].any()))
    return np.array(s, np.float64), np.array(correct, bool), np.array(eligible, bool)


def scores(bows: list, frames: np.ndarray, gt: np.ndarray, min_gap: int) -> dict:
    """AP, recall@1 and recall at 100% precision of top-1 detections (one sequence; the
    detections of :func:`detections`); ``top1`` the detections' scores and ``top1_true``
    whether each is a true loop."""
    s, correct, eligible = detections(bows, frames, gt, min_gap)
    n_pos = int(np.sum(eligible))
    prec, rec = pr_curve(s, correct, n_pos)
    full = prec >= 1.0 - 1e-12
    return {"AP": float(np.sum(np.diff(np.concatenate([[0.0], rec])) * prec)),
            "recall@1": float(correct.sum() / max(n_pos, 1)),
            "recall@P100": float(rec[full].max()) if full.any() else 0.0,
            "queries": len(s), "with_loop": n_pos, "top1": s.tolist(), "top1_true": correct.tolist()}


def threshold_at_precision(s: np.ndarray, correct: np.ndarray, precision: float) -> float:
    """The lowest detection score at which the detections scoring at least that much have
    at least ``precision`` precision (inf when no threshold reaches it)."""
    order = np.argsort(-s, kind="stable")
    ss, tp = s[order], np.cumsum(correct[order])
    # Only cut between distinct scores: a threshold keeps every detection scoring as much.
    last = np.r_[ss[1:] != ss[:-1], True]
    prec = tp / np.arange(1, len(ss) + 1)
    ok = np.flatnonzero(last & (prec >= precision))
    return float(ss[ok[-1]]) if len(ok) else float("inf")


def false_positive_check(s: np.ndarray, threshold: float) -> dict:
    """Detections of a sequence without a revisit (every detection is false): how many score
    at least ``threshold``, the highest score and its ratio to the threshold."""
    top = float(s.max()) if len(s) else 0.0
    return {"queries": len(s), "false_positives": int(np.sum(s >= threshold)), "threshold": threshold,
            "max_score": top, "max_over_threshold": top / threshold if np.isfinite(threshold) else 0.0}


def effective_size(words: list[np.ndarray]) -> float:
    """exp of the entropy of the word distribution over all the keyframes' features."""
    counts = np.bincount(np.concatenate(words).astype(np.int64))
    p = counts[counts > 0] / counts.sum()
    return float(np.exp(-np.sum(p * np.log(p))))


def same_points(kfs: Keyframes, min_gap: int, tol: float) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """Features of the same surface point seen on both visits: per query keyframe with a
    true loop in its database, its nearest true match (camera centres) j and the feature
    pairs (a in the query, b in j) whose world points are mutual nearest neighbours
    within ``tol`` m. Returns [(query, j, a, b)]."""
    out = []
    for i in range(len(kfs.frames)):
        older = np.flatnonzero(kfs.frames <= kfs.frames[i] - min_gap)
        true = older[kfs.gt[i, older]]
        if not len(true):
            continue
        j = int(true[np.argmin(np.linalg.norm(kfs.centres[true] - kfs.centres[i], axis=1))])
        pa, pb = kfs.points[i], kfs.points[j]
        va, vb = np.flatnonzero(np.isfinite(pa[:, 0])), np.flatnonzero(np.isfinite(pb[:, 0]))
        if not len(va) or not len(vb):
            continue
        dab, ab = cKDTree(pb[vb]).query(pa[va], distance_upper_bound=tol)
        _, ba = cKDTree(pa[va]).query(pb[vb])
        ok = np.isfinite(dab)
        ok[ok] &= ba[ab[ok]] == np.flatnonzero(ok)
        out.append((i, j, va[ok], vb[ab[ok]]))
    return out


def repeatability(words: list[np.ndarray], pairs: list[tuple[int, int, np.ndarray, np.ndarray]]) -> float:
    """Share of same-point feature pairs of the two visits that get the same word."""
    same = sum(int(np.sum(words[i][a] == words[j][b])) for i, j, a, b in pairs)
    n = sum(len(a) for _, _, a, _ in pairs)
    return same / n if n else float("nan")


# --- statistics ----------------------------------------------------------------------------

def contrast(a: np.ndarray, b: np.ndarray, rng: np.random.Generator) -> dict:
    """Paired contrast a - b over units: mean, bootstrap 95% CI, Wilcoxon signed-rank p."""
    d = np.asarray(a, float) - np.asarray(b, float)
    boot = d[rng.integers(0, len(d), (10_000, len(d)))].mean(1)
    p = float(wilcoxon(d).pvalue) if np.any(d != 0) else 1.0
    return {"mean": float(d.mean()), "ci95": [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))],
            "wilcoxon_p": p, "units": len(d), "wins": int((d > 0).sum()), "losses": int((d < 0).sum())}


def holm(ps: list[float]) -> list[float]:
    """Holm-adjusted p-values (step-down, monotone, capped at 1)."""
    order = np.argsort(ps, kind="stable")
    out, running = [0.0] * len(ps), 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(ps) - rank) * ps[i]))
        out[i] = running
    return out


# --- sequences -----------------------------------------------------------------------------

def describe(seq_dir: Path, cam, extractor: ORBExtractor) -> tuple[list, list, np.ndarray, list]:
    """ORB features of every frame of a TUM-layout render with depth: descriptors, positions,
    (K, 4, 4) camera poses and the features' world points from the depth map (NaN: no depth)."""
    seq = open_sequence("tum", seq_dir)
    depth_files = [line.split()[1] for line in (seq_dir / "depth.txt").read_text().splitlines()
                   if line and not line.startswith("#")]
    if len(depth_files) != len(seq):
        raise SystemExit(f"bench_track_words: {seq_dir}: {len(depth_files)} depth images for {len(seq)} frames")
    desc, uv, poses, points = [], [], [], []
    for k in range(len(seq)):
        rec = seq[k]
        kps = extractor.extract(rec.image)
        desc.append(kps.desc)
        uv.append(np.asarray(kps.uv, np.float32))
        poses.append(rec.T_wc)
        depth = cv2.imread(str(seq_dir / depth_files[k]), cv2.IMREAD_UNCHANGED).astype(np.float64) / 5000.0
        u = np.clip(np.rint(kps.uv[:, 0]).astype(int), 0, depth.shape[1] - 1)
        v = np.clip(np.rint(kps.uv[:, 1]).astype(int), 0, depth.shape[0] - 1)
        z = depth[v, u]
        z[z <= 0] = np.nan
        pc = np.stack([(kps.uv[:, 0] - cam.cx) / cam.fx * z, (kps.uv[:, 1] - cam.cy) / cam.fy * z, z], 1)
        points.append(pc @ rec.T_wc[:3, :3].T + rec.T_wc[:3, 3])
    return desc, uv, np.stack(poses), points


def _keyframes(name: str, cached: Path, make: Callable[[], tuple], extractor: ORBExtractor, args,
               frames: np.ndarray | None = None) -> Keyframes:
    """A sequence's Keyframes from ``make() -> (desc, uv, poses, points)`` (per keyframe), its
    features, tracks and points kept in ``cached`` (named by the extractor's settings);
    keyframes at ``frames`` (default: every ``--kf-every`` frames)."""
    key = hashlib.sha1(f"{FEATURE_CACHE_VERSION} {extractor.config!r}".encode()).hexdigest()[:12]
    cached = cached.parent / f"{cached.name}_{key}.npz"
    if cached.exists():
        with np.load(cached) as z:
            sizes, tid, poses = z["sizes"], z["tracks"], z["poses"]
            cut = np.cumsum(sizes)[:-1]
            desc, uv, points = np.split(z["desc"], cut), np.split(z["uv"], cut), np.split(z["points"], cut)
    else:
        desc, uv, poses, points = make()
        tid = build_tracks(desc, uv, np.zeros(len(desc), np.int64), progress=False)
        cached.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cached, sizes=np.array([len(d) for d in desc]), desc=np.concatenate(desc), uv=np.concatenate(uv),
                 points=np.concatenate(points), tracks=tid, poses=poses)
    tracks = np.split(tid, np.cumsum([len(d) for d in desc])[:-1])
    window = max(1, args.min_gap // args.kf_every)  # keyframes less than min_gap frames older, and itself
    frames = np.arange(len(desc)) * args.kf_every if frames is None else frames
    return Keyframes(name, frames, desc, uv, tracks, window, loop_truth(poses, args.dist, args.angle),
                     poses[:, :3, 3], points)


def office_keyframes(cache_dir: Path, seed: int, args, extractor: ORBExtractor) -> Keyframes:
    """Render (or reuse) office ``seed`` with depth at the keyframe rate, and describe it."""
    gt_file = cache_dir / "two_lap_40s_wide.txt"
    if not gt_file.exists():
        two_lap_trajectory(gt_file)
    rate = args.fps / args.kf_every
    opts = SynthOptions(trajectory="replay", gt=str(gt_file), fps=rate, scene_seed=seed, noise=2.0,
                        exposure_drift=0.1, seed=seed, depth=True)
    seq_dir = render_sequence(cache_dir / f"office{seed}_two_laps_wide_{rate:g}fps_depth", opts, progress=False,
                              cache=True)
    # Features, tracks and depth points are kept beside the render.
    return _keyframes(f"office{seed}", seq_dir / "keyframes", lambda: describe(seq_dir, opts.camera, extractor),
                      extractor, args)


def replay_keyframes(cache_dir: Path, seed: int, args, extractor: ORBExtractor) -> Keyframes:
    """The ``fr3_replay_hard`` preset (the real fr3 long-office camera path round a desk,
    back to its start, in synthetic room ``seed``; motion blur, exposure steps, vignetting,
    noise, JPEG) with depth at the keyframe rate, its first ``--replay-s`` seconds."""
    rate = args.fps / args.kf_every
    opts = synth_options("fr3_replay_hard", scene_seed=seed, seed=seed, fps=rate, depth=True,
                         duration=args.replay_s)
    length = "all" if args.replay_s is None else f"{args.replay_s:g}s"
    seq_dir = render_sequence(cache_dir / f"replay{seed}_fr3_hard_{length}_{rate:g}fps_depth", opts,
                              progress=False, cache=True)
    return _keyframes(f"replay{seed}", seq_dir / "keyframes", lambda: describe(seq_dir, opts.camera, extractor),
                      extractor, args)


STREET_SECOND_PASS = {"left": 1.0, "lower": 0.2}  # the second pass: metres left of and below the first


def street_passes(seed: int, seconds: float, rate: float):
    """Street ``seed`` (:func:`~orbslam_hgcn.synth.street.build_street`) and two drives
    along the same route from the same start: the first on the right-hand lane, the second
    ``STREET_SECOND_PASS`` metres left of it and lower (another lane, a lower car), with its
    own pose jitter. Returns (options, scene, first drive, second drive, (N,) frame times
    of a pass)."""
    from orbslam_hgcn.synth.street import Drive, PlanarPath, StreetSpec, build_street

    spec = StreetSpec()
    opts = street_options(scene_seed=seed, seed=seed, fps=rate, duration=seconds, noise=1.5, exposure_drift=0.1,
                          depth=True, layout="kitti")
    scene, first = build_street(seed, seconds * spec.speed + 1.0, spec)
    spec2 = dataclasses.replace(spec, lane_offset=spec.lane_offset - STREET_SECOND_PASS["left"],
                                camera_height=spec.camera_height - STREET_SECOND_PASS["lower"])
    path2 = PlanarPath(np.array(scene.layout["corners"]), spec.corner_radius, -spec2.lane_offset)
    second = Drive(path2, spec2, seed + 1000)
    return opts, scene, first, second, np.arange(int(round(seconds * rate))) / rate


def street_keyframes(cache_dir: Path, seed: int, args, extractor: ORBExtractor) -> Keyframes:
    """Street ``seed`` driven twice (:func:`street_passes`), KITTI 00's camera, rendered at
    the keyframe rate with sensor noise and exposure drift (each pass its own); the second
    pass's keyframes follow the first's."""
    rate = args.fps / args.kf_every

    def make():
        from orbslam_hgcn.synth.degrade import Degradations
        from orbslam_hgcn.synth.sequence import REF_DEPTH, CameraEffects, camera_frame, make_renderer

        opts, scene, first, second, times = street_passes(seed, args.street_s, rate)
        renderer = make_renderer(scene, opts)  # one renderer: the second pass reuses the first's textures
        desc, uv, poses, points = [], [], [], []
        for p, drive in enumerate((first, second)):
            o = dataclasses.replace(opts, seed=seed + 1000 * p)
            effects = CameraEffects(o)
            degrade = Degradations(o, o.camera, float(times[0]), float(times[-1]), REF_DEPTH["street"])
            for k, t in enumerate(times.tolist()):
                img, inv_depth = camera_frame(renderer, drive, t, k, o, effects, degrade, grey=True)
                T = drive(np.array([t]))[0]
                kps = extractor.extract(img)
                desc.append(kps.desc)
                uv.append(np.asarray(kps.uv, np.float32))
                poses.append(T)
                points.append(depth_points(kps.uv, inv_depth, o.camera, T))
        return desc, uv, np.stack(poses), points

    return _keyframes(f"street{seed}", cache_dir / f"street{seed}_two_passes_{args.street_s:g}s_{rate:g}fps" / "keyframes",
                      make, extractor, args)


def depth_points(uv: np.ndarray, inv_depth: np.ndarray, cam, T_wc: np.ndarray) -> np.ndarray:
    """(N, 3) world points of pixels ``uv`` from an (H, W) inverse depth map (NaN: none)."""
    u = np.clip(np.rint(uv[:, 0]).astype(int), 0, inv_depth.shape[1] - 1)
    v = np.clip(np.rint(uv[:, 1]).astype(int), 0, inv_depth.shape[0] - 1)
    w = inv_depth[v, u].astype(np.float64)
    z = np.where(w > 0, 1.0 / np.maximum(w, 1e-12), np.nan)
    pc = np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], 1)
    return pc @ T_wc[:3, :3].T + T_wc[:3, 3]


def map_window(frames: np.ndarray, min_gap: int) -> int:
    """The most keyframes a track may reach back (itself included) so that every member is
    less than ``min_gap`` frames older than the keyframe, for keyframes at irregular
    ``frames``: the fewest keyframes within ``min_gap`` frames over the keyframes at least
    ``min_gap`` frames into the sequence (all of them when none is)."""
    lo = np.searchsorted(frames, frames - min_gap, side="right")
    count = np.arange(len(frames)) - lo + 1
    later = frames - min_gap >= frames[0]
    return int(max(1, count[later].min() if later.any() else count.min()))


def map_keyframes(map_file: Path, seq_dir: Path, args) -> Keyframes:
    """The keyframes of a map saved by ``orbslam-hgcn run --save-map`` over the sequence in
    ``seq_dir`` (any kind :func:`open_sequence` detects): their features in keyframe id order,
    each feature's track its map point (-1: none), loop truth from the sequence's ground-truth poses at the keyframes' times, frames
    the keyframes' frame numbers in the sequence; no depth points."""
    from orbslam_hgcn.map.io import read_header

    a, _ = read_header(map_file)
    order = np.argsort(a["kf_id"], kind="stable")
    off = a["kf_feat_offset"]
    desc = [a["kp_desc"][off[k]:off[k + 1]] for k in order]
    uv = [np.asarray(a["kp_uv"][off[k]:off[k + 1]], np.float32) for k in order]
    tracks = [a["kp_point"][off[k]:off[k + 1]].astype(np.int64) for k in order]
    seq = open_sequence(None, seq_dir)
    ts = seq.timestamps
    idx = np.clip(np.searchsorted(ts, a["kf_timestamp"][order]), 1, len(ts) - 1)
    idx -= (a["kf_timestamp"][order] - ts[idx - 1]) < (ts[idx] - a["kf_timestamp"][order])
    poses = [seq.pose(int(i)) for i in idx]
    if any(p is None for p in poses):
        raise SystemExit(f"bench_track_words: {seq_dir}: no ground-truth pose for every keyframe of {map_file}")
    frames = idx.astype(np.int64)
    poses = np.stack(poses)
    return Keyframes(map_file.stem, frames, desc, uv, tracks, map_window(frames, args.min_gap),
                     loop_truth(poses, args.dist, args.angle), poses[:, :3, 3],
                     [np.full((len(d), 3), np.nan) for d in desc])


KITTI_DIR = Path(__file__).resolve().parents[2] / "shared/data/kitti00_first160/sequences/00"


def kitti_keyframes(cache_dir: Path, args, extractor: ORBExtractor) -> Keyframes:
    """The real KITTI 00 frames 0-159 (no revisit), a keyframe every ``--kf-every`` frames;
    no depth (no same-point pairs)."""
    if not (args.kitti_dir / "image_0").is_dir():
        raise SystemExit(f"bench_track_words: {args.kitti_dir}: no KITTI image_0 folder (--kitti-dir)")
    seq = open_sequence("kitti", args.kitti_dir)
    frames = np.arange(0, len(seq), args.kf_every)

    def make():
        desc, uv, poses = [], [], []
        for k in frames.tolist():
            rec = seq[k]
            kps = extractor.extract(rec.image)
            desc.append(kps.desc)
            uv.append(np.asarray(kps.uv, np.float32))
            poses.append(rec.T_wc)
        return desc, uv, np.stack(poses), [np.full((len(d), 3), np.nan) for d in desc]

    return _keyframes("kitti00_0-159", cache_dir / f"kitti00_first{len(seq)}_every{args.kf_every}" / "keyframes",
                      make, extractor, args, frames=frames)


# The photos family (settings fixed before its first run; see the module docstring).
PHOTO_SOURCES = ("camvid",)  # held-out sources whose consecutive images see the same street
PHOTO_UNIT = 24  # images per unit, about: a source's held-out run is cut into round(n / 24) blocks
PHOTO_MIN_INLIERS = 40  # a true pair: at least this many fundamental-matrix RANSAC inliers (match_pair)


def photo_units(folder: Path) -> list[tuple[str, list[Path]]]:
    """The units of ``--family photos``: per source of :data:`PHOTO_SOURCES` its held-out
    images (:func:`~orbslam_hgcn.vocabulary.training.photos.photo_files`, never a training
    image) in order, cut into ``round(n / PHOTO_UNIT)`` blocks of consecutive images as near
    equal as can be; each (name, files), the name ``SOURCE_FIRST-LAST`` by file index."""
    from orbslam_hgcn.vocabulary.training.photos import photo_files

    held = photo_files(folder, "heldout")
    missing = [s for s in PHOTO_SOURCES if s not in held]
    if missing:
        raise SystemExit(f"bench_track_words: {folder}: no held-out {', '.join(missing)} images")
    out = []
    for source in PHOTO_SOURCES:
        files = held[source]
        for block in np.array_split(np.arange(len(files)), max(1, round(len(files) / PHOTO_UNIT))):
            first, last = (files[i].stem.rsplit("_", 1)[1] for i in (block[0], block[-1]))
            out.append((f"{source}_{first}-{last}", [files[i] for i in block]))
    return out


def photo_inliers(desc: list[np.ndarray], uv: list[np.ndarray]) -> np.ndarray:
    """(K, K) int: verified matches (:func:`match_pair`, fundamental-matrix RANSAC inliers)
    of every pair of images, the older image first; symmetric, 0 on the diagonal."""
    n = np.zeros((len(desc), len(desc)), np.int64)
    for j in range(len(desc)):
        for i in range(j):
            n[i, j] = n[j, i] = len(match_pair(desc[i], desc[j], uv[i], uv[j])[0])
    return n


def photo_cache_key(files: list[Path], extractor: ORBExtractor) -> str:
    """The cache key of figures computed from the features of ``files``: extractor settings
    and file names."""
    return hashlib.sha1(f"{FEATURE_CACHE_VERSION} {extractor.config!r} {[f.name for f in files]}".encode()).hexdigest()[:12]


def photo_features(files: list[Path], extractor: ORBExtractor) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """ORB descriptors (N_i, 32) and keypoint positions (N_i, 2) float32 of each image file."""
    from orbslam_hgcn.datasets.base import read_image

    kps = [extractor.extract(read_image(f)) for f in files]
    return [k.desc for k in kps], [np.asarray(k.uv, np.float32) for k in kps]


def same_place(inliers: np.ndarray, min_inliers: int) -> np.ndarray:
    """(K, K) bool loop truth from :func:`photo_inliers`: at least ``min_inliers``, never an
    image with itself."""
    gt = inliers >= min_inliers
    np.fill_diagonal(gt, False)
    return gt


def photo_keyframes(cache_dir: Path, unit: int, args, extractor: ORBExtractor) -> Keyframes:
    """Unit ``unit`` of :func:`photo_units` (its images the keyframes, in order, one frame
    apart): ORB features, tracks between consecutive images and the pairs' inlier counts
    kept in the cache; loop truth: at least ``--min-inliers`` inliers; no depth, no pose."""
    name, files = photo_units(args.photo_dir)[unit]
    cached = cache_dir / "photos" / f"{name}_{photo_cache_key(files, extractor)}.npz"
    if cached.exists():
        with np.load(cached) as z:
            cut = np.cumsum(z["sizes"])[:-1]
            desc, uv, tid, inliers = np.split(z["desc"], cut), np.split(z["uv"], cut), z["tracks"], z["inliers"]
    else:
        desc, uv = photo_features(files, extractor)
        tid = build_tracks(desc, uv, np.zeros(len(desc), np.int64), progress=False)
        inliers = photo_inliers(desc, uv)
        cached.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cached, sizes=np.array([len(d) for d in desc]), desc=np.concatenate(desc), uv=np.concatenate(uv),
                 tracks=tid, inliers=inliers)
    tracks = np.split(tid, np.cumsum([len(d) for d in desc])[:-1])
    gt = same_place(inliers, args.min_inliers)
    return Keyframes(name, np.arange(len(desc)) * args.kf_every, desc, uv, tracks, max(1, args.min_gap // args.kf_every),
                     gt, np.zeros((len(desc), 3)), [np.full((len(d), 3), np.nan) for d in desc])


def run_sequence(kfs: Keyframes, vocabs: dict[int, dict], arms: dict[int, list[str]], args) -> dict:
    pairs = same_points(kfs, args.min_gap, args.point_tol)
    out: dict = {"keyframes": len(kfs.frames), "same_point_pairs": int(sum(len(a) for _, _, a, _ in pairs)),
                 "features_with_track": float(np.mean([len(m[0]) / max(len(d), 1)
                                                       for m, d in zip(kfs.members(), kfs.desc)]))}
    for size, vs in vocabs.items():
        for arm in arms[size]:
            kind, fn = ARMS[arm]
            words = fn(vs[kind], kfs)
            bows = [vs[kind].bow_from_words(w) for w in words]
            r = scores(bows, kfs.frames, kfs.gt, args.min_gap)
            r["repeatability"] = repeatability(words, pairs)
            r["effective_words"] = effective_size(words)
            out[f"{size} {arm}"] = r
    return out


def _finite_mean(values: list[float]) -> float:
    """Mean of the finite values (NaN when none: no same-point pairs without depth)."""
    v = np.asarray(values, np.float64)
    return float(v[np.isfinite(v)].mean()) if np.isfinite(v).any() else float("nan")


def summarise(per_seq: dict[str, dict], arms: dict[int, list[str]]) -> tuple[dict, dict]:
    """Per word count and arm the mean figures; the contrasts (with Holm p)."""
    names = list(per_seq)
    means = {}
    for size in arms:
        for arm in arms[size]:
            rs = [per_seq[n][f"{size} {arm}"] for n in names]
            means[f"{size} {arm}"] = {k: _finite_mean([r[k] for r in rs])
                                      for k in ("AP", "recall@1", "recall@P100", "repeatability", "effective_words")}
    rng = np.random.default_rng(0)
    table = {}
    for size in arms:
        for metric in METRICS:
            for a, b in CONTRASTS:
                if a in arms[size] and b in arms[size]:
                    va = np.array([per_seq[n][f"{size} {a}"][metric] for n in names])
                    vb = np.array([per_seq[n][f"{size} {b}"][metric] for n in names])
                    table[f"{size} {a}-{b} {metric}"] = contrast(va, vb, rng)
    for key, p in zip(table, holm([c["wilcoxon_p"] for c in table.values()])):
        table[key]["holm_p"] = p
    return means, table


# Per family: its default sequences (seeds; the KITTI stretch is one) and settings. The
# offices' were frozen on validation seeds 0-2; the others were set before their first run.
FAMILIES: dict[str, dict] = {
    "office": {"seeds": TEST_SEEDS, "fps": 10.0, "kf_every": 3, "min_gap": 100, "dist": 0.5, "angle": 30.0},
    "street": {"seeds": list(range(10, 18)), "fps": 10.0, "kf_every": 3, "min_gap": 100, "dist": 4.0, "angle": 30.0},
    "replay": {"seeds": list(range(10, 16)), "fps": 10.0, "kf_every": 3, "min_gap": 100, "dist": 0.5, "angle": 30.0},
    "kitti": {"seeds": [0], "fps": 10.0, "kf_every": 3, "min_gap": 30, "dist": 4.0, "angle": 30.0},
    "map": {"seeds": [], "fps": 10.0, "kf_every": 1, "min_gap": 100, "dist": 0.5, "angle": 30.0},
    # an image is a frame; the units are photo_units' blocks; truth by inliers, not by pose
    "photos": {"seeds": [], "fps": 1.0, "kf_every": 1, "min_gap": 2, "dist": None, "angle": None},
}
SETTINGS = ("fps", "kf_every", "min_gap", "dist", "angle")
FAMILY_TITLE = {"office": "rendered two-lap offices", "street": "rendered street drives, driven twice",
                "replay": "hard fr3 replays (the real path round a desk, back to its start)",
                "map": "saved ORB-tree SLAM maps (the map's keyframes; tracks from its map points)",
                "photos": "runs of held-out real CamVid street photos (no vocabulary trained on them; truth: "
                          f"at least {PHOTO_MIN_INLIERS} fundamental-matrix inliers)"}
FP_PRECISION = 0.9  # the KITTI check's threshold: the score that gives this precision on the offices


def family_args(args, family: str) -> argparse.Namespace:
    """``args`` with the family's settings; the options given on the command line override
    them for ``--family`` itself (the calibration offices of ``kitti`` keep the office ones)."""
    a = argparse.Namespace(**vars(args))
    for k in SETTINGS:
        given = getattr(args, k)
        setattr(a, k, given if given is not None and family == args.family else FAMILIES[family][k])
    a.family = family
    return a


def units(args) -> list[tuple[str, int]]:
    """The sequences of a run as (family, seed): ``kitti`` adds its calibration offices."""
    if args.family == "map":
        return [("map", i) for i in range(len(args.maps))]
    if args.family == "photos":
        return [("photos", i) for i in (args.scene_seeds or range(len(photo_units(args.photo_dir))))]
    out = [(args.family, seed) for seed in (args.scene_seeds or FAMILIES[args.family]["seeds"])]
    if args.family == "kitti":
        out = out[:1] + [("office", seed) for seed in args.calib_seeds]
    return out


def keyframes_of(family: str, seed: int, args, extractor: ORBExtractor) -> Keyframes:
    a = family_args(args, family)
    if family == "kitti":
        return kitti_keyframes(args.cache_dir, a, extractor)
    if family == "map":
        map_file, seq_dir = args.maps[seed]
        return map_keyframes(map_file, seq_dir, a)
    if family == "photos":
        return photo_keyframes(args.cache_dir, seed, a, extractor)
    return {"office": office_keyframes, "street": street_keyframes, "replay": replay_keyframes}[family](
        args.cache_dir, seed, a, extractor)


def kitti_check(kitti: dict, offices: list[dict], arms: dict[int, list[str]]) -> dict:
    """Per word count and arm the false-positive check of the KITTI stretch: the threshold
    that gives ``FP_PRECISION`` on the calibration offices' pooled top-1 detections, and
    :func:`false_positive_check` of the stretch's detections at it."""
    out = {}
    for size in arms:
        for arm in arms[size]:
            key = f"{size} {arm}"
            s = np.concatenate([np.asarray(o[key]["top1"], np.float64) for o in offices])
            c = np.concatenate([np.asarray(o[key]["top1_true"], bool) for o in offices])
            thr = threshold_at_precision(s, c, FP_PRECISION)
            out[key] = false_positive_check(np.asarray(kitti[key]["top1"], np.float64), thr)
    return out


def record_figures(name: str, means: dict, table: dict, n_sequences: int, load_start: float,
                   family: str = "office") -> Path | None:
    """``bench/results/NAME.json`` for the README, short: per word count the arms' mean AP
    and recall@1, and the AP contrasts with their CI, wins/losses and Holm p (the other
    figures are in ``--json``)."""
    sizes = list(dict.fromkeys(key.split()[0] for key in means))
    figs = []
    for size in sizes:
        arms = {key.split(" ", 1)[1]: m for key, m in means.items() if key.split()[0] == size}
        figs.append((f"{size} words, AP", ", ".join(f"{a} {m['AP']:.3f}" for a, m in arms.items())))
        figs.append((f"{size} words, recall@1", ", ".join(f"{a} {m['recall@1']:.3f}" for a, m in arms.items())))
        contrasts = [f"{key.split()[1]} {c['mean']:+.3f} [{c['ci95'][0]:+.3f}, {c['ci95'][1]:+.3f}] "
                     f"{c['wins']}/{c['losses']} Holm p {c['holm_p']:.2g}"
                     for key, c in table.items() if key.split()[0] == size and key.endswith(" AP")]
        if contrasts:
            figs.append((f"{size} words, AP contrasts", "; ".join(contrasts)))
    return figures.record(name, f"Keyframe words in place recognition: arms over {n_sequences} "
                                f"{FAMILY_TITLE[family]} (means; paired contrasts with bootstrap 95% CI, "
                                f"wins/losses; the rest in --json)",
                          figs, bench_file=__file__, load_start=load_start,
                          measures=None if family == "map" else [  # no SLAM run but the map family's saved maps
                              "bench/bench_place_recognition.py", "orbslam_hgcn/vocabulary", "orbslam_hgcn/features",
                              "orbslam_hgcn/match", "orbslam_hgcn/geometry", "orbslam_hgcn/map", "orbslam_hgcn/datasets",
                              "orbslam_hgcn/synth", "orbslam_hgcn/data", "orbslam_hgcn/configs", "orbslam_hgcn/config.py",
                              "orbslam_hgcn/config_files.py", "orbslam_hgcn/compiled.py", "orbslam_hgcn/aot.py",
                              "orbslam_hgcn/npzfile.py", "orbslam_hgcn/outputs.py", "orbslam_hgcn/trajectory.py"])


def record_kitti(name: str, check: dict, n_offices: int, load_start: float) -> Path | None:
    sizes = list(dict.fromkeys(key.split()[0] for key in check))
    figs = []
    for size in sizes:
        arms = {key.split(" ", 1)[1]: c for key, c in check.items() if key.split()[0] == size}
        queries = next(iter(arms.values()))["queries"]
        figs.append((f"{size} words, false positives of {queries} queries",
                     ", ".join(f"{a} {c['false_positives']}" for a, c in arms.items())))
    return figures.record(name, f"Keyframe words on the real KITTI 00 frames 0-159 (no revisit): a false-positive "
                                f"check, not AP. Per arm the top-1 detections scoring at least the threshold that "
                                f"gives {FP_PRECISION:.0%} precision on {n_offices} validation offices "
                                f"(thresholds and scores in --json)",
                          figs, bench_file=__file__, load_start=load_start,
                          measures=[  # extraction, tracks and words on frames: no SLAM run
                              "bench/bench_place_recognition.py", "orbslam_hgcn/vocabulary", "orbslam_hgcn/features",
                              "orbslam_hgcn/match", "orbslam_hgcn/geometry", "orbslam_hgcn/map", "orbslam_hgcn/datasets",
                              "orbslam_hgcn/synth", "orbslam_hgcn/data", "orbslam_hgcn/configs", "orbslam_hgcn/config.py",
                              "orbslam_hgcn/config_files.py", "orbslam_hgcn/compiled.py", "orbslam_hgcn/aot.py",
                              "orbslam_hgcn/npzfile.py", "orbslam_hgcn/outputs.py", "orbslam_hgcn/trajectory.py"])


_WORKER: dict = {}


def _init_worker(args) -> None:
    faiss.omp_set_num_threads(args.threads)
    vocab_1000 = args.vocab_1000 or args.cache_dir / "vocab1000"
    vocabs = {size: {kind: load_vocabulary(f) for kind, f in vocab_files(size, vocab_1000).items()
                     if any(ARMS[a][0] == kind for a in arms)} for size, arms in args.size_arms.items()}
    _WORKER.update(args=args, extractor=ORBExtractor(), vocabs=vocabs)


def _sequence(unit: tuple[str, int]) -> tuple[str, dict]:
    args = _WORKER["args"]
    kfs = keyframes_of(*unit, args, _WORKER["extractor"])
    return kfs.name, run_sequence(kfs, _WORKER["vocabs"], args.size_arms, family_args(args, unit[0]))


def _plain(value):
    """A value as JSON holds it: paths as strings (also inside the (map, sequence) pairs of --maps), NaN as null."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, float) and not np.isfinite(value):
        return None  # a figure that cannot be computed (no depth: no repeatability) is null, not NaN
    return value


def _fmt(x: float) -> str:
    """A figure for the console: n/a where it cannot be computed (NaN: no depth, no same-point pairs)."""
    return f"{x:.3f}" if np.isfinite(x) else "n/a"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache-dir", type=Path, default=Path("/tmp/orbslam_hgcn_bench"))
    ap.add_argument("--family", choices=list(FAMILIES), default="office",
                    help="sequences: rendered two-lap offices (default), street drives driven twice, hard fr3 "
                         "replays, the real KITTI 00 stretch (a false-positive check), saved maps, or runs of "
                         "held-out real photos")
    ap.add_argument("--scene-seeds", type=int, nargs="+", default=None,
                    help="scene seeds (default: the family's: offices 10..29, validation used 0 1 2; streets "
                         "10..17; replays 10..15); photos: unit numbers (default all)")
    ap.add_argument("--calib-seeds", type=int, nargs="+", default=[0, 1, 2],
                    help="kitti: the office seeds whose detections set each arm's threshold")
    ap.add_argument("--sizes", type=int, nargs="+", choices=(8000, 1000), default=[8000, 1000])
    ap.add_argument("--arms", nargs="+", choices=list(ARMS), default=list(ARMS))
    ap.add_argument("--vocab-1000", type=Path, default=None, help="1000-word vocabularies (default CACHE/vocab1000)")
    ap.add_argument("--fps", type=float, default=None, help="frame rate the gaps count in (default 10)")
    ap.add_argument("--kf-every", type=int, default=None,
                    help="a keyframe every this many frames (only those are rendered; default 3)")
    ap.add_argument("--min-gap", type=int, default=None,
                    help="query keyframes at least this many frames older (default 100; kitti 30)")
    ap.add_argument("--dist", type=float, default=None, help="loop: camera centres within this (m; default 0.5, "
                                                              "street and kitti 4)")
    ap.add_argument("--angle", type=float, default=None, help="loop: optical axes within this (degrees; default 30)")
    ap.add_argument("--street-s", type=float, default=30.0, help="street: seconds of each pass")
    ap.add_argument("--replay-s", type=float, default=None, help="replay: its first this many seconds (default all)")
    ap.add_argument("--kitti-dir", type=Path, default=KITTI_DIR)
    ap.add_argument("--photo-dir", type=Path, default=None,
                    help="photos: the real photo folder (default shared/data/real_photos beside the project)")
    ap.add_argument("--min-inliers", type=int, default=PHOTO_MIN_INLIERS,
                    help="photos: a true pair has at least this many fundamental-matrix RANSAC inliers")
    ap.add_argument("--maps", nargs="+", default=[], metavar="MAP.npz=SEQ_DIR",
                    help="map: maps saved by 'orbslam-hgcn run --vocab orb --save-map', each with its sequence")
    ap.add_argument("--point-tol", type=float, default=None,
                    help="same surface point: world points within this (m; default 0.01, street 0.05)")
    ap.add_argument("--threads", type=int, default=1,
                    help="faiss threads (word search is exact: the words do not depend on it; 1 is fastest on a "
                         "busy machine)")
    ap.add_argument("--jobs", type=int, default=1, help="sequences processed at once (processes)")
    ap.add_argument("--prepare-only", action="store_true",
                    help="only render and describe the sequences into --cache-dir (several can run at once)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--record", metavar="NAME", default=None, help="write bench/results/NAME.json (bench/figures.py)")
    args = ap.parse_args(argv)
    if args.family == "map":
        if not args.maps or any("=" not in m for m in args.maps):
            ap.error("--family map needs --maps MAP.npz=SEQ_DIR ...")
        args.maps = [tuple(Path(x) for x in m.split("=", 1)) for m in args.maps]
    if args.photo_dir is None:
        from orbslam_hgcn.vocabulary.training.photos import default_photo_folder

        args.photo_dir = default_photo_folder()
    if args.point_tol is None:
        args.point_tol = 0.05 if args.family == "street" else 0.01
    load_start = os.getloadavg()[0]
    faiss.omp_set_num_threads(args.threads)
    t0 = time.perf_counter()
    todo = units(args)
    if args.prepare_only:
        extractor = ORBExtractor()
        for family, seed in todo:
            kfs = keyframes_of(family, seed, args, extractor)
            print(f"{kfs.name}: rendered and described ({time.perf_counter() - t0:.0f} s)", flush=True)
        return 0
    args.size_arms = arms = arms_by_size(args.sizes, args.arms, args.vocab_1000 or args.cache_dir / "vocab1000")
    per_seq: dict[str, dict] = {}
    with multiprocessing.get_context("spawn").Pool(args.jobs, _init_worker, (args,)) as pool:
        for name, r in pool.imap(_sequence, todo):
            per_seq[name] = r
            pairs = "no depth" if args.family == "photos" else f"{r['same_point_pairs']} same-point pairs"
            print(f"{name}: {r['keyframes']} keyframes, {100 * r['features_with_track']:.0f}% of features with a "
                  f"causal track, {pairs}, "
                  f"{r[f'{args.sizes[0]} {arms[args.sizes[0]][0]}']['with_loop']} queries with a loop", flush=True)
            for size, size_arms in arms.items():
                print(f"  {size:5d} " + "  ".join(f"{a} {r[f'{size} {a}']['AP']:.3f}/{r[f'{size} {a}']['recall@1']:.3f}"
                                                 for a in size_arms) + "   (AP/R@1)", flush=True)
    settings = {k: _plain(v) for k, v in vars(family_args(args, args.family)).items()}
    if args.family == "kitti":
        name = next(iter(per_seq))
        if any(per_seq[name][k]["with_loop"] for k in per_seq[name] if k[:1].isdigit()):
            raise SystemExit(f"bench_track_words: {name} has a true loop at these settings: not a false-positive check")
        check = kitti_check(per_seq[name], [per_seq[n] for n in list(per_seq)[1:]], arms)
        print(f"\nfalse-positive check on {name} (no revisit; not AP): per arm the top-1 detections of its "
              f"{check[next(iter(check))]['queries']} queries scoring at least the threshold that gives "
              f"{FP_PRECISION:.0%} precision on the pooled offices {args.calib_seeds}")
        for key, c in check.items():
            print(f"  {key:10s} threshold {c['threshold']:.4f}  false positives {c['false_positives']:3d}/{c['queries']}"
                  f"  max score {c['max_score']:.4f} ({c['max_over_threshold']:.2f} x threshold)")
        print(f"({time.perf_counter() - t0:.0f} s)")
        if args.json is not None:
            args.json.write_text(json.dumps(_plain({"settings": settings, "sequences": per_seq,
                                                    "false_positive_check": check}), indent=1))
        if args.record:
            record_kitti(args.record, check, len(per_seq) - 1, load_start)
        return 0
    means, table = summarise(per_seq, arms)
    print(f"\nper arm, mean over {len(per_seq)} sequences: AP, recall@1, recall@100%P, same-point word "
          f"repeatability, effective words (exp entropy)")
    for key, m in means.items():
        print(f"  {key:10s} AP {m['AP']:.3f}  R@1 {m['recall@1']:.3f}  R@100P {m['recall@P100']:.3f}  "
              f"repeat {_fmt(m['repeatability'])}  eff. words {m['effective_words']:.0f}")
    print("\npaired contrasts over sequences: mean difference [bootstrap 95% CI], wins/losses, Wilcoxon p, Holm p")
    for key, c in table.items():
        print(f"  {key:22s} {c['mean']:+.4f} [{c['ci95'][0]:+.4f}, {c['ci95'][1]:+.4f}]  {c['wins']}/{c['losses']}  "
              f"p {c['wilcoxon_p']:.4f}  Holm {c['holm_p']:.4f}")
    print(f"({time.perf_counter() - t0:.0f} s)")
    if args.json is not None:
        args.json.write_text(json.dumps(_plain({"settings": settings, "sequences": per_seq, "means": means,
                                                "contrasts": table}), indent=1))
    if args.record:
        record_figures(args.record, means, table, len(per_seq), load_start, args.family)
    return 0


if __name__ == "__main__":
    sys.exit(main())
