"""Long runs: how the system's cost and memory grow over a KITTI-length drive and a many-lap office.

Scenarios (``--scenarios``), each rendered once into the cache folder (``--data``) by the
renderer and reused after:

* ``street``: ``orbslam-hgcn synth --scene street --layout kitti --duration 450
  --draw-distance 150``: 4500 frames at 10 Hz with KITTI 00's camera, in the KITTI layout;
  the drive never comes back, so it has no loop to close. Surfaces farther than 150 m are
  left to the sky: where a long straight comes into view whole, drawing all of it took
  1-2.5 s a frame (about 10,000 tiles) and the render over two hours;
* ``office``: ``orbslam-hgcn synth --laps 6 --duration 240``: 7200 frames at 30 Hz in the
  TUM layout, 6 laps round a desk, each lap beside the others.

``--duration-scale F`` renders F times the length (a smoke test: 0.05); the office then has
round(6 F) laps, at least two, each at least the renderer's shortest lap (10 s), so the last
may be cut short. Each sequence is run as a user runs it, ``orbslam-hgcn run
SEQ --out DIR --no-progress`` in its own process with the default settings, unpaced
(``--speed 0``) and paced at the camera's rate (the default, ``--speed 1``) (``--modes``),
beside the CPU load of ``--load`` (as bench_real.py: ``none``, ``nice19``, ``hog``).

Printed per scenario, mode and load:

* the run: its wall time, exit status (a run that ended early is reported with a note:
  ``stats.json`` says why), frames tracked, keyframes and map points at the end, points
  created in all, maps, loops closed and maps merged;
* peak memory: the largest sum of PSS (proportional set size, ``/proc/PID/smaps_rollup``:
  a page shared by n processes counts 1/n in each, so the code and libraries that the
  child processes share with the run count once) over the run's process tree (the run and
  its child processes: extraction, local and global BA, their helpers), sampled every
  0.2 s, and the largest VmRSS of the run process alone. Where a process's smaps_rollup
  cannot be read (kernels before 4.14), its VmRSS counts instead and the report says the
  sum is an upper bound. Linux only (elsewhere the bench says so and prints the rest);
* cost growth, from the run's ``series.npz``: tracking ms per frame (frames tracked) and
  the tracking thread's CPU ms per frame (what the frame's tracking did, without its waits
  for a core, the GIL or the map's lock: where the wall time grows and this does not, the
  growth is contention),
  local mapping ms per keyframe, loop detection ms per keyframe and the keyframe-database
  query ms per keyframe (both over the keyframes whose detection queried the database;
  detection is skipped right after the map's start and after a loop), each as median and
  mean in the first and the last quarter of the run (by the frame a keyframe was made
  from) and last/first. The issue's target: the last quarter's cost per frame and per
  keyframe at most 1.2x the first quarter's on the street drive (``ok`` or ``OVER``);
* the scene's part and the map's (``--tail-alone``, on by default): the last quarter of
  the sequence is run again on its own, from a fresh map, in the same mode; its tracking
  ms per frame and local mapping ms per keyframe (medians, leaving out its first tenth,
  where the map starts) against the full run's last quarter. The full run's cost over the
  tail's alone is what the map grown over the first three quarters adds (1.00: nothing);
  the tail's alone over the full run's first quarter is what the scene adds;
* the map and memory over the run: at the end of each tenth of the frames, the camera
  and wall time, keyframes and map points (counted every 10th frame by the run), the
  process tree's PSS and the run process's VmRSS at that moment; then how much each grew from
  the first tenth to the last. The map's point store keeps culled points (flagged), so
  memory follows the points created rather than those alive;
* real time: the real-time factor (``real_time.real_time_factor``: camera seconds per
  wall second; paced, 1.00 means the run kept up with its camera), frames dropped (none
  on a recorded sequence: a run behind its camera falls behind the clock instead), the lag
  behind the camera (paced: p95 and max) and the frame latency p95;
* office, per lap: whether the lap found its way into the map made by the earlier laps and
  how, judged from a quarter lap before the lap's first frame (the camera sees its start
  before it gets there) to a quarter lap before its end; the verdict is the earliest of:
  ``loop`` (the loop closer's event: a loop closed, its frame and the frame over half a
  lap earlier it matched), ``merge`` (another map merged), ``joined`` (a frame tracked
  against a reference keyframe, the local map's keyframe sharing most points with it,
  made over half a lap earlier: the map was joined by tracking, and loop detection, which
  skips connected keyframes, then finds no loop there), ``relocalised`` (into a keyframe
  made over half a lap earlier), else ``not joined``; with the first frame and the share
  of frames tracked against an earlier lap's keyframes, and the times tracking was lost.

The full bench (both scenarios, both modes, one load) takes about 20 minutes on 2 cores
(450 s + 240 s of paced runs, the unpaced ones, and each last quarter again: the street's
runs 9.5 minutes and its tails about 2.5, the office's 6.3 and 2), and the renders about
18 minutes more the first time (street 13, office 5). A progress line is printed per
phase (render, run) and every minute of a run.

Usage::

    python bench/bench_long.py [--scenarios street office] [--modes unpaced paced]
                               [--load none|nice19|hog ...] [--hog N] [--duration-scale F]
                               [--data DIR] [--keep DIR] [--json FILE] [--no-tail-alone]
                               [--record NAME]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import numpy as np

from bench_real import LOADS, start_load, stop_load  # noqa: E402 - a sibling script

SCENARIOS: dict[str, dict[str, Any]] = {
    "street": {"what": "KITTI-length street drive, KITTI layout, never comes back",
               "synth": ["--scene", "street", "--layout", "kitti"], "duration": 450.0, "fps": 10.0, "laps": 0,
               "kind": "kitti", "draw_distance": 150.0},
    "office": {"what": "many-lap office, TUM layout, laps round a desk",
               "synth": [], "duration": 240.0, "fps": 30.0, "laps": 6, "kind": "tum"},
}  # fmt: skip
MODES = {"unpaced": ["--speed", "0"], "paced": []}  # paced: the default --speed 1
TARGET_RATIO = 1.2  # the issue's target: last-quarter cost at most this x the first quarter's (street)
SAMPLE_S = 0.2


def _cli() -> list[str] | None:
    """The command that runs orbslam-hgcn beside this interpreter, or None without it."""
    exe = Path(sys.executable).with_name("orbslam-hgcn")
    if exe.exists():
        return [str(exe)]
    if find_spec("orbslam_hgcn") is not None:
        return [sys.executable, "-m", "orbslam_hgcn.cli"]
    found = shutil.which("orbslam-hgcn")
    return [found] if found else None


# --- memory of a process tree --------------------------------------------------------------
def proc_supported() -> bool:
    """Whether this system has Linux's /proc (VmRSS per process)."""
    return sys.platform.startswith("linux") and Path("/proc/self/status").is_file()


