"""Build orbslam_hgcn/data/vocab_hgcn_graph.npz and vocab_hgcn_graph_mean.npz: the shipped
k-means words with the graph network over causal feature tracks, with attention (arm
C-att of the track-words ablation) or plain mean aggregation (arm C).

The words are those of the shipped k-means vocabulary (its PCA and centroids: a lone
descriptor gets its k-means word); the file adds the track network
(:mod:`orbslam_hgcn.vocabulary.track_network`), trained by
:func:`orbslam_hgcn.vocabulary.training.track_net.train_track_network` on the k-means
vocabulary's own training data (the real photographs of ``tools/train_default_vocabs.py``,
held-out images excluded), with feature tracks matched between consecutive images of each
photo source. The descriptor cache and the tracks are shared with train_default_vocabs.py
in ``--work-dir``.

    python tools/train_graph_vocab.py                        # attention: vocab_hgcn_graph.npz
    python tools/train_graph_vocab.py --aggregation mean     # vocab_hgcn_graph_mean.npz
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_default_vocabs import training_data, training_tracks  # noqa: E402

from orbslam_hgcn.vocabulary import load_vocabulary  # noqa: E402
from orbslam_hgcn.vocabulary.base import VocabularyMetadata, now_iso  # noqa: E402
from orbslam_hgcn.vocabulary.hgcn_vocab import HGCNVocabulary  # noqa: E402
from orbslam_hgcn.vocabulary.loading import SHIPPED  # noqa: E402
from orbslam_hgcn.vocabulary.training.track_net import TrackNetConfig, train_track_network  # noqa: E402
from orbslam_hgcn.vocabulary.training import photos  # noqa: E402

log = logging.getLogger("train_graph_vocab")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work-dir", type=Path, default=Path.home() / ".cache" / "orbslam_hgcn" / "vocab_training")
    ap.add_argument("--photos", type=Path, default=photos.default_photo_folder(),
                    help="folder of real photos named <source>_<NNNN>.jpg (default: shared/data/real_photos)")
    ap.add_argument("--n-features", "--features", dest="n_features", type=int, default=1000)
    ap.add_argument("--words", default="kmeans", help="the vocabulary whose PCA and words are used (default kmeans)")
    ap.add_argument("--aggregation", choices=("attention", "mean"), default="attention")
    ap.add_argument("--window", type=int, default=TrackNetConfig.window)
    ap.add_argument("--epochs", type=int, default=TrackNetConfig.epochs)
    ap.add_argument("--max-nodes", type=int, default=TrackNetConfig.max_nodes, help="training centres at most")
    ap.add_argument("--candidates", type=int, default=TrackNetConfig.candidates,
                    help="hard negatives per centre in the softmax (0: all words)")
    ap.add_argument("--device", default="auto", help="torch device (auto: a GPU when torch sees one)")
    ap.add_argument("--out", type=Path, default=None,
                    help="default: orbslam_hgcn/data/vocab_hgcn_graph.npz (attention) or vocab_hgcn_graph_mean.npz")
    args = ap.parse_args(argv)
    if args.out is None:
        args.out = SHIPPED["hgcn_graph" if args.aggregation == "attention" else "hgcn_graph_mean"]
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    args.work_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if not args.photos.is_dir():
        ap.error(f"--photos {args.photos}: no such folder")
    data, photos_line, tag = training_data(args.work_dir, args.photos, args.n_features)
    track_ids = training_tracks(args.work_dir, data, tag)
    words = load_vocabulary(args.words)
    if not hasattr(words, "centroids"):
        ap.error(f"--words {args.words}: needs a flat vocabulary with centroids (kmeans)")
    x = words.project(data.desc)
    cfg = dataclasses.replace(TrackNetConfig(), aggregation=args.aggregation, window=args.window,
                              epochs=args.epochs, max_nodes=args.max_nodes, candidates=args.candidates)
    log.info("training the track network (%s) on %d descriptors, %d tracked", args.aggregation, len(x),
             int((track_ids >= 0).sum()))
    net, stats = train_track_network(x, track_ids, words.centroids, cfg, desc=data.desc, device=args.device)
    history = stats.pop("validation_history")
    stats["validation_history_every_10"] = history[::10]
    trained_on = f"track network: {photos_line}; words: {words.metadata.trained_on}"
    meta = VocabularyMetadata(
        kind="hgcn", n_words=words.n_words, descriptor_type=words.descriptor_type,
        descriptor_dim=words.metadata.descriptor_dim, trained_on=trained_on, n_images=len(data.groups),
        n_descriptors=len(x), created=now_iso(),
        params={"arm": "C-att" if args.aggregation == "attention" else "C",
                "words": f"k-means centroids of {args.words!r} (a lone descriptor keeps its k-means word)",
                "decoder": "nearest k-means centroid of log_0 of the network output",
                **dataclasses.asdict(cfg), "n_features": args.n_features,
                "weighting": "tf-idf", "scoring": "L1"},
        stats={**stats, "tracked_descriptors": int((track_ids >= 0).sum()),
               "total_seconds": round(time.perf_counter() - t0, 1)},
    )
    vocab = HGCNVocabulary(words.pca, words.centroids, words.coarse_centroids, words.word_coarse,
                           words.ivf_centroids, words.nprobe, words.idf, meta, assignment="centroid")
    vocab.track_network = net
    vocab.save(args.out)
    print(meta.describe())
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
