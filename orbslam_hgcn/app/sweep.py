"""Evaluation sweeps: sequences x vocabularies x parameter sets x runs (``orbslam-hgcn sweep``).

A manifest (YAML) lists the sequences, the vocabularies, the runs per cell and optional
parameter overrides::

    sequences:
      - {name: loop, path: data/synth/loop0}
      - {name: kitti00, path: ../shared/data/kitti00_first160/sequences/00, kind: kitti}
    vocabularies: [orb, hgcn]
    runs: 3
    sequential: false          # true: every run in sequential mode (reproducible)
    overrides: {}              # section.key: value, applied to every run

A sequence may also give ``camera`` (a camera/stage config file or a shipped camera name,
as ``run --config``) and ``max_frames``; ``max_frames`` and ``speed`` may also be given for
every sequence at the top level. ``params`` (optional) adds a parameter axis: a list of
``{name: NAME, overrides: {section.key: value}}``, each applied on top of ``overrides``.
Relative paths are taken from the manifest's folder. Every key is checked before anything
runs; an error names the manifest's line.

Each run is one ``orbslam-hgcn run`` in its own process, with its results (trajectories,
stats.json with the ATE, run.log) in ``OUT/<sequence>/<vocabulary>/<params>/run<k>/``
(``<params>`` is ``default`` without a parameter axis). The runs go through an
:class:`~orbslam_hgcn.engine.Engine`: a local Ray instance with ``jobs`` runs at a
time, an existing Ray cluster, or, without Ray, in order. A run whose stats.json says it
completed is not run again (a sweep resumes where it stopped); a run whose process is
killed (a signal) is run once more and then recorded as failed; any other failure is
recorded with its error and the other runs go on. Ctrl-C stops the sweep; the tables are
written for the runs that finished.

The tables (``OUT/sweep.md``, ``OUT/sweep.json``) hold one record per cell (sequence,
vocabulary, parameter set): runs, runs that count, failed runs, keyframe ATE after Sim(3)
alignment (median, min, max over the runs that count, metres in the JSON), share of
frames tracked and frames per second (medians), and every run. A run is marked failed as
``compare`` marks it (:func:`~orbslam_hgcn.app.compare.outcome_from_stats`: more than
10% of its frames without a pose, or a map reset): flagged X, left out of the figures.
One box plot of the ATE per sequence: ``OUT/sweep_ate_<sequence>.png``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shlex
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from orbslam_hgcn.config import load_yaml, resolve_config, section_from_yaml
from orbslam_hgcn.errors import ConfigError, Terminated, where
from orbslam_hgcn.app.compare import (
    MAX_UNTRACKED_SHARE, RunOutcome, check_sequence_path, check_vocabulary, outcome_from_stats, run_status, summarise,
)
from orbslam_hgcn.app.processes import finished_stats, run_argv, run_processes
from orbslam_hgcn.engine import Engine
from orbslam_hgcn.outputs import check_output_folder

log = logging.getLogger(__name__)

DEFAULT_PARAMS = "default"
TOP_KEYS = ("sequences", "vocabularies", "runs", "sequential", "speed", "max_frames", "overrides", "params")
SEQUENCE_KEYS = ("name", "path", "kind", "camera", "max_frames")
KINDS = ("tum", "euroc", "kitti", "folder", "video")


# --- The manifest ---------------------------------------------------------------------


@dataclass(frozen=True)
class SequenceSpec:
    name: str
    path: str  # absolute
    kind: str | None = None
    camera: str | None = None  # config file (absolute) or shipped camera name
    max_frames: int | None = None


@dataclass(frozen=True)
class ParamSet:
    name: str
    overrides: dict[str, Any] = field(default_factory=dict)  # "section.key" -> value


@dataclass(frozen=True)
class Manifest:
    path: str
    sequences: list[SequenceSpec]
    vocabularies: list[str]
    runs: int = 1
    sequential: bool = False
    speed: float | None = None
    params: list[ParamSet] = field(default_factory=lambda: [ParamSet(DEFAULT_PARAMS)])

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


class _Lines:
    """Line numbers of the manifest's nodes, by key path (for error messages)."""

    def __init__(self, text: str) -> None:
        try:
            self.root = yaml.compose(text)
        except yaml.YAMLError:
            self.root = None

    def line(self, *keys: str | int) -> int | None:
        node, line = self.root, None
        for k in keys:
            if node is None:
                break
            line = node.start_mark.line + 1
            nxt = None
            if isinstance(node, yaml.MappingNode):
                for kn, vn in node.value:
                    if kn.value == k:
                        nxt, line = vn, kn.start_mark.line + 1
                        break
            elif isinstance(node, yaml.SequenceNode) and isinstance(k, int) and k < len(node.value):
                nxt = node.value[k]
                line = nxt.start_mark.line + 1
            node = nxt
        if node is not None:
            line = node.start_mark.line + 1 if line is None else line
        return line


