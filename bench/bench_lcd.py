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
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

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
