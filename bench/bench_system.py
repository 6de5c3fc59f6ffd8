"""Throughput and tracking latency of the whole system, sequential against threaded.

Sequences (640x480, 1000 ORB features; rendered once into the cache folder, default
~/.cache/orbslam_hgcn): ``loop_default`` (900 frames round the desk) and ``fr3_replay``
(2613 frames, the camera path of TUM fr3 long_office_household, Sturm et al., IROS 2012,
replayed in a synthetic office).

Modes: ``sequential`` (local mapping after each keyframe, on the tracking thread),
``threaded`` (local mapping and loop closing in worker threads, bundle adjustments solved
in a child process, the next frame's ORB features extracted in another) and
``threaded-inproc`` (worker threads, BA solved in the mapping thread: gtsam keeps the GIL,
so tracking stalls while it iterates).

Each run is made in its own process (so peak memory is its own). Images are decoded by a
reader thread a few frames ahead (``--preload``: all of them before the clock starts);
decode time is printed apart. Printed per run: frames/s over the run, per-frame tracking
latency (from the start of the frame's ORB extraction to the end of its tracking and of
handing keyframes over; in threaded mode the extraction runs on the prefetch thread while
the previous frame is tracked, so the latency also holds the wait for that frame): median,
p95, max, over all frames and over the frames during which a bundle adjustment or pose
graph was being solved; map-lock waits; waits for local mapping to take a keyframe that
is due (``threads.keyframe_wait_s``); local mapping per keyframe; ATE after Sim(3)
alignment; peak RSS of the process and of its children (the BA and extraction processes; with
``--preload`` the children's figure also counts the parent's pages at fork time, so quote
memory from runs without it). ``--profile`` runs the tracking thread under cProfile and
prints where its time goes. ``--rate HZ`` hands frames out no faster than a camera of that
rate would, and also prints the latency from each frame's due time (which grows when the
system falls behind the camera), the frames/s from the first frame's arrival to the last
pose, and the share of frames tracked within two frame periods of their due time. ``--config YAML`` overrides stage sections (``threads``,
``local_mapping``, ...).

Usage::

    python bench/bench_system.py [--sequences loop_default fr3_replay] [--modes sequential threaded]
                                 [--max-frames N] [--loop] [--preload] [--rate HZ] [--profile]
                                 [--config YAML] [--cache DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import io
import json
import logging
import os
import pstats
import queue
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FR3_GT = REPO.parent / "shared" / "data" / "tum_fr3_long_office_household_sample" / "groundtruth.txt"
MODES = ("sequential", "threaded", "threaded-inproc")


class ReaderSequence:
    """A sequence whose images a reader thread decodes ahead into a bounded queue.

    Frames must be read in order (as System.run does). decode_ms: (N,) per image. rate > 0:
    frame i is handed out no earlier than i / rate seconds after frame 0, as a camera
    delivers them.
    """

    def __init__(self, base, n: int, ahead: int = 16, preload: bool = False, rate: float = 0.0) -> None:
        self.base, self.n, self.rate = base, n, rate
        self._t0: float | None = None
        self.name, self.camera, self.ground_truth = base.name, base.camera, base.ground_truth
        self.color = getattr(base, "color", False)
        self.decode_ms: list[float] = []
        self.waited_ms = 0.0
        self._q: queue.Queue = queue.Queue(maxsize=n if preload else ahead)
        self._thread = threading.Thread(target=self._read, name="bench-reader", daemon=True)
        self._thread.start()
        if preload:
            self._thread.join()

    def _read(self) -> None:
        for i in range(self.n):
            t = time.perf_counter()
            rec = self.base[i]
            self.decode_ms.append(1000.0 * (time.perf_counter() - t))
            self._q.put(rec)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int):
        t = time.perf_counter()
        rec = self._q.get()
        self.waited_ms += 1000.0 * (time.perf_counter() - t)
        assert rec.index == i, "frames are read in order"
        if self.rate > 0:  # a camera: frame i exists from t0 + i / rate on
            if self._t0 is None:
                self._t0 = time.perf_counter()
            time.sleep(max(0.0, self._t0 + i / self.rate - time.perf_counter()))
        return rec

    @property
    def timestamps(self) -> np.ndarray:
        return self.base.timestamps[: self.n]


def _from_arrival(seq: ReaderSequence, system) -> np.ndarray:
    """(N,) ms from the time each frame was due from the camera (frame i: i / rate after
    frame 0) to the end of its tracking: the frame's latency plus how late its extraction
    started (when the system falls behind the camera)."""
    started = np.asarray(system.frame_started) - seq._t0
    due = np.arange(len(started)) / seq.rate
    return np.maximum(started - due, 0.0) * 1000.0 + np.asarray(system.timings["frame"])


def _paced(seq: ReaderSequence, system, from_arrival: np.ndarray) -> dict:
    """How a paced run kept up with its camera: frames/s from the first frame's arrival to
    the last frame's pose (the run's wall time also holds the start-up and the final
    drain), the share of frames tracked within two frame periods of their due time, and
    how late the last frame was."""
    end = system.frame_started[-1] + system.timings["frame"][-1] / 1000.0
    return {
        "fps_camera_span": len(from_arrival) / (end - seq._t0),
        "within_two_periods": float(np.mean(from_arrival <= 2000.0 / seq.rate)),
        "last_lag_ms": float(from_arrival[-1]),
    }


def _summary(v) -> dict:
    v = np.asarray(v, dtype=np.float64)
    if len(v) == 0:
        return {"n": 0, "median": float("nan"), "p95": float("nan"), "max": float("nan")}
    return {"n": int(len(v)), "median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(v.max())}


def _children_cpu_s() -> float:
    """CPU seconds of the child processes that have ended (the BA and extraction processes end with the run)."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_one(
    path: str, mode: str, max_frames: int | None, loop: bool, preload: bool, profile: bool, top: int,
    rate: float = 0.0, config: str | None = None,
) -> dict:  # fmt: skip
    """One run in this process; returns its figures."""
    from orbslam_hgcn.datasets import open_sequence
    from orbslam_hgcn.app.run import open_vocabulary, trajectory_ate
    from orbslam_hgcn.runtime.system import Configs, System

    base = open_sequence("tum", path)
    n = len(base) if max_frames is None else min(len(base), max_frames)
    configs = Configs.from_yaml(config)
    configs = dataclasses.replace(
        configs,
        # speed 0: the system takes frames as they come; ReaderSequence paces them (--rate).
        threads=dataclasses.replace(
            configs.threads, sequential=mode == "sequential", process_solver=mode == "threaded", speed=0.0
        ),
        loop_closing=dataclasses.replace(configs.loop_closing, enabled=loop),
    )
    vocabulary = open_vocabulary(None, loop)
    system = System(base.camera, configs, vocabulary=vocabulary)
    seq = ReaderSequence(base, n, preload=preload, rate=rate)
    load0 = os.getloadavg()[0]
    prof = cProfile.Profile() if profile else None
    children0 = _children_cpu_s()
    t0, c0 = time.perf_counter(), time.process_time()
    summary = prof.runcall(system.run, seq, n, False) if prof else system.run(seq, n, progress=False)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    stats = system.stats()
    frame = np.asarray(system.timings["frame"])
    opt = np.asarray(system.frame_optimising, dtype=bool)
    # Only when every frame was timed (frames skipped while lost get no latency).
    arrival = _from_arrival(seq, system) if rate > 0 and len(system.frame_started) == summary.frames else None
    mt = system.mapper.timings
    out = {
        "mode": mode,
        "sequence": base.name,
        "rate": rate,
        "preload": preload,
        "frames": summary.frames,
        "wall_s": wall,
        "cpu_s": cpu,
        "cpu_children_s": _children_cpu_s() - children0,
        "fps": summary.frames / wall,
        "load": [load0, os.getloadavg()[0]],
        "decode_ms": _summary(seq.decode_ms),
        "reader_wait_ms_total": seq.waited_ms,
        "latency_all": _summary(frame),
        "latency_from_arrival": _summary(arrival) if arrival is not None else None,
        "paced": _paced(seq, system, arrival) if arrival is not None else None,
        "latency_optimising": _summary(frame[opt]),
        "latency_not_optimising": _summary(frame[~opt]),
        "extraction": _summary(system.timings["extraction"]),
        "tracking": _summary(system.timings["tracking"]),
        "lock_wait": _summary(system.timings["lock_wait"]),
        "keyframe_wait": _summary(system.timings["keyframe_wait"]),
        "mapping_total": _summary(mt.get("total", [])),
        "mapping_steps": {k: _summary(v) for k, v in mt.items() if k not in ("total", "total_cpu", "local_ba_cpu")},
        "mapping_counts": stats["mapping_counts"],
        "frames_stats": stats["frames"],
        "keyframes": stats["keyframes"],
        "loops": len(stats.get("loop_closing", {}).get("loops", [])),
        "loop_timing_ms": stats.get("loop_closing", {}).get("timing_ms", {}),
        "ate_kf": trajectory_ate(base.ground_truth, system.keyframe_trajectory()),
        "ate_cam": trajectory_ate(base.ground_truth, system.camera_trajectory()),
        "maxrss_self_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "maxrss_children_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0,
        "threads_left": [t.name for t in threading.enumerate() if t.name.startswith("orbslam-")],
    }
    if prof is not None:
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(top)
        out["profile"] = "\n".join(buf.getvalue().splitlines()[6:])
    return out


