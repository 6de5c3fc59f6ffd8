"""What a run leaves behind: trajectories rebuilt from the map, timing statistics, files.

The camera trajectory is rebuilt as ORB-SLAM2's System::SaveTrajectoryTUM does: every
tracked frame stored its pose relative to its reference keyframe, ``T_cr``; at the end its
pose is ``T_cw = T_cr @ T_rw`` with the reference keyframe's optimised pose. A reference
keyframe culled meanwhile is replaced by its spanning-tree parent through the relative pose
it kept (``T_cp``). Only the frames of one map are written (the largest of an atlas, or the
map it was merged into); the others (before initialisation, lost, tracked in a map
discarded by a reset or in another map of the atlas) are left out of the file and counted.

With ``tracking.refine_frame_poses`` (the default) the frames then go one step further
than ORB-SLAM2: each pose so rebuilt is the start of one more motion-only optimisation
against the final map, from the inlier matches the frame was tracked with
(:func:`~orbslam_hgcn.tracking.frame_ops.refine_recorded_pose`). A keyframe's own frame
keeps its keyframe's pose, and a frame with too few of its points left keeps the rebuilt one.

Beside ``stats.json`` (summaries: count, median, p95, mean, max) a run writes the series
they summarise, ``series.npz`` (:func:`write_series`, :func:`read_series`; numpy arrays, no
pickles), to see how costs grow over a long run (``bench/bench_long.py``):

* per frame processed, in order: ``frame`` (index in the sequence), ``frame_t`` (its
  timestamp, s), ``frame_wall`` (``time.time()`` when its pose came out), ``tracking_ms``
  (NaN on frames not tracked and on the initialising one, as ``tracking_per_frame``
  leaves them out), ``frame_ms`` (latency, extraction start to pose, as ``frame_total``),
  ``frame_ref_kf`` (the reference keyframe its pose is recorded against; -1 none),
  ``tracking_cpu_ms`` (the tracking thread's CPU time for the frame, NaN where
  ``tracking_ms`` is: the wall time less what the thread waited for the CPU, the GIL or a
  lock);
* every :data:`COUNT_EVERY`-th frame processed: ``count_frame``, ``count_keyframes`` and
  ``count_points`` (the active map's good keyframes and points after tracking that frame;
  counted only so often, since counting walks the map);
* per keyframe local mapping finished, in order: ``kf_id``, ``kf_frame`` (the frame it was
  made from), ``kf_mapping_ms`` and ``kf_local_ba_ms`` (as ``local_mapping_per_keyframe``
  and ``local_ba_per_keyframe``: the time local mapping waited for its local BA after fusion
  and wrote it back), ``kf_wall`` (``time.time()`` when mapping finished it);
* per keyframe checked for a loop, in order: ``loop_kf_id``, ``loop_detect_ms`` (detection:
  database purge, query, consistency, indexing), ``loop_query_ms`` (the keyframe
  database's loop query alone; NaN when detection was skipped, too soon after the map's
  start or the last loop), ``loop_db_keyframes`` (keyframes in the database after it).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from orbslam_hgcn.config import BackendConfig
from orbslam_hgcn.errors import OrbslamError
from orbslam_hgcn.geometry.se3 import inv_T
from orbslam_hgcn.map import Map
from orbslam_hgcn.npzfile import atomic_save_npz, read_npz
from orbslam_hgcn.tracking.frame_ops import pose_from_reference, refine_recorded_pose
from orbslam_hgcn.tracking.tracker import PoseRecord, TrackingState
from orbslam_hgcn.trajectory import Trajectory, write_tum

log = logging.getLogger(__name__)

SERIES_FILE = "series.npz"
COUNT_EVERY = 10  # series.npz: the map's keyframes and points are counted every this many frames


def keyframe_trajectory(m: Map) -> Trajectory:
    """T_wc of every good keyframe, in keyframe order."""
    kfs = m.keyframes()
    if not kfs:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    return Trajectory(np.array([kf.timestamp for kf in kfs]), np.stack([kf.T_wc for kf in kfs]))


def camera_trajectory(
    records: Iterable[PoseRecord], m: Map, generation: int | None = None,
    refine: BackendConfig | None = None, min_points: int = 30,
) -> Trajectory:  # fmt: skip
    """T_wc of every frame with a pose in map ``m`` (see the module text): its reference
    keyframe is one of the map's (in an atlas keyframe ids are unique across maps, and a
    merged map holds the keyframes of both). ``generation``: also only the records of that
    generation (a tracker without an atlas numbers the keyframes of each new map from 0).
    ``refine``: optimise again each frame that recorded its matches, with this pose
    optimiser's settings, where at least ``min_points`` of its points are left."""
    stamps, poses = [], []
    for rec in records:
        if rec.T_cr is None or rec.ref_kf_id < 0 or not m.owns(rec.ref_kf_id):
            continue
        if generation is not None and rec.generation != generation:
            continue
        T_cw = pose_from_reference(m, rec.ref_kf_id, rec.T_cr)
        if T_cw is None:
            log.warning("frame %d: reference keyframe chain ends at a culled keyframe; pose left out", rec.frame_id)
            continue
        ref = m.keyframe(rec.ref_kf_id)
        if refine is not None and rec.matches is not None and (ref.bad or ref.frame_id != rec.frame_id):
            refined = refine_recorded_pose(m, rec.matches, T_cw, refine, min_points)
            if refined is not None:  # else too few points left: the pose the keyframe carries
                T_cw = refined
        stamps.append(rec.timestamp)
        poses.append(inv_T(T_cw))
    if not stamps:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    order = np.argsort(stamps, kind="stable")
    return Trajectory(np.asarray(stamps)[order], np.stack(poses)[order])


