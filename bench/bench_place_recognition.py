"""Place recognition with the two shipped vocabularies on synthetic sequences with revisits.

Sequences (default ``--trajectory twolap``): the camera walks twice round the desk of a
synthetic office (``orbslam_hgcn.synth.sequence``; scene seeds 0, 1, 2 by default, not
training scenes of the shipped vocabularies, which use 1001..), 40 s per lap at 10 fps,
with sensor noise and exposure drift. The laps are two generated loops (``LoopPath``) with
different random seeds: different start points, speeds, heights and gaze wander, so the
second lap revisits the places of the first from other viewpoints (0.3 m farther out and
0.15 m lower). ``--trajectory tum`` replays the real camera motion of TUM
fr3/long_office_household instead (one loop round a desk).

Protocol: every ``--kf-every``-th frame is a keyframe; each keyframe queries a
KeyframeDatabase holding the keyframes at least ``--min-gap`` frames older, and its best
match (highest L1 score) is a detection. Ground-truth loops: camera centres within
``--dist`` metres and optical axes within ``--angle`` degrees. Sweeping a threshold over the
detections' scores gives precision-recall (recall over the keyframes that have a true
loop among their database keyframes); printed: recall at 100% precision, area under the
PR curve (average precision), and CPU milliseconds per keyframe for the BoW vector and per
database query. The sequences of several scenes (``--scene-seeds``) are pooled.

    python bench/bench_place_recognition.py                       # render (first run), evaluate
    python bench/bench_place_recognition.py --orb A.npz --hgcn B.npz
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.datasets import open_sequence
from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence
from orbslam_hgcn.synth.trajectory import DeskSpec, LoopPath
from orbslam_hgcn.features.orb import ORBExtractor
from orbslam_hgcn.trajectory import Trajectory, write_tum
from orbslam_hgcn.map.database import KeyframeDatabase
from orbslam_hgcn.vocabulary import load_vocabulary

REPO = Path(__file__).resolve().parents[1]
TUM_GT = REPO.parent / "shared" / "data" / "tum_fr3_long_office_household_sample" / "groundtruth.txt"


def two_lap_trajectory(path: Path, lap_s: float = 40.0, seeds: tuple[int, int] = (3, 4)) -> Path:
    """Write a TUM file of two generated loops round one desk (100 Hz poses).

    The second lap keeps 0.3 m more clearance from the desk and walks 0.15 m lower, so its
    revisits see the places at another scale and angle.
    """
    desk = DeskSpec(1.6, 0.8, 0.74)
    t = np.arange(0.0, lap_s, 0.01)
    lap1 = LoopPath(desk, lap_s, seeds[0])(t)
    lap2 = LoopPath(desk, lap_s, seeds[1], clearance=1.35, eye_height=1.30)(t)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_tum(path, Trajectory(np.concatenate([t, t + lap_s]), np.concatenate([lap1, lap2])))
    return path


def loop_truth(T_wc: np.ndarray, max_dist: float, max_angle: float) -> np.ndarray:
    """(K, K) bool: camera centres within max_dist and optical axes within max_angle degrees."""
    P, z = T_wc[:, :3, 3], T_wc[:, :3, 2]
    d = np.linalg.norm(P[:, None] - P[None], axis=-1)
    cos = np.clip(z @ z.T, -1, 1)
    return (d <= max_dist) & (cos >= np.cos(np.radians(max_angle)))


def pr_curve(scores: np.ndarray, correct: np.ndarray, n_positive: int) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall at every threshold (detections sorted by decreasing score)."""
    order = np.argsort(-scores, kind="stable")
    tp = np.cumsum(correct[order])
    k = np.arange(1, len(order) + 1)
    return tp / k, tp / max(n_positive, 1)


