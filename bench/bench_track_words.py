"""Track words against lone words in place recognition: the ablation of the keyframe BoW.

Arms (same sequences, keyframes, tracks and database protocol):

* ``A0``  k-means words of lone descriptors (the shipped k-means vocabulary);
* ``A1``  the shipped HGCN's words of lone descriptors (its network on one descriptor);
* ``B0``  k-means word of each feature's causal track mean (no network);
* ``B0h`` the shipped HGCN's word of the causal track mean (the network on the mean);
* ``C``   the graph network over the causal track mates with mean aggregation (its
  k-means words; ``--graph-mean``, the shipped ``hgcn_graph_mean``), ``C-att`` the same
  with attention (``--graph``, the shipped ``hgcn_graph``): :mod:`orbslam_hgcn.vocabulary.track_network`;
* ``orb`` the ORB tree of about the flat vocabularies' size (``orb10k``) on lone descriptors.

Sequences: the place-recognition offices of ``bench_place_recognition.py`` (two laps round
a desk, one rendered sequence per scene seed, not training scenes), keyframes every
``--kf-every`` frames. Tracks: features matched between consecutive keyframes
(:func:`orbslam_hgcn.vocabulary.training.tracks.build_tracks`: mutual nearest neighbours, ratio
test, RANSAC fundamental matrix), standing in for the map's point observations. A
keyframe's track mean uses the members in itself and the keyframes before it that are
less than ``--min-gap`` frames older (causal, and never reaching the keyframes a query is
allowed to match, so a query and its true match never share a track member); a feature
whose track has no such earlier member keeps its lone word. Each keyframe queries a
database of the keyframes at least ``--min-gap`` frames older; its best match is a
detection, true when the two cameras are within ``--dist`` m and ``--angle`` degrees.

Per sequence and arm: average precision (PR curve over the detections' scores), recall@1
(true top-1 detections / queries with a true loop in the database) and recall at 100%
precision. Paired contrasts over sequences (units): mean difference, bootstrap 95% CI
(10 000 resamples of the units), Wilcoxon signed-rank p (exact for few units), Holm-
corrected over all contrasts and both metrics. Results as JSON with ``--json``.

    python bench/bench_track_words.py [--scene-seeds 0 1 2 3 4 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import wilcoxon

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_place_recognition import loop_truth, pr_curve, two_lap_trajectory  # noqa: E402

from orbslam_hgcn.datasets import open_sequence  # noqa: E402
from orbslam_hgcn.features.orb import ORBExtractor  # noqa: E402
from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence  # noqa: E402
from orbslam_hgcn.map.database import KeyframeDatabase  # noqa: E402
from orbslam_hgcn.vocabulary import load_vocabulary  # noqa: E402
from orbslam_hgcn.vocabulary.track_network import window_words  # noqa: E402
from orbslam_hgcn.vocabulary.training.tracks import build_tracks  # noqa: E402

ARMS = ("A0", "A1", "B0", "B0h", "C", "C-att", "orb")
CONTRASTS = (("B0", "A0"), ("B0h", "A1"), ("B0h", "B0"), ("A1", "A0"), ("C-att", "A0"), ("C-att", "B0"),
             ("C", "B0"))
METRICS = ("AP", "recall@1")


def causal_means(x: list[np.ndarray], tracks: list[np.ndarray], window: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per keyframe k: (rows of its features with an earlier track member in keyframes
    k - window + 1 .. k, (R, d) means of those members' reduced descriptors x)."""
    out = []
    for k in range(len(x)):
        lo = max(0, k - window + 1)
        ids = np.concatenate([tracks[j] for j in range(lo, k + 1)])
        pts = np.concatenate([x[j] for j in range(lo, k + 1)]).astype(np.float64)
        valid = ids >= 0
        uid, inv, cnt = np.unique(ids[valid], return_inverse=True, return_counts=True)
        sums = np.zeros((len(uid), pts.shape[1]))
        np.add.at(sums, inv, pts[valid])
        t = tracks[k]
        pos = np.searchsorted(uid, t)
        has = (t >= 0) & (pos < len(uid))
        has[has] &= uid[pos[has]] == t[has]
        rows = np.flatnonzero(has)
        rows = rows[cnt[pos[rows]] >= 2]
        out.append((rows, (sums[pos[rows]] / cnt[pos[rows], None]).astype(np.float32)))
    return out