def _check_overrides(raw: Any, mpath: Path, lines: _Lines, *keys: str | int) -> dict[str, Any]:
    """``section.key: value`` pairs checked against the stage configs' dataclasses."""
    from orbslam_hgcn.runtime.system import Configs

    loc = where(mpath, lines.line(*keys))
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{loc}: overrides: expected a mapping of section.key: value, found {raw!r}")
    sections = {f.name: type(getattr(Configs(), f.name)) for f in dataclasses.fields(Configs)}
    out: dict[str, Any] = {}
    for key, value in raw.items():
        kloc = where(mpath, lines.line(*keys, key))
        section, _, name = str(key).partition(".")
        if not name or section not in sections:
            raise ConfigError(f"{kloc}: override {key!r}: expected section.key with section one of "
                              f"{', '.join(sections)}")
        try:
            section_from_yaml(sections[section], {section: {name: value}}, "overrides", section)
        except ConfigError as exc:
            msg = str(exc).removeprefix("overrides [").split("]: ", 1)[-1]
            raise ConfigError(f"{kloc}: override {key!r}: {msg}") from None
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{kloc}: override {key!r}: {exc}") from None
        out[str(key)] = value
    return out


def _positive_int(value: Any, loc: str, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{loc}: {what} must be a whole number of at least 1, found {value!r}")
    return value


def load_manifest(path: str | Path) -> Manifest:
    """Read and check a sweep manifest; any problem is a ConfigError naming its line."""
    mpath = Path(path)
    data = load_yaml(mpath)
    lines = _Lines(mpath.read_text(encoding="utf-8"))
    base = mpath.resolve().parent

    def at(*keys: str | int) -> str:
        return where(mpath, lines.line(*keys))

    for key in data:
        if key not in TOP_KEYS:
            raise ConfigError(f"{at(key)}: unknown key {key!r}; known keys: {', '.join(TOP_KEYS)}")
    raw_seqs = data.get("sequences")
    if not isinstance(raw_seqs, list) or not raw_seqs:
        raise ConfigError(f"{at('sequences') if 'sequences' in data else mpath}: sequences: give a list of "
                          "{name, path[, kind, camera, max_frames]}")
    top_frames = None
    if data.get("max_frames") is not None:
        top_frames = _positive_int(data["max_frames"], at("max_frames"), "max_frames")
    seqs: list[SequenceSpec] = []
    for i, s in enumerate(raw_seqs):
        if isinstance(s, str):
            s = {"path": s}
        if not isinstance(s, dict):
            raise ConfigError(f"{at('sequences', i)}: a sequence is a mapping {{name, path, ...}}, found {s!r}")
        for key in s:
            if key not in SEQUENCE_KEYS:
                raise ConfigError(f"{at('sequences', i, key)}: unknown sequence key {key!r}; known keys: "
                                  f"{', '.join(SEQUENCE_KEYS)}")
        if not s.get("path"):
            raise ConfigError(f"{at('sequences', i)}: sequence without a path")
        p = check_sequence_path(s["path"], base, at("sequences", i, "path"))
        name = str(s.get("name") or p.name)
        if not name or "/" in name or name.startswith("."):
            raise ConfigError(f"{at('sequences', i, 'name')}: bad sequence name {name!r} (it names a folder)")
        if any(q.name == name for q in seqs):
            raise ConfigError(f"{at('sequences', i, 'name')}: sequence name {name!r} given twice")
        kind = s.get("kind")
        if kind is not None and kind not in KINDS:
            raise ConfigError(f"{at('sequences', i, 'kind')}: kind must be one of {', '.join(KINDS)}, found {kind!r}")
        camera = s.get("camera")
        if camera is not None:
            cp = Path(str(camera)).expanduser()
            cp = cp if cp.is_absolute() else base / cp
            resolved = resolve_config(cp) if cp.is_file() else resolve_config(str(camera))
            if not Path(resolved).is_file():
                raise ConfigError(f"{at('sequences', i, 'camera')}: camera config not found: {camera}")
            camera = str(Path(resolved).resolve())
        frames = top_frames
        if s.get("max_frames") is not None:
            frames = _positive_int(s["max_frames"], at("sequences", i, "max_frames"), "max_frames")
        seqs.append(SequenceSpec(name, str(p.resolve()), kind, camera, frames))
    vocabs_raw = data.get("vocabularies", ["orb", "hgcn"])
    if isinstance(vocabs_raw, str):
        vocabs_raw = [vocabs_raw]
    if not isinstance(vocabs_raw, list) or not vocabs_raw:
        raise ConfigError(f"{at('vocabularies')}: vocabularies: give a list (orb, hgcn, kmeans, orb10k or files)")
    vocabs: list[str] = []
    for i, v in enumerate(vocabs_raw):
        ok = check_vocabulary(str(v), base, at("vocabularies", i))
        if any(Path(x).stem == Path(ok).stem for x in vocabs):
            raise ConfigError(f"{at('vocabularies', i)}: vocabulary {Path(ok).stem!r} given twice")
        vocabs.append(ok)
    runs = _positive_int(data.get("runs", 1), at("runs"), "runs")
    sequential = data.get("sequential", False)
    if not isinstance(sequential, bool):
        raise ConfigError(f"{at('sequential')}: sequential must be true or false, found {sequential!r}")
    speed = data.get("speed")
    if speed is not None:
        if isinstance(speed, bool) or not isinstance(speed, (int, float)) or not speed >= 0:
            raise ConfigError(f"{at('speed')}: speed must be a number >= 0, found {speed!r}")
        speed = float(speed)
    common = _check_overrides(data.get("overrides"), mpath, lines, "overrides")
    params = [ParamSet(DEFAULT_PARAMS, common)]
    if data.get("params") is not None:
        raw_params = data["params"]
        if not isinstance(raw_params, list) or not raw_params:
            raise ConfigError(f"{at('params')}: params: give a list of {{name, overrides}}")
        params = []
        for i, ps in enumerate(raw_params):
            if not isinstance(ps, dict) or not ps.get("name") or set(ps) - {"name", "overrides"}:
                raise ConfigError(f"{at('params', i)}: a parameter set is {{name: NAME, overrides: {{...}}}}")
            pname = str(ps["name"])
            if "/" in pname or pname.startswith(".") or any(q.name == pname for q in params):
                raise ConfigError(f"{at('params', i, 'name')}: bad or repeated parameter-set name {pname!r}")
            own = _check_overrides(ps.get("overrides"), mpath, lines, "params", i, "overrides")
            params.append(ParamSet(pname, {**common, **own}))
    return Manifest(str(mpath.resolve()), seqs, vocabs, runs, sequential, speed, params)


# --- Runs -----------------------------------------------------------------------------


@dataclass(frozen=True)
class RunSpec:
    """One run: its place in the sweep, its folder and its command line."""

    sequence: str
    vocab: str  # as the manifest gives it (a name or a file)
    params: str
    run: int
    out: str  # absolute
    argv: list[str]  # without the program: ["run", PATH, "--out", ...]

    @property
    def label(self) -> str:
        return Path(self.vocab).stem

    @property
    def rel(self) -> str:
        return f"{self.sequence}/{self.label}/{self.params}/run{self.run}"

    @property
    def command(self) -> str:
        return "orbslam-hgcn " + shlex.join(self.argv)


def _config_with_overrides(camera: str | None, overrides: dict[str, Any]) -> dict[str, Any]:
    data = dict(load_yaml(camera)) if camera else {}
    for key, value in overrides.items():
        section, _, name = key.partition(".")
        data[section] = {**(data.get(section) or {}), name: value}
    return data


def plan_runs(m: Manifest, out: str | Path) -> list[RunSpec]:
    """Every run of the sweep, in table order (sequence, vocabulary, parameter set, run);
    writes each cell's config file (camera config + overrides) where there are overrides."""
    out = Path(out).resolve()
    specs = []
    for s in m.sequences:
        for v in m.vocabularies:
            for ps in m.params:
                cell = out / s.name / Path(v).stem / ps.name
                config = s.camera
                if ps.overrides:
                    cell.mkdir(parents=True, exist_ok=True)
                    cfg = cell / "config.yaml"
                    cfg.write_text(yaml.safe_dump(_config_with_overrides(s.camera, ps.overrides), sort_keys=False),
                                   encoding="utf-8")
                    config = str(cfg)
                for k in range(1, m.runs + 1):
                    run_out = cell / f"run{k}"
                    argv = run_argv(s.path, run_out, v, s.kind, config, s.max_frames, m.sequential, m.speed)
                    specs.append(RunSpec(s.name, v, ps.name, k, str(run_out), argv))
    return specs


# --- Tables ---------------------------------------------------------------------------


@dataclass
class SweepRun:
    """One run's record: where it is in the sweep and its figures."""

    sequence: str
    params: str
    outcome: RunOutcome
    command: str
    attempts: int = 0  # processes started in this sweep (0: finished before, read back)

    def to_json(self) -> dict[str, Any]:
        d = {"sequence": self.sequence, "params": self.params, **dataclasses.asdict(self.outcome)}
        d["command"], d["attempts"] = self.command, self.attempts
        return d


@dataclass
class Sweep:
    manifest: Manifest
    runs: list[SweepRun]
    cells: list[dict[str, Any]]
    paths: dict[str, Path] = field(default_factory=dict)
    interrupted: bool = False
    executed: list[str] = field(default_factory=list)  # runs started by this sweep (rel paths)
    terminated: bool = False  # interrupted by SIGTERM rather than Ctrl-C
    engine: str = ""

    def to_json(self) -> dict[str, Any]:
        return {"manifest": self.manifest.to_json(), "engine": self.engine, "interrupted": self.interrupted,
                "cells": self.cells, "runs": [r.to_json() for r in self.runs]}


def outcome_of(spec: RunSpec, stats: dict[str, Any] | None, error: str | None, base: Path) -> RunOutcome:
    rel = str(Path(spec.out).relative_to(base)) if Path(spec.out).is_relative_to(base) else spec.out
    if error is None and stats is not None:
        return outcome_from_stats(spec.label, spec.run, Path(rel), stats)
    return RunOutcome(spec.label, spec.run, rel, ok=False, error=error or "not run")


def cell_records(m: Manifest, runs: list[SweepRun]) -> list[dict[str, Any]]:
    """One record per (sequence, vocabulary, parameter set), in the manifest's order."""
    cells = []
    for s in m.sequences:
        for v in m.vocabularies:
            for ps in m.params:
                label = Path(v).stem
                mine = [r.outcome for r in runs if r.sequence == s.name and r.params == ps.name
                        and r.outcome.vocab == label]
                if not mine:
                    continue
                summ = summarise(mine, [label])[label]
                ate, tracked, fps = summ["ate_rmse_m"], summ["tracked_share"], summ["fps"]
                cells.append({
                    "sequence": s.name, "vocabulary": label, "params": ps.name,
                    "runs": summ["runs"], "runs_ok": summ["ok"], "failed_runs": summ["runs"] - summ["ok"],
                    "failures": summ["failures"],
                    "ate_median_m": ate["median"], "ate_min_m": ate["min"], "ate_max_m": ate["max"],
                    "ate_values_m": ate["values"],
                    "tracked_share": tracked["median"], "fps": fps["median"],
                    "loops_closed": summ["loops_closed"]["median"],
                })
    return cells


def _mm(x: float | None) -> str:
    return "n/a" if x is None else f"{1000.0 * x:.2f}"


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100.0 * x:.1f}%"