def _children(pid: int) -> list[int]:
    """Child process ids of ``pid`` (every thread's children file; else a scan of /proc)."""
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return []
    kids: list[int] = []
    for t in tasks:
        try:
            with open(f"/proc/{pid}/task/{t}/children") as fh:
                kids += [int(x) for x in fh.read().split()]
        except FileNotFoundError:
            if not os.path.exists(f"/proc/{pid}/task/{t}"):
                continue  # the thread ended meanwhile
            return _children_by_scan(pid)  # a kernel without the children files
        except OSError:
            continue
    return kids


def _children_by_scan(pid: int) -> list[int]:
    kids = []
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as fh:
                stat = fh.read()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2:].split()  # after the command name, which may hold spaces
        if len(fields) > 1 and int(fields[1]) == pid:
            kids.append(int(name))
    return kids


def process_tree(root: int) -> list[int]:
    """``root`` and its descendants alive now."""
    seen, todo = [], [root]
    while todo:
        pid = todo.pop()
        if pid in seen:
            continue
        seen.append(pid)
        todo.extend(_children(pid))
    return seen


def _proc_kb(path: str, key: str) -> int | None:
    """The kB figure of the line starting with ``key`` in a /proc file (None: gone,
    unreadable, or no such line, as a zombie's VmRSS)."""
    try:
        with open(path) as fh:
            for line in fh:
                if line.startswith(key):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def rss_kb(pid: int) -> int | None:
    """VmRSS of ``pid`` in kB (None: gone, or no resident set, as a zombie)."""
    return _proc_kb(f"/proc/{pid}/status", "VmRSS:")


def pss_kb(pid: int) -> int | None:
    """PSS of ``pid`` in kB (its private pages, and 1/n of each page it shares with n - 1
    other processes); None when gone or when the kernel has no smaps_rollup."""
    return _proc_kb(f"/proc/{pid}/smaps_rollup", "Pss:")


class MemorySampler:
    """Samples the memory of a process tree every ``interval_s`` on a thread of its own:
    ``samples`` holds (time.time(), tree kB (sum of PSS), root kB (VmRSS), processes);
    ``rss_fallbacks`` counts the processes whose PSS could not be read, summed by VmRSS."""

    def __init__(self, root: int, interval_s: float = SAMPLE_S) -> None:
        self.root, self.interval_s = root, interval_s
        self.samples: list[tuple[float, int, int, int]] = []
        self.rss_fallbacks = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-long-memory", daemon=True)

    def start(self) -> MemorySampler:
        self._thread.start()
        return self

    def sample(self) -> tuple[float, int, int, int] | None:
        pids = process_tree(self.root)
        sizes = {p: rss_kb(p) for p in pids}
        if sizes.get(self.root) is None:
            return None
        tree = 0
        for p, rss in sizes.items():
            if not rss:
                continue
            pss = pss_kb(p)
            if pss is None:
                if not rss_kb(p):
                    continue  # it ended between the two reads (a helper process): not counted
                self.rss_fallbacks += 1
            tree += rss if pss is None else pss
        return time.time(), tree, int(sizes[self.root]), sum(1 for v in sizes.values() if v)

    def _run(self) -> None:
        while not self._stop.is_set():
            s = self.sample()
            if s is not None:
                self.samples.append(s)
            self._stop.wait(self.interval_s)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def peak_kb(self) -> int:
        return max((s[1] for s in self.samples), default=0)

    @property
    def peak_root_kb(self) -> int:
        return max((s[2] for s in self.samples), default=0)

    @property
    def max_processes(self) -> int:
        return max((s[3] for s in self.samples), default=0)