def _fmt(d: dict) -> str:
    return f"median {d['median']:7.1f}  p95 {d['p95']:7.1f}  max {d['max']:7.1f}  (n={d['n']})"


def report(r: dict) -> None:
    paced = f"frames handed out at {r['rate']:g}/s" if r.get("rate") else "frames as fast as taken"
    images = "images decoded before the clock started" if r.get("preload") else "images decoded during the run"
    print(f"\n== {r['sequence']} / {r['mode']} ({paced}; {images}): {r['frames']} frames in {r['wall_s']:.1f} s "
          f"-> {r['fps']:.2f} frames/s (CPU: this process {r['cpu_s']:.0f} s, BA and extraction processes "
          f"{r.get('cpu_children_s', 0):.0f} s; load avg {r['load'][0]:.1f} -> {r['load'][1]:.1f})")
    print(f"PNG decode (reader thread) ms/frame:  {_fmt(r['decode_ms'])}; tracking waited on the reader "
          f"{r['reader_wait_ms_total'] / 1000:.1f} s in all")
    print(f"tracking latency ms/frame, all:        {_fmt(r['latency_all'])}")
    if r.get("latency_from_arrival"):
        print(f"  from the frame's due time:           {_fmt(r['latency_from_arrival'])}")
    if r.get("paced"):
        p = r["paced"]
        print(f"  against the camera: {p['fps_camera_span']:.2f} frames/s from the first frame's arrival to the last "
              f"pose; {100 * p['within_two_periods']:.1f}% of frames tracked within two frame periods of their "
              f"due time; the last one {p['last_lag_ms']:.0f} ms after it")
    print(f"  while a BA / pose graph was solved:  {_fmt(r['latency_optimising'])}")
    print(f"  otherwise:                           {_fmt(r['latency_not_optimising'])}")
    print(f"  extraction:                          {_fmt(r['extraction'])}")
    print(f"  tracking:                            {_fmt(r['tracking'])}")
    print(f"  map lock wait:                       {_fmt(r['lock_wait'])}")
    if r.get("keyframe_wait", {}).get("n"):
        w = r["keyframe_wait"]
        print(f"  waits for local mapping to take a due keyframe: {w['n']}, median {w['median']:.1f} ms, "
              f"max {w['max']:.1f} ms")
    print(f"local mapping ms/keyframe:             {_fmt(r['mapping_total'])}")
    for k, v in r["mapping_steps"].items():
        print(f"  {k:<35}  {_fmt(v)}")
    f = r["frames_stats"]
    print(f"frames tracked {f['tracked']}, lost {f['lost']}, resets {f['reset']}; keyframes mapped "
          f"{r['mapping_counts'].get('keyframes', 0)}, kept {r['keyframes']}; loops closed {r['loops']}")
    if r.get("loop_timing_ms"):
        print("loop closing mean ms: " + ", ".join(f"{k} {v:.0f}" for k, v in r["loop_timing_ms"].items()))
    for label in ("ate_kf", "ate_cam"):
        a = r[label]
        txt = a.get("error") or f"rmse {100 * a['rmse_m']:.2f} cm over {a['pairs']} poses"
        print(f"ATE Sim(3) {label[4:]}: {txt}")
    print(f"peak RSS: this process {r['maxrss_self_mb']:.0f} MB, largest child {r['maxrss_children_mb']:.0f} MB; "
          f"stage threads left after run: {r['threads_left'] or 'none'}")
    if "profile" in r:
        print("-- tracking thread, cProfile top by own time --")
        print(r["profile"])


