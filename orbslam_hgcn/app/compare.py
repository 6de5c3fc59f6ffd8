"""Compare visual vocabularies end to end: the ``orbslam-hgcn compare`` command.

Runs the whole system (loop closing on) N times per vocabulary over one dataset through
:func:`~orbslam_hgcn.app.run.run_dataset`, each run in its own folder
``OUT/<vocab>/run<i>``, and summarises per vocabulary: keyframe ATE after Sim(3)
alignment (Umeyama 1991; median, min, max over the runs), loops closed, frames lost and
frames per second. Writes ``OUT/compare.md`` (Markdown tables), ``OUT/compare.json`` and
``OUT/compare_ate.png`` (a box plot of the ATE). With the stages run in order every run of
one vocabulary gives the same result (seeded RANSAC); repeated runs differ only when the
stages run on threads, through timing. A run that stopped with an error, or ended early
(its ``stats.json`` says ``"complete": false``), is recorded as failed with the reason and
the comparison goes on; a run interrupted (Ctrl-C, SIGTERM) ends the comparison, which
still writes its files for the runs made.

A run that leaves more than :data:`MAX_UNTRACKED_SHARE` of its frames without a pose, or
resets its map, counts as failed, as ORB-SLAM's tables mark such runs: its ATE is still
shown per run, flagged, but it is left out of the vocabulary's ATE median, min and max, so
no headline figure comes from a sliver of the sequence.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from orbslam_hgcn.app.processes import run_argv, run_processes
from orbslam_hgcn.config import ThreadsConfig
from orbslam_hgcn.datasets import detect_kind
from orbslam_hgcn.engine import Engine
from orbslam_hgcn.errors import ConfigError, OrbslamError, Terminated
from orbslam_hgcn.outputs import check_output_folder

log = logging.getLogger(__name__)

RunFn = Callable[..., Any]

# A run that leaves more than this share of its frames without a pose has failed.
MAX_UNTRACKED_SHARE = 0.10


@dataclass
class RunOutcome:
    """One run: the figures read back from its ``stats.json`` (None when it failed)."""

    vocab: str
    run: int
    out: str
    ok: bool
    error: str | None = None
    ate_rmse_m: float | None = None  # keyframes, Sim(3); None when not available
    ate_error: str | None = None  # why the ATE is not available
    loops_closed: int | None = None
    frames: int | None = None
    frames_lost: int | None = None
    wall_s: float | None = None
    fps: float | None = None
    tracked: int | None = None  # frames with a pose in the final map
    resets: int | None = None  # map resets
    dropped: int | None = None  # frames dropped unprocessed (behind the camera)
    failed: str | None = None  # why the run counts as failed (too few frames tracked, a reset)

    @property
    def counts(self) -> bool:
        """Whether the run's ATE counts in the summary (it ran and did not fail)."""
        return self.ok and self.failed is None


@dataclass
class Comparison:
    """Every run, the per-vocabulary summary and the files written."""

    dataset: dict[str, Any]
    runs: list[RunOutcome]
    summary: dict[str, dict[str, Any]]
    paths: dict[str, Path] = field(default_factory=dict)
    interrupted: bool = False  # a run was interrupted and the comparison stopped there
    terminated: bool = False  # by SIGTERM rather than Ctrl-C

    def to_json(self) -> dict[str, Any]:
        return {"dataset": self.dataset, "summary": self.summary, "runs": [asdict(r) for r in self.runs]}


