"""``orbslam-hgcn run`` as child processes on the engine: what ``sweep`` and ``compare``
run. Each run is one process with its results in its own folder; a process killed by a
signal is started once more, and the result of each says how it went (attempts, exit
status, error, the run's stats).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from orbslam_hgcn.engine import Engine, TaskFailed

# The program a run's process starts: this interpreter with the package's entry point.
# (Tests replace it to stand in for a run.)
RUN_PROGRAM: list[str] = [sys.executable, "-m", "orbslam_hgcn"]


def run_argv(path: str | Path, out: str | Path, vocab: str, kind: str | None = None, config: str | Path | None = None,
             max_frames: int | None = None, sequential: bool = False, speed: float | None = None) -> list[str]:
    """The ``orbslam-hgcn run`` arguments of one run (loop closing on, no progress bar)."""
    argv = ["run", str(path), "--out", str(out), "--vocab", vocab, "--no-progress"]
    if kind:
        argv += ["--dataset", kind]
    if config:
        argv += ["--config", str(config)]
    if max_frames:
        argv += ["--max-frames", str(max_frames)]
    if sequential:
        argv.append("--sequential")
    if speed is not None:
        argv += ["--speed", f"{speed:g}"]
    return argv


def run_processes(argvs: Sequence[tuple[list[str], str]], engine: Engine) -> Iterator[tuple[int, dict[str, Any]]]:
    """Run ``orbslam-hgcn run`` processes ((argv, out folder) each) on the engine (inside
    its ``with`` block): (index, :func:`execute_run`'s result) as each ends; a task Ray
    could not run yields a result with its ``error``."""
    import orbslam_hgcn

    pythonpath = str(Path(orbslam_hgcn.__file__).resolve().parents[1])
    tasks = [{"program": list(RUN_PROGRAM), "argv": argv, "out": out, "pythonpath": pythonpath} for argv, out in argvs]
    for j, result in engine.imap_unordered(execute_run, tasks):
        if isinstance(result, TaskFailed):
            result = {"attempts": 2, "returncode": None, "error": f"task failed: {result}", "stats": None,
                      "killed": [], "process_wall_s": None}
        yield j, result


def finished_stats(out: str | Path) -> dict[str, Any] | None:
    """The stats of a run that completed (its stats.json says so), else None."""
    p = Path(out) / "stats.json"
    try:
        stats = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return stats if isinstance(stats, dict) and stats.get("complete", False) else None


def _signal_name(num: int) -> str:
    try:
        return signal.Signals(num).name
    except ValueError:
        return f"signal {num}"


def _last_error(log_path: Path) -> str:
    try:
        lines = [ln for ln in log_path.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    errors = [ln for ln in lines if "error" in ln.lower()]
    return (errors or lines or [""])[-1].strip()


def execute_run(task: dict[str, Any]) -> dict[str, Any]:
    """Run one ``orbslam-hgcn run`` process (the task of the engine). A process killed by
    a signal is started once more; the result says how it went: ``attempts``,
    ``returncode``, ``error`` (None when the run completed) and the run's ``stats``."""
    out = Path(task["out"])
    out.mkdir(parents=True, exist_ok=True)
    (out / "stats.json").unlink(missing_ok=True)  # a stale record of an earlier attempt
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (task["pythonpath"], env.get("PYTHONPATH")) if p)
    attempts, killed = 0, []
    rc = None
    t0 = time.perf_counter()
    while attempts < 2:
        attempts += 1
        with open(out / "run.log", "w", encoding="utf-8") as logf:
            rc = subprocess.run(task["program"] + task["argv"], stdout=logf, stderr=subprocess.STDOUT, env=env,
                                stdin=subprocess.DEVNULL).returncode
        if rc >= 0:
            break
        killed.append(_signal_name(-rc))
    wall = time.perf_counter() - t0
    stats = None
    try:
        stats = json.loads((out / "stats.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        pass
    error = None
    if rc is not None and rc < 0:
        error = f"run process killed ({', then '.join(killed)}) on both attempts"
    elif stats is None:
        error = _last_error(out / "run.log") or f"run exited with status {rc} without writing stats.json"
    elif not stats.get("complete", True):
        end = stats.get("end", {})
        error = f"ended early ({end.get('kind')}): {end.get('reason')}"
    return {"attempts": attempts, "returncode": rc, "error": error, "stats": stats, "killed": killed,
            "process_wall_s": wall}