def ensure_sequence(name: str, cache: Path) -> Path:
    from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence

    options = SynthOptions(trajectory="replay", gt=str(FR3_GT)) if name == "fr3_replay" else SynthOptions()
    out = cache / name
    render_sequence(out, options, progress=True, cache=True)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sequences", nargs="+", choices=("loop_default", "fr3_replay"), default=["loop_default"])
    p.add_argument("--modes", nargs="+", choices=MODES, default=["sequential", "threaded"])
    default_cache = os.environ.get("ORBSLAM_HGCN_CACHE", str(Path.home() / ".cache" / "orbslam_hgcn"))
    p.add_argument("--cache", default=default_cache, help="folder of rendered sequences")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--loop", action="store_true", help="with loop closing (HGCN vocabulary)")
    p.add_argument("--preload", action="store_true", help="decode every image before the clock starts")
    p.add_argument("--profile", action="store_true", help="cProfile the tracking thread")
    p.add_argument("--rate", type=float, default=0.0, help="hand frames out at this many per second, as a camera")
    p.add_argument("--config", default=None, help="YAML with stage sections (threads, local_mapping, ...)")
    p.add_argument("--top", type=int, default=25)
    p.add_argument("--json", default=None, help="also write the figures to this file")
    p.add_argument("--one", nargs=2, metavar=("PATH", "MODE"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.one:
        r = run_one(
            args.one[0], args.one[1], args.max_frames, args.loop, args.preload, args.profile, args.top, args.rate,
            args.config,
        )  # fmt: skip
        print("RESULT " + json.dumps(r))
        return 0
    print(f"uptime: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}; "
          f"{os.cpu_count()} CPUs; OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}")
    results = []
    for name in args.sequences:
        path = ensure_sequence(name, Path(args.cache).expanduser())
        for mode in args.modes:
            cmd = [sys.executable, __file__, "--one", str(path), mode, "--top", str(args.top)]
            cmd += ["--max-frames", str(args.max_frames)] if args.max_frames else []
            cmd += ["--rate", str(args.rate)] if args.rate > 0 else []
            cmd += ["--config", str(Path(args.config).resolve())] if args.config else []
            flags = (("--loop", args.loop), ("--preload", args.preload), ("--profile", args.profile))
            cmd += [f for f, on in flags if on]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
            if proc.returncode != 0 or not lines:
                print(f"\n== {name} / {mode}: FAILED (exit {proc.returncode})\n{proc.stderr[-3000:]}")
                continue
            r = json.loads(lines[-1][len("RESULT "):])
            results.append(r)
            report(r)
    by = {(r["sequence"], r["mode"]): r for r in results}
    for name in {r["sequence"] for r in results}:
        s, t = by.get((name, "sequential")), by.get((name, "threaded"))
        if s and t:
            print(f"\n{name}: threaded / sequential frames/s = {t['fps'] / s['fps']:.2f}; tracking p95 "
                  f"{s['latency_all']['p95']:.0f} -> {t['latency_all']['p95']:.0f} ms; p95 while optimising "
                  f"{s['latency_optimising']['p95']:.0f} -> {t['latency_optimising']['p95']:.0f} ms")
    print(f"\nuptime at the end: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