# --- the figures -----------------------------------------------------------------------------
def quarter_stats(index: np.ndarray, values: np.ndarray, lo: float, hi: float) -> dict[str, Any]:
    """Median, mean and count of the finite ``values`` whose ``index`` (a frame) lies in the
    first quarter of [lo, hi] and in the last; ``ratio_median`` and ``ratio_mean``: last over
    first (NaN when a quarter is empty or its first figure is 0)."""
    index, values = np.asarray(index, np.float64), np.asarray(values, np.float64)
    span = hi - lo + 1
    ok = np.isfinite(values)
    out: dict[str, Any] = {}
    for name, sel in (("first", index < lo + span / 4.0), ("last", index >= lo + 3.0 * span / 4.0)):
        v = values[sel & ok]
        out[name] = {"n": int(len(v)), "median": float(np.median(v)) if len(v) else math.nan,
                     "mean": float(v.mean()) if len(v) else math.nan}  # fmt: skip
    for stat in ("median", "mean"):
        a, b = out["first"][stat], out["last"][stat]
        out[f"ratio_{stat}"] = b / a if np.isfinite(a) and np.isfinite(b) and a > 0 else math.nan
    return out


def cost_growth(series: dict[str, np.ndarray]) -> dict[str, dict[str, Any]]:
    """:func:`quarter_stats` of tracking ms per frame, local mapping, loop detection and
    database query ms per keyframe, quarters over the frames processed."""
    frames = series["frame"]
    if len(frames) == 0:
        return {}
    lo, hi = float(frames.min()), float(frames.max())
    frame_of = dict(zip(series["kf_id"].tolist(), series["kf_frame"].tolist()))
    queried = np.isfinite(series["loop_query_ms"])
    loop_frames = np.array([frame_of.get(int(k), -1) for k in series["loop_kf_id"]], np.float64)
    known = loop_frames >= 0
    return {
        "tracking ms/frame": quarter_stats(frames, series["tracking_ms"], lo, hi),
        **({"tracking CPU ms/frame": quarter_stats(frames, series["tracking_cpu_ms"], lo, hi)}
           if "tracking_cpu_ms" in series else {}),
        "local mapping ms/kf": quarter_stats(series["kf_frame"], series["kf_mapping_ms"], lo, hi),
        "loop detection ms/kf": quarter_stats(loop_frames[known & queried], series["loop_detect_ms"][known & queried],
                                              lo, hi),
        "db query ms/kf": quarter_stats(loop_frames[known & queried], series["loop_query_ms"][known & queried], lo, hi),
    }  # fmt: skip


def tenths(series: dict[str, np.ndarray], samples: list[tuple[float, int, int, int]], parts: int = 10) -> list[dict]:
    """At the end of each tenth of the frames processed: frame, camera and wall seconds
    since the first frame, the map's keyframes and points (the last count at or before the
    frame), and the memory sample at or before that moment (tree and run process, MB;
    None without samples)."""
    n = len(series["frame"])
    if n == 0:
        return []
    t0, w0 = float(series["frame_t"][0]), float(series["frame_wall"][0])
    counts_at = series["count_frame"]
    order = np.argsort([s[0] for s in samples]) if samples else np.zeros(0, int)
    times = np.array([samples[i][0] for i in order]) if samples else np.zeros(0)
    rows = []
    for k in range(1, parts + 1):
        i = max(0, int(math.ceil(k * n / parts)) - 1)
        f, wall = int(series["frame"][i]), float(series["frame_wall"][i])
        # counts are taken in processing order; the last one at or before this frame's position
        c = int(np.searchsorted(counts_at, f, side="right")) - 1
        j = int(np.searchsorted(times, wall, side="right")) - 1
        sample = samples[order[j]] if j >= 0 else None
        rows.append({
            "tenth": k, "frame": f, "camera_s": float(series["frame_t"][i]) - t0, "wall_s": wall - w0,
            "keyframes": int(series["count_keyframes"][c]) if c >= 0 else None,
            "points": int(series["count_points"][c]) if c >= 0 else None,
            "tree_mb": sample[1] / 1024.0 if sample else None, "run_mb": sample[2] / 1024.0 if sample else None,
        })  # fmt: skip
    return rows


def _ratio(a: float | None, b: float | None) -> float:
    return b / a if a and b is not None and a > 0 else math.nan


def growth(rows: list[dict]) -> dict[str, float]:
    """Last tenth over first: keyframes, map points, tree and run-process memory; and the
    run process's memory added per 1000 map points added (MB)."""
    if not rows:
        return {}
    a, b = rows[0], rows[-1]
    out = {k: _ratio(a[k], b[k]) for k in ("keyframes", "points", "tree_mb", "run_mb")}
    dp = (b["points"] or 0) - (a["points"] or 0)
    out["run_mb_per_1000_points"] = ((b["run_mb"] - a["run_mb"]) / dp * 1000.0
                                     if dp > 0 and a["run_mb"] is not None and b["run_mb"] is not None
                                     else math.nan)  # fmt: skip
    return out


