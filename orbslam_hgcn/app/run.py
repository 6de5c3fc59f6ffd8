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

import logging
import math
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from orbslam_hgcn.app.ending import RunEnd
from orbslam_hgcn.app.settings import (  # noqa: F401 - camera_from_config: a name the benches use
    camera_from_config,
    check_user_config,
    config_camera,
    flag_layer,
    resolve_settings,
    user_config,
)
from orbslam_hgcn.app.slam import DEFAULT_VOCAB, Slam, open_vocabulary  # noqa: F401 - names of this module
from orbslam_hgcn.datasets import detect_kind, open_sequence
from orbslam_hgcn.datasets.live import is_live
from orbslam_hgcn.errors import FrameError, OrbslamError, StageError, Terminated
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.map.ply import check_ply_path
from orbslam_hgcn.outputs import check_output_file, check_output_folder
from orbslam_hgcn.runtime.system import INTERRUPTED, TERMINATED
from orbslam_hgcn.trajectory import Trajectory
from orbslam_hgcn.viz.sinks import parse_rerun_arg

log = logging.getLogger(__name__)


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


def run_dataset(
    path: str | Path,
    out: str | Path,
    kind: str | None = None,
    config: str | Path | None = None,
    max_frames: int | None = None,
    loop_closing: bool | None = None,
    progress: bool = True,
    vocab: str | None = None,
    rerun: Sequence[str] | None = None,
    load_map: str | Path | None = None,
    save_map: str | Path | None = None,
    localization: bool = False,
    sequential: bool | None = None,
    speed: float | None = None,
    on_bad_frame: str = "skip",
    drop_late: bool | None = None,
    export_ply: str | Path | None = None,
) -> RunReport:
    """Open a dataset, run the system over it, write the results into ``out``.

    Bad input (arguments, config, dataset listing, an output folder that is a file or
    cannot be written) raises an OrbslamError before the first frame. After that the run
    always writes its results and returns; ``RunReport.end`` says how it ended (see the
    module text). ``on_bad_frame``: ``skip`` (default) skips a frame whose image cannot be
    read, with a warning, and counts it; ``stop`` ends the run on it.

    Settings are resolved as for every command (:mod:`orbslam_hgcn.app.settings`): the
    arguments ``loop_closing``, ``sequential``, ``speed`` and ``drop_late`` override the
    config when given; None takes the config (loop closing on, threaded, ``threads.speed``
    1, no frame dropped). ``sequential``: local mapping and loop closing in order after
    each frame (reproducible results) instead of in worker threads. ``speed``: threaded
    runs take frames no faster than this many times the rate of their timestamps (0: as
    fast as they are processed). ``drop_late``: a paced threaded run drops the frames that
    wait longer than ``threads.frame_buffer_s`` (a live source).

    ``rerun``: the ``--rerun`` tokens (``["spawn"]``, ``["save", "FILE.rrd"]``,
    ``["connect", "HOST:PORT"]``) to visualise the run in rerun as it goes
    (:mod:`orbslam_hgcn.viz.live`); None: no visualisation.

    ``load_map``: start from a saved map (:mod:`orbslam_hgcn.app.mapfile`),
    relocalising on it first; ``vocab`` then defaults to the map's vocabulary.
    ``localization``: with ``load_map``, track without changing the map. ``save_map``:
    write the map at the end (also listed in ``paths`` as ``map``). ``export_ply``: write
    the map's points, coloured from the dataset's images, and keyframe poses as PLY
    (``paths``: ``ply_points``, ``ply_keyframes``).
    """
    if is_live(path):
        if speed is not None:
            raise OrbslamError(f"{path}: --speed is for recorded sequences; a live source runs at its own rate")
        return run_live(str(path), out, config, max_frames, loop_closing, progress, vocab, rerun, load_map,
                        save_map, localization, sequential, drop_late, export_ply)  # fmt: skip
    if on_bad_frame not in ("skip", "stop"):
        raise OrbslamError(f"--on-bad-frame must be skip or stop, found {on_bad_frame!r}")
    if max_frames is not None and max_frames < 1:
        raise OrbslamError(f"--max-frames must be at least 1, found {max_frames}")
    if localization and load_map is None:
        raise OrbslamError("--localization needs a saved map: --load-map FILE")
    out = check_output_folder(out)
    if save_map is not None:
        save_map = check_output_file(save_map, "--save-map")
    if export_ply is not None:
        export_ply = check_ply_path(export_ply)
    if rerun is not None:
        parse_rerun_arg(rerun)  # bad tokens fail before the dataset is read
    user = user_config(config)
    check_user_config(user)  # a bad --config fails before the dataset is read
    camera = config_camera(user)
    sequence = open_sequence(kind, path, camera)
    dataset_kind = kind or detect_kind(path)
    camera_origin = camera_source(path, dataset_kind, user.origin if camera is not None else None)
    flags = flag_layer(sequential=sequential, loop_closing=loop_closing, speed=speed, drop_late=drop_late)
    settings = resolve_settings(sequence.camera, dataset_kind, user, flags)
    log.info("%s", settings.line(camera_origin))
    slam = Slam(sequence.camera, vocab=vocab, load_map=load_map, localization=localization, rerun=rerun, out=out,
                name=sequence.name, _settings=settings)  # fmt: skip
    log.info("%s: %d frames, camera %s", sequence.name, len(sequence), sequence.camera.name)
    end, crash = RunEnd(), None
    t_run = time.perf_counter()
    from tqdm.contrib.logging import logging_redirect_tqdm  # 40 ms of imports: not before it is needed

    with logging_redirect_tqdm():
        try:
            summary = slam.run_sequence(sequence, max_frames, progress=progress, on_bad_frame=on_bad_frame)
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
            slam.close(drain=False)  # System.run has drained the stages; stops the rerun recording
    wall_s = time.perf_counter() - t_run
    dataset = {"path": str(path), "kind": kind or "auto", "name": sequence.name, "frames": len(sequence)}
    colours = None
    if export_ply is not None:
        colours = dataset_images(kind, path, camera)
    return finish_run(slam, out, end, crash, wall_s, dataset, camera_origin, sequence.ground_truth,
                      on_bad_frame=on_bad_frame, save_map=save_map, export_ply=export_ply,
                      image_of=colours)  # fmt: skip


