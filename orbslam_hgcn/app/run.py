"""Run the system over a dataset and write its results: the ``orbslam-hgcn run`` command.

Writes into the output folder ``KeyFrameTrajectory.txt`` and ``CameraTrajectory.txt``
(TUM format, ``T_wc``, as ORB-SLAM writes them) and ``stats.json`` (frame counts, tracking
events, per-stage timings and, when the dataset has ground truth, the ATE after Sim(3)
alignment, Umeyama 1991, as monocular scale is unobservable).

A run never loses what it computed: whatever ends it (an unreadable frame with
``--on-bad-frame stop``, a worker thread or child process failing, Ctrl-C, SIGTERM, a bug)
the results of the frames processed are written, ``stats.json`` says ``"complete": false``
and why (``"end"``), and the command exits with the status of that ending
(:data:`~orbslam_hgcn.app.ending.EXIT_STATUS`). The output folder is checked before the first frame.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from orbslam_hgcn.config import VocabularyConfig, dataset_settings, load_camera, load_yaml, resolve_config
from orbslam_hgcn.datasets import detect_kind, open_sequence
from orbslam_hgcn.errors import FrameError, OrbslamError, StageError, VocabularyError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.app.ending import RunEnd
from orbslam_hgcn.outputs import check_output_file, check_output_folder
from orbslam_hgcn.runtime.system import TERMINATED, Configs, System
from orbslam_hgcn.trajectory import Trajectory
from orbslam_hgcn.viz.sinks import parse_rerun_arg

log = logging.getLogger(__name__)

# The vocabulary of a run without --vocab: the arm that won the place-recognition ablation
# (bench/bench_track_words.py; README "Shipped vocabularies"): k-means words of lone
# descriptors. Neither the shipped HGCN (its network is in effect the identity) nor the
# track network over map points beat it there. The vocabulary config's default kind.
DEFAULT_VOCAB = VocabularyConfig.kind

CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")

def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


@dataclass
class RunReport:
    """What a run produced: output files, stats, ATE figures (None without ground truth),
    and how it ended."""

    paths: dict[str, Path]
    stats: dict[str, Any]
    ate: dict[str, Any] = field(default_factory=dict)
    interrupted: bool = False
    end: RunEnd = field(default_factory=RunEnd)

    @property
    def complete(self) -> bool:
        return self.end.complete

    @property
    def exit_status(self) -> int:
        return self.end.exit_status


def camera_from_config(path: str | Path | None) -> PinholeCamera | None:
    """The camera of a config file when it holds one (flat keys or a ``camera:`` section)."""
    if path is None:
        return None
    data = load_yaml(path)
    section = data.get("camera") if isinstance(data.get("camera"), dict) else data
    if any(k in section for k in CAMERA_KEYS):
        return load_camera(path)
    return None


def camera_source(path: str | Path, kind: str, config: str | Path | None) -> str:
    """Where the camera of a run comes from: ``config`` (--config, when it holds a camera),
    else the dataset's own calibration (a TUM folder's ``camera.yaml``, else its folder
    name; KITTI's ``calib.txt``; EuRoC's ``sensor.yaml``)."""
    if config is not None:
        return str(config)
    p = Path(path).expanduser()
    kind = kind.lower()
    if kind == "tum":
        if (p / "camera.yaml").is_file():
            return str(p / "camera.yaml")
        from orbslam_hgcn.datasets.tum import infer_tum_camera

        name = infer_tum_camera(p.resolve())
        return f"{name} (from the folder name)" if name else "the dataset"
    if kind == "kitti":
        return str(p / "calib.txt")
    if kind == "euroc":
        return "the dataset's sensor.yaml"
    return "the dataset"


def settings_source(camera: PinholeCamera, settings_path: Path | None, kind: str) -> str | None:
    """How the shipped stage settings of a run were chosen (see
    :func:`~orbslam_hgcn.config.dataset_settings`): ``"camera"`` when the shipped config has
    the run's camera, ``"kind"`` when it is the default of the dataset kind's family (the
    camera matches no shipped config), None when there are none."""
    if settings_path is None:
        return None
    matched, _ = dataset_settings(camera, None)  # without a kind: a camera match only
    return "camera" if matched == settings_path else "kind"


def settings_line(camera_origin: str, settings_path: Path | None, chosen_by: str | None,
                  config: str | Path | None) -> str:
    """The log line that says where a run's camera and stage settings come from."""
    line = f"camera from {camera_origin}; "
    if settings_path is None:
        line += "stage settings: the defaults"
    elif chosen_by == "camera":
        line += f"stage settings of {settings_path.stem} (its camera is this camera)"
    else:
        line += (f"stage settings of {settings_path.stem} (the defaults for this kind of dataset: the camera "
                 "matches no shipped config)")
    return line + (f", then {config}" if config is not None else "")