def lap_evidence(series: dict[str, np.ndarray], stats: dict, n_frames: int, lap_frames: float) -> list[dict]:
    """Per lap (``lap_frames`` frames each; the last may be cut short) of an office of
    ``n_frames`` frames, what joined it to the map of the earlier laps. Lap k's window runs
    from a quarter lap before its first frame to a quarter lap before its end (the camera
    sees the lap's start before it gets there; the first lap's from frame 0, the last's to
    the end). In the window: loops closed and maps merged (frame, matched frame) with a
    frame over half a lap earlier, relocalisations into a keyframe made over half a lap
    earlier, frames tracked against a reference keyframe made over half a lap earlier (how
    many, the first), times lost; the verdict is ``first lap``, else the earliest of
    ``loop``, ``merge``, ``joined`` (tracking), ``relocalised``, or ``not joined``."""
    lap_len = float(lap_frames)
    laps = max(1, int(math.ceil(n_frames / lap_len - 1e-9)))
    half, quarter = lap_len / 2.0, lap_len / 4.0
    frame_of = dict(zip(series["kf_id"].tolist(), series["kf_frame"].tolist()))
    frames, refs = series["frame"], series["frame_ref_kf"]
    tracked = np.isfinite(series["tracking_ms"])
    far = 10**12
    ref_frame = np.array([frame_of.get(int(r), far) if r >= 0 else far for r in refs], np.float64)
    earlier = tracked & (frames - ref_frame > half)
    lc = stats.get("loop_closing") or {}
    loops = [(int(e["frame_id"]), int(e["loop_frame_id"])) for e in lc.get("loops", [])]
    merges = [(int(e["frame_id"]), int(e["match_frame_id"])) for e in lc.get("merges", [])]
    relocs = [(int(h[0]), int(frame_of.get(int(h[1]), far))) for h in (stats.get("relocalization") or {}).get("history", [])]
    lost = [int(e["frame"]) for e in stats.get("events", []) if e.get("event") == "lost"]
    out = []
    for k in range(laps):
        a, b = int(round(k * lap_len)), min(n_frames, int(round((k + 1) * lap_len)))
        wa = 0 if k == 0 else int(round(a - quarter))
        wb = n_frames if k == laps - 1 else int(round(b - quarter))

        def inside(f: int, wa: int = wa, wb: int = wb) -> bool:
            return wa <= f < wb

        sel = (frames >= wa) & (frames < wb)
        joined = frames[sel & earlier]
        lap = {
            "lap": k + 1, "frames": (a, b - 1), "window": (wa, wb - 1), "processed": int(sel.sum()),
            "loops": [(f, g) for f, g in loops if inside(f) and f - g > half],
            "merges": [(f, g) for f, g in merges if inside(f) and f - g > half],
            "relocalised": [f for f, g in relocs if inside(f) and f - g > half],
            "joined_frames": int(len(joined)), "joined_from": int(joined.min()) if len(joined) else None,
            "lost": sum(1 for f in lost if inside(f)),
        }  # fmt: skip
        first = [(f, "loop") for f, _ in lap["loops"][:1]] + [(f, "merge") for f, _ in lap["merges"][:1]]
        first += [(lap["joined_from"], "joined")] if lap["joined_from"] is not None else []
        first += [(lap["relocalised"][0], "relocalised")] if lap["relocalised"] else []
        lap["verdict"] = "first lap" if k == 0 else min(first)[1] if first else "not joined"
        out.append(lap)
    return out


def _lap_text(lap: dict) -> str:
    parts = [f"window {lap['window'][0]}-{lap['window'][1]}"]
    for f, g in lap["loops"]:
        parts.append(f"loop closed at frame {f} with frame {g}")
    for f, g in lap["merges"]:
        parts.append(f"maps merged at frame {f} with frame {g}")
    if lap["joined_frames"]:
        share = 100.0 * lap["joined_frames"] / max(lap["processed"], 1)
        parts.append(f"tracked against keyframes of an earlier lap from frame {lap['joined_from']} "
                     f"({share:.0f}% of the window's frames)")  # fmt: skip
    elif lap["lap"] > 1:
        parts.append("no frame tracked against an earlier lap's keyframes")
    if lap["relocalised"]:
        parts.append(f"relocalised into an earlier lap {len(lap['relocalised'])} time(s), first at frame "
                     f"{lap['relocalised'][0]}")  # fmt: skip
    if lap["lost"]:
        parts.append(f"lost {lap['lost']} time(s)")
    return "; ".join(parts)


# --- the last quarter alone ------------------------------------------------------------------
def tail_sequence(seq: Path, kind: str, start: int, dest: Path) -> Path:
    """A sequence of the frames ``start``.. of ``seq`` (as rendered: TUM or KITTI layout),
    made under ``dest`` of links to the same image files; returns the folder to run."""
    dest.mkdir(parents=True, exist_ok=True)
    if kind == "kitti":
        root = seq.parent.parent  # .../sequences/NN -> the folder holding poses/
        out = dest / "sequences" / seq.name
        (out / "image_0").mkdir(parents=True, exist_ok=True)
        times = [t for t in (seq / "times.txt").read_text().splitlines() if t.strip()]
        (out / "times.txt").write_text("\n".join(times[start:]) + "\n")
        shutil.copy(seq / "calib.txt", out / "calib.txt")
        images = sorted((seq / "image_0").iterdir())
        for i, img in enumerate(images[start:]):
            (out / "image_0" / f"{i:06d}{img.suffix}").symlink_to(img.resolve())
        poses = root / "poses" / f"{seq.name}.txt"
        if poses.is_file():
            (dest / "poses").mkdir(exist_ok=True)
            rows = [r for r in poses.read_text().splitlines() if r.strip()]
            (dest / "poses" / poses.name).write_text("\n".join(rows[start:]) + "\n")
        return out
    lines = (seq / "rgb.txt").read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    rows = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    (dest / "rgb.txt").write_text("\n".join(head + rows[start:]) + "\n")
    for name in ("rgb", "groundtruth.txt", "camera.yaml"):
        if (seq / name).exists():
            (dest / name).symlink_to((seq / name).resolve())
    return dest