def outcome_from_stats(vocab: str, run: int, out: Path, stats: dict[str, Any]) -> RunOutcome:
    """The figures of one finished run from its stats dict (as written to stats.json)."""
    ate = stats.get("ate_sim3", {}).get("keyframes", {})
    f = stats["frames"]
    frames = int(f["frames"])
    wall = float(stats["wall_s"])
    tracked, resets = int(f["tracked"]), int(stats.get("map_resets", 0))
    reasons = []
    if frames - tracked > MAX_UNTRACKED_SHARE * frames:
        reasons.append(f"{frames - tracked} of {frames} frames without a pose")
    if resets:
        reasons.append(f"{resets} map reset(s)")
    return RunOutcome(
        vocab=vocab, run=run, out=str(out), ok=True,
        ate_rmse_m=float(ate["rmse_m"]) if "rmse_m" in ate else None,
        ate_error=None if "rmse_m" in ate else ate.get("error", "no ground truth"),
        loops_closed=len(stats.get("loop_closing", {}).get("loops", [])),
        frames=frames, frames_lost=int(f["lost"]), wall_s=wall,
        fps=frames / wall if wall > 0 else None,
        tracked=tracked, resets=resets, dropped=int(f.get("dropped", 0)),
        failed="; ".join(reasons) or None,
    )  # fmt: skip


def check_vocabulary(v: str, base: Path, loc: str = "--vocabs") -> str:
    """The vocabulary argument of a run: a shipped name, or an absolute file path (relative
    ones from ``base``); a ConfigError at ``loc`` when it is neither."""
    from orbslam_hgcn.vocabulary.loading import SHIPPED

    if v in SHIPPED:
        return v
    p = Path(v).expanduser()
    p = p if p.is_absolute() else base / p
    if not p.is_file():
        raise ConfigError(f"{loc}: unknown vocabulary {v!r}: not a shipped one ({', '.join(SHIPPED)}) nor a file")
    return str(p)


def check_sequence_path(raw: str | Path, base: Path, loc: str = "PATH") -> Path:
    """A sequence's path (relative ones from ``base``), which must exist; a ConfigError at
    ``loc`` when it does not."""
    p = Path(str(raw)).expanduser()
    p = p if p.is_absolute() else base / p
    if not p.exists():
        raise ConfigError(f"{loc}: sequence path not found: {p}")
    return p


def _spread(values: list[float]) -> dict[str, Any]:
    if not values:
        return {"median": None, "min": None, "max": None, "values": []}
    v = np.asarray(values, dtype=np.float64)
    return {"median": float(np.median(v)), "min": float(v.min()), "max": float(v.max()), "values": list(values)}


