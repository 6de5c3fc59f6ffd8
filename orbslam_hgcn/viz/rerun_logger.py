"""Live and recorded visualisation of a SLAM run in rerun (https://rerun.io, SDK 0.41).

:class:`RerunLogger` takes plain arrays (:class:`~orbslam_hgcn.viz.records.FrameLog`,
:class:`~orbslam_hgcn.viz.records.MapSnapshot`), never map objects. Everything is logged on
two timelines: ``frame`` (frame index) and ``time`` (dataset timestamp). Per frame: the
image, keypoints, camera pose and plots; the map at a reduced rate (every
``log_every_map`` frames, on keyframe inserts, and always on a loop closure, where the
corrected map replaces the old one). Each map log replaces the whole map entity, so points
culled or moved by bundle adjustment and loop correction are shown as they are.

Calls may come from several threads (rerun's recording stream is thread-safe; each call
sets the time on its own thread).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import threading
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import rerun as rr

from orbslam_hgcn.config import VizConfig
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.viz import records as ent
from orbslam_hgcn.viz.blueprint import FRAME_TIMELINE, TIME_TIMELINE, default_blueprint
from orbslam_hgcn.viz.records import FrameLog, MapSnapshot, state_code, state_name
from orbslam_hgcn.viz.shapes import edge_segments, frustum_strips, point_colours, unique_edges
from orbslam_hgcn.viz.sinks import DEFAULT_PORT, attach_sink

log = logging.getLogger(__name__)

GREEN, RED, BLUE, ORANGE, GREY = (40, 220, 60), (230, 50, 50), (70, 140, 255), (255, 150, 0), (200, 200, 200)
# Colours of the inactive maps of an atlas, by map id.
MAP_PALETTE = ((200, 120, 255), (255, 200, 40), (0, 200, 200), (255, 110, 180), (150, 210, 90), (160, 120, 80))


def _packed(rgb: tuple[int, ...], alpha: int = 255) -> np.ndarray:
    """(1,) uint32 0xRRGGBBAA: a colour rerun takes without conversion."""
    r, g, b = rgb
    return np.array([(r << 24) | (g << 16) | (b << 8) | alpha], dtype=np.uint32)


_GREEN, _RED, _BLUE, _GREY = _packed(GREEN), _packed(RED), _packed(BLUE), _packed(GREY)
_BLUE_FAINT = _packed(BLUE, 90)
KEYPOINT_RADIUS = rr.Radius.ui_points(2.5)
MAP_POINT_RADIUS = rr.Radius.ui_points(1.5)
THIN, MEDIUM, THICK = rr.Radius.ui_points(0.5), rr.Radius.ui_points(1.5), rr.Radius.ui_points(3.0)
EPOCH_MIN_S = 1e8  # timestamps above this are Unix epochs (TUM, EuRoC); below, durations


@functools.cache
def _strip_type() -> pa.DataType:
    """The arrow type rerun gives a batch of LineStrip3D."""
    return rr.components.LineStrip3DBatch([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]]).as_arrow_array().type


def _strips(vertices: np.ndarray) -> pa.Array:
    """(S, L, 3) strips of equal length as rerun's LineStrip3D arrow array.

    rerun's own conversion computes the S offsets in a Python loop (about 0.3 us a strip);
    building them with numpy keeps logging thousands of edges cheap.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    n_strips = len(vertices)
    length = vertices.shape[1] if vertices.ndim == 3 and n_strips else 0
    offsets = pa.array(np.arange(n_strips + 1, dtype=np.int32) * length)
    points = rr.encodings.Vec3DBatch(vertices.reshape(n_strips * length, 3)).as_arrow_array()
    return pa.ListArray.from_arrays(offsets, points, type=_strip_type())


