"""Vocabulary training time and peak memory at 100k and 1M descriptors.

Each (kind, size) is trained in its own subprocess; its peak resident memory is the
child's ``ru_maxrss`` (torch allocates outside Python's tracemalloc), and the memory of
the loaded descriptors alone (measured in the child before training) is printed beside it.

Data: real ORB-SLAM descriptors extracted from synthetic office renders (the descriptor
cache written by ``tools/train_default_vocabs.py``: 10 scenes x 60 frames, ~600k
descriptors). Sizes beyond the cache are filled with copies of cached descriptors with 8
random bits flipped each (a copy keeps its source image id), which the output states.

    python bench/bench_vocab_train.py --cache ~/.cache/orbslam_hgcn/vocab_training/descriptors_10x60_1000.npz
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_CACHE = Path.home() / ".cache" / "orbslam_hgcn" / "vocab_training" / "descriptors_10x60_1000.npz"


def load_descriptors(cache: Path, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, int]:
    """(n, 32) descriptors, (n,) image ids and how many are bit-flipped copies."""
    with np.load(cache) as z:
        desc, counts = z["desc"], z["counts"]
    image_ids = np.repeat(np.arange(len(counts)), counts)
    rng = np.random.default_rng(seed)
    if n <= len(desc):
        pick = np.sort(rng.choice(len(desc), n, replace=False))
        return desc[pick], image_ids[pick], 0
    extra = n - len(desc)
    src = rng.integers(0, len(desc), extra)
    copies = desc[src].copy()
    bits = rng.integers(0, 256, (extra, 8))
    rows = np.repeat(np.arange(extra), 8)
    np.bitwise_xor.at(copies, (rows, (bits // 8).ravel()), (1 << (bits % 8)).astype(np.uint8).ravel())
    return np.concatenate([desc, copies]), np.concatenate([image_ids, image_ids[src]]), extra


def child(kind: str, n: int, cache: Path, words: int | None) -> None:
    from orbslam_hgcn.config import HgcnTrainConfig
    from orbslam_hgcn.vocabulary.training.train import train_vocabulary

    desc, image_ids, n_copies = load_descriptors(cache, n)
    rss_data = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    hgcn = HgcnTrainConfig() if words is None else dataclasses.replace(HgcnTrainConfig(), n_words=words)
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t = time.perf_counter()
    vocab = train_vocabulary(kind, desc, image_ids, hgcn=hgcn, progress=False)
    seconds = time.perf_counter() - t
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime)
    print(json.dumps({"kind": kind, "n": n, "copies": n_copies, "seconds": seconds, "cpu_seconds": cpu,
                      "words": vocab.n_words,
                      "rss_data_mb": rss_data / 1024,
                      "rss_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "stats": vocab.metadata.stats}))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="descriptor cache (.npz)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    ap.add_argument("--kinds", nargs="+", default=["orb", "hgcn"], choices=("orb", "hgcn"))
    ap.add_argument("--words", type=int, default=None, help="HGCN words (default: HgcnTrainConfig)")
    ap.add_argument("--child", nargs=2, metavar=("KIND", "N"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child[0], int(args.child[1]), args.cache, args.words)
        return 0
    if not args.cache.is_file():
        print(f"{args.cache}: descriptor cache not found; run tools/train_default_vocabs.py first", file=sys.stderr)
        return 2
    with np.load(args.cache) as z:
        n_real = len(z["desc"])
    print(f"data: {n_real} real ORB descriptors from synthetic renders ({args.cache}); larger sizes add "
          "copies with 8 random bits flipped")
    print("time: wall seconds and CPU seconds (all threads; on a shared machine wall time includes waiting)")
    print(f"{'kind':5s} {'descriptors':>11s} {'flipped':>8s} {'words':>7s} {'wall s':>8s} {'CPU s':>8s} "
          f"{'data MB':>8s} "
          f"{'peak MB':>8s}  stages (wall s)")
    for n in args.sizes:
        for kind in args.kinds:
            cmd = [sys.executable, __file__, "--cache", str(args.cache), "--child", kind, str(n)]
            if args.words:
                cmd += ["--words", str(args.words)]
            out = subprocess.run(cmd, capture_output=True, text=True)
            if out.returncode != 0:
                print(f"{kind:5s} {n:11d} failed: {out.stderr.strip().splitlines()[-1:]}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            st = r["stats"]
            stages = ", ".join(f"{k[:-8]} {v:.0f}s" for k, v in st.items()
                               if k.endswith("_seconds") and k != "train_seconds")
            print(f"{kind:5s} {n:11d} {r['copies']:8d} {r['words']:7d} {r['seconds']:8.1f} {r['cpu_seconds']:8.1f} "
                  f"{r['rss_data_mb']:8.0f} {r['rss_peak_mb']:8.0f}  {stages}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
