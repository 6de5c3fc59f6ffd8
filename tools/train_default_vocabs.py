"""Build the shipped vocabularies (orbslam_hgcn/data/vocab_{orb,hgcn,kmeans}_default.npz and
vocab_orb10k.npz) from real photographs.

Training imagery: the photos of ``shared/data/real_photos`` (``--photos`` for another folder
laid out the same way) less the held-out images of
:data:`orbslam_hgcn.vocabulary.training.photos.HOLDOUT`, which the benches use to judge the
vocabularies on real images no vocabulary has seen. No benchmark sequence (KITTI, TUM,
EuRoC) and no render is in it. ``--with-renders`` adds rendered office loops
(``orbslam_hgcn.synth``, scene seeds 1001..), for measuring whether renders help; the shipped
files do not use them.

Every vocabulary is trained on the same descriptors (ORB-SLAM's extractor, 1000 features per
image): ``orb`` is the ORB tree at the shape of ORB-SLAM's ORBvoc (k = 10, L = 6),
``orb10k`` the tree at the flat vocabularies' size (k = 10, L = 4), ``kmeans`` the HGCN
vocabulary's ablation (its PCA and seed k-means at the same word count), ``hgcn`` the HGCN
vocabulary, whose seed labels are shared along feature tracks matched between consecutive
images of each photo source (the CamVid drives and the head-worn walks are video frames);
``hgcn_graph`` and ``hgcn_graph_mean`` add the track network (attention, mean) to the new
k-means words (tools/train_graph_vocab.py). The run is reproducible: the same arguments give the same files (up to the creation date).

    python tools/train_default_vocabs.py                 # all six shipped files
    python tools/train_default_vocabs.py --kinds orb     # only the ORB tree
    python tools/train_default_vocabs.py --out-dir DIR   # write elsewhere

The descriptor cache and the tracks stay in ``--work-dir`` for later runs (and for
tools/train_graph_vocab.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.config import HgcnTrainConfig, TreeTrainConfig
from orbslam_hgcn.vocabulary.loading import SHIPPED
from orbslam_hgcn.vocabulary.training import photos
from orbslam_hgcn.vocabulary.training.tracks import build_tracks
from orbslam_hgcn.vocabulary.training.train import TrainingData, extract_descriptors, open_image_source, select_images, train_vocabulary

log = logging.getLogger("train_default_vocabs")

FIRST_SCENE_SEED = 1001
ORB_LEVELS = 6  # ORB-SLAM's ORBvoc.txt: k = 10, L = 6
KINDS = ("orb", "orb10k", "kmeans", "hgcn", "hgcn_graph", "hgcn_graph_mean")  # in build order
# The arm of bench/bench_track_words.py each flat vocabulary is (its metadata's params).
ARMS = {"kmeans": "A0", "hgcn": "A1"}
# What each file is for, kept in its metadata (``vocab info`` prints it).
ROLES = {
    "orb": "the ORB baseline at ORB-SLAM's ORBvoc shape; exported with 'vocab export orb' it is ORB-SLAM3's vocabulary "
           "in bench/bench_peer.py (gate: >= 98% of KITTI 00 frames 0-159 tracked)",
    "orb10k": "the ORB tree at the flat vocabularies' size: the baselines (BoW, FAB-MAP 2.0) of 'lcd' and arm 'orb' "
              "of bench/bench_track_words.py",
    "kmeans": "default vocabulary of run: no arm beat its words (A0) in bench/bench_track_words.py, on the rendered "
              "families or on the held-out real photographs (bench/results/track_words*.json)",
    "hgcn": "the paper's vocabulary (arm A1); the demo and 'compare' run it against the ORB tree",
}


def render_training_scenes(work: Path, n_scenes: int, frames: int, progress: bool) -> list[Path]:
    """Render (or reuse) one sparse loop per training scene; returns the sequence folders."""
    from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence

    folders = []
    for k in range(n_scenes):
        seed = FIRST_SCENE_SEED + k
        opts = SynthOptions(trajectory="loop", frames=frames, fps=frames / 30.0, scene_seed=seed, texture_seed=seed,
                            seed=seed, noise=2.0, exposure_drift=0.1)
        folders.append(render_sequence(work / f"scene_{seed}", opts, progress=progress))
    return folders


def training_data(work: Path, photo_folder: Path, features: int, renders: int = 0,
                  frames: int = 60) -> tuple[TrainingData, str, str]:
    """Descriptors of the training photos (and renders), the metadata's ``trained_on`` line,
    and the tag naming the cache files."""
    sources = photos.photo_sources(photo_folder, "train")
    trained_on = photos.describe(photo_folder, "train")
    tag = f"photos{sum(s.n for s in sources)}"
    if renders:
        folders = render_training_scenes(work, renders, frames, progress=True)
        sources += [open_image_source(f) for f in folders]
        trained_on += (f"; renders: synthetic office loops, scene seeds {FIRST_SCENE_SEED}.."
                       f"{FIRST_SCENE_SEED + renders - 1}, {frames} frames each")
        tag += f"_renders{renders}x{frames}"
    tag += f"_{features}"
    pairs = select_images(sources, None)
    data = extract_descriptors(sources, pairs, features, work / f"descriptors_{tag}.npz")
    return data, trained_on, tag


def training_tracks(work: Path, data: TrainingData, tag: str) -> np.ndarray:
    """Feature tracks of the training descriptors (cached in ``work``)."""
    track_file = work / f"tracks_{tag}.npz"
    if track_file.is_file():
        return np.load(track_file)["track"]
    track_ids = build_tracks(*data.per_image(), data.groups)
    np.savez(track_file, track=track_ids)
    return track_ids


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work-dir", type=Path, default=Path.home() / ".cache" / "orbslam_hgcn" / "vocab_training")
    ap.add_argument("--photos", type=Path, default=photos.default_photo_folder(),
                    help="folder of real photos named <source>_<NNNN>.jpg (default: shared/data/real_photos)")
    ap.add_argument("--n-features", "--features", dest="n_features", type=int, default=1000, help="ORB features per image")
    ap.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS))
    ap.add_argument("--hgcn-words", type=int, default=HgcnTrainConfig.n_words, help="hgcn and kmeans words")
    ap.add_argument("--orb-levels", type=int, default=ORB_LEVELS)
    ap.add_argument("--no-tracks", action="store_true",
                    help="hgcn: no shared labels along feature tracks of consecutive images")
    ap.add_argument("--with-renders", type=int, default=0, metavar="S",
                    help="add S rendered office loops (60 frames each) to the photos (not in the shipped files)")
    ap.add_argument("--out-dir", type=Path, default=None, help="write here instead of orbslam_hgcn/data/")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    args.work_dir.mkdir(parents=True, exist_ok=True)
    if not args.photos.is_dir():
        ap.error(f"--photos {args.photos}: no such folder")
    data, trained_on, tag = training_data(args.work_dir, args.photos, args.n_features, args.with_renders)
    log.info("%d descriptors from %d images", len(data.desc), len(data.groups))
    for kind in [k for k in KINDS if k in args.kinds]:
        if kind in ("hgcn_graph", "hgcn_graph_mean"):
            import train_graph_vocab  # the track network over the k-means words just written

            out = SHIPPED[kind] if args.out_dir is None else args.out_dir / SHIPPED[kind].name
            words = SHIPPED["kmeans"] if args.out_dir is None else args.out_dir / SHIPPED["kmeans"].name
            graph_args = ["--work-dir", str(args.work_dir), "--photos", str(args.photos), "--n-features",
                          str(args.n_features), "--words", str(words), "--out", str(out),
                          "--aggregation", "attention" if kind == "hgcn_graph" else "mean"]
            if train_graph_vocab.main(graph_args) != 0:
                return 1
            continue
        out = SHIPPED[kind] if args.out_dir is None else args.out_dir / SHIPPED[kind].name
        t = time.perf_counter()
        if kind in ("orb", "orb10k"):
            levels = args.orb_levels if kind == "orb" else 4
            vocab = train_vocabulary("orb", data.desc, data.image_ids, tree=TreeTrainConfig(levels=levels),
                                     trained_on=trained_on)
        elif kind == "kmeans":
            vocab = train_vocabulary("kmeans", data.desc, data.image_ids,
                                     hgcn=dataclasses.replace(HgcnTrainConfig(), n_words=args.hgcn_words),
                                     trained_on=trained_on)
        else:
            track_ids = None if args.no_tracks else training_tracks(args.work_dir, data, tag)
            vocab = train_vocabulary("hgcn", data.desc, data.image_ids,
                                     hgcn=dataclasses.replace(HgcnTrainConfig(), n_words=args.hgcn_words),
                                     track_ids=track_ids, trained_on=trained_on)
        vocab.metadata.params["n_features"] = args.n_features
        if kind in ARMS:
            vocab.metadata.params["arm"] = ARMS[kind]
        if kind in ROLES:
            vocab.metadata.stats["role"] = ROLES[kind]
        vocab.save(out)
        log.info("%s: %d words, %.1f MB, trained in %.0f s", out, vocab.n_words, out.stat().st_size / 1e6,
                 time.perf_counter() - t)
        print(vocab.metadata.describe())
    return 0


if __name__ == "__main__":
    sys.exit(main())