class Rows:
    """A growable (N, columns) buffer (amortised O(1) appends, no per-frame copies)."""

    def __init__(self, columns: int = 3, dtype: type = np.float32) -> None:
        self._buf = np.zeros((256, columns), dtype=dtype)
        self.n = 0

    def append(self, row: np.ndarray) -> None:
        if self.n == len(self._buf):
            self._buf = np.vstack([self._buf, np.zeros_like(self._buf)])
        self._buf[self.n] = row
        self.n += 1

    def replace(self, rows: np.ndarray) -> None:
        """Hold ``rows`` (N, columns) instead of what was appended."""
        cols = self._buf.shape[1]
        rows = np.asarray(rows, dtype=self._buf.dtype).reshape(-1, cols)
        self._buf = np.vstack([rows, np.zeros((max(256, len(rows)), cols), self._buf.dtype)])
        self.n = len(rows)

    def clear(self) -> None:
        self.n = 0

    @property
    def array(self) -> np.ndarray:
        return self._buf[: self.n]


class RerunLogger:
    """Logs a SLAM run to a rerun viewer or ``.rrd`` file.

    camera:  intrinsics of the logged images (drawn as the current camera's pinhole).
    mode:    "spawn" (start a native viewer), "save" (target: FILE.rrd) or "connect"
             (target: gRPC URL or HOST:PORT). Without a display or a viewer, spawn and
             connect save to ``fallback_path`` instead (see :mod:`orbslam_hgcn.viz.sinks`);
             ``self.mode`` and ``self.target`` say what was used.
    log_every_map: overrides ``config.log_every_map`` when given.
    """

    def __init__(
        self,
        camera: PinholeCamera,
        mode: str = "save",
        target: str | Path | None = None,
        *,
        app_id: str = "orbslam_hgcn",
        log_every_map: int | None = None,
        config: VizConfig | None = None,
        recording_name: str | None = None,
        fallback_path: str | Path | None = None,
        port: int = DEFAULT_PORT,
    ) -> None:
        config = config or VizConfig()
        if log_every_map is not None:
            config = dataclasses.replace(config, log_every_map=int(log_every_map))
        self.camera = camera
        self.config = config
        self._lock = threading.Lock()
        self._rec = rr.RecordingStream(app_id)
        self.mode, self.target = attach_sink(
            self._rec, mode, None if target is None else str(target),
            blueprint=default_blueprint(), fallback_path=fallback_path, port=port,
        )
        log.info("rerun: %s -> %s", self.mode, self.target)
        if recording_name:
            self._rec.send_recording_name(recording_name)
        self._timestamps: dict[int, float] = {}
        self._epoch: bool | None = None
        self._last_frame = 0
        self._last_map_frame: int | None = None
        self._last_state: str | None = None
        self._n_loops = 0
        self._loop_edges = np.zeros((0, 2), dtype=np.int64)
        self._kf_ids = np.zeros(0, dtype=np.int64)
        self._kf_centres = np.zeros((0, 3), dtype=np.float32)
        self._trajectory = Rows(3, np.float32)  # camera centres
        self._other_maps: set[int] = set()
        self._closed = False
        self._log_static()

    # --- time ------------------------------------------------------------------------
    def _set_time(self, frame_index: int | None) -> None:
        """Set both timelines on the calling thread (the last frame's when index is None)."""
        idx = self._last_frame if frame_index is None else int(frame_index)
        self._rec.set_time(FRAME_TIMELINE, sequence=idx)
        ts = self._timestamps.get(idx)
        if ts is None:
            self._rec.disable_timeline(TIME_TIMELINE)
        elif self._epoch:
            self._rec.set_time(TIME_TIMELINE, timestamp=ts)
        else:
            self._rec.set_time(TIME_TIMELINE, duration=ts)

    def _log_static(self) -> None:
        rec, cam = self._rec, self.camera
        rec.log(ent.WORLD, rr.ViewCoordinates.RDF, static=True)
        rec.log(
            ent.IMAGE,
            rr.Pinhole(
                image_from_camera=cam.K, width=cam.width, height=cam.height,
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=self.config.frustum_depth * 2.0, color=GREEN,
            ),
            static=True,
        )
        rec.log(
            ent.PLOT_TRACKING,
            rr.SeriesLines(names=["tracked map points", "keypoints"], colors=[GREEN, GREY]),
            static=True,
        )
        styles = {
            ent.PLOT_FPS: ("frames per second", BLUE),
            ent.PLOT_KEYFRAMES: ("keyframes", BLUE),
            ent.PLOT_MAP_POINTS: ("map points", GREY),
            ent.PLOT_ATE: ("ATE RMSE [m]", ORANGE),
            ent.PLOT_STATE: (
                "tracking state (0 not initialised, 1 initialising, 2 ok, 3 recently lost, 4 lost)", GREEN
            ),
            ent.PLOT_LOOPS: ("loops closed", RED),
        }
        for path, (name, colour) in styles.items():
            rec.log(path, rr.SeriesLines(names=name, colors=colour), static=True)

    # --- per frame --------------------------------------------------------------------
    def log_frame(self, frame: FrameLog) -> None:
        """Image, keypoints (green tracked, red untracked), camera pose and plots of a frame."""
        rec, idx = self._rec, int(frame.index)
        with self._lock:
            if self._epoch is None:
                self._epoch = float(frame.timestamp) > EPOCH_MIN_S
            self._timestamps[idx] = float(frame.timestamp)
            self._last_frame = idx
            if frame.T_wc is not None:
                self._trajectory.append(frame.T_wc[:3, 3])
            state = state_name(frame.state)
            state_changed = state != self._last_state
            self._last_state = state
        self._set_time(idx)
        if frame.image is not None and idx % self.config.image_every == 0:
            self._log_image(frame.image)
        uv, tracked = frame.keypoints_uv, frame.tracked
        rec.log(ent.KEYPOINTS_TRACKED, rr.Points2D(uv[tracked], colors=_GREEN, radii=KEYPOINT_RADIUS))
        rec.log(ent.KEYPOINTS_UNTRACKED, rr.Points2D(uv[~tracked], colors=_RED, radii=KEYPOINT_RADIUS))
        if frame.T_wc is not None:
            rec.log(ent.CAMERA, rr.Transform3D(translation=frame.T_wc[:3, 3], mat3x3=frame.T_wc[:3, :3]))
        rec.log(ent.PLOT_TRACKING, rr.Scalars([float(frame.n_tracked), float(len(uv))]))
        rec.log(ent.PLOT_FPS, rr.Scalars(float(frame.fps)))
        rec.log(ent.PLOT_STATE, rr.Scalars(float(state_code(frame.state))))
        if frame.n_keyframes is not None:
            rec.log(ent.PLOT_KEYFRAMES, rr.Scalars(float(frame.n_keyframes)))
        if frame.n_map_points is not None:
            rec.log(ent.PLOT_MAP_POINTS, rr.Scalars(float(frame.n_map_points)))
        if state_changed:
            rec.log(ent.EVENTS, rr.TextLog(f"tracking state: {state}", level="INFO"))

    def log_camera_pose(self, frame_index: int, T_wc: np.ndarray) -> None:
        """The camera pose, (4, 4) T_wc, of an earlier frame whose pose became known later
        (the first keyframe of a monocular initialisation)."""
        T_wc = np.asarray(T_wc, dtype=np.float64)
        self._set_time(frame_index)
        self._rec.log(ent.CAMERA, rr.Transform3D(translation=T_wc[:3, 3], mat3x3=T_wc[:3, :3]))

    def _log_image(self, image: np.ndarray) -> None:
        fmt = self.config.image_format
        if fmt == "jpeg":
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.config.jpeg_quality])
            if ok:
                self._rec.log(ent.IMAGE, rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))
                return
            log.warning("JPEG encoding of a %s image failed; logging it raw", image.shape)
        if fmt != "none":
            self._rec.log(ent.IMAGE, rr.Image(image, color_model="L" if image.ndim == 2 else "BGR"))

    # --- map --------------------------------------------------------------------------
    @property
    def last_map_frame(self) -> int | None:
        """Frame index of the latest map log (None before the first)."""
        return self._last_map_frame

    def map_due(self, frame_index: int, keyframe_inserted: bool = False, loop_closed: bool = False) -> bool:
        """Whether the map should be logged at this frame (so the caller builds a snapshot)."""
        last = self._last_map_frame
        if loop_closed or last is None:
            return True
        since = int(frame_index) - last
        if keyframe_inserted and self.config.map_on_keyframe and since >= self.config.map_min_interval:
            return True
        return since >= self.config.log_every_map

    def log_map(self, snapshot: MapSnapshot, frame_index: int | None = None) -> None:
        """Log the whole map, replacing the previous one (at ``frame_index``, else the last frame).

        Map points coloured by ``config.point_colour``; one wire frustum per keyframe (all in
        one line-strip entity); covisibility edges (blue) and loop edges (red) between
        keyframe centres; the keyframe path and the estimated camera trajectory.
        """
        rec = self._rec
        pts = snapshot.points_w
        finite = np.isfinite(pts).all(axis=1)
        if not finite.all():
            log.debug("map log: %d non-finite points left out", int((~finite).sum()))
            pts, obs = pts[finite], snapshot.point_obs_count[finite]
        else:
            obs = snapshot.point_obs_count
        colours = point_colours(pts, obs, self.config.point_colour, (2.0, float(self.config.obs_colour_max)))
        order = np.argsort(snapshot.keyframe_ids, kind="stable")
        centres = snapshot.keyframe_centres.astype(np.float32)
        with self._lock:
            self._last_map_frame = self._last_frame if frame_index is None else int(frame_index)
            self._kf_ids, self._kf_centres = snapshot.keyframe_ids, centres
            self._loop_edges = unique_edges(self._loop_edges, snapshot.loop_edges)
            loop_edges = self._loop_edges
            trajectory = self._trajectory.array.copy()
        self._set_time(frame_index)
        rec.log(ent.MAP_POINTS, rr.Points3D(pts.astype(np.float32), colors=colours, radii=MAP_POINT_RADIUS))
        frusta = frustum_strips(snapshot.keyframe_T_wc, self.camera, self.config.frustum_depth)
        rec.log(ent.KEYFRAMES, rr.LineStrips3D(_strips(frusta), colors=_BLUE, radii=THIN))
        rec.log(ent.KEYFRAME_PATH, rr.LineStrips3D(_strips(centres[order][None]), colors=_BLUE, radii=THIN))
        covis = _strips(edge_segments(snapshot.keyframe_ids, centres, snapshot.covis_edges))
        rec.log(ent.COVISIBILITY, rr.LineStrips3D(covis, colors=_BLUE_FAINT, radii=THIN))
        self._log_loop_edges(snapshot.keyframe_ids, centres, loop_edges)
        rec.log(ent.TRAJECTORY, rr.LineStrips3D(_strips(trajectory[None]), colors=_GREEN, radii=MEDIUM))
        rec.log(ent.PLOT_KEYFRAMES, rr.Scalars(float(len(snapshot.keyframe_ids))))
        rec.log(ent.PLOT_MAP_POINTS, rr.Scalars(float(len(pts))))

    def _log_loop_edges(self, kf_ids: np.ndarray, centres: np.ndarray, edges: np.ndarray) -> None:
        segments = _strips(edge_segments(kf_ids, centres, edges))
        self._rec.log(ent.LOOP_EDGES, rr.LineStrips3D(segments, colors=_RED, radii=THICK))

    def log_step(
        self,
        frame: FrameLog,
        snapshot_fn: Callable[[], MapSnapshot] | None = None,
        *,
        keyframe_inserted: bool = False,
        loop: tuple[int, int] | None = None,
    ) -> None:
        """One frame of a run: :meth:`log_frame`, then :meth:`log_loop` if a loop closed
        (keyframe ids ``loop``), then the map when :meth:`map_due` (``snapshot_fn()`` builds
        the :class:`MapSnapshot` only then)."""
        self.log_frame(frame)
        if loop is not None:
            self.log_loop(frame.index, *loop)
        if snapshot_fn is not None and self.map_due(frame.index, keyframe_inserted, loop is not None):
            self.log_map(snapshot_fn(), frame.index)

    # --- events and evaluation -----------------------------------------------------------
    def log_loop(
        self, frame_index: int, kf_a: int, kf_b: int, snapshot: MapSnapshot | None = None
    ) -> None:
        """Mark a loop closure between keyframes ``kf_a`` and ``kf_b`` at ``frame_index``.

        Adds a text event and a step in the loops-closed plot, and draws the loop edge.
        With ``snapshot`` (the corrected map) the whole map is logged at that frame;
        otherwise the caller logs it (``map_due(..., loop_closed=True)`` is True).
        """
        with self._lock:
            self._n_loops += 1
            n = self._n_loops
            self._loop_edges = unique_edges(self._loop_edges, np.array([[kf_a, kf_b]]))
            edges, kf_ids, centres = self._loop_edges, self._kf_ids, self._kf_centres
        self._set_time(frame_index)
        text = f"loop closed: keyframe {kf_a} <-> keyframe {kf_b}"
        self._rec.log(ent.EVENTS, rr.TextLog(text, level="WARN"))
        self._rec.log(ent.PLOT_LOOPS, rr.Scalars(float(n)))
        if snapshot is not None:
            self.log_map(snapshot, frame_index)
        else:
            self._log_loop_edges(kf_ids, centres, edges)

    def log_event(self, frame_index: int, text: str, level: str = "WARN") -> None:
        """A text event on the timeline (a new map, a merge)."""
        self._set_time(frame_index)
        self._rec.log(ent.EVENTS, rr.TextLog(text, level=level))

    def log_other_maps(self, maps: list[tuple[int, np.ndarray, np.ndarray]], frame_index: int | None = None) -> None:
        """The inactive maps of an atlas, each in its own colour: (map id, (P, 3) points,
        (K, 3) keyframe centres) per map; maps logged before and absent now are cleared."""
        self._set_time(frame_index)
        with self._lock:
            shown, self._other_maps = self._other_maps, {int(i) for i, _, _ in maps}
        for map_id in shown - self._other_maps:
            self._rec.log(f"{ent.OTHER_MAPS}/map_{map_id}", rr.Clear(recursive=True))
        for map_id, points, centres in maps:
            colour = _packed(MAP_PALETTE[int(map_id) % len(MAP_PALETTE)])
            path = f"{ent.OTHER_MAPS}/map_{int(map_id)}"
            pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
            pts = pts[np.isfinite(pts).all(axis=1)]
            self._rec.log(f"{path}/points", rr.Points3D(pts, colors=colour, radii=MAP_POINT_RADIUS))
            self._rec.log(f"{path}/keyframes", rr.Points3D(np.asarray(centres, np.float32).reshape(-1, 3),
                                                           colors=colour, radii=MEDIUM))  # fmt: skip

    def log_trajectory(self, positions_w: np.ndarray, frame_index: int | None = None) -> None:
        """Replace the estimated trajectory, (M, 3) camera centres (e.g. after loop correction);
        later tracked frames extend it."""
        with self._lock:
            self._trajectory.replace(positions_w)
            traj = self._trajectory.array.copy()
        self._set_time(frame_index)
        self._rec.log(ent.TRAJECTORY, rr.LineStrips3D(_strips(traj[None]), colors=_GREEN, radii=MEDIUM))

    def log_ground_truth(self, positions_w: np.ndarray, frame_index: int | None = None) -> None:
        """Ground-truth camera centres aligned to the map, (M, 3), as one line strip."""
        gt = np.asarray(positions_w, dtype=np.float32).reshape(-1, 3)
        self._set_time(frame_index)
        self._rec.log(ent.GROUND_TRUTH, rr.LineStrips3D(_strips(gt[None]), colors=_GREY, radii=MEDIUM))

    def log_ate(self, value: float, frame_index: int | None = None) -> None:
        """Absolute trajectory error (RMSE, metres, after alignment) so far."""
        self._set_time(frame_index)
        self._rec.log(ent.PLOT_ATE, rr.Scalars(float(value)))

    # --- end ---------------------------------------------------------------------------
    def close(self, timeout_s: float = 10.0) -> None:
        """Flush everything; in save mode the ``.rrd`` is then complete on disk."""
        if self._closed:
            return
        self._closed = True
        try:
            self._rec.flush(timeout_sec=timeout_s)
        except RuntimeError as exc:  # a viewer that went away: keep the run's result
            log.warning("rerun: could not flush the recording to %s (%s)", self.target, exc)
        self._rec.disconnect()
        if self.mode == "save":
            log.info("rerun: recording saved to %s (view it with: rerun %s)", self.target, self.target)

    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
