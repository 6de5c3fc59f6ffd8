"""The Python API: :class:`Slam`, a SLAM system fed one image at a time from your own code.

::

    from orbslam_hgcn import Slam

    with Slam(camera="tum_fr3", vocab="kmeans") as slam:     # or a PinholeCamera / YAML file
        for t, image in frames:
            result = slam.track(image, t)                  # result.pose: T_wc (4, 4) or None
        slam.save("out")                                   # the files `orbslam-hgcn run` writes
        slam.save_map("room.npz")

``orbslam-hgcn run`` is a user of it: it builds a :class:`Slam` for the dataset's camera and
feeds it the dataset (:meth:`Slam.run_sequence`), or a live source frame by frame. Settings
are resolved once, as for every command (:mod:`orbslam_hgcn.app.settings`). Errors are
:class:`~orbslam_hgcn.errors.OrbslamError` subclasses: ``ConfigError`` (settings, camera),
``VocabularyError``, ``MapFileError``, ``DatasetError``, ``StageError`` (a worker failed).

Threaded (the default, as ``run``): local mapping and loop closing run in worker threads;
:meth:`Slam.track` returns once the frame's pose is out and, as ``run`` does over a recorded
sequence, after the waits for mapping that ``threads.mapping_sync`` asks (the same poses at
any pace). Sequential (``sequential=True``): every stage in order on the caller's thread,
bit for bit the poses of ``orbslam-hgcn run --sequential`` on the same frames.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orbslam_hgcn.app.settings import (
    Settings,
    UserConfig,
    camera_argument,
    flag_layer,
    resolve_settings,
    user_config,
)
from orbslam_hgcn.config import VocabularyConfig
from orbslam_hgcn.errors import ConfigError, OrbslamError, VocabularyError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.runtime.system import System, limit_library_threads
from orbslam_hgcn.trajectory import Trajectory

log = logging.getLogger(__name__)

# The vocabulary without --vocab / vocab=: the arm that won the place-recognition ablation
# (bench/bench_track_words.py; README "Shipped vocabularies"): k-means words of lone
# descriptors. Neither the shipped HGCN (its network is in effect the identity) nor the
# track network over map points beat it there. The vocabulary config's default kind.
DEFAULT_VOCAB = VocabularyConfig.kind


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


@dataclass(frozen=True)
class Tracked:
    """What :meth:`Slam.track` gives for one frame.

    pose: T_wc (4, 4), the camera-to-world pose, or None when the frame has none (not yet
    initialised, lost); state: ``"ok"``, ``"lost"`` or ``"not initialised"``; points: map
    points matched in the frame (inliers); keyframe: the frame became a keyframe;
    initialized: the map was made on this frame; map_changed: the map was reset, a new one
    started or relocalisation moved to another map of the atlas.
    """

    frame: int
    timestamp: float
    pose: np.ndarray | None
    state: str
    points: int
    keyframe: bool
    initialized: bool
    map_changed: bool

    @property
    def ok(self) -> bool:
        return self.state == "ok"


@dataclass(frozen=True)
class MapData:
    """The active map as numpy arrays (a copy: the system may go on changing its map).

    keyframe_ids (K,), keyframe_frames (K,) frame numbers, keyframe_times (K,) seconds,
    keyframe_poses (K, 4, 4) T_wc; point_ids (N,), points (N, 3) world positions,
    point_observations (N,) keyframes observing each point. Monocular: an arbitrary scale.
    """

    map_id: int
    keyframe_ids: np.ndarray
    keyframe_frames: np.ndarray
    keyframe_times: np.ndarray
    keyframe_poses: np.ndarray
    point_ids: np.ndarray
    points: np.ndarray
    point_observations: np.ndarray


class Slam:
    """Monocular SLAM fed frame by frame (see the module text).

    camera: a shipped camera name (``tum_fr3``, ``kitti_00-02``, ``euroc_cam0``, ...), a YAML
        file with ``fx, fy, cx, cy, width, height`` (and ``dist``), or a
        :class:`~orbslam_hgcn.geometry.camera.PinholeCamera`; None: the camera of ``config``.
    config: a YAML file, a shipped camera name, or a mapping of sections
        (``{"orb": {"n_features": 1500}}``), over the shipped settings of the camera.
    kind: the dataset family (``tum``, ``kitti``, ``euroc``) whose shipped settings apply
        when the camera matches no shipped config.
    vocab: ``kmeans`` (default), ``hgcn``, ``orb``, ``orb10k``, a vocabulary file, or ``none``;
        with ``load_map``, by default the map's own vocabulary.
    sequential, loop_closing: None takes the config (threaded; loop closing on).
    load_map: a map saved by :meth:`save_map` or ``run --save-map``; the first frames are
        relocalised in it. localization: with ``load_map``, track without changing the map.
    rerun: ``["spawn"]``, ``["save", "FILE.rrd"]`` or ``["connect", "HOST:PORT"]`` to log the
        run to rerun as it goes (``out``: where a recording goes when no viewer answers).
    """

    def __init__(
        self,
        camera: PinholeCamera | str | Path | None = None,
        *,
        config: str | Path | Mapping[str, Any] | None = None,
        kind: str | None = None,
        vocab: str | None = None,
        sequential: bool | None = None,
        loop_closing: bool | None = None,
        load_map: str | Path | None = None,
        localization: bool = False,
        rerun: Sequence[str] | None = None,
        out: str | Path | None = None,
        name: str = "slam",
        _settings: Settings | None = None,
    ) -> None:
        if _settings is not None:  # resolved by the caller (run, which logs them first)
            self.camera, self.settings = camera_argument(camera, _settings.user), _settings
        else:
            user = user_config(config)
            self.camera = camera_argument(camera, user)
            flags = flag_layer(sequential=sequential, loop_closing=loop_closing)
            self.settings = resolve_settings(self.camera, kind, user, flags)
        user = self.settings.user
        configs = self.settings.configs
        if localization and load_map is None:
            raise ConfigError("localization needs a saved map: load_map=FILE (--load-map)")
        rerun_sink = None
        if rerun is not None:
            from orbslam_hgcn.viz.sinks import parse_rerun_arg

            rerun_sink = parse_rerun_arg(rerun)
        self.vocab_name = vocab
        if load_map is not None:
            from orbslam_hgcn.app.mapfile import map_vocabulary_name

            self.vocab_name = vocab or map_vocabulary_name(load_map)  # the vocabulary the map was built with
        self.vocabulary = open_vocabulary(self.vocab_name, configs.loop_closing.enabled or load_map is not None)
        self.system = System(self.camera, configs, vocabulary=self.vocabulary)
        self.loaded_map = str(load_map) if load_map is not None else None
        self.localization = bool(localization)
        if load_map is not None:
            from orbslam_hgcn.app.mapfile import load_map as read_saved_map

            self.system.install_map(read_saved_map(load_map, self.vocabulary).map, localization)
        self.viz = None
        if rerun_sink is not None:
            from orbslam_hgcn.viz.live import attach_live_viz

            self.viz = attach_live_viz(self.system, *rerun_sink, out=out, config=user.path, name=name)
        self.viz_open = self.viz is not None
        self._frames = 0
        self._t0: float | None = None
        self._closed = False
        self._library_threads_set = False

    # --- settings ------------------------------------------------------------------------
    @property
    def configs(self) -> Any:
        """Every stage's settings as resolved (:class:`~orbslam_hgcn.runtime.system.Configs`)."""
        return self.system.configs

    @property
    def sequential(self) -> bool:
        return self.system.sequential

    @property
    def user_config(self) -> UserConfig:
        return self.settings.user

    # --- frames --------------------------------------------------------------------------
    def track(self, image: np.ndarray, timestamp: float | None = None, frame: int | None = None,
              resume_by: float = math.inf) -> Tracked:  # fmt: skip
        """Track one image: (H, W) uint8 gray or (H, W, 3) uint8 BGR, of the camera's size.

        timestamp: seconds (increasing); None: seconds since the first frame, by the clock.
        frame: the frame's number (default: one more than the last). resume_by
        (``time.perf_counter``): the latest a wait for mapping may hold this call (a live
        source that must not fall behind); by default as long as ``threads.sync_mapping_s``.
        """
        if self._closed:
            raise OrbslamError("this Slam is closed")
        image = self._check_image(image)
        now = time.perf_counter()
        if timestamp is None:
            if self._t0 is None:
                self._t0 = now
            timestamp = now - self._t0
        frame = self._frames if frame is None else int(frame)
        if not self._library_threads_set:
            self.system.library_threads = limit_library_threads(self.configs.threads.library_threads)
            self._library_threads_set = True
        system = self.system
        system._resume_by = resume_by  # as System.run sets it for each frame, in either mode
        result = system.process(image, float(timestamp), frame)
        system._clock_frame(_NO_PACER, float(timestamp), None)
        if system.observers:
            record = _Record(frame, float(timestamp), image)
            with system.map.lock:
                for observe in system.observers:
                    observe(system, record, result)
        self._frames = frame + 1
        pose = None
        if result.state.value == "ok" and result.frame is not None and result.frame.T_cw is not None:
            pose = result.frame.T_wc
        return Tracked(frame, float(timestamp), pose, result.state.value, int(result.n_inliers),
                       bool(result.new_keyframes) and not result.initialized, bool(result.initialized),
                       bool(result.reset or result.new_map or result.switched_map))  # fmt: skip

    def _check_image(self, image: Any) -> np.ndarray:
        img = np.asarray(image)
        cam = self.camera
        if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)):
            raise ConfigError(f"an image must be (H, W) or (H, W, 3) uint8, got {img.dtype} {img.shape}")
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        if (img.shape[1], img.shape[0]) != (cam.width, cam.height):
            raise ConfigError(f"the image is {img.shape[1]}x{img.shape[0]}, the camera {cam.width}x{cam.height}")
        return img

    def run_sequence(self, sequence: Any, max_frames: int | None = None, progress: bool | None = None,
                     on_bad_frame: str = "skip") -> Any:  # fmt: skip
        """Feed a recorded sequence (:func:`~orbslam_hgcn.datasets.open_sequence`): threaded,
        its frames read and extracted ahead and taken at the camera's pace
        (``threads.speed``), as ``orbslam-hgcn run`` does; returns the
        :class:`~orbslam_hgcn.runtime.system.RunSummary`. The stages are drained at its end."""
        summary = self.system.run(sequence, max_frames, progress=progress, on_bad_frame=on_bad_frame)
        self._frames = max(self._frames, summary.frames)
        return summary

    # --- results -------------------------------------------------------------------------
    @property
    def state(self) -> str:
        return self.system.tracker.state.value

    @property
    def frames(self) -> int:
        """Frames given so far."""
        return self._frames

    def map(self) -> MapData:
        """The map the trajectories come from (the atlas's largest) as numpy arrays."""
        m = self.system.output_map()
        with m.lock:
            kfs = m.keyframes()
            pids = np.asarray(m.point_ids(), dtype=np.int64)
            points = np.asarray(m.positions(pids), dtype=np.float64).reshape(-1, 3).copy()
            obs = np.asarray(m.n_observations(pids), dtype=np.int64).copy()
            poses = np.stack([kf.T_wc for kf in kfs]) if kfs else np.zeros((0, 4, 4))
            return MapData(
                int(m.map_id), np.array([kf.id for kf in kfs], dtype=np.int64),
                np.array([kf.frame_id for kf in kfs], dtype=np.int64),
                np.array([kf.timestamp for kf in kfs], dtype=np.float64), poses.copy(), pids.copy(), points, obs,
            )  # fmt: skip

    def keyframe_trajectory(self) -> Trajectory:
        """T_wc of every keyframe of the output map (KeyFrameTrajectory.txt)."""
        return self.system.keyframe_trajectory()

    def camera_trajectory(self) -> Trajectory:
        """T_wc of every frame tracked in the output map (CameraTrajectory.txt)."""
        return self.system.camera_trajectory()

    def stats(self) -> dict[str, Any]:
        """Counts and per-stage timings so far (stats.json)."""
        return self.system.stats()

    def save(self, out: str | Path, extra: dict[str, Any] | None = None,
             camera: Trajectory | None = None) -> dict[str, Path]:  # fmt: skip
        """Write KeyFrameTrajectory.txt, CameraTrajectory.txt (TUM, T_wc), stats.json and
        series.npz into ``out``, as ``orbslam-hgcn run`` writes them."""
        from orbslam_hgcn.outputs import check_output_folder

        out = check_output_folder(out)
        base = {
            "settings": self.settings_summary(),
            "vocabulary": repr(self.vocabulary) if self.vocabulary is not None else None,
            "map_file": {"loaded": self.loaded_map, "localization": self.localization},
        }
        base.update(extra or {})
        if self.viz is not None and "rerun" not in base:
            base["rerun"] = self.viz.summary()
        try:
            return self.system.save(out, base, camera)
        except OSError as exc:
            raise OrbslamError(f"{out}: cannot write the results ({exc.strerror or exc})") from None

    def settings_summary(self) -> dict[str, Any]:
        s = self.settings
        return {
            "dataset": s.settings_path.stem if s.settings_path is not None else None,
            "dataset_chosen_by": s.chosen_by,
            "config": s.user.origin or None,
            "orb_features": self.configs.orb.n_features,
        }

    def save_map(self, path: str | Path) -> Path:
        """Write the atlas (every map) with its vocabulary reference (``--load-map`` reads it)."""
        from orbslam_hgcn.app.mapfile import save_system_map
        from orbslam_hgcn.outputs import check_output_file

        return save_system_map(check_output_file(path, "the map file"), self.system, self.vocab_name)

    def export_ply(self, path: str | Path,
                   image_of: Callable[[int], np.ndarray | None] | None = None) -> dict[str, Path]:  # fmt: skip
        """Write the output map's points (``path``) and keyframe poses (``<stem>_keyframes.ply``)
        as PLY for MeshLab, Open3D or CloudCompare. ``image_of(frame)``: the image of a
        frame number (BGR or gray) to colour the points from; else they are coloured by
        how many keyframes observe them."""
        from orbslam_hgcn.map.ply import export_map_ply, point_colours_from_images

        m = self.system.output_map()
        with m.lock:
            colours = point_colours_from_images(m, image_of) if image_of is not None else None
            return export_map_ply(m, path, colours)

    # --- end -----------------------------------------------------------------------------
    def close(self, drain: bool = True) -> None:
        """Finish the keyframes handed to mapping (``drain``; else drop them), stop threads and
        processes, and end the rerun recording. Calling it again does nothing more."""
        self._closed = True
        viz, self.viz_open = self.viz_open, False
        try:
            self.system.close(drain)
        finally:
            if viz and self.viz is not None:
                try:
                    self.viz.finish(self.system)
                except Exception as exc:  # noqa: BLE001 - the run's own results come first
                    log.warning("rerun recording not finished: %s", exc)

    def __enter__(self) -> Slam:
        return self

    def __exit__(self, exc_type: Any, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            try:
                self.close(drain=False)
            except Exception as err:  # noqa: BLE001 - the exception already propagating wins
                log.error("while stopping after an error: %s", err)


@dataclass(frozen=True)
class _Record:
    """A frame as the system's observers see it (FrameRecord's fields)."""

    index: int
    timestamp: float
    image: np.ndarray
    T_wc: np.ndarray | None = None


class _NoPacer:
    """A frame fed by :meth:`Slam.track` has no camera clock to be late against."""

    @staticmethod
    def due(timestamp: float) -> None:
        return None


_NO_PACER: Any = _NoPacer()
