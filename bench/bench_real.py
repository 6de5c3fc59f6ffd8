"""Real images first: the system as a user runs it, on every real sample and the hard renders.

Sequences:

* ``kitti00``: KITTI odometry 00, frames 0-159 (real, 1241x376 at 10 Hz; Geiger, Lenz and
  Urtasun, CVPR 2012, CC BY-NC-SA 3.0), from ``../shared/data/kitti00_first160``;
* ``tum_sample``: the 19 real TUM fr3 long_office_household frames (Sturm et al., IROS
  2012, CC BY 4.0): 16 contiguous ones and three far later;
* ``euroc_sample``: the first 95 real EuRoC V1_01_easy cam0 frames (Burri et al., IJRR
  2016), with radial-tangential distortion; the vehicle hardly moves in them, so they
  test the distorted-camera path end to end, not initialisation;
* ``street``, ``fr3_hard``: the renderer's presets (``orbslam-hgcn synth --preset ...``,
  rendered once into the cache folder): a KITTI-like drive, and the fr3 camera path with
  motion blur along the motion, exposure steps, vignetting and JPEG artefacts.

Each run is ``orbslam-hgcn run SEQUENCE --out DIR`` in its own process, with the defaults a
user gets (threaded, frames paced at the camera's rate, stage settings picked from the
dataset's camera, HGCN vocabulary, loop closing on), or with ``--sequential``
(``--modes``). Printed per run, then the median per sequence and mode: the frame on which
the map was made, the share of frames tracked, map resets, frames dropped (a paced run
behind its camera, only with ``--drop-late``), keyframes, keyframe and camera-trajectory
ATE after Sim(3) alignment, local mapping and local BA ms per keyframe (median), and
frames/s over the run; then, for each run, the times tracking was lost, the real-time
factor (camera seconds per wall second), how far behind the camera the run fell (lag p95
and max), the frame latency p95 (extraction start to pose) and the largest keyframe and
camera pose errors; then the median time of each local mapping step.

``--load`` names the CPU load beside every run, as other jobs on a user's machine: ``none``,
``nice19`` (two CPU-bound processes at niceness 19, as a background job) or ``hog`` (one
CPU-bound process at normal priority); several loads run one after the other, each
printed with its own medians (``--load none nice19 hog``). ``--hog N`` adds N more
normal-priority processes.

Usage::

    python bench/bench_real.py [--sequences kitti00 tum_sample euroc_sample street fr3_hard]
                               [--modes threaded sequential] [--runs 3] [--seq-runs 1]
                               [--load none|nice19|hog ...] [--hog N]
                               [--args "--vocab orb"] [--cache DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
REAL = {
    "kitti00": (SHARED / "kitti00_first160" / "sequences" / "00", "kitti"),
    "tum_sample": (SHARED / "tum_fr3_long_office_household_sample", "tum"),
    "euroc_sample": (SHARED / "euroc_V1_01_easy_first95", "euroc"),
}
RENDERS = {"street": ("street", "kitti"), "fr3_hard": ("fr3_replay_hard", "tum")}


def _cli() -> list[str]:
    exe = Path(sys.executable).with_name("orbslam-hgcn")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "orbslam_hgcn.cli"]


def sequence_path(name: str, cache: Path) -> tuple[Path, str]:
    """(folder, dataset kind) of a bench sequence; renders are made on first use."""
    if name in REAL:
        path, kind = REAL[name]
        if not path.is_dir():
            raise SystemExit(f"bench_real: {name} not found at {path} (the shared sample data)")
        return path, kind
    preset, kind = RENDERS[name]
    out = cache / f"bench_{preset}"
    if not (out / ".complete").is_file():
        print(f"rendering {name} into {out} (once) ...", flush=True)
        subprocess.run([*_cli(), "synth", "--preset", preset, "--out", str(out), "--force"], check=True)
        (out / ".complete").write_text("ok\n")
    if kind == "kitti":
        seqs = sorted(p for p in (out / "sequences").iterdir() if p.is_dir()) if (out / "sequences").is_dir() else []
        return (seqs[0] if seqs else out), kind
    return out, kind


LOADS = {"none": (0, 0), "nice19": (2, 19), "hog": (1, 0)}  # (CPU-bound processes, niceness)


def _hog(niceness: int = 0) -> None:
    if niceness:
        os.nice(niceness)
    x = 0
    while True:
        x += 1


def start_load(load: str, hogs: int = 0) -> list:
    """Start the busy processes of ``load`` (LOADS) and ``hogs`` more at normal priority;
    stop them with :func:`stop_load`."""
    n_load, niceness = LOADS[load]
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_hog, daemon=True) for _ in range(hogs)]
    procs += [ctx.Process(target=_hog, args=(niceness,), daemon=True) for _ in range(n_load)]
    for p in procs:
        p.start()
    return procs


def stop_load(procs: list) -> None:
    for p in procs:
        p.terminate()
        p.join()


def run_once(path: Path, kind: str, mode: str, extra: list[str], hogs: int, load: str = "none") -> dict:
    """One ``orbslam-hgcn run`` in a child process, ``hogs`` normal-priority busy processes
    and the processes of ``load`` (LOADS) beside it; the figures from its stats.json."""
    out = Path(tempfile.mkdtemp(prefix="bench_real_"))
    cmd = [*_cli(), "run", str(path), "--dataset", kind, "--out", str(out / "run"), "--no-progress", *extra]
    if mode == "sequential":
        cmd.append("--sequential")
    procs = start_load(load, hogs)
    try:
        t0 = time.perf_counter()
        res = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    finally:
        stop_load(procs)
    stats_path = out / "run" / "stats.json"
    if res.returncode != 0 or not stats_path.is_file():
        shutil.rmtree(out, ignore_errors=True)
        tail = (res.stderr or res.stdout).strip().splitlines()[-3:]
        return {"error": f"exit {res.returncode}: " + " | ".join(tail)}
    s = json.loads(stats_path.read_text())
    shutil.rmtree(out, ignore_errors=True)
    f, t = s["frames"], s["timing_ms"]
    init = [e["frame"] for e in s.get("events", []) if e["event"] == "initialized"]
    ate = s.get("ate_sim3", {})

    def cm(name: str, key: str = "rmse_m") -> float:
        a = ate.get(name, {})
        return 100.0 * a[key] if key in a else float("nan")

    rt = s.get("real_time", {})

    return {
        "init_frame": init[0] if init else None,
        "frames": f["frames"],
        "tracked_share": f["tracked"] / max(f["frames"], 1),
        "lost_events": sum(e["event"] == "lost" for e in s.get("events", [])),
        "resets": s["map_resets"],
        "dropped": f.get("dropped", 0),
        "keyframes": s["keyframes"],
        "kf_ate_cm": cm("keyframes"),
        "cam_ate_cm": cm("camera"),
        "kf_max_cm": cm("keyframes", "max_m"),
        "cam_max_cm": cm("camera", "max_m"),
        "rtf": rt.get("real_time_factor"),
        "lag_p95_ms": rt.get("lag_ms", {}).get("p95") if rt.get("lag_ms", {}).get("count") else None,
        "lag_max_ms": rt.get("lag_ms", {}).get("max") if rt.get("lag_ms", {}).get("count") else None,
        "latency_p95_ms": rt.get("latency_ms", {}).get("p95"),
        "lm_ms": t["local_mapping_per_keyframe"]["median"],
        "ba_ms": t["local_ba_per_keyframe"]["median"],
        "steps_ms": {k: v["median"] for k, v in t["mapping_steps"].items()},
        "fps": f["frames"] / s["wall_s"] if s.get("wall_s") else float("nan"),
        "process_wall_s": wall,
        "features": s.get("settings", {}).get("orb_features"),
    }


ROW = "{:>4} {:>6} {:>7} {:>6} {:>7} {:>4} {:>9} {:>9} {:>7} {:>6} {:>6}"


def _row(label: str, r: dict) -> str:
    def f(x, fmt):
        return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, fmt)

    return ROW.format(
        label, f(r["init_frame"], "d") if isinstance(r["init_frame"], int) else f(r["init_frame"], ".0f"),
        f(100 * r["tracked_share"], ".1f"), f(r["resets"], ".0f"), f(r["dropped"], ".0f"), f(r["keyframes"], ".0f"),
        f(r["kf_ate_cm"], ".2f"), f(r["cam_ate_cm"], ".2f"), f(r["lm_ms"], ".0f"), f(r["ba_ms"], ".0f"),
        f(r["fps"], ".1f"),
    )  # fmt: skip


ROW2 = "{:>4} {:>5} {:>6} {:>9} {:>9} {:>10} {:>9} {:>10}"


def _row2(label: str, r: dict) -> str:
    def f(x, fmt):
        return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, fmt)

    return ROW2.format(
        label, f(r["lost_events"], ".0f"), f(r["rtf"], ".2f"), f(r["lag_p95_ms"], ".0f"), f(r["lag_max_ms"], ".0f"),
        f(r["latency_p95_ms"], ".0f"), f(r["kf_max_cm"], ".1f"), f(r["cam_max_cm"], ".1f"),
    )  # fmt: skip


def _median(rows: list[dict]) -> dict:
    keys = ("init_frame", "tracked_share", "resets", "dropped", "keyframes", "kf_ate_cm", "cam_ate_cm", "lm_ms",
            "ba_ms", "fps", "lost_events", "rtf", "lag_p95_ms", "lag_max_ms", "latency_p95_ms", "kf_max_cm",
            "cam_max_cm")  # fmt: skip
    out = {}
    for k in keys:
        v = [r[k] for r in rows if r.get(k) is not None]
        out[k] = float(np.median(v)) if v else None
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", nargs="+", default=["kitti00", "tum_sample", "euroc_sample", "street", "fr3_hard"],
                    choices=[*REAL, *RENDERS])  # fmt: skip
    ap.add_argument("--modes", nargs="+", default=["threaded", "sequential"], choices=["threaded", "sequential"])
    ap.add_argument("--runs", type=int, default=3, help="threaded runs per sequence (default 3)")
    ap.add_argument("--seq-runs", type=int, default=1,
                    help="sequential runs per sequence (default 1: they give the same result every time)")
    ap.add_argument("--load", nargs="+", default=["none"], choices=list(LOADS),
                    help="CPU load beside every run: none, nice19 (two busy processes at niceness 19), hog (one at "
                    "normal priority); several: each in turn (default none)")
    ap.add_argument("--hog", type=int, default=0, help="more busy processes (normal priority) beside every run")
    ap.add_argument("--args", default="", help="extra arguments for orbslam-hgcn run, e.g. \"--vocab orb\"")
    ap.add_argument("--cache", default=os.path.expanduser("~/.cache/orbslam_hgcn"))
    ap.add_argument("--json", default=None, help="also write every run's figures to this file")
    ap.add_argument("--record", default=None, metavar="NAME",
                    help="write the figures the README quotes to bench/results/NAME.json (bench/figures.py)")
    a = ap.parse_args()
    load_start = os.getloadavg()[0]
    extra = shlex.split(a.args)
    cache = Path(a.cache)
    cache.mkdir(parents=True, exist_ok=True)
    print(f"bench_real: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at start, "
          f"{a.hog} more busy process(es) beside each run; extra args: {a.args or '(none)'}")  # fmt: skip
    results: dict = {}
    for name, load, mode in ((n, ld, m) for n in a.sequences for ld in a.load for m in a.modes):
        path, kind = sequence_path(name, cache)
        print(f"\n== {name} ({path}), {mode}, load {load} (load average {os.getloadavg()[0]:.2f})")
        print(ROW.format("run", "init", "track%", "resets", "dropped", "kfs", "kfATE cm", "camATE cm", "LM ms",
                         "BA ms", "fps"))  # fmt: skip
        rows = []
        for k in range(a.runs if mode == "threaded" else a.seq_runs):
            r = run_once(path, kind, mode, extra, a.hog, load)
            if "error" in r:
                print(f"{k + 1:>4} failed: {r['error']}")
                continue
            rows.append(r)
            print(_row(str(k + 1), r), flush=True)
        if rows:
            med = _median(rows)
            print(_row("med", med))
            print(ROW2.format("run", "lost", "RTF", "lag p95", "lag max", "latency95", "kfmax cm", "cammax cm"))
            for k, r in enumerate(rows):
                print(_row2(str(k + 1), r))
            print(_row2("med", med))
            if len(rows) > 1:
                ates = [r["kf_ate_cm"] for r in rows if np.isfinite(r["kf_ate_cm"])]
                shares = [100 * r["tracked_share"] for r in rows]
                span = f"{min(ates):.2f}-{max(ates):.2f} cm" if ates else "n/a"
                print(f"spread over {len(rows)} runs: keyframe ATE {span}, tracked {min(shares):.1f}-"
                      f"{max(shares):.1f}%, resets {sum(r['resets'] for r in rows)} in all")  # fmt: skip
            steps = {s: float(np.median([r["steps_ms"].get(s, np.nan) for r in rows])) for s in rows[0]["steps_ms"]}
            print("local mapping steps, median ms: " + ", ".join(f"{s} {v:.0f}" for s, v in steps.items())
                  + f"; ORB features {rows[0]['features']}")  # fmt: skip
        results[f"{name}/{load}/{mode}"] = rows
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=2) + "\n")
    if a.record:
        _record(a.record, results, a.args, load_start)
    return 0


def _span(rows: list[dict], key: str, fmt: str) -> str:
    v = sorted(r[key] for r in rows if r.get(key) is not None and np.isfinite(r[key]))
    if not v:
        return "n/a"
    return format(v[0], fmt) if v[0] == v[-1] else f"{v[0]:{fmt}}-{v[-1]:{fmt}} (median {np.median(v):{fmt}})"


def _record(name: str, results: dict, extra: str, load_start: float) -> None:
    """The README's figures of this bench: one group per sequence, load and mode."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import figures

    figs = []
    for key, rows in results.items():
        if not rows:
            figs.append((key, "every run failed"))
            continue
        tracked = sorted(round(r["tracked_share"] * r["frames"]) for r in rows)
        figs.append((key, f"{len(rows)} runs: tracked {tracked[0]}-{tracked[-1]} of {rows[0]['frames']} frames, "
                          f"resets {sum(r['resets'] for r in rows)}, lost events {sum(r.get('lost_events') or 0 for r in rows)}, "
                          f"dropped {sum(r['dropped'] for r in rows)}, keyframe ATE {_span(rows, 'kf_ate_cm', '.2f')} cm, "
                          f"camera ATE {_span(rows, 'cam_ate_cm', '.2f')} cm, real-time factor {_span(rows, 'rtf', '.2f')}, "
                          f"frame latency p95 {_span(rows, 'latency_p95_ms', '.0f')} ms"))  # fmt: skip
    title = "`orbslam-hgcn run` defaults" + (f" with `{extra}`" if extra else "")
    figures.record(name, title, figs, bench_file=__file__, load_start=load_start)


if __name__ == "__main__":
    sys.exit(main())