def tail_costs(series: dict[str, np.ndarray]) -> dict[str, float]:
    """Median tracking ms per frame and local mapping ms per keyframe of a run of the last
    quarter alone, leaving out its first tenth (the map's start)."""
    frames = series["frame"]
    if len(frames) == 0:
        return {}
    lo, hi = float(frames.min()), float(frames.max())
    skip = lo + 0.1 * (hi - lo + 1)
    out = {}
    costs = [("tracking ms/frame", frames, series["tracking_ms"]),
             ("local mapping ms/kf", series["kf_frame"], series["kf_mapping_ms"])]
    if "tracking_cpu_ms" in series:
        costs.insert(1, ("tracking CPU ms/frame", frames, series["tracking_cpu_ms"]))
    for name, index, values in costs:
        index, values = np.asarray(index, np.float64), np.asarray(values, np.float64)
        v = values[(index >= skip) & np.isfinite(values)]
        out[name] = float(np.median(v)) if len(v) else math.nan
    return out


def tail_comparison(full: dict[str, Any], alone: dict[str, float]) -> dict[str, dict[str, float]]:
    """Per cost: the full run's first and last quarter medians, the last quarter's alone,
    ``map`` (full run's last quarter / alone) and ``scene`` (alone / full run's first)."""
    out = {}
    for name, a in alone.items():
        q = full.get("growth", {}).get(name)
        if q is None:
            continue
        first, last = q["first"]["median"], q["last"]["median"]
        out[name] = {"first": first, "last": last, "alone": a, "map": _ratio(a, last), "scene": _ratio(first, a)}
    return out


# --- rendering and running -----------------------------------------------------------------
def plan(name: str, scale: float) -> dict[str, Any]:
    """The render of scenario ``name`` at ``scale`` times its length: duration, frames,
    laps, the synth arguments, its cache folder name."""
    sc = SCENARIOS[name]
    duration = round(sc["duration"] * scale, 3)
    frames = int(round(duration * sc["fps"]))
    laps = max(2, int(round(sc["laps"] * scale))) if sc["laps"] > 1 else 0
    args = [*sc["synth"], "--duration", f"{duration:g}"] + (["--laps", str(laps)] if laps else [])
    folder = f"{name}_{frames}f" + (f"_{laps}laps" if laps else "")
    if sc.get("draw_distance"):
        args += ["--draw-distance", f"{sc['draw_distance']:g}"]
        folder += f"_dd{sc['draw_distance']:g}"
    # The renderer's lap: the duration over the laps, but never shorter than its shortest loop.
    lap_frames = max(duration / laps, _min_loop_s()) * sc["fps"] if laps else 0.0
    return {"name": name, "duration": duration, "frames": frames, "laps": laps, "lap_frames": lap_frames,
            "fps": sc["fps"], "kind": sc["kind"], "synth": args, "folder": folder, "what": sc["what"]}  # fmt: skip


def _min_loop_s() -> float:
    try:
        from orbslam_hgcn.synth.sequence import MIN_LOOP_S
    except ImportError:
        return 10.0
    return float(MIN_LOOP_S)


def render(p: dict, data: Path, cli: list[str]) -> Path:
    """The sequence folder of plan ``p`` under ``data``, rendered on first use (a folder
    without its .complete mark is rendered again)."""
    out = data / p["folder"]
    if not (out / ".complete").is_file():
        cmd = [*cli, "synth", *p["synth"], "--out", str(out), "--force"]
        print(f"[{p['name']}] rendering {p['frames']} frames into {out} (once; the street drive takes several "
              f"minutes): {' '.join(cmd[len(cli):])}", flush=True)  # fmt: skip
        t0 = time.perf_counter()
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            tail = " | ".join((res.stderr or res.stdout).strip().splitlines()[-3:])
            raise RuntimeError(f"rendering failed (exit {res.returncode}): {tail}")
        (out / ".complete").write_text(" ".join(cmd[len(cli):]) + "\n")
        print(f"[{p['name']}] rendered in {time.perf_counter() - t0:.0f} s", flush=True)
    else:
        print(f"[{p['name']}] using the render in {out}", flush=True)
    if p["kind"] == "kitti":
        seqs = sorted(q for q in (out / "sequences").iterdir() if q.is_dir()) if (out / "sequences").is_dir() else []
        return seqs[0] if seqs else out
    return out


