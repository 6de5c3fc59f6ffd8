"""FAB-MAP 2.0 cost at vocabulary scale: Chow-Liu learning and per-image inference.

Synthetic binary occurrences drawn from a random tree over V words (each word copies its
parent with probability ``strength``, else is on with probability ``rate``, so about
``rate * V`` words per image). Prints the Chow-Liu learning time and the median / 90th
percentile time of one FAB-MAP 2.0 query (likelihoods of all places + new place) against
an index of ``--places`` places.

    python bench/bench_fabmap.py [--words 10000] [--places 1000] [--queries 500]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.placerec.chow_liu import learn_chow_liu_tree
from orbslam_hgcn.placerec.fabmap import FabMap2

# Known-answer problems shared with the tests (tests/*_fixtures.py).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from placerec_fixtures import random_tree_model, sample_tree  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--words", type=int, default=10000)
    ap.add_argument("--places", type=int, default=1000)
    ap.add_argument("--train", type=int, default=1000, help="training images for the tree")
    ap.add_argument("--queries", type=int, default=500)
    ap.add_argument("--rate", type=float, default=0.03)
    ap.add_argument("--strength", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    rng = np.random.default_rng(args.seed)
    model = random_tree_model(args.words, rng, rate=args.rate, strength=args.strength)
    train = sample_tree(model, args.train, rng)
    places = sample_tree(model, args.places, rng)
    queries = sample_tree(model, args.queries, rng)
    print(f"words {args.words}, places {args.places}, training images {args.train}, "
          f"mean words per image {places.sum(axis=1).mean():.0f}")

    t0 = time.perf_counter()
    tree = learn_chow_liu_tree(train, progress=True)
    t_tree = time.perf_counter() - t0
    true_edges = {frozenset((int(q), int(p))) for q, p in enumerate(model.parent) if p >= 0}
    recovered = len(tree.edges() & true_edges) / len(true_edges)
    print(f"Chow-Liu tree: {t_tree:.1f} s, true edges recovered {100 * recovered:.1f}%")

    for method in ("mean_field", "sampled"):
        fm = FabMap2(tree, train=train, num_samples=1000, seed=args.seed)
        index = fm.build_index(places)
        times = []
        for z in queries:
            obs = np.flatnonzero(z)
            t0 = time.perf_counter()
            ll = fm.log_likelihoods(obs, index)
            ll_new = fm.new_place_log_likelihood(obs, method)
            times.append(time.perf_counter() - t0)
        assert np.all(np.isfinite(ll)) and np.isfinite(ll_new)
        t = np.array(times) * 1e3
        print(f"FAB-MAP 2.0 query ({method} new place): median {np.median(t):.2f} ms, "
              f"p90 {np.percentile(t, 90):.2f} ms over {len(t)} images (target <= 10 ms)")


if __name__ == "__main__":
    main()