def trajectory_ate(gt: Trajectory, est: Trajectory) -> dict[str, Any]:
    """ATE of ``est`` after Sim(3) alignment: rmse/mean/median/max (m), pairs, scale; or
    {"error": reason} when it cannot be computed."""
    from orbslam_hgcn.evaluation.ate import evaluate

    if len(est) < 3:
        return {"error": f"only {len(est)} poses estimated"}
    try:
        r = evaluate(gt, est, align="sim3")
    except OrbslamError as exc:
        return {"error": str(exc)}
    return {
        "rmse_m": r.ate.rmse,
        "mean_m": r.ate.mean,
        "median_m": r.ate.median,
        "max_m": r.ate.max,
        "pairs": r.num_pairs,
        "scale": r.scale,
    }


def open_vocabulary(vocab: str | None, loop_closing: bool) -> Any:
    """The vocabulary of a run: ``vocab`` is a shipped name (``orb``, ``hgcn``, ``kmeans``, ...),
    a vocabulary file, or ``none``; None means :data:`DEFAULT_VOCAB`. Without loop closing a
    missing default only costs relocalisation (a warning); otherwise it is an error."""
    from orbslam_hgcn.vocabulary import load_vocabulary

    name = vocab or DEFAULT_VOCAB
    if name == "none":
        if loop_closing:
            raise OrbslamError("loop closing needs a vocabulary: use --vocab orb|hgcn|kmeans|orb10k|FILE, or --no-loop")
        return None
    try:
        return load_vocabulary(name)
    except VocabularyError as exc:
        if vocab is None and not loop_closing:
            log.warning("%s; running without a vocabulary (no relocalisation)", exc)
            return None
        raise