def scores(bows: list, frames: np.ndarray, gt: np.ndarray, min_gap: int) -> dict:
    """AP, recall@1 and recall at 100% precision of top-1 detections (one sequence)."""
    s, correct, eligible = [], [], []
    db = KeyframeDatabase()
    added = 0
    for i in range(len(bows)):
        while added < len(bows) and frames[added] <= frames[i] - min_gap:
            db.add(added, bows[added])
            added += 1
        if added == 0:
            continue
        res = db.query(bows[i], max_results=1)
        s.append(res[0][1] if res else 0.0)
        correct.append(bool(res) and bool(gt[i, res[0][0]]))
        eligible.append(bool(gt[i, :added].any()))
    correct = np.array(correct)
    n_pos = int(np.sum(eligible))
    prec, rec = pr_curve(np.array(s), correct, n_pos)
    full = prec >= 1.0 - 1e-12
    return {"AP": float(np.sum(np.diff(np.concatenate([[0.0], rec])) * prec)),
            "recall@1": float(correct.sum() / max(n_pos, 1)),
            "recall@P100": float(rec[full].max()) if full.any() else 0.0,
            "queries": len(s), "with_loop": n_pos}


def contrast(a: np.ndarray, b: np.ndarray, rng: np.random.Generator) -> dict:
    d = np.asarray(a) - np.asarray(b)
    boot = d[rng.integers(0, len(d), (10_000, len(d)))].mean(1)
    p = float(wilcoxon(d).pvalue) if np.any(d != 0) else 1.0
    return {"mean": float(d.mean()), "ci95": [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))],
            "wilcoxon_p": p, "units": len(d), "wins": int((d > 0).sum()), "losses": int((d < 0).sum())}