def frame_counts(records: list[PoseRecord], m: Map, atlas: Any = None) -> dict[str, Any]:
    """Frames by outcome, each counted once: tracked (a pose in map ``m``, the one the
    trajectories are written from), in another map of the atlas (a pose in a map never
    merged into ``m``), discarded by a map reset (a pose in a map since discarded), lost,
    not initialised, dropped unprocessed (a paced run behind its camera), skipped as
    unreadable; and the share of all frames tracked."""
    tracked = other = reset = lost = not_init = dropped = unreadable = 0
    for r in records:
        if r.unreadable:
            unreadable += 1
        elif r.dropped:
            dropped += 1
        elif r.T_cr is not None and r.ref_kf_id >= 0:
            if m.owns(r.ref_kf_id):
                tracked += 1
            elif atlas is not None and atlas.map_of(r.ref_kf_id) is not None:
                other += 1
            else:
                reset += 1
        elif r.state == TrackingState.LOST:
            lost += 1
        else:
            not_init += 1
    n = len(records)
    return {
        "frames": n, "tracked": tracked, "lost": lost, "not_initialized": not_init, "reset": reset,
        "dropped": dropped, "unreadable": unreadable, "other_maps": other, "tracked_share": tracked / n if n else 0.0,
    }  # fmt: skip


def summary_ms(values: list[float] | np.ndarray) -> dict[str, float | None]:
    """Median, 95th percentile, mean and max of timings in ms (None when there are none)."""
    v = np.asarray(values, dtype=np.float64)
    if len(v) == 0:
        return {"count": 0, "median": None, "p95": None, "mean": None, "max": None}
    return {
        "count": int(len(v)),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "mean": float(v.mean()),
        "max": float(v.max()),
    }


def series_arrays(
    frames: list[tuple[int, float, float, float, float, float]], counts: list[tuple[int, int, int]],
    mapped: list[tuple[int, int, float, float, float]], loops: list[tuple[int, float, float, int]],
    records: Iterable[PoseRecord] = (),
) -> dict[str, np.ndarray]:  # fmt: skip
    """The arrays of ``series.npz`` (see the module text) from a run's rows: ``frames``
    (frame, timestamp, tracking ms or NaN, frame ms, wall time, tracking CPU ms or NaN), ``counts`` (frame,
    keyframes, points), ``mapped`` (kf id, frame, local mapping ms, local BA ms, wall time),
    ``loops`` (kf id, detection ms, query ms or NaN, database keyframes); ``records``: the
    tracker's, for each frame's reference keyframe."""

    def cols(rows: list[tuple], n: int) -> list[np.ndarray]:
        a = np.asarray(rows, dtype=np.float64).reshape(len(rows), n)
        return [a[:, i] for i in range(n)]

    ref_of = {r.frame_id: r.ref_kf_id for r in records}
    f, t, trk, fms, wall, cpu = cols(frames, 6)
    cf, ck, cp = cols(counts, 3)
    kid, kfr, kms, kba, kwall = cols(mapped, 5)
    lid, ldet, lq, ldb = cols(loops, 4)
    i64 = np.int64
    return {
        "frame": f.astype(i64), "frame_t": t, "frame_wall": wall, "tracking_ms": trk, "frame_ms": fms,
        "tracking_cpu_ms": cpu,
        "frame_ref_kf": np.array([ref_of.get(int(k), -1) for k in f], dtype=i64),
        "count_frame": cf.astype(i64), "count_keyframes": ck.astype(i64), "count_points": cp.astype(i64),
        "kf_id": kid.astype(i64), "kf_frame": kfr.astype(i64), "kf_mapping_ms": kms, "kf_local_ba_ms": kba,
        "kf_wall": kwall,
        "loop_kf_id": lid.astype(i64), "loop_detect_ms": ldet, "loop_query_ms": lq,
        "loop_db_keyframes": ldb.astype(i64),
    }  # fmt: skip


def write_series(path: str | Path, arrays: dict[str, np.ndarray]) -> Path:
    """Write ``series.npz`` (:func:`series_arrays`) atomically."""
    return atomic_save_npz(path, arrays)


def read_series(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of a run's ``series.npz``; an OrbslamError names a missing or damaged file."""
    return read_npz(Path(path), "series", OrbslamError)


def write_outputs(
    out: str | Path, kf_traj: Trajectory, cam_traj: Trajectory, stats: dict[str, Any],
    series: dict[str, np.ndarray] | None = None,
) -> dict[str, Path]:  # fmt: skip
    """Write KeyFrameTrajectory.txt, CameraTrajectory.txt (TUM, T_wc), stats.json and, when
    given, the per-frame and per-keyframe ``series`` (series.npz)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "keyframes": out / "KeyFrameTrajectory.txt",
        "camera": out / "CameraTrajectory.txt",
        "stats": out / "stats.json",
    }
    write_tum(paths["keyframes"], kf_traj)
    write_tum(paths["camera"], cam_traj)
    paths["stats"].write_text(json.dumps(stats, indent=2, sort_keys=False) + "\n", encoding="utf-8")
    if series is not None:
        paths["series"] = write_series(out / SERIES_FILE, series)
    return paths