def run_dataset(
    path: str | Path,
    out: str | Path,
    kind: str | None = None,
    config: str | Path | None = None,
    max_frames: int | None = None,
    loop_closing: bool = False,
    progress: bool = True,
    vocab: str | None = None,
    rerun: Sequence[str] | None = None,
    load_map: str | Path | None = None,
    save_map: str | Path | None = None,
    localization: bool = False,
    sequential: bool = False,
    speed: float | None = None,
    on_bad_frame: str = "skip",
    drop_late: bool = False,
) -> RunReport:
    """Open a dataset, run the system over it, write the results into ``out``.

    Bad input (arguments, config, dataset listing, an output folder that is a file or
    cannot be written) raises an OrbslamError before the first frame. After that the run
    always writes its results and returns; ``RunReport.end`` says how it ended (see the
    module text). ``on_bad_frame``: ``skip`` (default) skips a frame whose image cannot be
    read, with a warning, and counts it; ``stop`` ends the run on it.

    ``sequential``: local mapping and loop closing in order after each frame (reproducible
    results) instead of in worker threads. ``speed``: threaded runs take frames no faster
    than this many times the rate of their timestamps (0: as fast as they are processed);
    None: ``threads.speed`` of the config (default 1). ``drop_late``: a paced threaded run
    drops the frames that wait longer than ``threads.frame_buffer_s`` (a live source), as
    ``threads.drop_late: true`` of the config does; otherwise every frame is processed.

    ``rerun``: the ``--rerun`` tokens (``["spawn"]``, ``["save", "FILE.rrd"]``,
    ``["connect", "HOST:PORT"]``) to visualise the run in rerun as it goes
    (:mod:`orbslam_hgcn.viz.live`); None: no visualisation.

    ``load_map``: start from a saved map (:mod:`orbslam_hgcn.app.mapfile`),
    relocalising on it first; ``vocab`` then defaults to the map's vocabulary.
    ``localization``: with ``load_map``, track without changing the map. ``save_map``:
    write the map at the end (also listed in ``paths`` as ``map``).
    """
    rerun_sink = parse_rerun_arg(rerun) if rerun is not None else None
    if on_bad_frame not in ("skip", "stop"):
        raise OrbslamError(f"--on-bad-frame must be skip or stop, found {on_bad_frame!r}")
    if max_frames is not None and max_frames < 1:
        raise OrbslamError(f"--max-frames must be at least 1, found {max_frames}")
    out = check_output_folder(out)
    if save_map is not None:
        save_map = check_output_file(save_map, "--save-map")
    if config is not None:
        config = resolve_config(config)  # a path, or a shipped camera name such as tum_fr3
    user_layer = load_yaml(config) if config is not None else {}
    Configs.from_layers([(user_layer, config or "")])  # a bad --config fails before the dataset is read
    camera = camera_from_config(config)
    sequence = open_sequence(kind, path, camera)
    dataset_kind = kind or detect_kind(path)
    settings_path, settings = dataset_settings(sequence.camera, dataset_kind)
    camera_origin = camera_source(path, dataset_kind, config if camera is not None else None)
    settings_origin = settings_source(sequence.camera, settings_path, dataset_kind)
    log.info("%s", settings_line(camera_origin, settings_path, settings_origin, config))
    configs = Configs.from_layers([(settings, settings_path or ""), (user_layer, config or "")])
    if speed is not None:
        configs = dataclasses.replace(configs, threads=dataclasses.replace(configs.threads, speed=speed))
    if drop_late:
        configs = dataclasses.replace(configs, threads=dataclasses.replace(configs.threads, drop_late=True))
    if max_frames is not None and max_frames < 1:
        raise OrbslamError(f"--max-frames must be at least 1, found {max_frames}")
    if localization and load_map is None:
        raise OrbslamError("--localization needs a saved map: --load-map FILE")
    if load_map is not None:
        from orbslam_hgcn.app.mapfile import install_map, load_map as read_saved_map, map_vocabulary_name

        vocab = vocab or map_vocabulary_name(load_map)  # by default the vocabulary the map was built with
    vocabulary = open_vocabulary(vocab, loop_closing or load_map is not None)
    if not loop_closing:
        configs = dataclasses.replace(configs, loop_closing=dataclasses.replace(configs.loop_closing, enabled=False))
    system = System(sequence.camera, configs, vocabulary=vocabulary, sequential=sequential)
    if load_map is not None:
        install_map(system, read_saved_map(load_map, vocabulary).map, localization)
    log.info("%s: %d frames, camera %s", sequence.name, len(sequence), sequence.camera.name)
    viz = None
    if rerun_sink is not None:
        from orbslam_hgcn.viz.live import attach_live_viz

        viz = attach_live_viz(system, *rerun_sink, out=out, config=config, name=sequence.name)
    end, crash = RunEnd(), None
    t_run = time.perf_counter()
    from tqdm.contrib.logging import logging_redirect_tqdm  # 40 ms of imports: not before it is needed

    with logging_redirect_tqdm():
        try:
            summary = system.run(sequence, max_frames, progress=progress, on_bad_frame=on_bad_frame)
            if summary.interrupted:
                end_kind = "terminated" if summary.stop_reason == TERMINATED else "interrupted"
                end = RunEnd(end_kind, summary.stop_reason or end_kind)
        except FrameError as exc:
            end = RunEnd("bad_frame", _first_line(exc), frame=exc.frame)
        except StageError as exc:
            end = RunEnd("stage_failed", _first_line(exc), stage=exc.stage)
        except Exception as exc:  # noqa: BLE001 - a bug: the results so far are still written
            crash = traceback.format_exc()
            end = RunEnd("internal_error", f"{type(exc).__name__}: {_first_line(exc)}")
        finally:
            if viz is not None:
                try:
                    viz.finish(system)
                except Exception as exc:  # noqa: BLE001 - the run's own results come first
                    log.warning("rerun recording not finished: %s", exc)
    wall_s = time.perf_counter() - t_run
    if not end.complete:
        log.warning("the run ended early (%s): %s; writing the results of the frames processed", end.kind,
                    end.reason)  # fmt: skip
    camera = system.camera_trajectory()
    ate: dict[str, Any] = {}
    if sequence.ground_truth is not None and len(sequence.ground_truth) >= 3:
        ate = {
            "keyframes": trajectory_ate(sequence.ground_truth, system.keyframe_trajectory()),
            "camera": trajectory_ate(sequence.ground_truth, camera),
        }
    extra = {
        "dataset": {"path": str(path), "kind": kind or "auto", "name": sequence.name, "frames": len(sequence)},
        "settings": {
            "camera": camera_origin,
            "dataset": settings_path.stem if settings_path is not None else None,
            "dataset_chosen_by": settings_origin,
            "config": str(config) if config is not None else None,
            "orb_features": configs.orb.n_features,
        },
        "vocabulary": repr(vocabulary) if vocabulary is not None else None,
        "complete": end.complete,
        "end": end.to_json(),
        "interrupted": end.kind in ("interrupted", "terminated"),
        "on_bad_frame": on_bad_frame,
        "wall_s": wall_s,
        "ate_sim3": ate,
        "map_file": {"loaded": str(load_map) if load_map else None, "localization": localization},
    }
    if viz is not None:
        extra["rerun"] = viz.summary()
    try:
        paths = system.save(out, extra, camera)
        if crash is not None:
            paths["traceback"] = out / "traceback.txt"
            paths["traceback"].write_text(crash, encoding="utf-8")
    except OSError as exc:
        raise OrbslamError(f"{out}: cannot write the results ({exc.strerror or exc})") from None
    if save_map is not None:
        from orbslam_hgcn.app.mapfile import save_system_map

        try:
            paths["map"] = save_system_map(save_map, system, vocab)
        except (OrbslamError, OSError) as exc:
            if end.complete:
                raise
            log.warning("map not saved after the run ended early: %s", exc)
    stats = system.stats()
    stats.update(extra)
    return RunReport(paths, stats, ate, extra["interrupted"], end)