def evaluate(vocab, sequences: list[tuple[list[np.ndarray], np.ndarray, np.ndarray]], min_gap: int) -> dict:
    """Top-1 detections of every keyframe of every sequence, pooled into one PR curve.

    sequences: per sequence (keyframe descriptors, (K,) frame numbers, (K, K) loop truth).
    """
    scores, correct, eligible, q_cpu, bow_cpu = [], [], [], [], []
    for descs, frames, gt in sequences:
        c = time.process_time()
        bows = [vocab.transform(d)[0] for d in descs]
        bow_cpu.append((time.process_time() - c) / len(descs))
        db = KeyframeDatabase()
        added = 0
        for i in range(len(bows)):
            while added < len(bows) and frames[added] <= frames[i] - min_gap:
                db.add(added, bows[added])
                added += 1
            if added == 0:
                continue
            c = time.process_time()
            res = db.query(bows[i], max_results=1)
            q_cpu.append(time.process_time() - c)
            scores.append(res[0][1] if res else 0.0)
            correct.append(bool(res) and bool(gt[i, res[0][0]]))
            eligible.append(bool(gt[i, :added].any()))
    scores, correct = np.array(scores), np.array(correct)
    prec, rec = pr_curve(scores, correct, int(np.sum(eligible)))
    full = prec >= 1.0 - 1e-12
    r_at_p100 = float(rec[full].max()) if full.any() else 0.0
    ap = float(np.sum(np.diff(np.concatenate([[0.0], rec])) * prec))
    return {"queries": len(scores), "with_loop": int(np.sum(eligible)), "top1_correct": int(correct.sum()),
            "recall@P100": r_at_p100, "AP": ap, "bow_ms": 1e3 * float(np.mean(bow_cpu)),
            "query_ms": 1e3 * float(np.median(q_cpu))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache-dir", type=Path, default=Path("/tmp/orbslam_hgcn_bench"))
    ap.add_argument("--scene-seeds", type=int, nargs="+", default=[0, 1, 2],
                    help="evaluation scenes (one sequence each; results are pooled)")
    ap.add_argument("--trajectory", choices=("twolap", "tum"), default="twolap")
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--kf-every", type=int, default=3, help="keyframe every n-th frame")
    ap.add_argument("--min-gap", type=int, default=100, help="query keyframes at least this many frames older")
    ap.add_argument("--dist", type=float, default=0.5, help="ground-truth loop: camera centres within (m)")
    ap.add_argument("--angle", type=float, default=30.0, help="ground-truth loop: optical axes within (deg)")
    ap.add_argument("--orb", default="orb", help="ORB tree vocabulary (default: shipped)")
    ap.add_argument("--hgcn", default="hgcn", help="HGCN vocabulary (default: shipped)")
    ap.add_argument("--extra", nargs="*", default=[], help="more vocabulary files to evaluate")
    ap.add_argument("--render-only", action="store_true")
    args = ap.parse_args(argv)

    if args.trajectory == "tum":
        gt_file, name = TUM_GT, "tum_fr3_replay"
    else:
        gt_file, name = two_lap_trajectory(args.cache_dir / "two_lap_40s_wide.txt"), "two_laps_wide"
    seq_dirs = []
    for seed in args.scene_seeds:
        opts = SynthOptions(trajectory="replay", gt=str(gt_file), fps=args.fps, scene_seed=seed,
                            noise=2.0, exposure_drift=0.1, seed=seed)
        seq_dirs.append(render_sequence(args.cache_dir / f"office{seed}_{name}_{args.fps:g}fps", opts, progress=True, cache=True))
    if args.render_only:
        return 0
    extractor = ORBExtractor()
    sequences = []
    for seq_dir in seq_dirs:
        seq = open_sequence("tum", seq_dir)
        kf_frames = np.arange(0, len(seq), args.kf_every)
        descs, poses = [], []
        for f in kf_frames:
            rec = seq[int(f)]
            descs.append(extractor.extract(rec.image).desc)
            poses.append(rec.T_wc)
        sequences.append((descs, kf_frames, loop_truth(np.stack(poses), args.dist, args.angle)))
        print(f"sequence {seq_dir.name}: {len(seq)} frames, {len(kf_frames)} keyframes (every {args.kf_every})")
    print(f"queries against keyframes >= {args.min_gap} frames older; loops: <= {args.dist} m and <= {args.angle} deg; "
          "pooled over the sequences")
    print(f"{'vocabulary':44s} {'words':>7s} {'queries':>7s} {'w/loop':>6s} {'top1 ok':>7s} "
          f"{'R@P100':>7s} {'AP':>6s} {'BoW ms':>7s} {'query ms':>8s}")
    for name in [args.orb, args.hgcn, *args.extra]:
        vocab = load_vocabulary(name)
        r = evaluate(vocab, sequences, args.min_gap)
        label = f"{vocab.kind}:{Path(name).name}"
        print(f"{label:44s} {vocab.n_words:7d} {r['queries']:7d} {r['with_loop']:6d} {r['top1_correct']:7d} "
              f"{r['recall@P100']:7.3f} {r['AP']:6.3f} {r['bow_ms']:7.2f} {r['query_ms']:8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