def run_once(seq: Path, kind: str, mode: str, load: str, hogs: int, cli: list[str], label: str,
             keep: Path | None = None, heartbeat_s: float = 60.0) -> dict[str, Any]:  # fmt: skip
    """One ``orbslam-hgcn run`` of ``seq`` in ``mode`` beside ``load``, its process tree's
    memory sampled meanwhile: its stats, series, memory samples, wall time and exit status,
    or ``error`` when it wrote no stats.json."""
    tmp = Path(tempfile.mkdtemp(prefix="bench_long_"))
    out = (keep / label.replace("/", "_")) if keep is not None else tmp / "run"
    if out.exists():
        shutil.rmtree(out)
    cmd = [*cli, "run", str(seq), "--dataset", kind, "--out", str(out), "--no-progress", *MODES[mode]]
    print(f"[{label}] run started {time.strftime('%H:%M:%S')}: {' '.join(cmd[len(cli):])}", flush=True)
    procs = start_load(load, hogs)
    sampler = None
    try:
        t0 = time.perf_counter()
        with open(tmp / "stdout.txt", "w") as so, open(tmp / "stderr.txt", "w") as se:
            try:
                proc = subprocess.Popen(cmd, stdout=so, stderr=se)
            except OSError as exc:
                shutil.rmtree(tmp, ignore_errors=True)
                return {"error": f"cannot start {cmd[0]}: {exc}"}
            if proc_supported():
                sampler = MemorySampler(proc.pid).start()
            next_beat = t0 + heartbeat_s
            while proc.poll() is None:
                time.sleep(0.5)
                if time.perf_counter() >= next_beat:
                    next_beat += heartbeat_s
                    mem = f", process tree {sampler.samples[-1][1] / 1024:.0f} MB" if sampler and sampler.samples else ""
                    print(f"[{label}] ... {time.perf_counter() - t0:.0f} s{mem}", flush=True)
        wall = time.perf_counter() - t0
    finally:
        if sampler is not None:
            sampler.stop()
        stop_load(procs)
    rc = proc.returncode
    print(f"[{label}] run finished in {wall:.0f} s (exit {rc})", flush=True)
    stderr = (tmp / "stderr.txt").read_text(errors="replace")
    stats_path, series_path = out / "stats.json", out / "series.npz"
    result: dict[str, Any] = {"exit": rc, "wall_s": wall, "samples": sampler.samples if sampler else [],
                              "peak_tree_mb": sampler.peak_kb / 1024 if sampler else None,
                              "peak_run_mb": sampler.peak_root_kb / 1024 if sampler else None,
                              "max_processes": sampler.max_processes if sampler else None,
                              "rss_fallbacks": sampler.rss_fallbacks if sampler else None}  # fmt: skip
    try:
        if not stats_path.is_file():
            tail = " | ".join(stderr.strip().splitlines()[-3:])
            result["error"] = f"exit {rc}, no stats.json: {tail or '(no output)'}"
            return result
        try:
            stats = json.loads(stats_path.read_text())
        except (OSError, ValueError) as exc:
            result["error"] = f"exit {rc}: {stats_path} cannot be read ({exc})"
            return result
        result["stats"] = stats
        if series_path.is_file():
            try:
                with np.load(series_path, allow_pickle=False) as z:
                    result["series"] = {k: z[k] for k in z.files}
            except (OSError, ValueError) as exc:
                result["error"] = f"exit {rc}: {series_path} cannot be read ({exc})"
        else:
            result["error"] = f"exit {rc}: no series.npz beside stats.json (a run of code older than the bench?)"
        if rc != 0 or not stats.get("complete", True):
            end = stats.get("end") or {}
            result["note"] = f"ended early (exit {rc}): {end.get('kind', '?')}: {end.get('reason', '')}".rstrip(": ")
        return result
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# --- the report ------------------------------------------------------------------------------
def run_tail(seq: Path, p: dict, mode: str, load: str, hogs: int, cli: list[str], label: str,
             keep: Path | None, fig: dict[str, Any]) -> dict[str, Any]:  # fmt: skip
    """Run the last quarter of ``seq`` alone (:func:`tail_sequence`) in ``mode`` beside
    ``load``, print and return its comparison with the full run's figures ``fig``."""
    start = int(round(0.75 * p["frames"]))
    with tempfile.TemporaryDirectory(prefix="bench_long_tail_") as tmp:
        tail = tail_sequence(seq, p["kind"], start, Path(tmp))
        r = run_once(tail, p["kind"], mode, load, hogs, cli, f"{label}/tail", keep)
    if "series" not in r:
        print(f"last quarter alone: the run failed ({r.get('error', 'no series.npz')})\n")
        return {"error": r.get("error", "no series.npz")}
    cmp = tail_comparison(fig, tail_costs(r["series"]))
    print(f"\nthe last quarter (frames {start}-{p['frames'] - 1}) run alone from a fresh map, {mode}: "
          f"tracked {r['stats']['frames']['tracked']} of {r['stats']['frames']['frames']}; medians, its first tenth "
          "left out")  # fmt: skip
    row = "{:<21} {:>9} {:>9} {:>9} {:>11} {:>11}"
    print(row.format("", "first1", "last4", "alone4", "map: 4/alone", "scene: alone/1"))
    for name, c in cmp.items():
        print(row.format(name, _f(c["first"], ".2f"), _f(c["last"], ".2f"), _f(c["alone"], ".2f"),
                         _f(c["map"], ".2f") + "x", _f(c["scene"], ".2f") + "x"))  # fmt: skip
    print("(map: what the map grown over the first three quarters adds to the last quarter's cost; scene: what the "
          "last quarter's frames cost more than the first's on their own)\n", flush=True)  # fmt: skip
    return cmp


def _f(x: Any, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, fmt)


