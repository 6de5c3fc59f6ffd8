"""The SLAM system: extraction and tracking on the calling thread, then local mapping and
loop closing, in order or in worker threads.

:class:`System` is the only place that knows every stage. The stages meet only here: the
tracker returns its new keyframes, :meth:`System._on_keyframe` hands each to a stage runner
(:mod:`orbslam_hgcn.runtime.stages`), which passes it to the local mapper and the keyframes
it keeps to the loop closer, if one is plugged in (any object with ``process(keyframe)``).

Sequential mode (``ThreadsConfig.sequential``; ``System(sequential=True)``): a keyframe is
mapped and loop-checked before the next frame, so local mapping is always idle when the
tracker asks, and a run gives the same result every time. Threaded mode (the default, as
in ORB-SLAM): local mapping and loop closing run in worker threads as in ORB-SLAM,
the tracker holds the map lock while it tracks a frame, and bundle adjustments are solved
in child processes. :meth:`System.run` then reads images ahead on a reader thread,
extracts the next frame's features in a child process while the current one is tracked,
and takes frames no faster than their timestamps say a camera delivers them
(``threads.speed``): local mapping makes keyframes when it is free, so a run faster than
the camera would map with fewer keyframes, the fewer the faster the machine. Every frame
of a recorded sequence is processed: a machine too slow for the camera's rate falls behind
the clock, and :meth:`System.stats` says by how much (``real_time``); only a live source
drops late frames (``threads.drop_late``).
On a machine with few cores the real-time path goes first: the BA processes and the worker
threads run at a lower CPU priority (``threads.solver_nice``, ``threads.worker_nice``).
Threads and processes live from the first frame to :meth:`System.close`,
which :meth:`System.run` calls at its end (also on Ctrl-C or an error); a stage's exception
is raised in the caller's thread as a :class:`~orbslam_hgcn.runtime.worker.WorkerError`.

This module holds :class:`System` (its stages, one frame, a whole sequence),
:class:`Configs` and :class:`RunSummary`. System inherits the rest from modules of their
own: how keyframes are handed to local mapping and how long the tracker waits for it
(:class:`~orbslam_hgcn.runtime.handover.HandoverPolicy`), the stages' move to another map
of the atlas (:class:`~orbslam_hgcn.runtime.map_switch.MapSwitching`), and what a run
reports: statistics, series, trajectories, the files it saves
(:class:`~orbslam_hgcn.runtime.report.SystemReport`). The frames reach :meth:`System.run`
through :mod:`orbslam_hgcn.runtime.feed` (pacing, reading and extracting ahead).
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from orbslam_hgcn.config import (
    BackendConfig,
    InitializerConfig,
    LocalMappingConfig,
    LoopClosingConfig,
    MapConfig,
    ORBConfig,
    RelocalizationConfig,
    SystemConfig,
    ThreadsConfig,
    TrackingConfig,
    check_sections,
    load_yaml,
    section_from_yaml,
)
from orbslam_hgcn.childprocess import stopping
from orbslam_hgcn.datasets import Sequence
from orbslam_hgcn.datasets.base import FrameRecord, SequenceEnded
from orbslam_hgcn.errors import ConfigError, DatasetError, FrameError, Terminated
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.features.orb import ORBExtractor
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.loop.closer import LoopCloser
from orbslam_hgcn.map import Frame
from orbslam_hgcn.map.atlas import Atlas
from orbslam_hgcn.mapping.local_mapper import LocalMapper
from orbslam_hgcn.runtime.extraction import ExtractionError, ExtractionProcess, warm_up_extractors
from orbslam_hgcn.runtime.feed import Features, Skipped, _freeze_startup_objects, _Pacer, _Prefetch
from orbslam_hgcn.runtime.handover import HandoverPolicy
from orbslam_hgcn.runtime.locks import TrackingFirstLock, first
from orbslam_hgcn.runtime.map_switch import MapSwitching
from orbslam_hgcn.runtime.report import SystemReport
from orbslam_hgcn.runtime.results import COUNT_EVERY
from orbslam_hgcn.runtime.stages import SequentialStages, ThreadedStages
from orbslam_hgcn.tracking.relocalization import Relocalizer
from orbslam_hgcn.tracking.tracker import Tracker, TrackingState, TrackResult
from orbslam_hgcn.map.database import KeyframeDatabase

log = logging.getLogger(__name__)

INTERRUPTED = "interrupted (Ctrl-C)"  # RunSummary.stop_reason
TERMINATED = "terminated (SIGTERM)"
MAX_LOST_EXTRACTION = 3  # extraction processes a run may lose before it stops


def limit_library_threads(n: int) -> dict[str, int]:
    """Let OpenCV and faiss (when loaded: the vocabularies' word search) use ``n`` threads
    in this process (``threads.library_threads``; 0: leave their defaults); returns the
    counts now in force, by library."""
    if n > 0:
        cv2.setNumThreads(n)
    counts = {"opencv": int(cv2.getNumThreads())}
    faiss = sys.modules.get("faiss")
    if faiss is not None:
        if n > 0:
            faiss.omp_set_num_threads(n)
        counts["faiss"] = int(faiss.omp_get_max_threads())
    return counts


def warm_up_kernels() -> float:
    """Compile (first run after an install) or load from numba's cache the compiled kernels
    of tracking and local mapping: :func:`orbslam_hgcn.runtime.kernels.warm_up_tracking`."""
    from orbslam_hgcn.runtime.kernels import warm_up_tracking

    return warm_up_tracking()


@dataclass(frozen=True)
class Configs:
    """Every stage's configuration (YAML sections: orb, initializer, tracking,
    local_mapping, backend, map, system, loop_closing, relocalization, threads)."""

    orb: ORBConfig = field(default_factory=ORBConfig)
    initializer: InitializerConfig = field(default_factory=InitializerConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    local_mapping: LocalMappingConfig = field(default_factory=LocalMappingConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    map: MapConfig = field(default_factory=MapConfig)
    system: SystemConfig = field(default_factory=SystemConfig)
    loop_closing: LoopClosingConfig = field(default_factory=LoopClosingConfig)
    relocalization: RelocalizationConfig = field(default_factory=RelocalizationConfig)
    threads: ThreadsConfig = field(default_factory=ThreadsConfig)

    @classmethod
    def from_yaml(cls, path: str | Path | None) -> Configs:
        """Defaults, overridden by the sections present in the YAML file ``path``."""
        if path is None:
            return cls()
        return cls.from_layers([(load_yaml(path), path)])

    @classmethod
    def from_layers(cls, layers: list[tuple[dict[str, Any], str | Path]]) -> Configs:
        """Defaults, overridden key by key by each layer in turn: (the mapping of a config
        file, its path for error messages). Each layer is validated on its own, so an error
        names the file that holds the bad key, or the section no stage knows."""
        defaults = cls()
        stages = [f.name for f in dataclasses.fields(cls)]
        for data, path in layers:
            check_sections(data, path, stages)
        kw = {}
        for f in dataclasses.fields(cls):
            section_type = type(getattr(defaults, f.name))
            merged: dict[str, Any] = {}
            for data, path in layers:
                section_from_yaml(section_type, data, path, f.name)  # validates this layer
                merged.update((data or {}).get(f.name) or {})
            kw[f.name] = section_from_yaml(section_type, {f.name: merged}, "<merged settings>", f.name)
        return cls(**kw)


@dataclass
class RunSummary:
    """Outcome of :meth:`System.run`: frames seen, whether it was interrupted (and how:
    ``"interrupted (Ctrl-C)"``, ``"terminated (SIGTERM)"``; None when it was not)."""

    frames: int
    interrupted: bool
    wall_s: float
    stop_reason: str | None = None


class System(HandoverPolicy, MapSwitching, SystemReport):
    """Monocular SLAM over one camera.

    sequential: run the stages in order on the calling thread (True) or local mapping and
    loop closing in worker threads (False); None: as ``configs.threads.sequential``.
    """

    def __init__(
        self,
        camera: PinholeCamera,
        configs: Configs | None = None,
        vocabulary: Any = None,
        loop_closer: Any = None,
        relocalizer: Any = None,
        sequential: bool | None = None,
    ) -> None:
        self.camera = camera
        self.configs = c = configs or Configs()
        self.sequential = c.threads.sequential if sequential is None else bool(sequential)
        self._stages: SequentialStages | ThreadedStages | None = None
        self.vocabulary = vocabulary
        self.loop_closer = loop_closer
        self.relocalizer = relocalizer
        # Maps: the active one in self.map; a new one is started when tracking stays lost,
        # the others kept for relocalisation and merging (orbslam_hgcn.map.atlas).
        self.atlas = Atlas(c.map)
        self.map = self.atlas.active
        self.extractor = ORBExtractor(c.orb)
        n_init = max(1, int(round(c.orb.n_features * c.tracking.init_features_factor)))
        self.init_extractor = ORBExtractor(dataclasses.replace(c.orb, n_features=n_init))
        # Threaded runs with threads.extraction_process: both extractors in a child process
        # (started by the first run, stopped by close()), which knows them by these names.
        self._extraction: ExtractionProcess | None = None
        self._extractor_names = {"init": self.init_extractor, "normal": self.extractor}
        # With a vocabulary, keyframes go into one keyframe database that relocalisation and
        # loop closing share; the loop closer indexes them (and closes loops when
        # loop_closing.enabled).
        self.database: KeyframeDatabase | None = None
        if vocabulary is not None:
            self.database = KeyframeDatabase()
            if relocalizer is None:
                self.relocalizer = Relocalizer(self.map, self.database, c.relocalization, c.backend, vocabulary)
            if loop_closer is None:
                self.loop_closer = LoopCloser(self.map, self.database, c.loop_closing, c.backend, vocabulary)
        self.tracker = Tracker(
            self.map, c.tracking, c.initializer, c.backend, vocabulary=vocabulary, mapping_idle=self._mapping_idle,
            relocalizer=self.relocalizer, atlas=self.atlas,
        )
        self.atlas.merge_hooks.append(self.tracker.rescale_records)
        self.mapper = LocalMapper(self.map, c.local_mapping, c.backend, vocabulary=vocabulary)
        self.timings: dict[str, list[float]] = {
            "extraction": [], "tracking": [], "tracking_cpu": [], "frame": [], "lock_wait": [], "keyframe_wait": [],
            "mapping_sync": [],
        }  # fmt: skip
        # Per frame of timings["frame"]: whether a BA or pose graph was being solved during it,
        # and when (time.perf_counter) the frame's extraction started.
        self.frame_optimising: list[bool] = []
        # (stages, their count of optimisations started) when the last frame's pose came
        # out: an optimisation started during the waits after it (local BA beside
        # triangulation runs in them) counts for the next frame, whose latency holds them.
        self._activity_mark: tuple[Any, int] | None = None
        self.frame_started: list[float] = []
        # The series of series.npz (runtime/results.py): per frame processed (frame, timestamp,
        # tracking ms or NaN, frame ms, time.time()); every COUNT_EVERY-th frame (frame, the
        # active map's keyframes, points); per keyframe mapped (filled by the stage runner).
        self.frame_series: list[tuple[int, float, float, float, float, float]] = []
        self.count_series: list[tuple[int, int, int]] = []
        self.keyframe_series: list[tuple[int, int, float, float, float]] = []
        self.events: list[dict[str, Any]] = []
        self.n_resets = 0
        # Frames skipped because their image could not be read: {frame, t, error}.
        self.bad_frames: list[dict[str, Any]] = []
        self.n_extraction_lost = 0  # extraction processes that died during the run
        self.library_threads: dict[str, int] = {}  # set by run(): threads of OpenCV and faiss
        self.ahead_nice = 0  # set by run(): niceness added to the reader and the extraction process
        # Niceness added to the BA processes: threads.solver_nice, but none in an unpaced run
        # (set with the stage runner; see ThreadsConfig.solver_nice).
        self.solver_nice = self.configs.threads.solver_nice
        # Paced runs: per frame processed, how late (ms) its pose came out after the camera
        # would have delivered it; the camera time and wall time the run spanned (s).
        self.lags_ms: list[float] = []
        self._span: tuple[float, float] | None = None  # (first frame's perf_counter, timestamp)
        # perf_counter when run() started and when it returned (stages drained).
        self._run_times: tuple[float, float | None] | None = None
        self._last_out: tuple[float, float] | None = None  # (last pose's perf_counter, timestamp)
        self._resume_by: float | None = None  # see run(): the latest a keyframe may hold the tracker
        self._hold_points = False  # see process(): threads.mapping_sync "points" in force
        # Called as observer(system, record, result) after every frame of :meth:`run`
        # (visualisation, progress reporting); they must not change the map.
        self.observers: list[Callable[[System, FrameRecord, TrackResult], None]] = []
        # The tracking kernels are compiled (first run after an install) or loaded from
        # their cache here rather than inside the first frames.
        warm_up_kernels()

    # --- stages ------------------------------------------------------------------------
    @property
    def stages(self) -> SequentialStages | ThreadedStages:
        """The stage runner (threads and solver processes start on first use)."""
        if self._stages is None:
            if self.sequential:
                self._stages = SequentialStages(self.mapper, self.loop_closer, series=self.keyframe_series)
            else:
                self._share_map()
                t = self.configs.threads
                self.solver_nice = t.solver_nice if t.speed > 0 else 0  # run()'s pace
                self._stages = ThreadedStages(
                    self.mapper, self.loop_closer, t.process_solver, self.solver_nice, t.worker_nice,
                    series=self.keyframe_series, local_ba_process=t.local_ba_process,
                )
        return self._stages

    def _share_map(self) -> None:
        """Give the map a lock that lets tracking go first (threaded mode; no other thread
        may hold the map's lock yet)."""
        if not isinstance(self.tracker.map.lock, TrackingFirstLock):
            self.tracker.map.lock = TrackingFirstLock()

    def close(self, drain: bool = True) -> None:
        """Finish the keyframes handed to local mapping and loop closing (``drain``; else
        drop them), stop their threads and solver processes. Raises a stage's error."""
        stages, self._stages = self._stages, None
        extraction, self._extraction = self._extraction, None
        try:
            if stages is not None:
                stages.close(drain)
        finally:
            if extraction is not None:
                extraction.close()

    def __enter__(self) -> System:
        return self

    def __exit__(self, exc_type: Any, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self._close_quietly()

    def _close_quietly(self) -> None:
        """Stop without draining while another exception propagates (logged, not raised)."""
        try:
            self.close(drain=False)
        except Exception as exc:  # noqa: BLE001 - the exception already propagating wins
            log.error("while stopping after an error: %s", exc)

    # --- one frame -----------------------------------------------------------------------
    def _extractor_now(self) -> ORBExtractor:
        """The extractor the tracker's state asks for (more features while initialising)."""
        initializing = self.tracker.state == TrackingState.NOT_INITIALIZED
        return self.init_extractor if initializing else self.extractor

    def _extract(self, image: np.ndarray, extractor: ORBExtractor, remote: bool = False) -> KeypointSet:
        """Keypoints of ``image`` by ``extractor``; with ``remote``, in the extraction
        process when the system has one and it has started (the same keypoints either way)."""
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if remote and self._extraction is not None and not self._extraction.starting:
            name = next(k for k, e in self._extractor_names.items() if e is extractor)
            try:
                return self._extraction.extract(name, image)[0]
            except ExtractionError as exc:
                # A process that died (killed, out of memory) is replaced by the next request;
                # this frame is extracted here meanwhile. An error it reports is a bug: raised.
                # While this process stops (SIGTERM) it is neither lost nor replaced.
                if exc.lost and stopping():
                    log.debug("%s", exc)
                    return extractor.extract(image, self.camera)
                if not exc.lost or self.n_extraction_lost >= MAX_LOST_EXTRACTION:
                    raise
                self.n_extraction_lost += 1
                log.warning("%s; extracting this frame here, the next ones in a new process", exc)
        return extractor.extract(image, self.camera)

    def process(
        self, image: np.ndarray, timestamp: float, frame_id: int, features: Features | None = None
    ) -> TrackResult:
        """Extract, track and map one image ((H, W) uint8 gray or (H, W, 3) BGR).

        features: the image's keypoints already extracted, with the extractor used; they
        are extracted again if the tracker now needs the other extractor. The frame's
        latency (``timings["frame"]``) then counts from the start of that extraction.
        """
        t0 = time.perf_counter()
        stages = self.stages
        stages.check()
        started, optimising = stages.activity.started, stages.optimising
        if self._activity_mark is not None and self._activity_mark[0] is stages:
            started = self._activity_mark[1]
        if not self.tracker.can_recover:
            return self.tracker.skip(frame_id, timestamp)
        extractor = self._extractor_now()
        if features is not None and features.extractor is extractor:
            kps, extraction_ms = features.keypoints, features.ms
            t0 = min(t0, features.started)
        else:
            kps = self._extract(image, extractor)
            extraction_ms = 1000.0 * (time.perf_counter() - t0)
        t1 = time.perf_counter()
        threads = self.configs.threads
        sync = self._resume_by is not None and threads.sync_mapping_s > 0
        self.tracker.starved_on_interval = sync and threads.mapping_sync == "due"
        # "points": local mapping holds after a keyframe's new points until the next frame
        # is tracked (ThreadedStages.hold_points).
        hold = self._hold_points = sync and threads.mapping_sync == "points"
        if isinstance(stages, ThreadedStages):
            stages.hold_points = hold
        submitted = stages.submitted
        # A loop correction pausing local mapping waits for this frame's keyframe to be
        # handed over (ThreadedStages.pause_mapping); after a map reset it is handed over
        # below, once the stages are on the new map.
        with stages.handover():
            with first(self.tracker.map.lock):
                self.timings["lock_wait"].append(1000.0 * (time.perf_counter() - t1))
                result = self.tracker.track(Frame(frame_id, timestamp, self.camera, kps))
                if len(self.frame_series) % COUNT_EVERY == 0:  # under the lock already held
                    m = self.tracker.map
                    self.count_series.append((frame_id, m.n_keyframes(), m.n_points()))
            map_changed = result.reset or result.new_map or result.switched_map
            if not map_changed:
                for kf in result.new_keyframes:
                    self._on_keyframe(kf)
        self.timings["extraction"].append(extraction_ms)
        if result.state == TrackingState.OK and not result.initialized:
            self.timings["tracking"].append(result.time_ms)
            self.timings["tracking_cpu"].append(result.cpu_ms)
        if map_changed:
            self._map_changed(frame_id, timestamp, result)
        if result.initialized:
            self.events.append({"frame": frame_id, "t": timestamp, "event": "initialized", "map": self.map.map_id,
                                "keyframe_frames": [kf.frame_id for kf in result.new_keyframes]})
        if result.lost:
            self.events.append({"frame": frame_id, "t": timestamp, "event": "lost", "map": self.map.map_id})
        if map_changed:
            for kf in result.new_keyframes:
                self._on_keyframe(kf)
        # The frame's latency: from the start of its extraction to its pose. The waits
        # below hold the next frames, whose latency then counts them.
        self.timings["frame"].append(1000.0 * (time.perf_counter() - t0))
        self.frame_started.append(t0)
        tracked = result.state == TrackingState.OK and not result.initialized
        self.frame_series.append((frame_id, timestamp, result.time_ms if tracked else math.nan,
                                  self.timings["frame"][-1], time.time(),
                                  result.cpu_ms if tracked else math.nan))  # fmt: skip
        optimising = optimising or stages.optimising or stages.activity.started != started
        self.frame_optimising.append(bool(optimising))
        self._activity_mark = (stages, stages.activity.started)
        if hold:
            self._pipeline_mapping(result, stages, submitted)
        elif sync and threads.mapping_sync == "due":
            if result.keyframe_starved:
                # The next keyframe is due and mapping has not taken the previous one yet.
                self._map_due_keyframe(result, stages)
        elif result.keyframe_starved and threads.keyframe_wait_s > 0:
            self._map_starved_frame(result, stages)
        elif result.new_keyframes and sync:
            # Local mapping finishes the keyframe before the next frame is tracked.
            t3 = time.perf_counter()
            limit = min(threads.sync_mapping_s, self._resume_by - t3)
            if limit > 0:
                stages.wait_for_mapping(limit, done=True)
            self.timings["mapping_sync"].append(1000.0 * (time.perf_counter() - t3))
        return result

    # --- a whole sequence ----------------------------------------------------------------
    def run(
        self, sequence: Sequence, max_frames: int | None = None, progress: bool | None = None,
        on_bad_frame: str = "skip",
    ) -> RunSummary:  # fmt: skip
        """Process the frames of ``sequence`` in order.

        A frame whose image cannot be read (missing, empty, truncated or corrupt file, wrong
        size: a DatasetError of the reader) is skipped with a warning and recorded
        (``on_bad_frame="skip"``: :attr:`bad_frames`, ``frames.unreadable`` in the stats)
        or ends the run with a :class:`~orbslam_hgcn.errors.FrameError` (``"stop"``).
        Ctrl-C (or :class:`~orbslam_hgcn.errors.Terminated`) stops after the current step;
        what exists is kept (``RunSummary.interrupted``). At the end (also after Ctrl-C)
        the keyframes handed to the stages are finished and their threads joined. On an
        error every thread and child process is stopped and the error propagates; the map
        and the tracker's records keep what was processed, so :meth:`save` still writes it.
        """
        if on_bad_frame not in ("skip", "stop"):
            raise ConfigError(f"on_bad_frame must be skip or stop, found {on_bad_frame!r}")
        n = len(sequence) if max_frames is None else min(len(sequence), max_frames)
        show = self.configs.system.progress if progress is None else progress
        bar = tqdm(total=n, unit="frame", disable=not show, dynamic_ncols=True)
        t0 = time.perf_counter()
        self._run_times = (t0, None)
        done, stop_reason = 0, None
        threads = self.configs.threads
        # Threaded runs take frames no faster than the camera would deliver them; sequential
        # runs give the same result at any pace.
        pacer = _Pacer(0.0 if self.sequential else threads.speed, threading.Event())
        self.library_threads = limit_library_threads(threads.library_threads)
        prefetch, frozen = None, False
        try:
            try:
                # Threaded: the worker threads (and a local BA process, with
                # threads.local_ba_process) start now, not waited for.
                self.stages  # noqa: B018
                # Unpaced, the reader and the extraction process work ahead, off the tracker's
                # path: it gets the CPU first (threads.ahead_nice).
                prefetching = not self.sequential and threads.prefetch
                self.ahead_nice = threads.ahead_nice if prefetching and pacer.speed == 0 else 0
                if prefetching:
                    if threads.extraction_process and self._extraction is None:
                        self._extraction = ExtractionProcess(
                            {name: e.config for name, e in self._extractor_names.items()}, self.camera,
                            nice=self.ahead_nice,
                        )
                        # Not waited for: until the child has built its extractors (about a
                        # second: imports, compiled kernels) the frames are extracted in this
                        # process (_extract), as is the frame on which the tracker's state
                        # changes (process()). Both extractors' kernels and pyramid tables are
                        # loaded here meanwhile, rather than inside those frames.
                        self._extraction.start()
                        warm_up_extractors(self._extractor_names.values(), self.camera)
                    buffer_s = threads.frame_buffer_s if threads.drop_late else 0.0
                    # Ahead by more than a frame only unpaced: a paced run behind its camera would
                    # extract frames the tracker cannot take yet, on the cores local mapping needs.
                    depth = threads.prefetch_frames if pacer.speed == 0 else 1
                    prefetch = _Prefetch(
                        self, sequence, n, pacer, buffer_s=buffer_s, depth=depth, reader_nice=self.ahead_nice
                    )
                frozen = _freeze_startup_objects()
                stamps = np.asarray(sequence.timestamps, dtype=np.float64)  # as announced
                i = 0
                while i < n:
                    try:
                        if prefetch is not None:
                            i, rec, features, skipped = prefetch.take(i)
                        else:
                            rec, features, skipped = self._read_frame(sequence, i, stamps), None, []
                            if isinstance(rec, Skipped):
                                rec, skipped = None, [rec]
                            else:
                                pacer.wait(rec.timestamp)
                    except SequenceEnded as exc:
                        log.info("the sequence ends at frame %d: %s", i, exc)
                        break
                    i += 1
                    for s in skipped:
                        done += 1
                        bar.update(1)
                        if s.error is None:
                            self.tracker.drop(s.index, s.timestamp)
                        else:
                            self._skip_unreadable(s, on_bad_frame)
                    if rec is None:
                        continue
                    t_frame = time.perf_counter()
                    # A keyframe's mapping may hold the tracker (threads.sync_mapping_s); with
                    # drop_late, not so long that the next frame would wait more than half the frame
                    # queue. A recorded sequence loses no frame to the wait: it runs late.
                    due = pacer.due(float(stamps[i])) if i < n else None
                    late_ok = due is None or not threads.drop_late
                    self._resume_by = math.inf if late_ok else due + 0.5 * threads.frame_buffer_s
                    result = self.process(rec.image, rec.timestamp, rec.index, features)
                    self._clock_frame(pacer, rec.timestamp, features)
                    if self.observers:
                        with self.map.lock:
                            for observe in self.observers:
                                observe(self, rec, result)
                    done += 1
                    bar.update(1)
                    dt = time.perf_counter() - t_frame
                    # Counts only when the map is free: the bar must not wait for a stage.
                    if show and self.map.lock.acquire(blocking=False):
                        try:
                            bar.set_postfix(
                                state=result.state.value, kf=self.map.n_keyframes(), pts=self.map.n_points(),
                                fps=f"{1.0 / max(dt, 1e-6):.1f}", refresh=False,
                            )  # fmt: skip
                        finally:
                            self.map.lock.release()
            except KeyboardInterrupt as exc:
                stop_reason = TERMINATED if isinstance(exc, Terminated) else INTERRUPTED
                log.warning("%s after %d frames; saving what exists", stop_reason, done)
            except BaseException:
                # The reader and the prefetch job first, so that no job starts a child process
                # again while the stages stop.
                if prefetch is not None:
                    prefetch.close()
                    prefetch = None
                bar.close()
                self._close_quietly()
                raise
            finally:
                if prefetch is not None:
                    prefetch.close()
            bar.close()
            try:
                self.close(drain=True)
            except KeyboardInterrupt as exc:  # a second Ctrl-C while the stages finish: stop them now
                stop_reason = stop_reason or (TERMINATED if isinstance(exc, Terminated) else INTERRUPTED)
                self._close_quietly()
            except BaseException:
                self._close_quietly()
                raise
        finally:
            if frozen:  # on every way out: the caller's collector as it was
                gc.unfreeze()
        self._run_times = (t0, time.perf_counter())
        return RunSummary(done, stop_reason is not None, self._run_times[1] - t0, stop_reason)

    def _clock_frame(self, pacer: _Pacer, timestamp: float, features: Features | None) -> None:
        """Note when the pose of the frame of ``timestamp`` came out: its lag behind the
        camera (paced runs) and the span of the run (real-time factor)."""
        now = time.perf_counter()
        if self._span is None and np.isfinite(timestamp):
            start = self.frame_started[-1] if self.frame_started else now
            self._span = (features.started if features is not None else start, timestamp)
        if np.isfinite(timestamp):
            self._last_out = (now, timestamp)
        due = pacer.due(timestamp)
        if due is not None:
            self.lags_ms.append(1000.0 * (now - due))

    def _read_frame(self, sequence: Sequence, i: int, stamps: np.ndarray) -> FrameRecord | Skipped:
        """Frame ``i`` of ``sequence``, or a :class:`Skipped` saying why it cannot be read
        (``stamps``: the sequence's timestamps). Raises SequenceEnded at its end."""
        try:
            return sequence[i]
        except DatasetError as exc:
            return Skipped(i, float(stamps[i]), exc)

    def _skip_unreadable(self, s: Skipped, on_bad_frame: str) -> None:
        """Record an unreadable frame (the tracking state is unchanged; the motion model
        spans it as it spans a dropped frame), or stop the run on it."""
        self.tracker.drop(s.index, s.timestamp, unreadable=True)
        self.bad_frames.append({"frame": s.index, "t": s.timestamp, "error": str(s.error)})
        if on_bad_frame == "stop":
            raise FrameError(f"frame {s.index}: {s.error}", frame=s.index) from s.error
        n = len(self.bad_frames)
        if n <= 5 or n % 100 == 0:
            log.warning("frame %d skipped (%d so far): %s", s.index, n, s.error)