def holm(ps: list[float]) -> list[float]:
    order = np.argsort(ps)
    out, running = [0.0] * len(ps), 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(ps) - rank) * ps[i]))
        out[i] = running
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache-dir", type=Path, default=Path("/tmp/orbslam_hgcn_bench"))
    ap.add_argument("--scene-seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--kf-every", type=int, default=3)
    ap.add_argument("--min-gap", type=int, default=100, help="query keyframes at least this many frames older")
    ap.add_argument("--dist", type=float, default=0.5)
    ap.add_argument("--angle", type=float, default=30.0)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--graph", default="hgcn_graph", help="arm C-att: vocabulary with the attention track network")
    ap.add_argument("--graph-mean", default="hgcn_graph_mean",
                    help="arm C: vocabulary with the mean-aggregation track network")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    gt_file = two_lap_trajectory(args.cache_dir / "two_lap_40s_wide.txt")
    vocabs = {"kmeans": load_vocabulary("kmeans"), "hgcn": load_vocabulary("hgcn"), "orb": load_vocabulary("orb10k"),
              "graph": load_vocabulary(args.graph), "graph_mean": load_vocabulary(args.graph_mean)}
    extractor = ORBExtractor()
    window = max(1, args.min_gap // args.kf_every)  # keyframes less than min_gap frames older, and itself
    per_seq: dict[str, dict[str, dict]] = {}
    for seed in args.scene_seeds:
        opts = SynthOptions(trajectory="replay", gt=str(gt_file), fps=args.fps, scene_seed=seed,
                            noise=2.0, exposure_drift=0.1, seed=seed)
        seq_dir = render_sequence(args.cache_dir / f"office{seed}_two_laps_wide_{args.fps:g}fps", opts,
                                  progress=False, cache=True)
        seq = open_sequence("tum", seq_dir)
        frames = np.arange(0, len(seq), args.kf_every)
        desc, uv, poses = [], [], []
        for f in frames:
            rec = seq[int(f)]
            kps = extractor.extract(rec.image)
            desc.append(kps.desc)
            uv.append(np.asarray(kps.uv, np.float32))
            poses.append(rec.T_wc)
        gt = loop_truth(np.stack(poses), args.dist, args.angle)
        tid = build_tracks(desc, uv, np.zeros(len(desc), np.int64), progress=False)
        splits = np.cumsum([len(d) for d in desc])[:-1]
        tracks = np.split(tid, splits)
        bows: dict[str, list] = {}
        tracked_share = []
        for kind, arm_lone, arm_track in (("kmeans", "A0", "B0"), ("hgcn", "A1", "B0h")):
            v = vocabs[kind]
            x = [v.project(d) for d in desc]
            lone = [v.words_of_points(xi) for xi in x]
            means = causal_means(x, tracks, window)
            bows[arm_lone] = [v.bow_from_words(w) for w in lone]
            bows[arm_track] = []
            for w, (rows, m) in zip(lone, means):
                w = w.copy()
                if len(rows):
                    w[rows] = v.words_of_points(m)
                bows[arm_track].append(v.bow_from_words(w))
            tracked_share = [len(r) / max(len(xi), 1) for (r, _), xi in zip(means, x)]
        for arm, graph in (("C", vocabs["graph_mean"]), ("C-att", vocabs["graph"])):
            bows[arm] = [graph.bow_from_words(w) for w in window_words(graph, desc, tracks, window)]
        bows["orb"] = [vocabs["orb"].bow(d) for d in desc]
        name = f"office{seed}"
        per_seq[name] = {arm: scores(bows[arm], frames, gt, args.min_gap) for arm in ARMS}
        per_seq[name]["features_with_track_mean"] = float(np.mean(tracked_share))
        line = "  ".join(f"{arm} AP {per_seq[name][arm]['AP']:.3f} R@1 {per_seq[name][arm]['recall@1']:.3f}"
                         for arm in ARMS)
        print(f"{name}: {len(frames)} keyframes, {100 * np.mean(tracked_share):.0f}% of features with a track "
              f"mean; {line}", flush=True)
    rng = np.random.default_rng(0)
    names = list(per_seq)
    table = {}
    for metric in METRICS:
        for a, b in CONTRASTS:
            va = np.array([per_seq[n][a][metric] for n in names])
            vb = np.array([per_seq[n][b][metric] for n in names])
            table[f"{a}-{b} {metric}"] = contrast(va, vb, rng)
    for key, p in zip(table, holm([c["wilcoxon_p"] for c in table.values()])):
        table[key]["holm_p"] = p
    print(f"\nper arm, mean over {len(names)} sequences (min over sequences .. max):")
    for arm in ARMS:
        for metric in METRICS:
            vals = [per_seq[n][arm][metric] for n in names]
            print(f"  {arm:4s} {metric:9s} {np.mean(vals):.3f} ({min(vals):.3f} .. {max(vals):.3f})")
    print("\npaired contrasts over sequences: mean difference [bootstrap 95% CI], wins/losses, Wilcoxon p, Holm p")
    for key, c in table.items():
        print(f"  {key:18s} {c['mean']:+.4f} [{c['ci95'][0]:+.4f}, {c['ci95'][1]:+.4f}]  {c['wins']}/{c['losses']}  "
              f"p {c['wilcoxon_p']:.3f}  Holm {c['holm_p']:.3f}")
    print(f"({time.perf_counter() - t0:.0f} s)")
    if args.json is not None:
        args.json.write_text(json.dumps({"settings": vars(args) | {"cache_dir": str(args.cache_dir),
                                                                    "json": str(args.json)},
                                         "sequences": per_seq, "contrasts": table}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