def run_live(
    spec: str,
    out: str | Path,
    config: str | Path | None = None,
    max_frames: int | None = None,
    loop_closing: bool | None = None,
    progress: bool = True,
    vocab: str | None = None,
    rerun: Sequence[str] | None = None,
    load_map: str | Path | None = None,
    save_map: str | Path | None = None,
    localization: bool = False,
    sequential: bool | None = None,
    drop_late: bool | None = None,
    export_ply: str | Path | None = None,
    open_capture: Callable[[int | str], Any] | None = None,
) -> RunReport:
    """Run the system on a live source (``cam:N`` or a stream URL:
    :mod:`orbslam_hgcn.datasets.live`) until it ends, ``max_frames`` or Ctrl-C, and write
    the results as :func:`run_dataset` does. The camera's calibration comes from ``config``
    (a YAML file or a shipped camera name). ``drop_late`` (default on for a live source):
    frames that arrive while the system is busy are dropped, and a wait for mapping never
    holds a frame longer than half of ``threads.frame_buffer_s``; off: every frame is
    processed and the run falls behind. ``open_capture``: builds the capture object
    (default ``cv2.VideoCapture``; tests give a source that behaves like a camera)."""
    from orbslam_hgcn.datasets.live import LiveSource

    if max_frames is not None and max_frames < 1:
        raise OrbslamError(f"--max-frames must be at least 1, found {max_frames}")
    if localization and load_map is None:
        raise OrbslamError("--localization needs a saved map: --load-map FILE")
    out = check_output_folder(out)
    save_map = check_output_file(save_map, "--save-map") if save_map is not None else None
    export_ply = check_ply_path(export_ply) if export_ply is not None else None
    if rerun is not None:
        parse_rerun_arg(rerun)
    user = user_config(config)
    check_user_config(user)
    camera = config_camera(user)
    if camera is None:
        raise OrbslamError(f"{spec}: a live source carries no calibration: give its camera with --config "
                           "(a YAML file with fx, fy, cx, cy, width, height, or a shipped camera name such as "
                           "tum_fr3)")  # fmt: skip
    drop = True if drop_late is None else bool(drop_late)
    settings = resolve_settings(camera, None, user, flag_layer(sequential=sequential, loop_closing=loop_closing))
    log.info("%s", settings.line(user.origin))
    slam = Slam(camera, vocab=vocab, load_map=load_map, localization=localization, rerun=rerun, out=out,
                name=spec, _settings=settings)  # fmt: skip
    buffer_s = slam.configs.threads.frame_buffer_s
    end, crash, frames = RunEnd(), None, 0
    t_run = time.perf_counter()
    source = None
    from tqdm import tqdm

    bar = tqdm(total=max_frames, unit="frame", disable=not progress, dynamic_ncols=True)
    try:
        try:
            source = LiveSource(spec, camera, drop_late=drop, open_capture=open_capture)
            log.info("%s: reading frames (Ctrl-C ends the run and writes its results)", spec)
            for rec in source:
                resume_by = time.perf_counter() + 0.5 * buffer_s if drop else math.inf
                result = slam.track(rec.image, rec.timestamp, resume_by=resume_by)
                frames += 1
                bar.update(1)
                bar.set_postfix(state=result.state, dropped=source.dropped, refresh=False)
                if max_frames is not None and frames >= max_frames:
                    break
            slam.close(drain=True)
        except KeyboardInterrupt as exc:
            reason = TERMINATED if isinstance(exc, Terminated) else INTERRUPTED
            end = RunEnd("terminated" if isinstance(exc, Terminated) else "interrupted", reason)
            log.warning("%s after %d frames; saving what exists", reason, frames)
            try:
                slam.close(drain=True)
            except KeyboardInterrupt:  # a second Ctrl-C: stop the stages now
                slam.close(drain=False)
        except OrbslamError as exc:
            if frames == 0 and not isinstance(exc, StageError):
                slam.close(drain=False)
                raise  # the source could not be opened or read: a user error, nothing to save
            end = (RunEnd("stage_failed", _first_line(exc), stage=exc.stage) if isinstance(exc, StageError)
                   else RunEnd("bad_frame", _first_line(exc), frame=frames))  # fmt: skip
        except Exception as exc:  # noqa: BLE001 - a bug: the results so far are still written
            crash = traceback.format_exc()
            end = RunEnd("internal_error", f"{type(exc).__name__}: {_first_line(exc)}")
    finally:
        bar.close()
        if source is not None:
            source.close()
        slam.close(drain=False)
    dataset = {"path": spec, "kind": "live", "name": spec, "frames": frames,
               "grabbed": source.grabbed if source else 0, "dropped": source.dropped if source else 0,
               "drop_late": drop}  # fmt: skip
    return finish_run(slam, out, end, crash, time.perf_counter() - t_run, dataset, user.origin, None,
                      save_map=save_map, export_ply=export_ply)  # fmt: skip


