"""What the HGCN's network can learn from its seed labels, and whether run time gives its words.

Part ``ceiling``: on real frames (KITTI odometry 00, frames 0-159 from ``../shared/data``,
ORB-SLAM's extractor), descriptors are joined into feature tracks between consecutive
frames (``build_tracks``) and every track member is labelled as the HGCN's track-shared
seeds are: the nearest k-means centre (``--words``, in the 20-D PCA space) of its track's
mean. The table gives how often each rule recovers that label from what a network can see:

* the descriptor alone (the identity: what the untrained residual network does);
* a per-descriptor map fitted to move each descriptor to its track's mean on half of the
  tracks and scored on the other half (affine least squares; a 2-layer MLP, residual);
* the descriptor averaged with its 9 nearest neighbours in the kNN graph (the HGCN's
  graph): plain mean, weighted by descriptor similarity, or only neighbours within a
  Hamming distance;
* an oracle that averages the descriptor with those of its 9 nearest neighbours that belong
  to its own track (what aggregation could give if the graph knew the tracks).

Part ``agreement``: for a trained HGCN vocabulary (default: the shipped one) and the
descriptors it was trained on (the cache of ``tools/train_default_vocabs.py``), how often
the run-time word (the layers applied to a descriptor alone, then the nearest prototype)
equals the network's word for that descriptor inside the training graph, for the training
descriptors and for held-out ones: EuRoC V1_01_easy frames 0-94 that the shipped training
skipped (all but every 5th), placed in a graph over both.

    python bench/bench_hgcn_labels.py                       # both parts, about 5 min on 2 cores
    python bench/bench_hgcn_labels.py --parts ceiling --words 1000
    python bench/bench_hgcn_labels.py --parts agreement --vocab FILE --train-cache FILE.npz
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.vocabulary import load_vocabulary
from orbslam_hgcn.vocabulary.flat import kmeans, nearest
from orbslam_hgcn.vocabulary.graph import build_graph, configure_faiss, fit_pca
from orbslam_hgcn.vocabulary.training.tracks import build_tracks
from orbslam_hgcn.vocabulary.training.train import make_extractor, open_image_source

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
KITTI = SHARED / "kitti00_first160" / "sequences" / "00"
EUROC = SHARED / "euroc_V1_01_easy_first95"
DEFAULT_CACHE = Path.home() / ".cache" / "orbslam_hgcn" / "vocab_training" / "descriptors_10x60_real198_1000.npz"


def extract(path: Path, indices, n_features: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    src = open_image_source(path)
    _, fn = make_extractor(n_features)
    out = [fn(src.load(i)) for i in indices]
    return [d for d, _ in out], [uv for _, uv in out]


def ceiling(words: int, n_features: int, seed: int) -> None:
    import torch

    t0 = time.perf_counter()
    desc, uv = extract(KITTI, range(160), n_features)
    track = build_tracks(desc, uv, np.zeros(len(desc), np.int32), progress=False)
    d = np.concatenate(desc)
    x = fit_pca(d, 20, seed=seed).transform(d)
    centres = kmeans(x, words, 20, seed, 64)
    member = track >= 0
    tids, inv = np.unique(track[member], return_inverse=True)
    sums = np.zeros((len(tids), x.shape[1]))
    np.add.at(sums, inv, x[member])
    means = (sums / np.bincount(inv)[:, None]).astype(np.float32)
    label = np.full(len(x), -1)
    label[member] = nearest(means, centres)[inv]
    target = np.zeros_like(x)
    target[member] = means[inv]
    rng = np.random.default_rng(seed)
    fit_tracks = rng.random(len(tids)) < 0.5
    idx = np.flatnonzero(member)
    fit, held = np.zeros(len(x), bool), np.zeros(len(x), bool)
    fit[idx[fit_tracks[inv]]], held[idx[~fit_tracks[inv]]] = True, True

    def acc(points: np.ndarray, rows: np.ndarray = member) -> float:
        return 100 * float(np.mean(nearest(points.astype(np.float32), centres)[rows] == label[rows]))

    configure_faiss()
    import faiss

    index = faiss.IndexFlatL2(x.shape[1])
    index.add(x)
    nb = index.search(x, 10)[1][:, 1:]
    mates = (track[nb] == track[:, None]) & member[:, None]
    print(f"KITTI 00 frames 0-159: {len(x)} descriptors, {member.sum()} in {len(tids)} tracks "
          f"(mean length {np.bincount(inv).mean():.2f}); {words} words; track mates among the 9 nearest "
          f"neighbours: {mates[member].sum(1).mean():.2f} on average, at least one for "
          f"{100 * np.mean(mates[member].any(1)):.1f}% of track members")
    rows = [("descriptor alone (identity)", acc(x), acc(x, held))]
    a = np.hstack([x[fit], np.ones((fit.sum(), 1))])
    w = np.linalg.lstsq(a, target[fit], rcond=None)[0]
    rows.append(("affine map to the track mean (fitted on half)", None, acc(np.hstack([x, np.ones((len(x), 1))]) @ w, held)))
    torch.manual_seed(seed)
    mlp = torch.nn.Sequential(torch.nn.Linear(20, 128), torch.nn.ReLU(), torch.nn.Linear(128, 128), torch.nn.ReLU(),
                              torch.nn.Linear(128, 20))
    opt = torch.optim.Adam(mlp.parameters(), 1e-3)
    xf, yf = torch.from_numpy(x[fit]), torch.from_numpy(target[fit])
    for _ in range(30):
        perm = torch.randperm(len(xf))
        for s in range(0, len(xf), 1024):
            b = perm[s : s + 1024]
            loss = ((xf[b] + mlp(xf[b]) - yf[b]) ** 2).sum(1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    with torch.no_grad():
        moved = (torch.from_numpy(x) + mlp(torch.from_numpy(x))).numpy()
    rows.append(("MLP map to the track mean (fitted on half)", None, acc(moved, held)))
    for alpha in (0.25, 0.5, 1.0):
        rows.append((f"x + {alpha} mean of its 9-NN", acc((x + alpha * x[nb].mean(1)) / (1 + alpha)), None))

    def with_neighbours(weight: np.ndarray) -> np.ndarray:
        """Each descriptor averaged with its 9 neighbours, weighted by ``weight`` (N, 9) (itself: 1)."""
        return (x + (x[nb] * weight[..., None]).sum(1)) / (1 + weight.sum(1))[:, None]

    d2 = ((x[nb] - x[:, None]) ** 2).sum(-1)
    for tau in (0.1, 0.25, 0.5):
        rows.append((f"9-NN weighted by exp(-d^2 / {tau} median)",
                     acc(with_neighbours(np.exp(-d2 / (tau * np.median(d2))))), None))
    bits = np.unpackbits(d, axis=1)
    ham = np.stack([(bits[nb[:, j]] != bits).sum(1) for j in range(nb.shape[1])], axis=1)
    for thr in (20, 30, 40):
        s = (ham < thr).astype(np.float32)
        prec = 100 * float(mates[member][s[member] > 0].mean())
        rows.append((f"9-NN within Hamming {thr} ({prec:.0f}% of them track mates)", acc(with_neighbours(s)), None))
    rows.append(("oracle: 9-NN of its own track", acc(with_neighbours(mates.astype(np.float32))), None))
    print(f"\nshare of track members given their track-mean label (%), {time.perf_counter() - t0:.0f} s")
    print(f"{'rule':58s} {'all members':>12s} {'held-out half':>14s}")
    for name, a_all, a_held in rows:
        f = lambda v: "" if v is None else f"{v:.1f}"  # noqa: E731
        print(f"{name:58s} {f(a_all):>12s} {f(a_held):>14s}")


def agreement(vocab_path: str, cache: Path, sample: int) -> int:
    vocab = load_vocabulary(vocab_path)
    if vocab.kind != "hgcn" or getattr(vocab, "network", None) is None:
        print(f"{vocab_path}: not an HGCN vocabulary with its network", file=sys.stderr)
        return 2
    if not cache.is_file():
        print(f"{cache} not found: make it with `python tools/train_default_vocabs.py --with-real --kinds hgcn` "
              "(or pass the cache of the descriptors the vocabulary was trained on)", file=sys.stderr)
        return 2
    with np.load(cache) as z:
        train = z["desc"]
    if len(train) != vocab.metadata.n_descriptors:
        print(f"{cache}: {len(train)} descriptors, the vocabulary was trained on {vocab.metadata.n_descriptors}",
              file=sys.stderr)
        return 2
    held_desc, _ = extract(EUROC, [i for i in range(95) if i % 5], 1000)
    held = np.concatenate(held_desc)
    p = vocab.metadata.params
    t0 = time.perf_counter()
    x = vocab.project(np.concatenate([train, held]))
    adj = build_graph(x, int(p.get("knn", 9)), int(p.get("knn_exact_max", 60000)), int(p.get("knn_nprobe", 16)),
                      int(p.get("seed", 0)))
    in_graph = vocab.graph_words(x, adj)
    t_graph = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    rows = np.sort(rng.choice(len(train), min(sample, len(train)), replace=False))
    alone_train = vocab.words_of_points(x[rows])
    alone_held = vocab.words_of_points(x[len(train):])
    print(f"{vocab_path}: {vocab.n_words} words, assignment {vocab.assignment}; graph over {len(train)} training "
          f"and {len(held)} held-out descriptors (EuRoC V1_01_easy frames 0-94 not used in training) "
          f"in {t_graph:.0f} s")
    print(f"run-time word = in-graph word: training {100 * np.mean(alone_train == in_graph[rows]):.1f}% "
          f"({len(rows)} sampled), held-out {100 * np.mean(alone_held == in_graph[len(train):]):.1f}%")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", nargs="+", choices=("ceiling", "agreement"), default=["ceiling", "agreement"])
    ap.add_argument("--words", type=int, default=1000, help="ceiling: k-means words")
    ap.add_argument("--features", type=int, default=1000, help="ceiling: ORB features per KITTI frame")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--vocab", default="hgcn", help="agreement: HGCN vocabulary (a shipped name or a file)")
    ap.add_argument("--train-cache", type=Path, default=DEFAULT_CACHE,
                    help="agreement: descriptor cache the vocabulary was trained on")
    ap.add_argument("--sample", type=int, default=100_000, help="agreement: training descriptors compared")
    args = ap.parse_args(argv)
    if not KITTI.is_dir():
        print(f"{KITTI} not found: the real samples are expected in ../shared/data", file=sys.stderr)
        return 2
    if "ceiling" in args.parts:
        ceiling(args.words, args.features, args.seed)
    if "agreement" in args.parts:
        return agreement(args.vocab, args.train_cache, args.sample)
    return 0


if __name__ == "__main__":
    sys.exit(main())