def analyse(r: dict[str, Any], p: dict[str, Any], mode: str = "paced") -> dict[str, Any]:
    """The figures of one run in ``mode`` (see the module text)."""
    s, series = r["stats"], r.get("series")
    rt = s.get("real_time", {})
    lc = s.get("loop_closing") or {}
    out: dict[str, Any] = {
        "frames": s["frames"]["frames"], "tracked": s["frames"]["tracked"], "keyframes": s["keyframes"],
        "map_points": s["map_points"], "points_created": (s.get("mapping_counts") or {}).get("points_created"),
        "maps": len((s.get("atlas") or {}).get("maps") or []) or 1, "loops": len(lc.get("loops", [])),
        "merges": len(lc.get("merges", [])), "lost_events": sum(e["event"] == "lost" for e in s.get("events", [])),
        "resets": s.get("map_resets", 0), "rtf": rt.get("real_time_factor"), "dropped": rt.get("dropped", 0),
        "lag_p95_ms": rt.get("lag_ms", {}).get("p95"), "lag_max_ms": rt.get("lag_ms", {}).get("max"),
        "latency_p95_ms": rt.get("latency_ms", {}).get("p95"), "wall_s": r["wall_s"], "exit": r["exit"],
        "peak_tree_mb": r["peak_tree_mb"], "peak_run_mb": r["peak_run_mb"], "max_processes": r["max_processes"],
        "rss_fallbacks": r.get("rss_fallbacks"),
        "note": r.get("note"), "mode": mode,
    }  # fmt: skip
    if series is not None:
        out["growth"] = cost_growth(series)
        out["tenths"] = tenths(series, r["samples"])
        out["memory_growth"] = growth(out["tenths"])
        if p["laps"] > 1:
            out["laps"] = lap_evidence(series, s, p["frames"], p["lap_frames"])
    return out


def print_report(a: dict[str, Any], p: dict[str, Any], with_target: bool) -> None:
    print(f"run: {a['wall_s']:.0f} s, exit {a['exit']}" + (f" - {a['note']}" if a["note"] else ", complete")
          + f"; tracked {a['tracked']} of {a['frames']} frames, lost {a['lost_events']} time(s), resets {a['resets']}; "
          f"keyframes {a['keyframes']}, map points {a['map_points']} (created in all {_f(a['points_created'], 'd')}); "
          f"maps {a['maps']}, loops closed {a['loops']}, merges {a['merges']}")  # fmt: skip
    if a["peak_tree_mb"] is None:
        print("peak memory: not measured (it reads /proc/PID/status: Linux only)")
    else:
        what = "PSS" if not a.get("rss_fallbacks") else "PSS, VmRSS where unreadable: an upper bound"
        print(f"peak memory: process tree {a['peak_tree_mb']:.0f} MB (sum of {what}, up to {a['max_processes']} "
              f"processes), run process alone {a['peak_run_mb']:.0f} MB (VmRSS); sampled every {SAMPLE_S:g} s")  # fmt: skip
    what = "camera seconds per wall second" if a["mode"] == "unpaced" else "1.00: kept up with the camera"
    print(f"real time: factor {_f(a['rtf'], '.2f')} ({what}), dropped {a['dropped']}, lag p95 "
          f"{_f(a['lag_p95_ms'], '.0f')} ms, max {_f(a['lag_max_ms'], '.0f')} ms, latency p95 "
          f"{_f(a['latency_p95_ms'], '.0f')} ms")  # fmt: skip
    if "growth" not in a:
        print("(no series.npz: no growth figures)")
        return
    head = "{:<21} {:>5} {:>5} {:>9} {:>9} {:>7} {:>9} {:>9} {:>7}" + (" {:>8}" if with_target else "")
    print("\ncost, first and last quarter of the run")
    print(head.format("", "n1", "n4", "median1", "median4", "last/1", "mean1", "mean4", "last/1",
                      *(["target"] if with_target else [])))  # fmt: skip
    for name, q in a["growth"].items():
        verdict = []
        if with_target:
            r = q["ratio_median"]
            verdict = ["-" if not np.isfinite(r) else ("ok" if r <= TARGET_RATIO else "OVER")]
        print(head.format(name, q["first"]["n"], q["last"]["n"], _f(q["first"]["median"], ".2f"),
                          _f(q["last"]["median"], ".2f"), _f(q["ratio_median"], ".2f") + "x",
                          _f(q["first"]["mean"], ".2f"), _f(q["last"]["mean"], ".2f"),
                          _f(q["ratio_mean"], ".2f") + "x", *verdict))  # fmt: skip
    if with_target:
        print(f"(target: last quarter at most {TARGET_RATIO:g}x the first, on the medians)")
    print("\nmap and memory over the run (end of each tenth)")
    row = "{:>5} {:>6} {:>8} {:>7} {:>9} {:>10} {:>8} {:>7}"
    print(row.format("tenth", "frame", "camera s", "wall s", "keyframes", "map points", "tree MB", "run MB"))
    for t in a["tenths"]:
        print(row.format(t["tenth"], t["frame"], f"{t['camera_s']:.1f}", f"{t['wall_s']:.1f}", _f(t["keyframes"], "d"),
                         _f(t["points"], "d"), _f(t["tree_mb"], ".0f"), _f(t["run_mb"], ".0f")))  # fmt: skip
    g = a["memory_growth"]
    print(f"last tenth / first: keyframes {_f(g['keyframes'], '.2f')}x, map points {_f(g['points'], '.2f')}x, "
          f"process tree memory {_f(g['tree_mb'], '.2f')}x, run process {_f(g['run_mb'], '.2f')}x "
          f"({_f(g['run_mb_per_1000_points'], '.1f')} MB per 1000 map points added)")  # fmt: skip
    if "laps" in a:
        print("\nlaps (a lap joins the map when it closes a loop, merges, or is tracked against an earlier lap's "
              "keyframes)")  # fmt: skip
        for lap in a["laps"]:
            print(f"{lap['lap']:>3} frames {lap['frames'][0]}-{lap['frames'][1]}: {lap['verdict']}: {_lap_text(lap)}")


