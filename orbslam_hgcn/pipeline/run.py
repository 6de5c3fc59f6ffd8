"""Run the system over a dataset and write its results: the ``orbslam-hgcn run`` command.

Writes into the output folder ``KeyFrameTrajectory.txt`` and ``CameraTrajectory.txt``
(TUM format, ``T_wc``, as ORB-SLAM writes them) and ``stats.json`` (frame counts, tracking
events, per-stage timings and, when the dataset has ground truth, the ATE after Sim(3)
alignment, Umeyama 1991, as monocular scale is unobservable).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm.contrib.logging import logging_redirect_tqdm

from orbslam_hgcn.config import dataset_settings, load_camera, load_yaml, resolve_config
from orbslam_hgcn.datasets import detect_kind, open_sequence
from orbslam_hgcn.errors import OrbslamError, VocabularyError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.pipeline.system import Configs, System
from orbslam_hgcn.trajectory import Trajectory
from orbslam_hgcn.viz.sinks import parse_rerun_arg

log = logging.getLogger(__name__)

CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")


@dataclass
class RunReport:
    """What a run produced: output files, stats, ATE figures (None without ground truth)."""

    paths: dict[str, Path]
    stats: dict[str, Any]
    ate: dict[str, Any] = field(default_factory=dict)
    interrupted: bool = False


def camera_from_config(path: str | Path | None) -> PinholeCamera | None:
    """The camera of a config file when it holds one (flat keys or a ``camera:`` section)."""
    if path is None:
        return None
    data = load_yaml(path)
    section = data.get("camera") if isinstance(data.get("camera"), dict) else data
    if any(k in section for k in CAMERA_KEYS):
        return load_camera(path)
    return None


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
    """The vocabulary of a run: ``vocab`` is ``orb``, ``hgcn`` (the shipped defaults), a
    vocabulary file, or ``none``; None means the default HGCN one. Without loop closing a
    missing default only costs relocalisation (a warning); otherwise it is an error."""
    from orbslam_hgcn.vocabulary import load_vocabulary

    name = vocab or "hgcn"
    if name == "none":
        if loop_closing:
            raise OrbslamError("loop closing needs a vocabulary: use --vocab orb|hgcn|FILE, or --no-loop")
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
) -> RunReport:
    """Open a dataset, run the system over it, write the results into ``out``.

    ``sequential``: local mapping and loop closing in order after each frame (reproducible
    results) instead of in worker threads. ``speed``: threaded runs take frames no faster
    than this many times the rate of their timestamps (0: as fast as they are processed);
    None: ``threads.speed`` of the config (default 1).

    ``rerun``: the ``--rerun`` tokens (``["spawn"]``, ``["save", "FILE.rrd"]``,
    ``["connect", "HOST:PORT"]``) to visualise the run in rerun as it goes
    (:mod:`orbslam_hgcn.viz.live`); None: no visualisation.

    ``load_map``: start from a saved map (:mod:`orbslam_hgcn.pipeline.mapfile`),
    relocalising on it first; ``vocab`` then defaults to the map's vocabulary.
    ``localization``: with ``load_map``, track without changing the map. ``save_map``:
    write the map at the end (also listed in ``paths`` as ``map``).
    """
    rerun_sink = parse_rerun_arg(rerun) if rerun is not None else None
    if config is not None:
        config = resolve_config(config)  # a path, or a shipped camera name such as tum_fr3
    user_layer = load_yaml(config) if config is not None else {}
    Configs.from_layers([(user_layer, config or "")])  # a bad --config fails before the dataset is read
    camera = camera_from_config(config)
    sequence = open_sequence(kind, path, camera)
    settings_path, settings = dataset_settings(sequence.camera, kind or detect_kind(path))
    if settings_path is not None:
        log.info("stage settings of %s (the dataset's camera)%s", settings_path.stem,
                 f", then {config}" if config is not None else "")  # fmt: skip
    configs = Configs.from_layers([(settings, settings_path or ""), (user_layer, config or "")])
    if speed is not None:
        configs = dataclasses.replace(configs, threads=dataclasses.replace(configs.threads, speed=speed))
    if max_frames is not None and max_frames < 1:
        raise OrbslamError(f"--max-frames must be at least 1, found {max_frames}")
    if localization and load_map is None:
        raise OrbslamError("--localization needs a saved map: --load-map FILE")
    if load_map is not None:
        from orbslam_hgcn.pipeline.mapfile import install_map, load_map as read_saved_map, map_vocabulary_name

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
    with logging_redirect_tqdm():
        try:
            summary = system.run(sequence, max_frames, progress=progress)
        finally:
            if viz is not None:
                viz.finish(system)
    ate: dict[str, Any] = {}
    if sequence.ground_truth is not None and len(sequence.ground_truth) >= 3:
        ate = {
            "keyframes": trajectory_ate(sequence.ground_truth, system.keyframe_trajectory()),
            "camera": trajectory_ate(sequence.ground_truth, system.camera_trajectory()),
        }
    extra = {
        "dataset": {"path": str(path), "kind": kind or "auto", "name": sequence.name, "frames": len(sequence)},
        "settings": {
            "dataset": settings_path.stem if settings_path is not None else None,
            "config": str(config) if config is not None else None,
            "orb_features": configs.orb.n_features,
        },
        "vocabulary": repr(vocabulary) if vocabulary is not None else None,
        "interrupted": summary.interrupted,
        "wall_s": summary.wall_s,
        "ate_sim3": ate,
        "map_file": {"loaded": str(load_map) if load_map else None, "localization": localization},
    }
    if viz is not None:
        extra["rerun"] = viz.summary()
    paths = system.save(out, extra)
    if save_map is not None:
        from orbslam_hgcn.pipeline.mapfile import save_system_map

        paths["map"] = save_system_map(save_map, system, vocab)
    stats = system.stats()
    stats.update(extra)
    return RunReport(paths, stats, ate, summary.interrupted)


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
        "tracking ms/frame: median {median:.1f}, p95 {p95:.1f}, mean {mean:.1f}".format(**t["tracking_per_frame"])
        + " (CPU median {median:.1f})".format(**t["tracking_cpu_per_frame"]),
        "local mapping ms/keyframe: median {median:.0f}, p95 {p95:.0f}, mean {mean:.0f}".format(
            **t["local_mapping_per_keyframe"]
        ),
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
    if f["frames"] and f["frames"] - f["tracked"] > 0.1 * f["frames"]:
        lines.append(f"WARNING: {f['frames'] - f['tracked']} of {f['frames']} frames have no pose: the ATE below "
                     "covers only the frames tracked")  # fmt: skip
    if s["map_resets"]:
        lines.append(f"WARNING: the map was reset {s['map_resets']} time(s); frames before the last reset have "
                     "no pose")  # fmt: skip
    if f["tracked"] == 0:
        lines.append("WARNING: the map was never initialised (too little parallax or texture); "
                     "the trajectory files are empty")
    for name, a in report.ate.items():
        if "error" in a:
            lines.append(f"ATE ({name}): not available: {a['error']}")
        else:
            lines.append(
                f"ATE Sim(3) ({name}, {a['pairs']} poses): rmse {100 * a['rmse_m']:.2f} cm, "
                f"median {100 * a['median_m']:.2f} cm, max {100 * a['max_m']:.2f} cm"
            )
    if report.interrupted:
        lines.append("interrupted: results cover the frames processed so far")
    return lines