def summarise(runs: list[RunOutcome], vocabs: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Per vocabulary: runs, runs that count (ran and did not fail), failures, and
    median/min/max of ATE (over the runs that count), loops, frames lost, fps."""
    out: dict[str, dict[str, Any]] = {}
    for v in vocabs:
        mine = [r for r in runs if r.vocab == v]
        ok = [r for r in mine if r.ok]
        good = [r for r in ok if r.counts]
        out[v] = {
            "runs": len(mine),
            "ok": len(good),
            "failures": [{"run": r.run, "error": r.error or r.failed} for r in mine if not r.counts],
            "ate_rmse_m": _spread([r.ate_rmse_m for r in good if r.ate_rmse_m is not None]),
            "tracked_share": _spread([r.tracked / r.frames for r in ok if r.tracked is not None and r.frames]),
            "loops_closed": _spread([r.loops_closed for r in ok]),
            "frames_lost": _spread([r.frames_lost for r in ok]),
            "fps": _spread([r.fps for r in ok if r.fps is not None]),
        }
    return out


def run_status(r: RunOutcome) -> tuple[str, str]:
    """(status, ATE cell in mm) of a run for the tables: "ok", "X failed: <error>" when it
    stopped with an error, "X failed: <why>" when it ran but fails the bar (its ATE then
    flagged "(X)"), "ok (no ATE: <why>)"."""
    status = "ok" if r.ok else f"X failed: {r.error}"
    if r.ok and r.failed:
        status = f"X failed: {r.failed}"
    elif r.ok and r.ate_rmse_m is None:
        status = f"ok (no ATE: {r.ate_error})"
    return status, _mm(r.ate_rmse_m) + (" (X)" if r.ok and r.failed and r.ate_rmse_m is not None else "")


def _mm(x: float | None) -> str:
    return "n/a" if x is None else f"{1000.0 * x:.2f}"


def _num(x: float | None, fmt: str = "{:g}") -> str:
    return "n/a" if x is None else fmt.format(x)


def describe_run(r: RunOutcome) -> str:
    """One line on one run (ATE, loops, frames lost, fps, or why it failed)."""
    head = f"{r.vocab} run {r.run}"
    if not r.ok:
        return f"{head}: FAILED: {r.error}"
    ate = f"ATE {_mm(r.ate_rmse_m)} mm (keyframes, Sim(3))" if r.ate_rmse_m is not None else f"no ATE ({r.ate_error})"
    line = (f"{head}: {ate}, {r.loops_closed} loop(s) closed, {_tracked(r)} of frames tracked, "
            f"{r.frames_lost} of {r.frames} frames lost, {_num(r.fps, '{:.1f}')} fps")
    if r.failed:
        line += f"; FAILED ({r.failed}): its ATE does not count"
    return line


def _tracked(r: RunOutcome) -> str:
    return "n/a" if r.tracked is None or not r.frames else f"{100.0 * r.tracked / r.frames:.1f}%"


def _stages_text(threads: dict[str, Any] | None) -> str:
    """How the stages ran, for the comparison's heading (empty when unknown)."""
    if not threads:
        return ""
    if threads.get("sequential"):
        return ", stages in order"
    speed = threads.get("speed")
    if speed is None:
        return ", stages on threads"
    if speed > 0:
        return f", stages on threads, frames taken at {speed:g}x the rate of their timestamps"
    return ", stages on threads, frames taken as fast as processed"


def format_markdown(c: Comparison) -> str:
    """The summary table (one row per vocabulary) and the table of every run."""
    d = c.dataset
    lines = [
        f"# Vocabulary comparison: {d['name']}",
        "",
        f"Dataset `{d['path']}` ({d['kind']}), {d['max_frames'] or 'all'} frames, {d['runs']} run(s) per vocabulary, "
        f"loop closing on{_stages_text(d.get('threads'))}. ATE: keyframe trajectory after Sim(3) alignment, RMSE per run.",
        "",
        "| vocabulary | runs ok | ATE median (mm) | ATE min (mm) | ATE max (mm) | loops closed (median) | "
        "frames lost (median) | fps (median) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for v, s in c.summary.items():
        a = s["ate_rmse_m"]
        lines.append(
            f"| {v} | {s['ok']}/{s['runs']} | {_mm(a['median'])} | {_mm(a['min'])} | {_mm(a['max'])} | "
            f"{_num(s['loops_closed']['median'])} | {_num(s['frames_lost']['median'])} | "
            f"{_num(s['fps']['median'], '{:.2f}')} |"
        )
    lines += [
        "",
        f"Runs ok: runs that neither stopped with an error nor failed. A run fails (X) when more than "
        f"{100 * MAX_UNTRACKED_SHARE:.0f}% of its frames have no pose or its map was reset; its ATE is shown but "
        "left out of the figures above.",
        "",
        "| vocabulary | run | ATE (mm) | loops closed | frames | frames lost | fps | status | tracked | resets |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in c.runs:
        status, ate = run_status(r)
        lines.append(
            f"| {r.vocab} | {r.run} | {ate} | {_num(r.loops_closed)} | {_num(r.frames)} | "
            f"{_num(r.frames_lost)} | {_num(r.fps, '{:.2f}')} | {status.replace('|', '/')} | {_tracked(r)} | "
            f"{_num(r.resets)} |"
        )
    return "\n".join(lines) + "\n"


def _runs_on_engine(path, out, kind, config, runs, vocabs, max_frames, sequential, speed, jobs, address, on_run):
    """The runs of a comparison as processes on the sweep's engine: (outcomes in table
    order, dataset name, how the stages ran, interrupted)."""
    if config is not None:
        from orbslam_hgcn.config import resolve_config

        config = Path(resolve_config(config)).resolve() if Path(resolve_config(config)).is_file() else config
    plan = [(v, i, (out / Path(v).stem / f"run{i}").resolve()) for v in vocabs for i in range(1, runs + 1)]
    argvs = [(run_argv(Path(path).resolve(), o, v if not Path(v).is_file() else str(Path(v).resolve()), kind, config,
                       max_frames, sequential, speed), str(o)) for v, _, o in plan]
    found: dict[int, RunOutcome] = {}
    name, threads, interrupted, terminated = Path(path).name, None, False, False
    try:
        with Engine(jobs, address) as engine:
            for j, result in run_processes(argvs, engine):
                v, i, o = plan[j]
                stats = result["stats"]
                if stats is not None:
                    name = stats.get("dataset", {}).get("name", name)
                    threads = threads or stats.get("threads")
                if result["error"] is None and stats is not None:
                    found[j] = outcome_from_stats(v, i, o, stats)
                else:
                    found[j] = RunOutcome(v, i, str(o), ok=False, error=result["error"])
                if on_run is not None:
                    on_run(found[j])
    except KeyboardInterrupt as exc:
        interrupted, terminated = True, isinstance(exc, Terminated)
    return [found[j] for j in sorted(found)], name, threads, interrupted, terminated


def run_comparison(
    path: str | Path,
    out: str | Path,
    kind: str | None = None,
    config: str | Path | None = None,
    runs: int = 5,
    vocabs: Sequence[str] = ("orb", "hgcn"),
    max_frames: int | None = None,
    progress: bool = True,
    rerun_first: Sequence[str] | None = None,
    sequential: bool = False,
    speed: float | None = None,
    run_fn: RunFn | None = None,
    on_run: Callable[[RunOutcome], None] | None = None,
    jobs: int | None = None,
    address: str | None = None,
) -> Comparison:
    """Run every vocabulary ``runs`` times over the dataset at ``path`` (loop closing on)
    and write compare.md, compare.json and compare_ate.png into ``out``.

    rerun_first: ``--rerun`` tokens for the first run only (e.g. ``["save", "x.rrd"]``),
    used when :func:`run_dataset` accepts a ``rerun`` argument. sequential: run the stages
    in order (then every run of a vocabulary gives the same figures). speed: threaded runs
    take frames no faster than this many times their timestamps' rate (None: the config's
    ``threads.speed``; see :func:`run_dataset`). run_fn: replaces
    :func:`run_dataset` (same arguments), for tests. on_run: called with each run's
    outcome as soon as it is known (progress printing). jobs, address: make each run an
    ``orbslam-hgcn run`` process on the sweep's engine (:mod:`orbslam_hgcn.app.sweep`:
    a local Ray instance with ``jobs`` runs at a time, the Ray cluster at ``address``, or in
    order without Ray), the same folders and tables; a killed run is made once more.
    """
    import inspect

    from orbslam_hgcn.evaluation.plots import box_plot
    from orbslam_hgcn.app.run import run_dataset

    if runs < 1:
        raise ConfigError(f"--runs must be at least 1, found {runs}")
    if not vocabs:
        raise ConfigError("--vocabs: give at least one vocabulary (orb, hgcn or a file)")
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"--max-frames must be at least 1, found {max_frames}")
    if jobs is not None and jobs < 1:
        raise ConfigError(f"--jobs must be at least 1, found {jobs}")
    if speed is not None:
        ThreadsConfig(speed=speed)  # a bad value is a ConfigError here, not in every run
    # The sequence, the vocabularies and the output folder are checked as a sweep checks its
    # manifest, before the first run.
    check_sequence_path(path, Path.cwd())
    if kind is None:
        detect_kind(path)  # a folder that holds no sequence fails here, not in every run
    vocabs = [check_vocabulary(v, Path.cwd()) for v in vocabs]
    check_output_folder(out)
    run_fn = run_fn or run_dataset
    params = inspect.signature(run_fn).parameters
    accepts_rerun = "rerun" in params
    common: dict[str, Any] = {"sequential": True} if sequential and "sequential" in params else {}
    if speed is not None and "speed" in params:
        common["speed"] = speed
    if rerun_first is not None and not accepts_rerun:
        log.warning("this build records no rerun visualisation of runs; --rerun ignored")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    outcomes: list[RunOutcome] = []
    name = Path(path).name
    threads: dict[str, Any] | None = None  # how the stages ran, from the first run's stats
    interrupted = terminated = False
    if jobs is not None or address is not None:
        if rerun_first is not None:
            raise ConfigError("--jobs/--address make each run in its own process: no rerun recording there")
        outcomes, name, threads, interrupted, terminated = _runs_on_engine(
            path, out, kind, config, runs, vocabs, max_frames, sequential, speed, 1 if jobs is None else jobs, address,
            on_run)
    for v in vocabs if jobs is None and address is None else ():
        for i in range(1, runs + 1):
            if interrupted:
                break
            run_out = out / Path(v).stem / f"run{i}"
            kw: dict[str, Any] = dict(common)
            if accepts_rerun and rerun_first is not None and not outcomes:
                kw["rerun"] = list(rerun_first)
            log.info("vocabulary %s, run %d of %d -> %s", v, i, runs, run_out)
            try:
                report = run_fn(path, run_out, kind=kind, config=config, max_frames=max_frames, loop_closing=True,
                                progress=progress, vocab=v, **kw)
                stats = json.loads(Path(report.paths["stats"]).read_text(encoding="utf-8"))
                name = stats.get("dataset", {}).get("name", name)
                threads = threads or stats.get("threads")
                end = stats.get("end", {})
                if stats.get("complete", True):
                    outcomes.append(outcome_from_stats(v, i, run_out, stats))
                else:
                    error = f"ended early ({end.get('kind')}): {end.get('reason')}"
                    outcomes.append(RunOutcome(v, i, str(run_out), ok=False, error=error))
                    interrupted = end.get("kind") in ("interrupted", "terminated")
                    terminated = end.get("kind") == "terminated"
            except KeyboardInterrupt as exc:  # outside the run's own handling (setting up, between frames)
                interrupted, terminated = True, isinstance(exc, Terminated)
                outcomes.append(RunOutcome(v, i, str(run_out), ok=False, error="interrupted"))
            except OrbslamError as exc:  # a failed run is reported in the table; the others go on
                log.warning("vocabulary %s, run %d failed: %s", v, i, exc)
                outcomes.append(RunOutcome(v, i, str(run_out), ok=False, error=str(exc)))
            except Exception as exc:  # a crash too, with its traceback in the log
                log.exception("vocabulary %s, run %d failed", v, i)
                outcomes.append(RunOutcome(v, i, str(run_out), ok=False, error=f"{type(exc).__name__}: {exc}"))
            if on_run is not None:
                on_run(outcomes[-1])
    dataset = {"path": str(path), "kind": kind or "auto", "name": name, "max_frames": max_frames, "runs": runs,
               "config": str(config) if config else None, "threads": threads}
    comp = Comparison(dataset, outcomes, summarise(outcomes, list(vocabs)), interrupted=interrupted,
                      terminated=terminated)
    md = format_markdown(comp)
    comp.paths = {"markdown": out / "compare.md", "json": out / "compare.json", "plot": out / "compare_ate.png"}
    comp.paths["markdown"].write_text(md, encoding="utf-8")
    comp.paths["json"].write_text(json.dumps(comp.to_json(), indent=2) + "\n", encoding="utf-8")
    groups = {v: [1000.0 * x for x in s["ate_rmse_m"]["values"]] for v, s in comp.summary.items()}
    box_plot(groups, comp.paths["plot"], ylabel="keyframe ATE RMSE, Sim(3) (mm)",
             title=f"{name}: {runs} run(s) per vocabulary")
    return comp