def _real_time_line(rt: dict[str, Any]) -> str:
    """How the run kept up with its camera (System.real_time)."""
    rtf = rt.get("real_time_factor")
    line = "real time: " + (f"{rtf:.2f}x the camera's rate" if rtf is not None else "n/a")
    lag = rt.get("lag_ms", {})
    if lag.get("count"):
        line += f", lag behind the camera p95 {lag['p95']:.0f} ms, max {lag['max']:.0f} ms"
    lat = rt.get("latency_ms", {})
    if lat.get("count"):
        line += f"; frame latency p95 {lat['p95']:.0f} ms"
    return line


def _timing_line(what: str, t: dict[str, Any], of: str, fmt: str) -> str:
    """``what: median, p95, mean`` of a timing summary; says so when it holds no sample."""
    if not t["count"]:
        return f"{what}: no {of}, no timing"
    return f"{what}: median {t['median']:{fmt}}, p95 {t['p95']:{fmt}}, mean {t['mean']:{fmt}}"


def _why_no_pose(events: list[dict[str, Any]]) -> str:
    """Why no frame has a pose in the final map, from the run's events: never initialised,
    or initialised and then reset (with the reason the tracker gave)."""
    inits = [e for e in events if e["event"] == "initialized"]
    if not inits:
        return "the map was never initialised (too little parallax or texture)"
    parts = []
    for e in inits:
        kf = e.get("keyframe_frames") or []
        made = f"frames {kf[0]} and {kf[-1]}" if len(kf) >= 2 else f"frame {e['frame']}"
        ends = [r for r in events if r["event"] in ("reset", "new_map") and r["frame"] >= e["frame"]]
        text = f"the map was initialised on {made}"
        if ends:
            r = ends[0]
            what = "reset" if r["event"] == "reset" else "set aside for a new map"
            text += f", then {what} at frame {r['frame']}" + (f" ({r['why']})" if r.get("why") else "")
        parts.append(text)
    tail = "" if events and events[-1]["event"] == "initialized" else "; it was not initialised again"
    return "; ".join(parts) + tail