def _record_value(a: dict[str, Any]) -> str:
    parts = [f"peak memory {_f(a['peak_tree_mb'], '.0f')} MB"]
    for name, q in a.get("growth", {}).items():
        parts.append(f"{name} last/first {_f(q['ratio_median'], '.2f')}x")
    parts += [f"keyframes {a['keyframes']}", f"map points {a['map_points']}", f"loops {a['loops']}",
              f"merges {a['merges']}", f"tracked {a['tracked']} of {a['frames']}", f"real-time factor {_f(a['rtf'], '.2f')}",
              f"dropped {a['dropped']}"]  # fmt: skip
    for name, c in a.get("tail", {}).items():
        if isinstance(c, dict):
            parts.append(f"{name} last quarter in the run / alone {_f(c['map'], '.2f')}x")
    if "laps" in a:
        later = [lap for lap in a["laps"] if lap["lap"] > 1]
        parts.append(f"laps joined {sum(lap['verdict'] != 'not joined' for lap in later)} of {len(later)}")
    if a["note"]:
        parts.append("ended early")
    return ", ".join(parts)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS))
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES),
                    help="unpaced (--speed 0) and/or paced at the camera's rate (the default of run)")
    ap.add_argument("--load", nargs="+", default=["none"], choices=list(LOADS),
                    help="CPU load beside every run, as bench_real.py: none, nice19, hog (default none)")
    ap.add_argument("--hog", type=int, default=0, help="more busy processes (normal priority) beside every run")
    ap.add_argument("--duration-scale", type=float, default=1.0, metavar="F",
                    help="render F times each scenario's length (a smoke test: 0.05; the office then has "
                    "round(6 F) laps, at least 2, of 10 s or more)")
    ap.add_argument("--data", default=os.path.expanduser("~/.cache/orbslam_hgcn/bench_long"),
                    help="where the renders are kept (default ~/.cache/orbslam_hgcn/bench_long)")
    ap.add_argument("--keep", default=None, metavar="DIR", help="keep every run's output folder under DIR")
    ap.add_argument("--json", default=None, help="also write every run's figures to this file")
    ap.add_argument("--no-tail-alone", dest="tail_alone", action="store_false",
                    help="do not run each sequence's last quarter again on its own (the scene's part of the "
                    "growth against the map's)")
    ap.add_argument("--record", default=None, metavar="NAME",
                    help="write the figures to bench/results/NAME.json (bench/figures.py)")
    a = ap.parse_args()
    if a.duration_scale <= 0:
        ap.error("--duration-scale must be positive")
    cli = _cli()
    if cli is None:
        print("bench_long: orbslam-hgcn is not installed beside this Python (pip install -e . in the "
              "repository)", file=sys.stderr)  # fmt: skip
        return 2
    load_start = os.getloadavg()[0]
    data = Path(a.data).expanduser()
    data.mkdir(parents=True, exist_ok=True)
    keep = Path(a.keep).expanduser() if a.keep else None
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
    print(f"bench_long: {os.cpu_count()} CPUs, load average {load_start:.2f} at start; renders in {data}; "
          f"duration scale {a.duration_scale:g}")  # fmt: skip
    if not proc_supported():
        print("bench_long: no Linux /proc here: peak memory is not measured; every other figure is")
    t_start = time.perf_counter()
    results: dict[str, Any] = {}
    failed = 0
    for name in a.scenarios:
        p = plan(name, a.duration_scale)
        try:
            seq = render(p, data, cli)
        except (RuntimeError, OSError) as exc:
            print(f"[{name}] {exc}; scenario skipped", file=sys.stderr)
            failed += 1
            continue
        for load in a.load:
            for mode in a.modes:
                label = f"{name}/{mode}/{load}"
                r = run_once(seq, p["kind"], mode, load, a.hog, cli, label, keep)
                print(f"\n== {name}: {p['what']}; {p['frames']} frames at {p['fps']:g} Hz ({p['duration']:g} s"
                      + (f", {p['laps']} laps of {p['lap_frames'] / p['fps']:g} s" if p["laps"] else "") + f"), {mode}, load {load}")  # fmt: skip
                if "stats" not in r:
                    print(f"run failed: {r['error']}")
                    results[label] = {"error": r["error"]}
                    failed += 1
                    continue
                if "error" in r:
                    print(r["error"])
                fig = analyse(r, p, mode)
                print_report(fig, p, with_target=(name == "street"))
                print(flush=True)
                results[label] = fig
                if a.tail_alone and "growth" in fig:
                    fig["tail"] = run_tail(seq, p, mode, load, a.hog, cli, label, keep, fig)
    print(f"bench_long: done in {(time.perf_counter() - t_start) / 60:.1f} min"
          + (f"; {failed} run(s) or render(s) failed" if failed else ""))  # fmt: skip
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=2, default=str) + "\n")
    if a.record:
        _record(a.record, results, load_start, a.duration_scale)
    return 1 if failed else 0


def _record(name: str, results: dict, load_start: float, scale: float) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import figures

    figs = [(k, v["error"] if "error" in v else _record_value(v)) for k, v in results.items()]
    title = "long runs: cost and memory growth of `orbslam-hgcn run`" + (f" (duration x{scale:g})" if scale != 1 else "")
    figures.record(name, title, figs, bench_file=__file__, load_start=load_start)


if __name__ == "__main__":
    sys.exit(main())
