"""Visualise a running SLAM system in rerun: an observer for ``System.observers``.

:class:`LiveViz` is called after every frame of ``System.run`` as
``observer(system, record, result)`` and turns what the frame left behind into
:class:`~orbslam_hgcn.viz.records.FrameLog` / :class:`~orbslam_hgcn.viz.records.MapSnapshot`
records for :class:`~orbslam_hgcn.viz.rerun_logger.RerunLogger`, on the ``frame`` timeline:

- every frame: the image with tracked (green) and untracked (red) keypoints, the camera pose
  (one ``Transform3D`` per frame with a pose), tracked points, fps, keyframes, map points,
  tracking state and, when the sequence has ground truth, the ATE so far;
- at a reduced rate (:class:`~orbslam_hgcn.config.VizConfig`: every ``log_every_map``
  frames, on keyframe inserts, on every loop closure and at the end): the whole map (points
  coloured by observation count or height, keyframe frustums, covisibility and loop edges),
  the estimated trajectory and the ground truth aligned to it;
- loop closures as events on the timeline; after one, the corrected map and the trajectory
  rebuilt from the corrected keyframes replace the old ones;
- with an atlas, the maps that are not active, each in its own colour, and new active maps
  and merges as events.

It uses only the system's public attributes (``map``, ``tracker``, ``loop_closer``,
``camera``, ``camera_trajectory()``) and copies the map under its lock (``Map.lock``); it
never changes the map.

The ATE is the RMSE of the camera centres after the least-squares similarity alignment of
the estimate onto the ground truth (Umeyama, PAMI 1991; the same optimum as Horn's
closed form used here), as ``orbslam-hgcn eval --align sim3`` computes it. During the run
it uses the poses as tracked; at the end, and after loop closures, the poses rebuilt from
the optimised keyframes (as written to CameraTrajectory.txt).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from orbslam_hgcn.config import VizConfig, load_yaml, section_from_yaml
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.sim3 import horn_similarity
from orbslam_hgcn.map.graph import snapshot as map_snapshot
from orbslam_hgcn.viz.records import FrameLog, MapSnapshot
from orbslam_hgcn.viz.rerun_logger import RerunLogger, Rows

log = logging.getLogger(__name__)

MIN_ALIGN_PAIRS = 3  # as the ATE evaluation: fewer pairs cannot fix a similarity


def sim3_ate(est_w: np.ndarray, gt_w: np.ndarray) -> tuple[float, np.ndarray] | None:
    """ATE RMSE after aligning estimate onto ground truth with a similarity.

    est_w, gt_w: (N, 3) corresponding camera centres (estimate in map units, ground truth
    in metres). Returns (rmse in metres, (4, 4) S_gt_est) or None with fewer than three
    pairs or no spread of the estimate.
    """
    est = np.asarray(est_w, dtype=np.float64).reshape(-1, 3)
    gt = np.asarray(gt_w, dtype=np.float64).reshape(-1, 3)
    if len(est) < MIN_ALIGN_PAIRS or np.sum((est - est.mean(axis=0)) ** 2) < 1e-18:
        return None
    s, R, t = horn_similarity(gt, est)
    if not np.isfinite(s) or s <= 0:
        return None
    residual = s * est @ R.T + t - gt
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = s * R, t
    return float(np.sqrt(np.mean(np.sum(residual**2, axis=1)))), S


def gt_in_map(gt_w: np.ndarray, S_gt_est: np.ndarray) -> np.ndarray:
    """(N, 3) ground-truth centres carried into the map frame by the inverse of S_gt_est."""
    sR, t = S_gt_est[:3, :3], S_gt_est[:3, 3]
    s = np.cbrt(np.linalg.det(sR))
    return (np.asarray(gt_w, dtype=np.float64) - t) @ sR / (s * s)


def map_snapshot_of(system: Any) -> MapSnapshot:
    """The system's map as a :class:`MapSnapshot`, copied under the map's lock.

    Points are the map's good points with their observing-keyframe counts; covisibility
    edges are the pairs meeting the covisibility threshold; loop edges as recorded.
    """
    m = system.map
    with system.map.lock:
        snap = map_snapshot(m)
        obs = m.n_observations(snap.point_ids)
    return MapSnapshot(
        keyframe_ids=snap.kf_ids, keyframe_T_wc=snap.kf_T_wc, point_ids=snap.point_ids,
        points_w=snap.points, point_obs_count=obs, covis_edges=snap.covis_edges,
        loop_edges=snap.loop_edges,
    )


class LiveViz:
    """Logs a running :class:`~orbslam_hgcn.runtime.system.System` to rerun.

    Append it to ``system.observers`` (or use :func:`attach_live_viz`), run, then call
    :meth:`finish` with the system to log the final map and trajectories and close the
    recording. ``mode``/``target``/``fallback_path`` as for
    :class:`~orbslam_hgcn.viz.rerun_logger.RerunLogger`.
    """

    def __init__(
        self,
        camera: PinholeCamera,
        mode: str = "save",
        target: str | Path | None = None,
        *,
        config: VizConfig | None = None,
        fallback_path: str | Path | None = None,
        recording_name: str | None = None,
    ) -> None:
        self.logger = RerunLogger(
            camera, mode, target, config=config, recording_name=recording_name, fallback_path=fallback_path
        )
        self._generation: int | None = None
        self._n_loops = 0
        self._n_merges = 0
        self._active_map: int | None = None
        self._n_maps = 0
        self._last_index: int | None = None
        self._last_call: float | None = None
        self._est = Rows(3, np.float64)  # tracked camera centres with ground truth, map frame
        self._gt = Rows(3, np.float64)  # their ground-truth centres, metres
        self._gt_all = Rows(3, np.float64)  # every ground-truth centre seen, in frame order
        self._gt_by_stamp: dict[float, np.ndarray] = {}
        self._S_gt_est: np.ndarray | None = None
        self.frames_logged = 0
        self.poses_logged = 0
        self.wall_s = 0.0  # spent logging on the calling thread(s)
        self.cpu_s = 0.0
        self._finished = False

    @property
    def mode(self) -> str:
        return self.logger.mode

    @property
    def target(self) -> str:
        return self.logger.target

    def summary(self) -> dict[str, Any]:
        """Where the recording went and what logging cost on the calling thread(s): wall and
        CPU seconds spent in the observer and in :meth:`finish` (rerun encodes and writes
        in its own threads besides)."""
        return {
            "mode": self.mode, "target": self.target, "frames": self.frames_logged, "poses": self.poses_logged,
            "log_wall_s": round(self.wall_s, 4), "log_cpu_s": round(self.cpu_s, 4),
        }

    # --- per frame -----------------------------------------------------------------------
    def __call__(self, system: Any, record: Any, result: Any) -> None:
        """Log one processed frame (the ``System.observers`` signature)."""
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            self._log(system, record, result)
        finally:
            self.wall_s += time.perf_counter() - t0
            self.cpu_s += time.thread_time() - c0

    def _log(self, system: Any, record: Any, result: Any) -> None:
        now = time.perf_counter()
        fps = 1.0 / (now - self._last_call) if self._last_call is not None else 1000.0 / max(result.time_ms, 1e-3)
        self._last_call = now
        index = int(record.index)
        self._last_index = index
        tracker = system.tracker
        if tracker.generation != self._generation:
            self._new_map(tracker.generation)
        self._log_atlas(system, index)
        if record.T_wc is not None:
            gt_c = np.asarray(record.T_wc, dtype=np.float64)[:3, 3]
            self._gt_by_stamp[float(record.timestamp)] = gt_c
            self._gt_all.append(gt_c)
        frame = result.frame
        ok = frame is not None and frame.T_cw is not None and _state_ok(result.state)
        T_wc = frame.T_wc if ok else None
        if frame is not None:
            uv, tracked = frame.keypoints.uv_raw, frame.matched
        else:
            uv, tracked = np.zeros((0, 2), np.float32), np.zeros(0, bool)
        m = system.map
        flog = FrameLog(
            index=index, timestamp=float(record.timestamp), image=record.image, keypoints_uv=uv,
            tracked=tracked, T_wc=T_wc, state=result.state, n_tracked=int(np.count_nonzero(tracked)),
            fps=fps, n_keyframes=m.n_keyframes(), n_map_points=m.n_points(),
        )
        loops = list(getattr(system.loop_closer, "loops", None) or [])[self._n_loops:]
        self._n_loops += len(loops)
        first = (int(loops[0].kf_id), int(loops[0].loop_kf_id)) if loops else None
        self.logger.log_step(
            flog, lambda: map_snapshot_of(system), keyframe_inserted=bool(result.new_keyframes), loop=first
        )
        for ev in loops[1:]:
            self.logger.log_loop(index, int(ev.kf_id), int(ev.loop_kf_id))
        self.frames_logged += 1
        if T_wc is not None:
            self.poses_logged += 1
            if record.T_wc is not None:
                self._est.append(T_wc[:3, 3])
                self._gt.append(record.T_wc[:3, 3])
        if getattr(result, "initialized", False):
            self._log_initial_keyframe(record, result)
            if self.logger.last_map_frame != index:  # show the new map at once
                self.logger.log_map(map_snapshot_of(system), index)
        if loops:
            self._replace_trajectory(system, index)
        elif self._gt.n:
            self._log_ate(index)
        if self.logger.last_map_frame == index:
            self._log_ground_truth(index)

    def _log_atlas(self, system: Any, index: int) -> None:
        """An atlas that changed (a new active map, a merge): events on the timeline, and
        the inactive maps in their own colours."""
        atlas = getattr(system, "atlas", None)
        if atlas is None:
            return
        active = system.map.map_id
        merges = atlas.merges[self._n_merges :]
        self._n_merges += len(merges)
        for mg in merges:
            self.logger.log_event(index, f"maps merged: map {mg['merged_map']} into map {mg['active_map']} "
                                  f"(keyframes {mg['kf_id']} <-> {mg['match_kf_id']}, scale {mg['scale']:.3f})")
        changed = bool(merges) or active != self._active_map or len(atlas) != self._n_maps
        if active != self._active_map and self._active_map is not None:
            self.logger.log_event(index, f"map {active} is now the active map ({len(atlas)} maps)")
            self._new_map(self._generation)
        self._active_map, self._n_maps = active, len(atlas)
        if changed:
            with system.map.lock:
                others = [
                    (m.map_id, m.positions(m.point_ids()), np.array([kf.center for kf in m.keyframes()]).reshape(-1, 3))
                    for m in atlas.maps.values()
                    if m is not system.map
                ]
            self.logger.log_other_maps(others, index)
            if merges:
                self.logger.log_map(map_snapshot_of(system), index)

    def _new_map(self, generation: int) -> None:
        """A new map (the first, or after a reset): forget the trajectory of the old one."""
        first = self._generation is None
        self._generation = generation
        self._est.clear()
        self._gt.clear()
        self._S_gt_est = None
        if not first:
            self.logger.log_trajectory(np.zeros((0, 3)), self._last_index)

    def _log_initial_keyframe(self, record: Any, result: Any) -> None:
        """The first keyframe of an initialisation gets its pose only now: log it at its frame."""
        kf1 = result.new_keyframes[0]
        T_wc, T_wc_now = kf1.T_wc, result.frame.T_wc
        self.logger.log_camera_pose(int(kf1.frame_id), T_wc)
        self.poses_logged += 1
        gt1 = self._gt_by_stamp.get(float(kf1.timestamp))
        self._est.clear()
        self._gt.clear()
        if gt1 is not None and record.T_wc is not None:
            self._est.append(T_wc[:3, 3])
            self._gt.append(gt1)
            self._est.append(T_wc_now[:3, 3])
            self._gt.append(np.asarray(record.T_wc)[:3, 3])
        self.logger.log_trajectory(np.stack([T_wc[:3, 3], T_wc_now[:3, 3]]), int(result.frame.id))

    def _replace_trajectory(self, system: Any, index: int, final: bool = False) -> None:
        """Camera centres rebuilt from the (corrected) keyframes replace the tracked ones;
        ``final``: as CameraTrajectory.txt holds them (each frame optimised again against
        the final map), not done mid-run."""
        with system.map.lock:
            traj = system.camera_trajectory(refine=final)
        centres = traj.poses[:, :3, 3] if len(traj) else np.zeros((0, 3))
        self.logger.log_trajectory(centres, index)
        self._est.clear()
        self._gt.clear()
        for stamp, c in zip(traj.timestamps, centres):
            gt_c = self._gt_by_stamp.get(float(stamp))
            if gt_c is not None:
                self._est.append(c)
                self._gt.append(gt_c)
        self._log_ate(index)

    def _log_ate(self, index: int) -> float | None:
        out = sim3_ate(self._est.array, self._gt.array)
        if out is None:
            return None
        rmse, self._S_gt_est = out
        self.logger.log_ate(rmse, index)
        return rmse

    def _log_ground_truth(self, index: int) -> None:
        if self._S_gt_est is not None and self._gt_all.n:
            self.logger.log_ground_truth(gt_in_map(self._gt_all.array, self._S_gt_est), index)

    # --- end -------------------------------------------------------------------------------
    def finish(self, system: Any) -> None:
        """Log the final map, the trajectory rebuilt from the final keyframes, the aligned
        ground truth and final ATE at the last frame; then close the recording."""
        if self._finished:
            return
        self._finished = True
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            if self._last_index is not None:
                index = self._last_index
                self.logger.log_map(map_snapshot_of(system), index)
                self._replace_trajectory(system, index, final=True)
                self._log_ground_truth(index)
        finally:
            self.logger.close()
            self.wall_s += time.perf_counter() - t0
            self.cpu_s += time.thread_time() - c0


def _state_ok(state: Any) -> bool:
    name = getattr(state, "name", str(state))
    return str(name).lower() == "ok"


def viz_config_from(path: str | Path | None) -> VizConfig:
    """The ``viz:`` section of a YAML config file (defaults without a file or section)."""
    if path is None:
        return VizConfig()
    return section_from_yaml(VizConfig, load_yaml(path), path, "viz")


def attach_live_viz(
    system: Any,
    mode: str,
    target: str | None,
    *,
    out: str | Path | None = None,
    config: str | Path | None = None,
    name: str | None = None,
) -> LiveViz:
    """Build a :class:`LiveViz` for ``system`` and append it to ``system.observers``.

    ``mode``/``target``: as :func:`~orbslam_hgcn.viz.sinks.parse_rerun_arg` returns them.
    When spawn or connect find no viewer, the recording is saved to ``out/rerun.rrd``
    (``out``: the run's output folder). ``config``: YAML file whose ``viz:`` section
    (:class:`~orbslam_hgcn.config.VizConfig`) sets what is logged and how often.
    """
    fallback = Path(out) / "rerun.rrd" if out is not None else None
    viz = LiveViz(
        system.camera, mode, target, config=viz_config_from(config), fallback_path=fallback,
        recording_name=name,
    )
    system.observers.append(viz)
    return viz
