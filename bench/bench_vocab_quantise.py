"""Quantisation speed: one frame of 1000 ORB descriptors against ~10k words.

Queries: ORB-SLAM descriptors (1000 per frame) of the real TUM and EuRoC sample frames.
Vocabularies timed:

* ORB tree, k = 10, L = 4 (10^4 leaves at most), trained here on the same descriptors
  used to train the HGCN vocabularies (see --train);
* flat vocabulary layout with 10 000 words: PCA 256 -> 20, IVF search over the word
  centroids (4 sqrt(W) lists, nprobe lists probed) and the coarse-to-fine search that the
  flat vocabularies use up to 16384 words (:mod:`orbslam_hgcn.vocabulary.probe`). Its centroids are k-means centres of the PCA-projected training
  descriptors: the search cost depends on the number and layout of the centroids, not on
  how they were learned, and a full 10k-word HGCN training takes minutes;
* the shipped default vocabularies, when present; the HGCN vocabulary with its network
  (the layers, then the exact nearest prototype) and with the class-mean centroids, and
  the network assignment's stages (PCA, layers, prototype search) timed apart.

Printed per vocabulary: median CPU milliseconds (and wall milliseconds) over ``--runs``
frames for ``transform_words`` (descriptors -> word ids) and ``transform`` (BoW +
FeatureVector), and the IVF search's agreement with the exact nearest centroid. CPU time
is reported first because the machines this runs on are shared: wall time there includes
waiting for a core.

Threads, pinned and as run: a frame's faiss search runs on one OpenMP thread of the
calling thread (:class:`~orbslam_hgcn.vocabulary.graph.faiss_threads`); as run, faiss
takes its default (one OpenMP thread per core). Only the vocabularies whose word search
goes through faiss (the inverted-file rows) are timed both ways, in the same process; the
ORB tree, the shipped k-means and HGCN vocabularies (PCA table, probed search and network
layers: compiled kernels on the calling thread, no BLAS) use no thread pool, so pinned
and as run are the same call there: the bench says so instead of timing it twice.
``--threads`` sets the process default.

``--system``: the figure a keyframe really pays. Runs the system on the KITTI 00 sample
(``--system-frames`` frames, 2000 features, threaded, unpaced: ``--speed 0``) once per
vocabulary and repeat, orb and hgcn (and kmeans) interleaved in this one bench process,
and prints from each run's stats.json the median ``words`` step (BoW of a keyframe) and
``insert`` step (words, then the map updates under the map lock) of local mapping, their
ratios to the ORB tree's, frames/s, tracked share and keyframe ATE.

The ``= exact`` column is the share of descriptors given the word faiss's exhaustive
search gives (``words_of_points(..., exact=True)``).

    python bench/bench_vocab_quantise.py [--runs 300] [--system] [--system-reps 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import faiss
import numpy as np

from orbslam_hgcn.features.orb import ORBExtractor
from orbslam_hgcn.vocabulary import graph, load_vocabulary
from orbslam_hgcn.vocabulary.base import VocabularyMetadata
from orbslam_hgcn.vocabulary.loading import DEFAULT_FILES
from orbslam_hgcn.vocabulary.graph import fit_pca
from orbslam_hgcn.vocabulary.flat import KMeansVocabulary, PointIndex, kmeans, nearest
from orbslam_hgcn.vocabulary.orb_tree import train_tree_vocabulary

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
KITTI = SHARED / "kitti00_first160" / "sequences" / "00"


def query_frames() -> list[np.ndarray]:
    files = sorted((SHARED / "tum_fr3_long_office_household_sample" / "rgb").glob("*.png"))
    files += sorted((SHARED / "euroc_V1_01_easy_first95" / "mav0" / "cam0" / "data").glob("*.png"))[::5]
    ex = ORBExtractor()
    frames = [ex.extract(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)).desc for f in files]
    return [f[:1000] for f in frames if len(f) >= 1000]


def timeit(fn, frames: list[np.ndarray], runs: int) -> tuple[float, float]:
    """Median CPU and wall milliseconds of fn over ``runs`` frames.

    CPU time (``time.process_time``, all threads of this process) is what the call costs
    on an idle machine; wall time also counts waiting for the CPU on a shared machine.
    """
    for f in frames[:3]:
        fn(f)
    cpu, wall = [], []
    for r in range(runs):
        f = frames[r % len(frames)]
        c, t = time.process_time(), time.perf_counter()
        fn(f)
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - t)
    return 1e3 * float(np.median(cpu)), 1e3 * float(np.median(wall))


def flat_layout(desc: np.ndarray, words: int) -> tuple[KMeansVocabulary, KMeansVocabulary]:
    """Two vocabularies with the same k-means centroids: IVF search and exact flat search."""
    pca = fit_pca(desc, 20)
    x = pca.transform(desc)
    cent = kmeans(x, words, 10, 0, points_per_centroid=20)
    coarse = kmeans(cent, 100, 20, 0)
    ivf = kmeans(cent, int(4 * np.sqrt(words)), 20, 1)
    meta = VocabularyMetadata("kmeans", words, "binary", 32, trained_on="k-means centres (timing only)")
    wc = nearest(cent, coarse).astype(np.int32)
    idf = np.ones(words, np.float32)
    return (KMeansVocabulary(pca, cent, coarse, wc, ivf, 4, idf, meta),
            KMeansVocabulary(pca, cent, coarse, wc, np.zeros((0, 20), np.float32), 0, idf, meta))


def word_thread_pool(v) -> str | None:
    """The thread pool a vocabulary's run-time word search hands a frame to, or None: only
    faiss's inverted-file search (flat vocabularies above FLAT_MAX_WORDS words, or a file
    with lists) has one; the ORB tree, the PCA table, the probed search and the HGCN layers
    run on the calling thread alone."""
    if getattr(v, "assignment", "centroid") == "network":
        return None
    search = getattr(v, "_search", None)
    if isinstance(search, PointIndex) and search.index is not None:
        return "faiss OpenMP (inverted file)"
    return None


def word_path(v) -> str:
    """What a vocabulary's word search runs, in words (for the thread report)."""
    if not hasattr(v, "pca"):
        return "tree descent in numpy"
    net = " and network layers" if getattr(v, "assignment", "centroid") == "network" else ""
    return f"compiled PCA table{net} and probed search on the calling thread"