def format_report(report: RunReport) -> list[str]:
    """Human-readable summary lines of a run."""
    s = report.stats
    f = s["frames"]
    t = s["timing_ms"]
    share = 100.0 * f["tracked"] / f["frames"] if f["frames"] else 0.0
    lines = [
        f"frames {f['frames']}: tracked {f['tracked']} ({share:.1f}%), lost {f['lost']}, not initialised "
        f"{f['not_initialized']}, discarded by map resets {f['reset']} ({s['map_resets']} resets), "
        f"dropped behind the camera {f.get('dropped', 0)}",
        f"keyframes {s['keyframes']}, map points {s['map_points']}, final state: {s['final_state']}",
        _real_time_line(s.get("real_time", {})),
        _timing_line("tracking ms/frame", t["tracking_per_frame"], "frames tracked", ".1f")
        + (" (CPU median {median:.1f})".format(**t["tracking_cpu_per_frame"])
           if t["tracking_cpu_per_frame"]["count"] else ""),
        _timing_line("local mapping ms/keyframe", t["local_mapping_per_keyframe"], "keyframes mapped", ".0f"),
    ]
    atlas = s.get("atlas", {})
    if len(atlas.get("maps", [])) > 1 or atlas.get("merges") or atlas.get("maps_started", 1) > 1:
        lines.append(
            f"maps: {atlas.get('maps_started', 1)} started, {len(atlas.get('merges', []))} merge(s), "
            f"{atlas.get('maps_discarded', 0)} discarded, {len(atlas.get('maps', []))} left; trajectories from map "
            f"{atlas.get('output_map')}, {f.get('other_maps', 0)} frames tracked in the other maps"
        )
    for mg in atlas.get("merges", []):
        lines.append(f"maps merged: map {mg['merged_map']} into map {mg['active_map']} at frame {mg['frame_id']} "
                     f"(with frame {mg['match_frame_id']}), scale {mg['scale']:.3f}, {mg['n_matches']} matched points")
    for ev in s.get("loop_closing", {}).get("loops", []):
        lines.append(f"loop closed: keyframe {ev['kf_id']} (frame {ev['frame_id']}) with keyframe {ev['loop_kf_id']} "
                     f"(frame {ev['loop_frame_id']}), scale {ev['scale']:.3f}, {ev['n_matches']} matched points")
    reloc = s.get("relocalization", {})
    if reloc.get("successes"):
        lines.append(f"relocalised {reloc['successes']} times ({reloc['attempts']} attempts)")
    if f["lost"]:
        lines.append(f"WARNING: tracking was lost; {f['lost']} frames have no pose in CameraTrajectory.txt")
    if f["tracked"] and f["frames"] - f["tracked"] > 0.1 * f["frames"]:
        lines.append(f"WARNING: {f['frames'] - f['tracked']} of {f['frames']} frames have no pose: the ATE below "
                     "covers only the frames tracked")  # fmt: skip
    if s["map_resets"]:
        lines.append(f"WARNING: the map was reset {s['map_resets']} time(s); frames before the last reset have "
                     "no pose")  # fmt: skip
    if f["tracked"] == 0:
        lines.append(f"WARNING: {_why_no_pose(s.get('events', []))}; the trajectory files are empty")
    for name, a in report.ate.items():
        if "error" in a:
            lines.append(f"ATE ({name}): not available: {a['error']}")
        else:
            lines.append(
                f"ATE Sim(3) ({name}, {a['pairs']} poses): rmse {100 * a['rmse_m']:.2f} cm, "
                f"median {100 * a['median_m']:.2f} cm, max {100 * a['max_m']:.2f} cm"
            )
    if f.get("unreadable"):
        skipped = " skipped" if s.get("on_bad_frame", "skip") == "skip" else ""
        lines.append(f"WARNING: {f['unreadable']} unreadable frame(s){skipped} (listed in stats.json, bad_frames)")
    lost = s.get("child_processes_lost", {})
    if any(lost.values()):
        lines.append("WARNING: child processes lost and replaced: "
                     + ", ".join(f"{k} {v}" for k, v in lost.items() if v))  # fmt: skip
    if not report.complete:
        lines.append(f"ended early ({report.end.kind}: {report.end.reason}): results cover the frames processed "
                     "so far")  # fmt: skip
    return lines
