"""Build the shipped vocabularies (orbslam_hgcn/data/vocab_{orb,hgcn,kmeans}_default.npz and
vocab_orb10k.npz).

Training imagery: synthetic office scenes rendered by ``orbslam_hgcn.synth.sequence``
with scene (and texture) seeds 1001..1000+S, far from the seeds evaluation sequences use
(0 and small numbers), each seen along one generated loop round its desk, sampled sparsely
(default 60 frames per loop) so the images cover the whole room. The shipped files use
these only. ``--with-real`` adds real frames: the samples of KITTI odometry 00 (frames
0-159), TUM fr3 long_office_household (19 frames) and EuRoC V1_01_easy (every 5th of
frames 0-94) in ``../shared/data`` (``--real PATH ...`` for other sequences); those frames
must then not be used to evaluate loop detection with the vocabularies. Every vocabulary is trained on the same descriptors
(ORB-SLAM's extractor, 1000 features per image); the HGCN's seed labels are shared along
feature tracks matched between consecutive frames of each scene. ``kmeans`` is the HGCN
vocabulary's ablation (its PCA and seed k-means at the same word count, without the graph
and the network); ``orb10k`` is the ORB tree at about that size (k=10, L=4). The run is reproducible: the same
arguments give the same files (up to the creation date in the metadata).

    python tools/train_default_vocabs.py                 # render, extract, train both
    python tools/train_default_vocabs.py --kinds hgcn    # only the HGCN vocabulary
    python tools/train_default_vocabs.py --kinds kmeans orb10k
    python tools/train_default_vocabs.py --with-real --out-dir DIR   # real frames as well

Rendered frames and the descriptor cache stay in ``--work-dir`` for later runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from pathlib import Path


from orbslam_hgcn.config import HgcnTrainConfig, TreeTrainConfig
from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence
from orbslam_hgcn.vocabulary.loading import SHIPPED
from orbslam_hgcn.vocabulary.training.tracks import build_tracks
from orbslam_hgcn.vocabulary.training.train import extract_descriptors, open_image_source, select_images, train_vocabulary

log = logging.getLogger("train_default_vocabs")

FIRST_SCENE_SEED = 1001
SHARED_DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"
# (folder under SHARED_DATA, every n-th frame, description for the metadata)
REAL_SAMPLES = [
    ("kitti00_first160/sequences/00", 1, "KITTI odometry 00 frames 0-159"),
    ("tum_fr3_long_office_household_sample", 1, "TUM RGB-D fr3 long_office_household, 19 sample frames"),
    ("euroc_V1_01_easy_first95", 5, "EuRoC V1_01_easy cam0, every 5th of frames 0-94"),
]


def render_training_scenes(work: Path, n_scenes: int, frames: int, progress: bool) -> list[Path]:
    """Render (or reuse) one sparse loop per training scene; returns the sequence folders."""
    folders = []
    for k in range(n_scenes):
        seed = FIRST_SCENE_SEED + k
        opts = SynthOptions(trajectory="loop", frames=frames, fps=frames / 30.0, scene_seed=seed, texture_seed=seed,
                            seed=seed, noise=2.0, exposure_drift=0.1)
        folders.append(render_sequence(work / f"scene_{seed}", opts, progress=progress))
    return folders


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work-dir", type=Path, default=Path.home() / ".cache" / "orbslam_hgcn" / "vocab_training")
    ap.add_argument("--scenes", type=int, default=10, help="training scenes (seeds 1001..)")
    ap.add_argument("--frames", type=int, default=60, help="frames per scene, spread over one loop")
    ap.add_argument("--features", type=int, default=1000, help="ORB features per image")
    ap.add_argument("--kinds", nargs="+", choices=("orb", "hgcn", "kmeans", "orb10k"),
                    default=["orb", "hgcn", "kmeans", "orb10k"])
    ap.add_argument("--hgcn-words", type=int, default=HgcnTrainConfig.n_words, help="hgcn and kmeans words")
    ap.add_argument("--orb-levels", type=int, default=TreeTrainConfig.levels)
    ap.add_argument("--no-tracks", action="store_true",
                    help="hgcn: no shared labels along feature tracks of consecutive frames")
    ap.add_argument("--with-real", action="store_true",
                    help="train on the real samples in ../shared/data as well")
    ap.add_argument("--real", nargs="+", type=Path, default=None,
                    help="train on these real sequences as well (every frame)")
    ap.add_argument("--out-dir", type=Path, default=None, help="write here instead of orbslam_hgcn/data/")
    ap.add_argument("--render-only", action="store_true", help="only render the training scenes")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    args.work_dir.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    folders = render_training_scenes(args.work_dir, args.scenes, args.frames, progress=True)
    log.info("rendered %d scenes in %.0f s", len(folders), time.perf_counter() - t0)
    if args.render_only:
        return 0
    sources = [open_image_source(f) for f in folders]
    pairs = select_images(sources, None)
    trained_on = (f"synthetic office scenes (orbslam_hgcn.synth.sequence, loop trajectory, noise 2, "
                  f"exposure drift 0.1), scene/texture seeds {FIRST_SCENE_SEED}..{FIRST_SCENE_SEED + args.scenes - 1}, "
                  f"{args.frames} frames each")
    real = [(p, 1, str(p)) for p in args.real or []]
    if args.with_real:
        real += [(SHARED_DATA / sub, step, text) for sub, step, text in REAL_SAMPLES]
    missing = [str(p) for p, _, _ in real if not p.exists()]
    if missing:
        ap.error(f"real sequences not found: {', '.join(missing)}")
    for path, step, text in real:
        sources.append(open_image_source(path))
        k = len(sources) - 1
        pairs += [(k, i) for i in range(0, sources[k].n, step)]
    n_real = len(pairs) - sum(s.n for s in sources[: len(folders)])
    trained_on += ("; real: " + "; ".join(f"{text} ({sum(1 for s, _ in pairs if s == len(folders) + j)} images)"
                                          for j, (_, _, text) in enumerate(real))) if real else "; no evaluation imagery"
    tag = f"_real{n_real}" if real else ""
    cache = args.work_dir / f"descriptors_{args.scenes}x{args.frames}{tag}_{args.features}.npz"
    data = extract_descriptors(sources, pairs, args.features, cache)
    desc, image_ids = data.desc, data.image_ids
    log.info("%d descriptors from %d images (%d real)", len(desc), len(pairs), n_real)
    for kind in args.kinds:
        out = SHIPPED[kind] if args.out_dir is None else args.out_dir / SHIPPED[kind].name
        t = time.perf_counter()
        if kind in ("orb", "orb10k"):
            levels = args.orb_levels if kind == "orb" else 4
            vocab = train_vocabulary("orb", desc, image_ids, tree=TreeTrainConfig(levels=levels),
                                     trained_on=trained_on)
        elif kind == "kmeans":
            vocab = train_vocabulary("kmeans", desc, image_ids,
                                     hgcn=dataclasses.replace(HgcnTrainConfig(), n_words=args.hgcn_words),
                                     trained_on=trained_on)
        else:
            track_ids = None if args.no_tracks else build_tracks(*data.per_image(), data.groups)
            vocab = train_vocabulary("hgcn", desc, image_ids,
                                     hgcn=dataclasses.replace(HgcnTrainConfig(), n_words=args.hgcn_words),
                                     track_ids=track_ids, trained_on=trained_on)
        vocab.metadata.params["n_features"] = args.features
        vocab.save(out)
        log.info("%s: %d words, %.1f MB, trained in %.0f s", out, vocab.n_words, out.stat().st_size / 1e6,
                 time.perf_counter() - t)
        print(vocab.metadata.describe())
    return 0


if __name__ == "__main__":
    sys.exit(main())
