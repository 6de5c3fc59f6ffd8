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
behind its camera), keyframes, keyframe and camera-trajectory ATE after Sim(3) alignment,
local mapping and local BA ms per keyframe (median), and frames/s over the run; then the
median time of each local mapping step.

``--hog N`` runs N busy processes (one core each, normal priority) beside every run, as
another job on a user's machine would.

Usage::

    python bench/bench_real.py [--sequences kitti00 tum_sample euroc_sample street fr3_hard]
                               [--modes threaded sequential] [--runs 3] [--seq-runs 1] [--hog N]
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


def _hog() -> None:
    x = 0
    while True:
        x += 1


def run_once(path: Path, kind: str, mode: str, extra: list[str], hogs: int) -> dict:
    """One ``orbslam-hgcn run`` in a child process; the figures from its stats.json."""
    out = Path(tempfile.mkdtemp(prefix="bench_real_"))
    cmd = [*_cli(), "run", str(path), "--dataset", kind, "--out", str(out / "run"), "--no-progress", *extra]
    if mode == "sequential":
        cmd.append("--sequential")
    procs = [mp.get_context("spawn").Process(target=_hog, daemon=True) for _ in range(hogs)]
    for p in procs:
        p.start()
    try:
        t0 = time.perf_counter()
        res = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    finally:
        for p in procs:
            p.terminate()
            p.join()
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

    def cm(name: str) -> float:
        a = ate.get(name, {})
        return 100.0 * a["rmse_m"] if "rmse_m" in a else float("nan")

    return {
        "init_frame": init[0] if init else None,
        "frames": f["frames"],
        "tracked_share": f["tracked"] / max(f["frames"], 1),
        "resets": s["map_resets"],
        "dropped": f.get("dropped", 0),
        "keyframes": s["keyframes"],
        "kf_ate_cm": cm("keyframes"),
        "cam_ate_cm": cm("camera"),
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


def _median(rows: list[dict]) -> dict:
    keys = ("init_frame", "tracked_share", "resets", "dropped", "keyframes", "kf_ate_cm", "cam_ate_cm", "lm_ms",
            "ba_ms", "fps")  # fmt: skip
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
    ap.add_argument("--hog", type=int, default=0, help="busy processes beside every run (default 0)")
    ap.add_argument("--args", default="", help="extra arguments for orbslam-hgcn run, e.g. \"--vocab orb\"")
    ap.add_argument("--cache", default=os.path.expanduser("~/.cache/orbslam_hgcn"))
    ap.add_argument("--json", default=None, help="also write every run's figures to this file")
    a = ap.parse_args()
    extra = shlex.split(a.args)
    cache = Path(a.cache)
    cache.mkdir(parents=True, exist_ok=True)
    print(f"bench_real: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at start, "
          f"{a.hog} busy process(es) beside each run; extra args: {a.args or '(none)'}")  # fmt: skip
    results: dict = {}
    for name in a.sequences:
        path, kind = sequence_path(name, cache)
        for mode in a.modes:
            print(f"\n== {name} ({path}), {mode}")
            print(ROW.format("run", "init", "track%", "resets", "dropped", "kfs", "kfATE cm", "camATE cm", "LM ms",
                             "BA ms", "fps"))  # fmt: skip
            rows = []
            for k in range(a.runs if mode == "threaded" else a.seq_runs):
                r = run_once(path, kind, mode, extra, a.hog)
                if "error" in r:
                    print(f"{k + 1:>4} failed: {r['error']}")
                    continue
                rows.append(r)
                print(_row(str(k + 1), r), flush=True)
            if rows:
                med = _median(rows)
                print(_row("med", med))
                if len(rows) > 1:
                    ates = [r["kf_ate_cm"] for r in rows if np.isfinite(r["kf_ate_cm"])]
                    shares = [100 * r["tracked_share"] for r in rows]
                    span = f"{min(ates):.2f}-{max(ates):.2f} cm" if ates else "n/a"
                    print(f"spread over {len(rows)} runs: keyframe ATE {span}, tracked {min(shares):.1f}-"
                          f"{max(shares):.1f}%, resets {sum(r['resets'] for r in rows)} in all")  # fmt: skip
                steps = {s: float(np.median([r["steps_ms"].get(s, np.nan) for r in rows])) for s in rows[0]["steps_ms"]}
                print("local mapping steps, median ms: " + ", ".join(f"{s} {v:.0f}" for s, v in steps.items())
                      + f"; ORB features {rows[0]['features']}")  # fmt: skip
            results[f"{name}/{mode}"] = rows
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