def system_runs(vocabs: list[str], reps: int, frames: int, record: str | None = None) -> None:
    """Run the system on KITTI once per vocabulary and repeat (interleaved) and print the
    local mapping steps a keyframe pays for its words (see the module docstring)."""
    load_start = os.getloadavg()[0]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    rows: dict[str, list[dict]] = {v: [] for v in vocabs}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(reps):
            for v in vocabs:
                out = Path(tmp) / f"{v}_{r}"
                cmd = [sys.executable, "-m", "orbslam_hgcn", "run", str(KITTI), "--out", str(out), "--vocab", v,
                       "--speed", "0", "--no-progress", "--max-frames", str(frames)]
                subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                st = json.loads((out / "stats.json").read_text())
                steps = st["timing_ms"]["mapping_steps"]
                rows[v].append({
                    "words": steps["words"]["median"], "words_cpu": steps["words_cpu"]["median"],
                    "insert": steps["insert"]["median"],
                    "keyframes": steps["insert"]["count"], "fps": st["frames"]["tracked"] / st["wall_s"],
                    "tracked": st["frames"]["tracked_share"],
                    "ate_cm": 100 * st["ate_sim3"]["keyframes"].get("rmse_m", float("nan")),
                })
    print(f"\nin the running system: KITTI 00, {frames} frames of 2000 features, threaded, unpaced, "
          f"{reps} run(s) per vocabulary interleaved; medians per keyframe over each run, then the median over runs "
          f"(load average before: {os.getloadavg()[0]:.1f})")
    print("(words: wall ms; words CPU: CPU ms of the mapping thread, which runs the search; insert: wall ms)")
    print(f"{'vocab':8s} {'words':>7s} {'x orb':>6s} {'words CPU':>10s} {'x orb':>6s} {'insert':>7s} {'x orb':>6s} "
          f"{'keyframes':>10s} {'frames/s':>9s} {'x orb':>6s} {'tracked':>8s} {'KF ATE cm':>10s}")
    med = {v: {k: float(np.median([row[k] for row in rows[v]])) for k in rows[v][0]} for v in vocabs}
    ref = med.get("orb")
    for v in vocabs:
        m = med[v]
        ratio = (lambda k: f"{m[k] / ref[k]:6.2f}") if ref else (lambda k: "")
        print(f"{v:8s} {m['words']:7.1f} {ratio('words')} {m['words_cpu']:10.1f} {ratio('words_cpu')} "
              f"{m['insert']:7.1f} {ratio('insert')} "
              f"{m['keyframes']:10.0f} {m['fps']:9.1f} {ratio('fps')} {m['tracked']:8.3f} {m['ate_cm']:10.2f}")
    for v in vocabs:
        print(f"  {v} per run: " + "; ".join(
            f"words {row['words']:.1f} (CPU {row['words_cpu']:.1f}) insert {row['insert']:.1f} fps {row['fps']:.1f}"
            for row in rows[v]))
    if record:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        import figures

        figs = []
        for v in vocabs:
            m = med[v]
            x = (lambda k: f" ({m[k] / ref[k]:.2f}x orb)") if ref and v != "orb" else (lambda k: "")
            figs.append((v, f"words {m['words_cpu']:.1f} ms CPU{x('words_cpu')}, insert step {m['insert']:.1f} ms"
                            f"{x('insert')}, {m['fps']:.1f} frames/s{x('fps')}, tracked {100 * m['tracked']:.1f}%, "
                            f"keyframe ATE {m['ate_cm']:.2f} cm"))  # fmt: skip
        figures.record(record, f"Words a KITTI keyframe pays in the running system ({frames} frames, unpaced, "
                               f"median of {reps} run(s) per vocabulary)", figs, bench_file=__file__,
                       load_start=load_start)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--train", type=Path, default=None,
                    help="descriptor cache (.npz with 'desc') to train the timing vocabularies on; "
                         "default: the query frames' own descriptors")
    ap.add_argument("--words", type=int, default=10000)
    ap.add_argument("--runs", type=int, default=300)
    ap.add_argument("--threads", type=int, default=0, help="faiss threads of the process (default: faiss's own)")
    ap.add_argument("--system", action="store_true", help="also time words in the running system (KITTI)")
    ap.add_argument("--system-only", action="store_true", help="only the running system")
    ap.add_argument("--system-vocabs", nargs="+", default=["orb", "hgcn", "kmeans"])
    ap.add_argument("--system-reps", type=int, default=1)
    ap.add_argument("--system-frames", type=int, default=160)
    ap.add_argument("--record", default=None, metavar="NAME",
                    help="with --system-only: write the in-system figures to bench/results/NAME.json (bench/figures.py)")
    args = ap.parse_args(argv)
    if args.system_only:
        system_runs(args.system_vocabs, args.system_reps, args.system_frames, args.record)
        return 0
    if args.threads > 0:
        faiss.omp_set_num_threads(args.threads)
    frames = query_frames()
    if args.train is not None:
        with np.load(args.train) as z:
            train = z["desc"]
        src = str(args.train)
    else:
        train, src = np.concatenate(frames), "the query frames"
    rng = np.random.default_rng(0)
    if len(train) > 300_000:
        train = train[np.sort(rng.choice(len(train), 300_000, replace=False))]
    print(f"queries: {len(frames)} real frames x 1000 ORB descriptors (TUM fr3 + EuRoC samples); "
          f"timing vocabularies trained on {len(train)} descriptors of {src}; {faiss.omp_get_max_threads()} faiss "
          f"thread(s) in the process, one per frame search; "
          f"{args.runs} runs each")
    tree = train_tree_vocabulary(train, np.arange(len(train)) // 1000, k=10, levels=4, progress=False)
    ivf, flat = flat_layout(train, args.words)
    exact = np.concatenate([flat.words_of_points(flat.project(f), exact=True) for f in frames])
    rows = [(f"orb tree k=10 L=4 ({tree.n_words} words)", tree, None)]
    for nprobe in (1, 2, 4, 8):
        rows.append((f"flat layout, {args.words} words, IVF nprobe={nprobe}", ivf, nprobe))
    rows.append((f"flat layout, {args.words} words, probed", flat, 0))
    for kind, path in DEFAULT_FILES.items():
        if path.is_file():
            v = load_vocabulary(path)
            rows.append((f"shipped {kind} ({v.n_words} words)", v, None if kind == "orb" else -1))
    print("milliseconds per frame of 1000 descriptors, median CPU time (wall time)")
    print(f"{'vocabulary':46s} {'transform_words':>17s} {'transform (BoW+FV)':>19s} {'= exact':>8s}")
    for name, v, nprobe in rows:
        agree = ""
        if nprobe is not None:
            if nprobe > 0:
                v.nprobe = nprobe
            got = np.concatenate([v.transform_words(f) for f in frames])
            ref = exact if nprobe >= 0 else np.concatenate([v.words_of_points(v.project(f), exact=True)
                                                            for f in frames])
            agree = f"{100 * np.mean(got == ref):6.1f}%"
        w_cpu, w_wall = timeit(v.transform_words, frames, args.runs)
        t_cpu, t_wall = timeit(v.transform, frames, args.runs)
        print(f"{name:46s} {w_cpu:8.2f} ({w_wall:6.2f}) {t_cpu:10.2f} ({t_wall:6.2f}) {agree:>8s}")
    p_cpu, p_wall = timeit(ivf.project, frames, args.runs)
    print(f"(PCA projection alone: {p_cpu:.2f} ms CPU ({p_wall:.2f} ms wall) per 1000 descriptors)")
    if DEFAULT_FILES["hgcn"].is_file():
        v = load_vocabulary(DEFAULT_FILES["hgcn"])
        if getattr(v, "network", None) is not None:
            xs = [v.project(f) for f in frames]
            hs = [v.embed(x) for x in xs]
            e_cpu, e_wall = timeit(lambda x: v.embed(x), xs, args.runs)
            s_cpu, s_wall = timeit(lambda h: v.nearest_prototype(h), hs, args.runs)
            v.assignment = "centroid"
            c_cpu, c_wall = timeit(v.transform_words, frames, args.runs)
            v.assignment = "network"
            print(f"shipped hgcn, network assignment by stage: layers {e_cpu:.2f} ms CPU ({e_wall:.2f} wall), "
                  f"prototype search {s_cpu:.2f} ({s_wall:.2f}); centroid assignment instead: "
                  f"{c_cpu:.2f} ({c_wall:.2f})")
    print(f"threads, pinned (one faiss thread per frame search) against as run (faiss's default, "
          f"{faiss.omp_get_max_threads()} OpenMP threads), transform_words, same process:")
    for name, v, nprobe in rows:
        pool = word_thread_pool(v)
        if pool is None:
            print(f"  {name}: no thread pool in its word path ({word_path(v)}): pinned and as run are the "
                  f"same call, its row above")
            continue
        if nprobe is not None and nprobe > 0:
            v.nprobe = nprobe
        pinned = timeit(v.transform_words, frames, args.runs)
        small, graph.SMALL_BATCH = graph.SMALL_BATCH, 0
        try:
            free = timeit(v.transform_words, frames, args.runs)
        finally:
            graph.SMALL_BATCH = small
        print(f"  {name}: {pool}: pinned {pinned[0]:7.2f} ms CPU ({pinned[1]:7.2f} wall)   "
              f"as run {free[0]:7.2f} ({free[1]:7.2f})")
    if args.system:
        system_runs(args.system_vocabs, args.system_reps, args.system_frames)
    return 0


if __name__ == "__main__":
    sys.exit(main())