def dataset_images(kind: str | None, path: str | Path, camera: PinholeCamera | None) -> Callable[[int], Any]:
    """Colour images of a dataset by frame number (for a PLY's point colours), read once each."""

    def image_of(frame: int) -> Any:
        try:
            seq = image_of.seq  # type: ignore[attr-defined]
        except AttributeError:
            seq = image_of.seq = open_sequence(kind, path, camera, color=True)  # type: ignore[attr-defined]
        try:
            return seq[frame].image
        except (OrbslamError, IndexError):
            return None

    return image_of


def finish_run(
    slam: Slam, out: Path, end: RunEnd, crash: str | None, wall_s: float, dataset: dict[str, Any],
    camera_origin: str, ground_truth: Trajectory | None, *, on_bad_frame: str = "skip",
    save_map: Path | None = None, export_ply: Path | None = None, image_of: Callable[[int], Any] | None = None,
) -> RunReport:  # fmt: skip
    """Write the results of a run however it ended (the trajectories, stats.json, the saved
    map and PLY when asked) and report them."""
    if not end.complete:
        log.warning("the run ended early (%s): %s; writing the results of the frames processed", end.kind,
                    end.reason)  # fmt: skip
    camera = slam.camera_trajectory()
    ate: dict[str, Any] = {}
    if ground_truth is not None and len(ground_truth) >= 3:
        ate = {
            "keyframes": trajectory_ate(ground_truth, slam.keyframe_trajectory()),
            "camera": trajectory_ate(ground_truth, camera),
        }
    settings = {"camera": camera_origin, **slam.settings_summary()}
    extra = {
        "dataset": dataset,
        "settings": settings,
        "complete": end.complete,
        "end": end.to_json(),
        "interrupted": end.kind in ("interrupted", "terminated"),
        "on_bad_frame": on_bad_frame,
        "wall_s": wall_s,
        "ate_sim3": ate,
    }
    paths = slam.save(out, extra, camera)
    if crash is not None:
        paths["traceback"] = out / "traceback.txt"
        paths["traceback"].write_text(crash, encoding="utf-8")
    for what, target in (("map", save_map), ("PLY", export_ply)):
        if target is None:
            continue
        try:
            if what == "map":
                paths["map"] = slam.save_map(target)
            else:
                ply = slam.export_ply(target, image_of)
                paths["ply_points"], paths["ply_keyframes"] = ply["points"], ply["keyframes"]
        except (OrbslamError, OSError) as exc:
            if end.complete:
                raise
            log.warning("%s not written after the run ended early: %s", what, exc)
    stats = slam.stats()
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
