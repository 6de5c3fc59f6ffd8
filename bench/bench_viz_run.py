"""Overhead of live rerun logging on a real SLAM run (``orbslam-hgcn run --rerun save``).

The same sequence is run through :func:`orbslam_hgcn.app.run.run_dataset` with and
without ``--rerun save FILE.rrd``, alternating the order within each pair (plain first in
even pairs, logged first in odd ones) so that slow drifts of a shared machine's load fall
on both. Per run: wall time of the whole call (open, SLAM, final map log and flush of the
recording, writing results), wall time of the frame loop alone (``stats.json`` wall_s) and
process CPU time (all threads, rerun's encoder and writer threads included). Printed: each
pair and the median over pairs of the ratios logged / plain - 1. The one-off cost of the
first recording in a process (importing the rerun SDK, starting its recording machinery) is
measured before the pairs and printed apart, as a share of the median plain run.

Default sequence: the first 300 frames of the default synthetic loop round the desk
(``~/.cache/orbslam_hgcn/loop_default``, rendered there when missing), tracking and local
mapping without loop closing (the lightest SLAM configuration, so the largest relative
overhead).

    OMP_NUM_THREADS=1 python bench/bench_viz_run.py [--frames 300] [--pairs 3] [--loop]
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence
from orbslam_hgcn.app.run import run_dataset

TARGET = 0.10  # logging may add at most 10% to the run time
# Names of the rerun SDK's native threads (rerun-sdk 0.41: micro-batching, the recording
# stream, the .rrd writer, its async runtime and allocator).
RERUN_THREADS = ("ChunkBatcher", "RecordingStream", "file_writer", "tokio", "jemalloc", "rerun")


def ensure_loop_default(cache: Path) -> Path:
    out = cache / "loop_default"
    render_sequence(out, SynthOptions(), progress=True, cache=True)
    return out


def first_use_cost(tmp: Path) -> tuple[float, float]:
    """Seconds to import the rerun logger, and to open and close a first recording."""
    t0 = time.perf_counter()
    from orbslam_hgcn.viz.demo import demo_camera
    from orbslam_hgcn.viz.rerun_logger import RerunLogger

    t1 = time.perf_counter()
    RerunLogger(demo_camera(), "save", tmp / "warmup.rrd").close()
    return t1 - t0, time.perf_counter() - t1


def rerun_threads_cpu() -> float:
    """CPU seconds so far of this process's rerun SDK threads (Linux /proc; 0 elsewhere),
    recognised by the names the SDK gives them (:data:`RERUN_THREADS`)."""
    task_dir = Path("/proc/self/task")
    if not task_dir.is_dir():
        return 0.0
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for task in task_dir.iterdir():
        try:
            if not (task / "comm").read_text().strip().startswith(RERUN_THREADS):
                continue
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # the thread ended meanwhile
            continue
        total += (int(fields[11]) + int(fields[12])) / tick  # utime + stime
    return total


def one_run(path: Path, out: Path, frames: int, loop: bool, rrd: Path | None, sequential: bool) -> dict:
    rerun = ["save", str(rrd)] if rrd is not None else None
    # Threaded runs as fast as they go (no pacing to the camera), so that the logging's
    # cost shows in the wall time.
    kw = {"sequential": True} if sequential else {"speed": 0.0}
    r0, c0, t0 = rerun_threads_cpu(), time.process_time(), time.perf_counter()
    report = run_dataset(path, out, kind="tum", max_frames=frames, loop_closing=loop, progress=False,
                         vocab=None if loop else "none", rerun=rerun, **kw)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    f = report.stats["frames"]
    viz = report.stats.get("rerun", {})
    return {
        "wall": wall, "loop_wall": float(report.stats["wall_s"]), "cpu": cpu, "tracked": f["tracked"],
        "points": report.stats["map_points"], "keyframes": report.stats["keyframes"],
        "mib": rrd.stat().st_size / 2**20 if rrd is not None else 0.0,
        "log_wall": float(viz.get("log_wall_s", 0.0)), "log_cpu": float(viz.get("log_cpu_s", 0.0)),
        "sdk_cpu": rerun_threads_cpu() - r0 if rrd is not None else 0.0,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, default=None, help="TUM-layout sequence (default: loop_default)")
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "orbslam_hgcn")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--pairs", type=int, default=3, help="pairs of runs (plain, logged); median reported")
    p.add_argument("--loop", action="store_true", help="with loop closing and the default vocabulary")
    p.add_argument("--sequential", action="store_true",
                   help="stages in order after each frame (default: as orbslam-hgcn run, in worker threads)")
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    path = args.dataset or ensure_loop_default(args.cache)
    print(f"rerun logging overhead on a SLAM run: {path.name}, {args.frames} frames, loop closing "
          f"{'on' if args.loop else 'off'}, {'sequential' if args.sequential else 'threaded'} stages; OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
    print("overhead = logged / plain - 1 of the whole call; loop-only: of the frame loop; CPU: of process CPU "
          "time. In the logged run: log = wall time spent in the visualiser on the SLAM thread, sdk = CPU "
          "time of rerun's own threads, both as a share of the plain run's wall time.")
    print(f"{'pair':>4s} {'plain s':>8s} {'logged s':>9s} {'overhead':>9s} {'loop-only':>10s} {'CPU':>7s} "
          f"{'log':>6s} {'sdk':>6s} {'tracked':>8s} {'points':>7s} {'kfs':>4s} {'rrd MiB':>8s}")
    ratios: dict[str, list[float]] = {"wall": [], "loop_wall": [], "cpu": [], "log": [], "sdk": []}
    plain_walls = []
    with tempfile.TemporaryDirectory() as tmp:
        import_s, open_s = first_use_cost(Path(tmp))
        for i in range(args.pairs):
            runs = {}
            order = ("plain", "logged") if i % 2 == 0 else ("logged", "plain")
            for kind in order:
                rrd = Path(tmp) / f"run{i}.rrd" if kind == "logged" else None
                runs[kind] = one_run(path, Path(tmp) / f"{kind}{i}", args.frames, args.loop, rrd, args.sequential)
            a, b = runs["plain"], runs["logged"]
            plain_walls.append(a["wall"])
            for key in ("wall", "loop_wall", "cpu"):
                ratios[key].append(b[key] / a[key] - 1.0)
            ratios["log"].append(b["log_wall"] / a["wall"])
            ratios["sdk"].append(b["sdk_cpu"] / a["wall"])
            print(f"{i:4d} {a['wall']:8.1f} {b['wall']:9.1f} {100 * ratios['wall'][-1]:+8.1f}% "
                  f"{100 * ratios['loop_wall'][-1]:+9.1f}% {100 * ratios['cpu'][-1]:+6.1f}% "
                  f"{100 * ratios['log'][-1]:5.1f}% {100 * ratios['sdk'][-1]:5.1f}% "
                  f"{b['tracked']:8d} {b['points']:7d} {b['keyframes']:4d} {b['mib']:8.1f}")
    med = {k: float(np.median(v)) for k, v in ratios.items()}
    print(f"median over {args.pairs} pairs: wall {100 * med['wall']:+.1f}% (whole run incl. final map and flush), "
          f"frame loop {100 * med['loop_wall']:+.1f}%, CPU {100 * med['cpu']:+.1f}%; visualiser on the SLAM "
          f"thread {100 * med['log']:.1f}%, rerun threads {100 * med['sdk']:.1f}% of the plain run")
    once = import_s + open_s
    print(f"once per process: import of the rerun logger {import_s:.2f} s + first recording opened {open_s:.2f} s "
          f"= {100 * once / float(np.median(plain_walls)):.1f}% of the median plain run")
    verdict = "met" if med["wall"] <= TARGET else f"MISSED by {100 * (med['wall'] - TARGET):.1f} points"
    print(f"target wall overhead <= {100 * TARGET:.0f}%, paired runs: {verdict}")
    direct = med["log"] + med["sdk"]
    verdict = "met" if direct <= TARGET else f"MISSED by {100 * (direct - TARGET):.1f} points"
    print(f"target, measured inside the logged runs (visualiser + rerun threads = {100 * direct:.1f}%): {verdict}. "
          "On a machine shared with other jobs the paired figure carries their load swings; compare the "
          "CPU column and the spread over pairs.")


if __name__ == "__main__":
    main()
