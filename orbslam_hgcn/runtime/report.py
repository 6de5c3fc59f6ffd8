"""The results of a :class:`~orbslam_hgcn.runtime.system.System`'s run: the output map and
its trajectories, ``stats.json``'s statistics (:meth:`SystemReport.stats`, with
:meth:`SystemReport.real_time` and :func:`kernel_source`), the series of ``series.npz``
and the files of :meth:`SystemReport.save`. :class:`SystemReport` holds these methods of
System, which inherits them; the functions that rebuild trajectories, summarise timings and
write the files are in :mod:`orbslam_hgcn.runtime.results`.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from orbslam_hgcn.map import Map
from orbslam_hgcn.runtime.results import (
    camera_trajectory,
    frame_counts,
    keyframe_trajectory,
    series_arrays,
    summary_ms,
    write_outputs,
)
from orbslam_hgcn.trajectory import Trajectory, write_tum

MAX_BAD_FRAMES_LISTED = 100  # unreadable frames listed one by one in the stats


def kernel_source() -> dict[str, Any]:
    """Where this process's compiled kernels came from: ``built_ahead`` (the build of
    :mod:`orbslam_hgcn.aot`; else numba), ``not_built_why`` (why not), ``numba_imported``,
    and ``fallbacks``: kernels called with arguments their build does not take, which
    numba compiled or loaded instead."""
    from orbslam_hgcn import aot, compiled

    return {
        "built_ahead": compiled.BUILT is not None,
        "not_built_why": aot.status,
        "numba_imported": "numba" in sys.modules,
        "fallbacks": dict(aot.fallbacks),
    }


class SystemReport:
    """What a :class:`~orbslam_hgcn.runtime.system.System` reports of its run (a mixin of
    System: it reads the system's map, atlas, tracker, stages and the counts and timings
    that System.run and System.process keep)."""

    def real_time(self) -> dict[str, Any]:
        """How the run kept up with its camera: ``real_time_factor`` (camera seconds of the
        frames processed per wall second, from the first frame's extraction to the last
        pose; below 1 the run fell behind a camera at 1x), ``lag_ms`` (paced runs: per frame,
        from when the camera delivered it to its pose; max and p95 say how far behind real
        time the run fell), ``latency_ms`` (per frame, from the start of its extraction to
        its pose), frames dropped (only with threads.drop_late); ``startup_s``, from the
        start of :meth:`run` to the first frame's extraction (child processes starting), and
        ``frames_wall_s``, from there to the end of :meth:`run` (its stages drained): the
        time the run's frames took, without the start-up."""
        rtf = None
        if self._span is not None and self._last_out is not None and self._last_out[1] > self._span[1]:
            rtf = (self._last_out[1] - self._span[1]) / max(self._last_out[0] - self._span[0], 1e-9)
        startup_s = frames_wall_s = None
        if self._span is not None and self._run_times is not None:
            startup_s = max(0.0, self._span[0] - self._run_times[0])
            if self._run_times[1] is not None:
                frames_wall_s = self._run_times[1] - self._span[0]
        t = self.configs.threads
        return {
            "speed": 0.0 if self.sequential else t.speed,
            "drop_late": bool(t.drop_late and not self.sequential),
            "real_time_factor": rtf,
            "lag_ms": summary_ms(self.lags_ms),
            "latency_ms": summary_ms(self.timings["frame"]),
            "dropped": sum(1 for r in self.tracker.records if r.dropped),
            "startup_s": startup_s,
            "frames_wall_s": frames_wall_s,
        }

    def output_map(self) -> Map:
        """The map the trajectories are written from: the atlas's largest (ORB-SLAM3 saves
        its largest map)."""
        return self.atlas.largest()

    def keyframe_trajectory(self) -> Trajectory:
        return keyframe_trajectory(self.output_map())

    def camera_trajectory(self, refine: bool = True) -> Trajectory:
        """Every frame's pose in the output map, as CameraTrajectory.txt holds it: carried by
        its reference keyframe and, when ``tracking.refine_frame_poses`` is on, optimised
        again against the map as it is now (see :mod:`~orbslam_hgcn.runtime.results`).
        ``refine`` False skips that step (a live view's redraw mid-run)."""
        return self._camera_trajectory(self.output_map(), refine)

    def _camera_trajectory(self, m: Map, refine: bool) -> Trajectory:
        cfg = self.configs
        on = refine and cfg.tracking.refine_frame_poses
        return camera_trajectory(self.tracker.records, m, refine=cfg.backend if on else None,
                                 min_points=cfg.tracking.min_inliers)  # fmt: skip

    def stats(self) -> dict[str, Any]:
        """Counts and per-stage timings (ms) of the run so far."""
        out_map = self.output_map()
        counts = frame_counts(self.tracker.records, out_map, self.atlas)
        mt = self.mapper.timings
        opt = np.asarray(self.frame_optimising, dtype=bool)
        return {
            "frames": counts,
            "keyframes": out_map.n_keyframes(),
            "map_points": out_map.n_points(),
            "map_resets": self.n_resets,
            "atlas": {
                "maps": self.atlas.summary(),
                "output_map": out_map.map_id,
                "maps_started": sum(e["event"] == "new_map" for e in self.events) + 1,
                "maps_discarded": self.atlas.n_dropped,
                "merges": list(self.atlas.merges),
            },
            "final_state": self.tracker.state.value,
            "threads": {
                "sequential": self.sequential,
                "process_solver": self.configs.threads.process_solver,
                "local_ba_process": self.configs.threads.local_ba_process,
                "mapping_sync": self.configs.threads.mapping_sync,
                "speed": 0.0 if self.sequential else self.configs.threads.speed,
                "library_threads": self.library_threads,
                "ahead_nice": self.ahead_nice,
                "solver_nice": self.solver_nice if not self.sequential else 0,
            },
            "events": self.events,
            "kernels": kernel_source(),
            "real_time": self.real_time(),
            "timing_ms": {
                "extraction_per_frame": summary_ms(self.timings["extraction"]),
                "tracking_per_frame": summary_ms(self.timings["tracking"]),
                "tracking_cpu_per_frame": summary_ms(self.timings["tracking_cpu"]),
                "frame_total": summary_ms(self.timings["frame"]),
                "frame_total_while_optimising": summary_ms(np.asarray(self.timings["frame"])[opt]),
                "map_lock_wait_per_frame": summary_ms(self.timings["lock_wait"]),
                "keyframe_wait": summary_ms(self.timings["keyframe_wait"]),
                "mapping_sync": summary_ms(self.timings["mapping_sync"]),
                "local_mapping_per_keyframe": summary_ms(mt.get("total", [])),
                "local_mapping_cpu_per_keyframe": summary_ms(mt.get("total_cpu", [])),
                "local_ba_per_keyframe": summary_ms(mt.get("local_ba", [])),
                "local_ba_cpu_per_keyframe": summary_ms(mt.get("local_ba_cpu", [])),
                "mapping_steps": {
                    k: summary_ms(v)
                    for k, v in mt.items()
                    if k not in ("total", "total_cpu", "local_ba", "local_ba_cpu")
                },
            },
            "mapping_counts": dict(self.mapper.counts),
            "bad_frames": self.bad_frames[:MAX_BAD_FRAMES_LISTED],
            "child_processes_lost": {
                "extraction": self.n_extraction_lost, "local_ba": int(self.mapper.counts.get("ba_process_lost", 0)),
            },
            "loop_closing": self.loop_closer.stats() if hasattr(self.loop_closer, "stats") else {},
            "relocalization": self.relocalizer.stats() if hasattr(self.relocalizer, "stats") else {},
        }

    def series(self) -> dict[str, np.ndarray]:
        """The per-frame and per-keyframe series of the run so far (series.npz:
        :func:`~orbslam_hgcn.runtime.results.series_arrays`)."""
        loops = list(getattr(self.loop_closer, "series", []))
        return series_arrays(self.frame_series, self.count_series, list(self.keyframe_series), loops,
                             self.tracker.records)  # fmt: skip

    def save(
        self, out: str | Path, extra: dict[str, Any] | None = None, camera: Trajectory | None = None
    ) -> dict[str, Path]:
        """Write KeyFrameTrajectory.txt, CameraTrajectory.txt (the output map; ``camera``
        when given, else :meth:`camera_trajectory`), stats.json and series.npz
        (:meth:`series`) into ``out``; with
        several maps, each other map's trajectories into ``out/maps/``
        (KeyFrameTrajectory_map<id>.txt, CameraTrajectory_map<id>.txt), listed in
        stats.json under ``atlas.map_files``."""
        stats = self.stats()
        if extra:
            stats.update(extra)
        out_map = self.output_map()
        others = [m for m in self.atlas.maps.values() if m is not out_map and m.n_keyframes()]
        files: dict[str, dict[str, str]] = {}
        for m in others:
            folder = Path(out) / "maps"
            folder.mkdir(parents=True, exist_ok=True)
            kf_path = folder / f"KeyFrameTrajectory_map{m.map_id}.txt"
            cam_path = folder / f"CameraTrajectory_map{m.map_id}.txt"
            write_tum(kf_path, keyframe_trajectory(m))
            write_tum(cam_path, self._camera_trajectory(m, refine=True))
            files[str(m.map_id)] = {"keyframes": str(kf_path), "camera": str(cam_path)}
        stats["atlas"]["map_files"] = files
        if camera is None:
            camera = self.camera_trajectory()
        return write_outputs(out, self.keyframe_trajectory(), camera, stats, self.series())