def _fps(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def format_markdown(sw: Sweep) -> str:
    m = sw.manifest
    mode = "stages in order" if m.sequential else "stages on threads"
    lines = [
        "# Sweep",
        "",
        f"Manifest `{m.path}`: {len(m.sequences)} sequence(s) x {len(m.vocabularies)} vocabular(y/ies) x "
        f"{len(m.params)} parameter set(s) x {m.runs} run(s), loop closing on, {mode}. ATE: keyframe trajectory "
        "after Sim(3) alignment, RMSE per run; median, min and max over the runs that count.",
        "",
        "| sequence | vocabulary | params | runs ok | ATE median (mm) | ATE min (mm) | ATE max (mm) | "
        "tracked (median) | failed runs | fps (median) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in sw.cells:
        lines.append(f"| {c['sequence']} | {c['vocabulary']} | {c['params']} | {c['runs_ok']}/{c['runs']} | "
                     f"{_mm(c['ate_median_m'])} | {_mm(c['ate_min_m'])} | {_mm(c['ate_max_m'])} | "
                     f"{_pct(c['tracked_share'])} | {c['failed_runs']} | {_fps(c['fps'])} |")
    lines += [
        "",
        f"A run fails (X) when it stopped with an error, when more than {100 * MAX_UNTRACKED_SHARE:.0f}% of its "
        "frames have no pose, or when its map was reset; its ATE is shown but left out of the figures above.",
        "",
        "| sequence | vocabulary | params | run | ATE (mm) | tracked | resets | loops closed | fps | status |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sw.runs:
        o = r.outcome
        status, ate = run_status(o)
        tracked = o.tracked / o.frames if o.tracked is not None and o.frames else None
        lines.append(f"| {r.sequence} | {o.vocab} | {r.params} | {o.run} | {ate} | {_pct(tracked)} | "
                     f"{'n/a' if o.resets is None else o.resets} | "
                     f"{'n/a' if o.loops_closed is None else o.loops_closed} | {_fps(o.fps)} | "
                     f"{status.replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def write_tables(sw: Sweep, out: Path) -> None:
    from orbslam_hgcn.evaluation.plots import box_plot

    sw.paths = {"markdown": out / "sweep.md", "json": out / "sweep.json"}
    sw.paths["markdown"].write_text(format_markdown(sw), encoding="utf-8")
    sw.paths["json"].write_text(json.dumps(sw.to_json(), indent=2) + "\n", encoding="utf-8")
    for s in sw.manifest.sequences:
        cells = [c for c in sw.cells if c["sequence"] == s.name]
        if not cells:
            continue
        multi = len(sw.manifest.params) > 1
        groups = {(f"{c['vocabulary']}/{c['params']}" if multi else c["vocabulary"]):
                  [1000.0 * x for x in c["ate_values_m"]] for c in cells}
        path = out / f"sweep_ate_{s.name}.png"
        box_plot(groups, path, ylabel="keyframe ATE RMSE, Sim(3) (mm)",
                 title=f"{s.name}: {sw.manifest.runs} run(s) per cell")
        sw.paths[f"plot_{s.name}"] = path


def _running_medians(runs: list[SweepRun], names: Sequence[str]) -> str:
    parts = []
    for n in names:
        v = [r.outcome.ate_rmse_m for r in runs if r.sequence == n and r.outcome.counts
             and r.outcome.ate_rmse_m is not None]
        parts.append(f"{n} {1000 * float(np.median(v)):.2f} mm" if v else f"{n} n/a")
    return ", ".join(parts)


def run_sweep(
    manifest: str | Path | Manifest,
    out: str | Path,
    jobs: int = 1,
    address: str | None = None,
    use_ray: bool | None = None,
    progress: bool = True,
    on_run: Callable[[SweepRun], None] | None = None,
) -> Sweep:
    """Run every run of the manifest not finished yet, then write the tables (see the
    module text). on_run: called with each run's record as it ends (progress printing;
    an exception from it stops the sweep as Ctrl-C does). A Ctrl-C stops the sweep with
    ``interrupted`` set, after writing the tables of the runs that finished."""
    from tqdm import tqdm

    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    engine = Engine(jobs, address, use_ray)
    out = check_output_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    base = out.resolve()
    specs = plan_runs(m, base)
    records: dict[int, SweepRun] = {}
    todo = []
    for i, spec in enumerate(specs):
        stats = finished_stats(spec.out)
        if stats is not None:
            records[i] = SweepRun(spec.sequence, spec.params, outcome_of(spec, stats, None, base), spec.command)
        else:
            todo.append(i)
    if records:
        log.info("%d of %d runs finished before; running the other %d", len(records), len(specs), len(todo))
    executed: list[str] = []
    interrupted = terminated = False
    names = [s.name for s in m.sequences]
    bar = tqdm(total=len(specs), initial=len(records), desc="sweep", unit="run", disable=not progress)
    try:
        with engine:
            log.info("sweep: %d runs to make, %s", len(todo), engine.name)
            for j, result in run_processes([(specs[i].argv, specs[i].out) for i in todo], engine):
                spec = specs[todo[j]]
                executed.append(spec.rel)
                rec = SweepRun(spec.sequence, spec.params, outcome_of(spec, result["stats"], result["error"], base),
                               spec.command, result["attempts"])
                if rec.outcome.error:
                    log.warning("%s failed: %s", spec.rel, rec.outcome.error)
                records[todo[j]] = rec
                bar.update(1)
                bar.set_postfix_str(_running_medians(list(records.values()), names), refresh=True)
                if on_run is not None:
                    on_run(rec)
    except KeyboardInterrupt as exc:
        interrupted, terminated = True, isinstance(exc, Terminated)
        log.warning("sweep interrupted: writing the tables of the %d runs finished", len(records))
    finally:
        bar.close()
    runs = [records[i] for i in sorted(records)]
    sw = Sweep(m, runs, cell_records(m, runs), interrupted=interrupted, executed=executed, engine=engine.name,
               terminated=terminated)
    write_tables(sw, base)
    return sw
