"""Loop-closure detection benchmark: BoW, HGCN-BoW, FAB-MAP 2.0 and HGCN-FABMAP.

Two sources of data:

* ``--train DIR --test DIR``: rendered sequences written by ``orbslam-hgcn synth --loop-gt``
  (different scene seeds for train and test); the test folder's ``loop_gt.npy`` is the
  ground truth (or pass ``--gt``);
* by default, a textured-strip world: the camera travels along a long procedural mural
  (``orbslam_hgcn.synth.textures``), each image a perspective view of a
  640-pixel window with jittered viewpoint, noise and exposure; the test route passes the
  mural once and then revisits its first part; training uses another mural. Two images
  show the same place when their windows overlap by at least half.

Vocabularies are trained on the training images' ORB descriptors: the ORB tree with
``train_tree_vocabulary`` (k=10, L=4 by default) and, when the vocabulary package provides it, the
HGCN vocabulary; methods whose vocabulary cannot be built are reported as skipped.
Prints the comparison table (recall / accuracy at the thresholds, recall at 100%
precision, AUC) and the time of each stage.

    python bench/bench_lcd.py [--frames 48] [--revisit 20] [--train-frames 40] [--out DIR]

Rendered sequences, e.g. a loop round one office for training and the replayed motion of
TUM fr3/long_office_household (which revisits its start) through another for testing:

    orbslam-hgcn synth --out /tmp/synth_train --duration 40 --fps 3 --scene-seed 1 --loop-gt --texel-scale 2
    orbslam-hgcn synth --out /tmp/synth_replay --trajectory replay --fps 2 --scene-seed 2 --loop-gt \
        --texel-scale 2 --gt ../shared/data/tum_fr3_long_office_household_sample/groundtruth.txt
    python bench/bench_lcd.py --train /tmp/synth_train --test /tmp/synth_replay --min-gap 20

``--paper``: the experiment of the HGCN paper's Tables 1 and 2 (arXiv:2207.06738, "Semi-supervised
Vector-Quantization in Visual SLAM using HGCN"; International Journal of Intelligent Systems
2024, article 9992159) run as ``orbslam-hgcn lcd`` runs it by default (images sampled, the
exclusion window from the ground truth, thresholds fitted on the training sequence), one
table per test sequence, and ``--json`` for the figures:

* City Centre and New College (Cummins & Newman, IJRR 2008), each tested with the detectors
  trained on the other, when ``data_scripts/placerec.sh citycentre newcollege`` has fetched
  them under ``--data`` (default data/placerec);
* otherwise (and always with ``--rendered``): rendered office sequences (training: the
  fr3 long-office path replayed with blur, exposure steps and JPEG; test: a loop twice
  round another office at 30 frames/s), rendered once into ``--work``, and the real KITTI
  00 frames 0-159 of ../shared/data as a second training sequence (they hold no loop, so
  its thresholds are the fixed ones). The TUM and EuRoC samples there (19 and 95 nearly
  still frames) hold no loop and too few views to test or train on.

The published figures are not printed beside ours: the paper's tables could not be read
from where this bench was written, and no figure is quoted without its source.

``--sweep``: the default run beside hand-set configurations (every ``--strides`` image and
a window of ``--gaps-s`` seconds) on ``--train``/``--test``, each detector's best AUC over
them, and how far the default is from it:

    python bench/bench_lcd.py --sweep --train TRAIN --test TEST [--strides 1,3,5,10] [--gaps-s 2,5,10,20]

``--photos``: a real-image check on photographs no shipped vocabulary was trained on, with
lcd's default vocabularies (``orb10k`` for BoW and FAB-MAP 2.0, ``hgcn`` for the HGCN
methods; the run prints each one's training data from its metadata). ``orb10k`` was trained
on ``shared/data/real_photos`` without its held-out images
(:data:`orbslam_hgcn.vocabulary.training.photos.HOLDOUT`); the ``hgcn`` file's metadata names
rendered offices and KITTI, TUM and EuRoC frames, no real photo at all. Test sequence: the held-out
CamVid frames ``camvid_0560``..``camvid_0700`` (141 video frames of a street drive, about
1 s apart, in order). Training sequence, on which each detector's threshold is fitted as
lcd fits it: the 140 CamVid frames just before them, ``camvid_0420``..``camvid_0559``; they
are in ``orb10k``'s training set, which does not matter for fitting a threshold. The
held-out ICDAR 2015 images are left out: neighbouring ones share no geometry.

Ground truth: two images show the same place when they share at least ``--min-inliers``
(40) fundamental-matrix RANSAC inliers between their ORB-SLAM extractor features, the
geometric verification of ``bench_track_words.py --family photos`` (its
:func:`photo_inliers`, imported, not copied); the inlier matrices are cached under
``--work`` (about 10,000 image pairs per sequence: some 15 minutes on one busy core the
first time). Exclusion window: 2 images (the next frame is too easy). The detectors, their
words, threshold fitting and scores (AUC and recall at 100% precision with 95% bootstrap
CIs) are lcd's (:func:`orbslam_hgcn.placerec.lcd.run_lcd`), but lcd's own choice of
images and loops is bypassed: lcd keeps as loops only the *revisits* of a ground truth (a
true pair joined to the diagonal through true pairs is one continuous visit, not a loop),
and a drive that never comes back has next to none (the run prints how many lcd would keep:
8 of the test sequence's 1,792 true pairs, 5 of training's 717; 105 of the 141 test images
have a true pair 2 or more images back). So
this measures recognising the same place 2 or more frames later on real street images,
not closing a loop after a revisit; the warning that the best matches lie in the recent
past is expected here.

    python bench/bench_lcd.py --photos [--photo-dir DIR] [--min-inliers 40] [--json out.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from pathlib import Path

import cv2
import numpy as np

from orbslam_hgcn.config import FabmapConfig
from orbslam_hgcn.placerec.describe import Describer, describe_images
from orbslam_hgcn.placerec.lcd import (
    METHOD_VOCAB,
    METHODS,
    evaluate_methods,
    format_table,
    is_fabmap,
    quantize_sequences,
    write_outputs,
)

log = logging.getLogger("bench_lcd")

WIN = 640  # view window width on the mural, pixels
HEIGHT = 480


def mural(seed: int, length: int) -> np.ndarray:
    """(HEIGHT, length) uint8 grayscale procedural mural (print and wall styles alternating)."""
    from orbslam_hgcn.synth.textures import STYLES, make_texture

    rng = np.random.default_rng(seed)
    parts, done = [], 0
    while done < length:
        w = int(min(length - done, rng.integers(1500, 3000)))
        style = STYLES["print" if len(parts) % 2 == 0 else "wall"]
        parts.append(cv2.cvtColor(make_texture(rng, HEIGHT, w, 0.004, style), cv2.COLOR_BGR2GRAY))
        done += w
    return np.hstack(parts)


def view(strip: np.ndarray, x: float, rng: np.random.Generator) -> np.ndarray:
    """A (HEIGHT, WIN) perspective view of the window starting at ``x``, viewpoint jittered."""
    src = np.float32([[x, 0], [x + WIN, 0], [x + WIN, HEIGHT], [x, HEIGHT]])
    dst = np.float32([[0, 0], [WIN, 0], [WIN, HEIGHT], [0, HEIGHT]]) + rng.uniform(-25, 25, (4, 2)).astype(np.float32)
    H = cv2.getPerspectiveTransform(src, dst)
    img = cv2.warpPerspective(strip, H, (WIN, HEIGHT), borderMode=cv2.BORDER_REFLECT)
    gain = rng.uniform(0.8, 1.2)
    return np.clip(img * gain + rng.normal(0, 3, img.shape), 0, 255).astype(np.uint8)


def strip_world(args: argparse.Namespace) -> tuple[list, list, np.ndarray]:
    rng = np.random.default_rng(args.seed)
    step = args.step
    first = np.arange(args.frames) * step + rng.uniform(-20, 20, args.frames)
    back = np.arange(args.revisit) * step + rng.uniform(-0.2, 0.2, args.revisit) * WIN + 40
    x_test = np.clip(np.r_[first, back], 0, None)
    length = int(x_test.max()) + WIN + 64
    t0 = time.perf_counter()
    test_strip = mural(args.seed + 1, length)
    train_strip = mural(args.seed + 1000, args.train_frames * step + WIN + 64)
    test = [view(test_strip, x, rng) for x in x_test]
    x_train = np.arange(args.train_frames) * step
    train = [view(train_strip, x, rng) for x in x_train]
    gt = np.abs(x_test[:, None] - x_test[None, :]) <= WIN / 2
    np.fill_diagonal(gt, False)
    print(f"strip world: {len(train)} training and {len(test)} test images "
          f"({args.frames} first pass + {args.revisit} revisits, step {step} px) in {time.perf_counter() - t0:.1f} s")
    return train, test, gt


def folder_world(args: argparse.Namespace) -> tuple[list, list, np.ndarray]:
    from orbslam_hgcn.placerec.data import ImageSource, load_ground_truth

    train, test = ImageSource(args.train), ImageSource(args.test)
    gt = load_ground_truth(args.gt or Path(args.test) / "loop_gt.npy", n_images=len(test))
    return list(train), list(test), gt


def write_world(folder: Path, train: list, test: list, gt: np.ndarray) -> None:
    """Save the images as folder/train/*.png, folder/test/*.png and folder/test/loop_gt.npy."""
    for name, images in (("train", train), ("test", test)):
        (folder / name).mkdir(parents=True, exist_ok=True)
        for i, im in enumerate(images):
            cv2.imwrite(str(folder / name / f"{i:05d}.png"), im)
    np.save(folder / "test" / "loop_gt.npy", gt)
    print(f"wrote the images and ground truth under {folder}")


def train_vocabularies(train_desc: list[np.ndarray], args: argparse.Namespace) -> dict:
    """The ORB tree and (when available) the HGCN vocabulary trained on the training images,
    or loaded from ``--vocab-orb`` / ``--vocab-hgcn``; saved under ``--out`` when given."""
    from orbslam_hgcn.vocabulary.loading import load_vocabulary
    from orbslam_hgcn.vocabulary.orb_tree import train_tree_vocabulary

    desc = np.vstack(train_desc)
    ids = np.repeat(np.arange(len(train_desc)), [len(d) for d in train_desc])
    vocabs = {}
    t0 = time.perf_counter()
    if args.vocab_orb:
        vocabs["orb"] = load_vocabulary(args.vocab_orb)
    else:
        vocabs["orb"] = train_tree_vocabulary(desc, ids, k=10, levels=args.levels, trained_on="bench", progress=False)
    print(f"ORB tree: {vocabs['orb'].n_words} words, {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    if args.vocab_hgcn:
        vocabs["hgcn"] = load_vocabulary(args.vocab_hgcn)
    else:
        try:
            from orbslam_hgcn.config import HgcnTrainConfig
            from orbslam_hgcn.vocabulary.hgcn_vocab import train_hgcn_vocabulary
        except ImportError as exc:
            print(f"HGCN vocabulary: not available ({exc}); hgcn-* methods skipped")
            return vocabs
        cfg = dataclasses.replace(HgcnTrainConfig(), n_words=args.hgcn_words)  # other settings: defaults
        vocabs["hgcn"] = train_hgcn_vocabulary(desc, ids, cfg, trained_on="bench", progress=False)
    print(f"HGCN vocabulary: {vocabs['hgcn'].n_words} words, {time.perf_counter() - t0:.1f} s")
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        for kind, v in vocabs.items():
            if not getattr(args, f"vocab_{kind}"):
                print(f"wrote {v.save(Path(args.out) / f'vocab_{kind}.npz')}")
    return vocabs


PAPER_DATASETS = {"citycentre": "City Centre", "newcollege": "New College"}
KITTI_SHARED = Path(__file__).resolve().parents[1].parent / "shared/data/kitti00_first160/sequences/00"


def _placerec_dataset(folder: Path) -> tuple[Path, Path] | None:
    """(image folder, ground-truth file) of a data set unpacked by data_scripts/placerec.sh."""
    if not (folder / ".complete").is_file():
        return None
    gts = sorted(folder.rglob("*GroundTruth*.mat"))
    dirs: dict[Path, int] = {}
    for f in folder.rglob("*"):
        if f.suffix.lower() in (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp"):
            dirs[f.parent] = dirs.get(f.parent, 0) + 1
    if not gts or not dirs:
        return None
    return max(dirs, key=dirs.get), gts[0]


def paper_experiments(args: argparse.Namespace) -> list[dict]:
    """The (name, train, train_gt, test, test_gt, note) of each table to run."""
    data = Path(args.data)
    found = {k: _placerec_dataset(data / k) for k in PAPER_DATASETS}
    exps = []
    if all(found.values()) and not args.rendered:
        for test, other in (("citycentre", "newcollege"), ("newcollege", "citycentre")):
            exps.append({"name": f"{PAPER_DATASETS[test]} (trained on {PAPER_DATASETS[other]})",
                         "train": found[other][0], "train_gt": found[other][1],
                         "test": found[test][0], "test_gt": found[test][1]})
        return exps
    missing = [PAPER_DATASETS[k] for k, v in found.items() if not v]
    if missing and not args.rendered:
        print(f"{', '.join(missing)} not found under {data} (data_scripts/placerec.sh fetches them): "
              "rendered and shared sequences instead")
    from orbslam_hgcn.synth.sequence import render_sequence, synth_options

    work = Path(args.work)
    t0 = time.perf_counter()
    train = render_sequence(work / "office_replay_hard", synth_options(
        "fr3_replay_hard", loop_gt=True, scene_seed=3, texel_scale=2.0, frames=args.paper_train_frames), progress=False)
    test = render_sequence(work / "office_two_laps", synth_options(
        None, loop_gt=True, scene_seed=4, texel_scale=2.0, frames=args.paper_test_frames, laps=2, noise=2.0,
        exposure_drift=0.1, jpeg_quality=85), progress=False)
    print(f"rendered sequences in {work} ({time.perf_counter() - t0:.0f} s)")
    exps.append({"name": "rendered office loop (trained on the rendered fr3 replay)", "train": train,
                 "train_gt": None, "test": test, "test_gt": None})
    if KITTI_SHARED.is_dir():
        exps.append({"name": "rendered office loop (trained on real KITTI 00, frames 0-159)", "train": KITTI_SHARED,
                     "train_gt": None, "test": test, "test_gt": None})
    return exps


def _camera_stride(exp: dict) -> int | None:
    """2 when the Oxford ground truth covers one of the two cameras whose images alternate in
    the folder (a matrix half the image count): every other image, the first camera's."""
    from orbslam_hgcn.datasets.folder import list_images
    from orbslam_hgcn.placerec.data import load_ground_truth

    if exp["test_gt"] is None:
        return None
    halves = [len(load_ground_truth(exp[k + "_gt"])) * 2 == len(list_images(Path(exp[k]))) for k in ("train", "test")]
    if any(halves):
        if not all(halves):
            raise SystemExit("the training and test ground truths do not cover the same cameras")
        print("ground truth covers every other image (one camera of the alternating pair): --stride 2")
        return 2
    return None


def paper_main(args: argparse.Namespace) -> None:
    import json
    import tempfile

    from orbslam_hgcn.placerec.lcd import METHOD_LABEL, lcd_command
    from orbslam_hgcn.placerec.plots import _clean

    record = {"paper": "arXiv:2207.06738 (IJIS 2024, 9992159), Tables 1-2", "published_figures": None,
              "experiments": []}
    for exp in paper_experiments(args):
        out = Path(args.out) / f"paper_{len(record['experiments'])}" if args.out else Path(tempfile.mkdtemp())
        t0 = time.perf_counter()
        run = lcd_command(method="all", train=exp["train"], test=exp["test"], gt=exp["test_gt"],
                          train_gt=exp["train_gt"], out=out, stride=_camera_stride(exp))
        took = time.perf_counter() - t0
        print(f"\n{exp['name']}  ({took:.0f} s)")
        for line in run.lines:
            print(f"  {line}")
        print(f"  {'method':<13} {'recall%':>7} {'accuracy%':>9} {'R@100P%':>7} {'AUC%':>6}  threshold")
        rows = {}
        for r in run.results:
            s = r.score
            print(f"  {METHOD_LABEL[r.method]:<13} {100 * s.recall:7.1f} {100 * s.accuracy:9.1f} "
                  f"{100 * s.recall_at_100p:7.1f} {100 * s.auc:6.1f}  {s.threshold:.3g} ({r.threshold_from})")
            rows[r.method] = {**s.as_dict(), "threshold_from": r.threshold_from}
        record["experiments"].append({**{k: str(v) if v is not None else None for k, v in exp.items()},
                                      "seconds": took, "lines": run.lines, "methods": rows})
    print("\n(accuracy = precision TP/(TP+FP), the paper's eq. 10; published figures not shown: see the docstring)")
    if args.json:
        Path(args.json).write_text(json.dumps(_clean(record), indent=1), encoding="utf-8")
        print(f"wrote {args.json}")


def sweep_main(args: argparse.Namespace) -> None:
    """The default run and hand-set (stride, window) configurations on one train/test pair,
    with features and words computed once over every frame."""
    import json

    from orbslam_hgcn.placerec.experiment import prepare_sequence
    from orbslam_hgcn.placerec.lcd import METHOD_LABEL, WordData, evaluate_methods, load_vocabularies
    from orbslam_hgcn.placerec.plots import _clean
    from orbslam_hgcn.placerec.window import window_from_timestamps

    methods = list(METHODS)
    def_test = prepare_sequence(args.test, Path(args.gt) if args.gt else Path(args.test) / "loop_gt.npy",
                                stride=None, every_s=None, limit=None, min_gap=None, window_s=None)
    def_train = prepare_sequence(args.train, Path(args.train) / "loop_gt.npy", stride=None, every_s=None,
                                 limit=None, min_gap=None, window_s=None, name="training")
    all_test = prepare_sequence(args.test, Path(args.gt) if args.gt else Path(args.test) / "loop_gt.npy",
                                stride=1, every_s=None, limit=None, min_gap=1, window_s=None)
    all_train = prepare_sequence(args.train, Path(args.train) / "loop_gt.npy", stride=1, every_s=None, limit=None,
                                 min_gap=1, window_s=None, name="training")
    describer = Describer("orb", 1000)
    t0 = time.perf_counter()
    test_desc = describe_images(all_test.source, describer, total=len(all_test.source), desc="test features")
    train_desc = describe_images(all_train.source, describer, total=len(all_train.source), desc="train features")
    print(f"features of {len(test_desc)} test and {len(train_desc)} training frames: {time.perf_counter() - t0:.0f} s")
    vocabs = load_vocabularies(methods)
    words = {m: quantize_sequences(train_desc, test_desc, vocabs[m]) for m in methods}

    def run(test_idx, train_idx, test_gap, train_gap):
        wf = {m: WordData([w.train[i] for i in train_idx], [w.test[i] for i in test_idx], w.n_words)
              for m, w in words.items()}
        gt = all_test.gt[np.ix_(test_idx, test_idx)]
        train_gt = all_train.gt[np.ix_(train_idx, train_idx)]
        res = evaluate_methods(methods, wf, gt, FabmapConfig(min_gap=test_gap), train_gt=train_gt, train_gap=train_gap)
        return {r.method: {"auc": r.score.auc, "r100p": r.score.recall_at_100p, "recall": r.score.recall,
                           "accuracy": r.score.accuracy} for r in res}

    configs = {"default": run(def_test.source.indices, def_train.source.indices, def_test.window.gap,
                              def_train.window.gap)}
    t_test, t_train = all_test.source.all_timestamps, all_train.source.all_timestamps
    for stride in [int(x) for x in args.strides.split(",")]:
        ti, ri = np.arange(0, len(t_test), stride), np.arange(0, len(t_train), stride)
        for gap_s in [float(x) for x in args.gaps_s.split(",")]:
            g_test = window_from_timestamps(t_test[ti], gap_s).gap
            g_train = window_from_timestamps(t_train[ri], gap_s).gap
            name = f"stride {stride}, window {gap_s:g} s"
            configs[name] = run(ti, ri, g_test, g_train)
            print(f"{name}: " + ", ".join(f"{METHOD_LABEL[m]} AUC {100 * v['auc']:.1f}" for m, v in configs[name].items()))
    print(f"\n{'method':<13} {'default AUC%':>12} {'R@100P%':>7} {'best hand-set AUC%':>18}  {'(config)':<28} {'gap':>6}")
    summary = {}
    for m in methods:
        d = configs["default"][m]
        best = max((c for c in configs if c != "default"), key=lambda c: configs[c][m]["auc"])
        b = configs[best][m]["auc"]
        summary[m] = {"default_auc": d["auc"], "best_hand_set_auc": b, "best_config": best}
        print(f"{METHOD_LABEL[m]:<13} {100 * d['auc']:12.1f} {100 * d['r100p']:7.1f} {100 * b:18.1f}  "
              f"{best:<28} {100 * (b - d['auc']):+6.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps(_clean({"configs": configs, "summary": summary}), indent=1),
                                   encoding="utf-8")
        print(f"wrote {args.json}")


# --- --photos: held-out real CamVid photographs (see the docstring) ---------------------------
PHOTO_SOURCE = "camvid"
PHOTO_TRAIN = (420, 559)  # threshold fitting: the frames just before the hold-out (vocabulary training images)
PHOTO_GAP = 2  # exclusion window, images


def _track_words():
    """bench_track_words.py, the home of the photos family's geometric verification."""
    import sys

    here = str(Path(__file__).resolve().parent)
    if here not in sys.path:
        sys.path.insert(0, here)
    import bench_track_words

    return bench_track_words


def photo_sequences(folder: Path) -> tuple[list[Path], list[Path]]:
    """(training files, test files): CamVid ``PHOTO_TRAIN`` frames and every held-out CamVid frame."""
    from orbslam_hgcn.vocabulary.training.photos import photo_files

    held = photo_files(folder, "heldout").get(PHOTO_SOURCE, [])
    train = [f for f in photo_files(folder, "train").get(PHOTO_SOURCE, [])
             if PHOTO_TRAIN[0] <= int(f.stem.rsplit("_", 1)[1]) <= PHOTO_TRAIN[1]]
    if not held or len(train) != PHOTO_TRAIN[1] - PHOTO_TRAIN[0] + 1:
        raise SystemExit(f"bench_lcd: {folder}: expected the held-out {PHOTO_SOURCE} frames and "
                         f"{PHOTO_SOURCE}_{PHOTO_TRAIN[0]:04d}..{PHOTO_TRAIN[1]:04d}")
    return train, held


def photo_truth(files: list[Path], cache_dir: Path, min_inliers: int) -> tuple[np.ndarray, np.ndarray]:
    """(inliers, gt) of the images ``files``: the (n, n) fundamental-matrix RANSAC inlier
    counts of every pair (bench_track_words' :func:`photo_inliers` on ORB-SLAM extractor
    features; cached in ``cache_dir`` by extractor settings and file names) and the same-place
    matrix ``inliers >= min_inliers``, symmetric with a false diagonal."""
    from orbslam_hgcn.features.orb import ORBExtractor

    tw = _track_words()
    extractor = ORBExtractor()
    cached = Path(cache_dir) / f"inliers_{files[0].stem}-{files[-1].stem}_{tw.photo_cache_key(files, extractor)}.npy"
    if cached.exists():
        inliers = np.load(cached)
    else:
        inliers = tw.photo_inliers(*tw.photo_features(files, extractor))
        cached.parent.mkdir(parents=True, exist_ok=True)
        np.save(cached, inliers)
    return inliers, tw.same_place(inliers, min_inliers)


def photos_main(args: argparse.Namespace) -> None:
    import json

    from orbslam_hgcn.datasets.base import read_image
    from orbslam_hgcn.placerec.lcd import load_vocabularies, run_lcd
    from orbslam_hgcn.placerec.metrics import candidate_mask
    from orbslam_hgcn.placerec.plots import _clean
    from orbslam_hgcn.placerec.sequence import check_config
    from orbslam_hgcn.placerec.window import revisit_pairs
    from orbslam_hgcn.vocabulary.training.photos import default_photo_folder

    folder = Path(args.photo_dir) if args.photo_dir else default_photo_folder()
    min_inliers = args.min_inliers if args.min_inliers is not None else _track_words().PHOTO_MIN_INLIERS
    train_files, test_files = photo_sequences(folder)
    t0 = time.perf_counter()
    cache = Path(args.work) / "photos"
    (_, train_gt), (_, test_gt) = (photo_truth(f, cache, min_inliers) for f in (train_files, test_files))
    print(f"ground truth (>= {min_inliers} inliers; {time.perf_counter() - t0:.0f} s, cached in {cache})")
    counts = {}
    for name, files, gt in (("train", train_files, train_gt), ("test", test_files, test_gt)):
        outside = gt & candidate_mask(len(gt), PHOTO_GAP)
        counts[name] = {"images": len(files), "first": files[0].name, "last": files[-1].name,
                        "true_pairs": int(np.count_nonzero(np.tril(gt, -1))),
                        "pairs_outside_window": int(np.count_nonzero(outside)),
                        "queries_with_a_true_pair": int(outside.any(axis=1).sum()),
                        "lcd_revisit_pairs": int(np.count_nonzero(revisit_pairs(gt)))}
        c = counts[name]
        print(f"{name}: {c['images']} images {c['first']}..{c['last']}, {c['true_pairs']} true pairs, "
              f"{c['pairs_outside_window']} of them {PHOTO_GAP}+ images apart, {c['queries_with_a_true_pair']} "
              f"queries with one; lcd's revisit rule would keep {c['lcd_revisit_pairs']} pairs as loops")
    methods = list(METHODS)
    vocabs = load_vocabularies(methods)
    cfg = check_config(dataclasses.replace(FabmapConfig(), min_gap=PHOTO_GAP))
    t0 = time.perf_counter()
    results = run_lcd(methods, [read_image(f) for f in train_files], [read_image(f) for f in test_files], test_gt,
                      vocabs, Describer("orb", 1000), cfg, train_gt=train_gt, train_gap=PHOTO_GAP, progress=False)
    print(f"detectors: {time.perf_counter() - t0:.0f} s; vocabularies: "
          + ", ".join(f"{m} {vocabs[m]!r}" for m in methods))
    print(format_table(results))
    if args.json:
        record = {"photos": str(folder), "min_inliers": min_inliers, "exclusion_window": PHOTO_GAP,
                  "sequences": counts, "vocabularies": {m: repr(v) for m, v in vocabs.items()},
                  "methods": {r.method: {**r.score.as_dict(), "threshold_from": r.threshold_from,
                                         "train_score": r.train_score.as_dict() if r.train_score else None,
                                         "recent_past_share": r.recent_share} for r in results}}
        Path(args.json).write_text(json.dumps(_clean(record), indent=1), encoding="utf-8")
        print(f"wrote {args.json}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", default=None, help="rendered training sequence folder")
    ap.add_argument("--test", default=None, help="rendered test sequence folder (with loop_gt.npy)")
    ap.add_argument("--gt", default=None)
    ap.add_argument("--frames", type=int, default=48, help="strip world: first-pass test images")
    ap.add_argument("--revisit", type=int, default=20, help="strip world: revisiting test images")
    ap.add_argument("--train-frames", type=int, default=40)
    ap.add_argument("--step", type=int, default=256, help="strip world: pixels between images")
    ap.add_argument("--levels", type=int, default=4, help="ORB tree depth (k=10: 10^levels words)")
    ap.add_argument("--hgcn-words", type=int, default=8000, help="HGCN vocabulary size")
    ap.add_argument("--vocab-orb", default=None, help="use this ORB-tree vocabulary file")
    ap.add_argument("--vocab-hgcn", default=None, help="use this HGCN vocabulary file")
    ap.add_argument("--new-place", default="mean_field,sampled",
                    help="FAB-MAP new-place models to compare (comma list; MF / S in the table)")
    ap.add_argument("--min-gap", type=int, default=3,
                    help="compare only with images this many frames back (3: no shared view)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--write-world", default=None, help="also save the images and loop_gt.npy here")
    ap.add_argument("--out", default=None, help="write confusion matrices, PR curves and JSON here")
    ap.add_argument("--paper", action="store_true", help="the paper's Tables 1-2 (see the docstring)")
    ap.add_argument("--rendered", action="store_true", help="--paper: the rendered sequences even with the data sets")
    ap.add_argument("--data", default="data/placerec", help="--paper: where placerec.sh unpacked the data sets")
    ap.add_argument("--work", default="/tmp/orbslam_hgcn_bench_lcd", help="--paper: rendered sequences go here")
    ap.add_argument("--paper-train-frames", type=int, default=900, help="--paper: frames of the rendered training replay")
    ap.add_argument("--paper-test-frames", type=int, default=900, help="--paper: frames of the rendered test loop")
    ap.add_argument("--sweep", action="store_true", help="default vs hand-set configurations on --train/--test")
    ap.add_argument("--strides", default="1,3,5,10", help="--sweep: strides to try")
    ap.add_argument("--gaps-s", default="2,5,10,20", help="--sweep: exclusion windows (s) to try")
    ap.add_argument("--photos", action="store_true", help="held-out real CamVid photos (see the docstring)")
    ap.add_argument("--photo-dir", default=None, help="--photos: the real photo folder (default shared/data/real_photos)")
    ap.add_argument("--min-inliers", type=int, default=None,
                    help="--photos: a true pair has at least this many fundamental-matrix RANSAC inliers (40)")
    ap.add_argument("--json", default=None, help="--paper / --sweep / --photos: write the figures here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.paper:
        paper_main(args)
        return
    if args.sweep:
        sweep_main(args)
        return
    if args.photos:
        photos_main(args)
        return

    train, test, gt = folder_world(args) if args.train and args.test else strip_world(args)
    if args.write_world:
        write_world(Path(args.write_world), train, test, gt)
    describer = Describer("orb", 1000)
    t0 = time.perf_counter()
    train_desc = describe_images(train, describer, total=len(train), desc="train features")
    test_desc = describe_images(test, describer, total=len(test), desc="test features")
    print(f"ORB features: {np.mean([len(d) for d in train_desc + test_desc]):.0f} per image, "
          f"{time.perf_counter() - t0:.1f} s")
    vocabs = train_vocabularies(train_desc, args)
    methods = [m for m in METHODS if METHOD_VOCAB[m] in vocabs]
    words = {kind: quantize_sequences(train_desc, test_desc, v) for kind, v in vocabs.items()}
    t0 = time.perf_counter()
    results = []
    for new_place in args.new_place.split(","):
        cfg = FabmapConfig(min_gap=args.min_gap, new_place=new_place)
        todo = [m for m in methods if is_fabmap(m) or new_place == args.new_place.split(",")[0]]
        for r in evaluate_methods(todo, {m: words[METHOD_VOCAB[m]] for m in todo}, gt, cfg):
            if is_fabmap(r.method):
                label = f"{r.score.method} {'MF' if new_place == 'mean_field' else 'S'}"
                score = dataclasses.replace(r.score, method=label)
                r = dataclasses.replace(r, method=f"{r.method}-{new_place}", score=score)
            results.append(r)
    print(f"detection and scoring: {time.perf_counter() - t0:.1f} s")
    print(format_table(results))
    if args.out:
        for p in write_outputs(results, gt, args.out, {"bench": vars(args)}):
            print(f"wrote {p}")


if __name__ == "__main__":
    main()
