"""The SLAM system: extraction and tracking on the calling thread, then local mapping and
loop closing, in order or in worker threads.

:class:`System` is the only place that knows every stage. The stages meet only here: the
tracker returns its new keyframes, :meth:`System._on_keyframe` hands each to a stage runner
(:mod:`orbslam_hgcn.runtime.stages`), which passes it to the local mapper and the keyframes
it keeps to the loop closer, if one is plugged in (any object with ``process(keyframe)``).

Sequential mode (``ThreadsConfig.sequential``, the default of the class): a keyframe is
mapped and loop-checked before the next frame, so local mapping is always idle when the
tracker asks, and a run gives the same result every time. Threaded mode (the default of
``orbslam-hgcn run``): local mapping and loop closing run in worker threads as in ORB-SLAM,
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
"""

from __future__ import annotations

import collections
import dataclasses
import gc
import logging
import math
import queue
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
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
from orbslam_hgcn.map import Frame, KeyFrame, Map
from orbslam_hgcn.map.atlas import Atlas
from orbslam_hgcn.mapping.local_mapper import LocalMapper
from orbslam_hgcn.runtime.extraction import ExtractionError, ExtractionProcess, warm_up_extractors
from orbslam_hgcn.runtime.locks import TrackingFirstLock, first
from orbslam_hgcn.runtime.results import (
    COUNT_EVERY,
    camera_trajectory,
    frame_counts,
    keyframe_trajectory,
    series_arrays,
    summary_ms,
    write_outputs,
)
from orbslam_hgcn.runtime.stages import SequentialStages, ThreadedStages
from orbslam_hgcn.runtime.worker import lower_thread_priority
from orbslam_hgcn.tracking.relocalization import Relocalizer
from orbslam_hgcn.tracking.tracker import Tracker, TrackingState, TrackResult
from orbslam_hgcn.trajectory import Trajectory, write_tum
from orbslam_hgcn.map.database import KeyframeDatabase

log = logging.getLogger(__name__)

INTERRUPTED = "interrupted (Ctrl-C)"  # RunSummary.stop_reason
TERMINATED = "terminated (SIGTERM)"
MAX_LOST_EXTRACTION = 3  # extraction processes a run may lose before it stops
MAX_BAD_FRAMES_LISTED = 100  # unreadable frames listed one by one in the stats


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


@dataclass(frozen=True)
class Features:
    """An image's ORB keypoints, the extractor that found them, when extraction started
    (``time.perf_counter``) and how long it took (ms)."""

    extractor: ORBExtractor
    keypoints: KeypointSet
    started: float
    ms: float


class _Pacer:
    """Holds frames back until a camera running at ``speed`` times the rate of their
    timestamps would have delivered them (``ThreadsConfig.speed``; 0: never waits).

    The clock starts at the first frame. A wait longer than ``max_wait_s`` (a gap in the
    timestamps) is cut to that, and the clock starts again from that frame. A frame already
    due is handed out at once: a system behind its camera is not slowed further. ``halt``
    ends a wait early (shutdown).
    """

    def __init__(self, speed: float, halt: threading.Event, max_wait_s: float = 1.0) -> None:
        self.speed, self.halt, self.max_wait_s = float(speed), halt, max_wait_s
        self._anchor: tuple[float, float] | None = None  # (perf_counter, timestamp)

    def wait(self, timestamp: float) -> None:
        if self.speed <= 0 or not np.isfinite(timestamp):
            return
        now = time.perf_counter()
        if self._anchor is None:
            self._anchor = (now, timestamp)
            return
        wait = self._anchor[0] + (timestamp - self._anchor[1]) / self.speed - now
        if wait > self.max_wait_s:
            self._anchor = (now + self.max_wait_s, timestamp)
            wait = self.max_wait_s
        if wait > 0:
            self.halt.wait(wait)

    def delivered(self, timestamp: float) -> bool:
        """Whether a camera would already have delivered the frame of ``timestamp`` (False
        when not pacing, or before the first frame)."""
        due = self.due(timestamp)
        return due is not None and due <= time.perf_counter()

    def due(self, timestamp: float) -> float | None:
        """When (time.perf_counter) a camera delivers the frame of ``timestamp``; None when
        not pacing or before the first frame."""
        if self.speed <= 0 or self._anchor is None or not np.isfinite(timestamp):
            return None
        return self._anchor[0] + (timestamp - self._anchor[1]) / self.speed


@dataclass(frozen=True)
class Skipped:
    """A frame of a run that was not processed: ``error`` None when it was dropped behind
    the camera, else why its image could not be read."""

    index: int
    timestamp: float
    error: DatasetError | None = None


def _freeze_startup_objects() -> bool:
    """Move every object alive now (modules, vocabulary, kernels, settings) out of the
    cyclic garbage collector's reach until the run ends (:func:`gc.freeze`): a full
    collection during the run then walks only the objects the run made. Measured unpaced on
    KITTI 00: the two or three full collections during the frames took about 100 ms each,
    on the tracking and mapping threads' shared lock. Objects frozen by someone else are
    left as they are (nothing is frozen, and nothing unfrozen at the end). Returns whether
    this call froze them."""
    if gc.get_freeze_count() or not gc.isenabled():
        return False
    gc.freeze()
    return True


class _Prefetch:
    """Reads frames ahead of tracking and extracts the features of frames i + 1 .. i +
    ``depth`` while frame i is tracked (threaded mode of :meth:`System.run`; one frame ahead
    while the tracker is not tracking).

    A reader thread (its niceness raised by ``reader_nice``) decodes up to ``ahead`` frames
    in order (one reader: video files need it). A frame that cannot be read (a DatasetError:
    missing, empty, corrupt, wrong size) is handed on as such and the reader goes on; any
    other error reading a frame is raised when that frame is taken, and ends the reading. A
    frame's job starts once the pacer hands it out. Extraction runs on a thread of its own,
    or in the system's extraction process when it has one. The extractor is chosen from the
    tracker's state when the job starts; if the state has changed when the frame is
    processed, :meth:`System.process` extracts again.

    With ``buffer_s`` > 0 (``threads.drop_late``: a live source), a paced run behind its
    camera drops frames as a camera driver whose queue holds ``buffer_s`` seconds of frames
    does: a frame is dropped, unprocessed, when the camera would already have delivered the
    frames of the next ``buffer_s`` seconds by the time the system is ready for it. 0 (a
    recorded sequence): no frame is dropped.
    """

    def __init__(
        self, system: System, sequence: Sequence, n: int, pacer: _Pacer, ahead: int = 4, buffer_s: float = 0.0,
        depth: int = 1, reader_nice: int = 0,
    ) -> None:
        self.system, self.sequence, self.n, self.pacer = system, sequence, n, pacer
        self.reader_nice = reader_nice
        self.buffer_s = buffer_s
        self.depth = max(1, depth)
        self._timestamps = np.asarray(sequence.timestamps, dtype=np.float64)
        self._records: queue.Queue = queue.Queue(maxsize=ahead)
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, name="orbslam-reader", daemon=True)
        self._reader.start()
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="orbslam-prefetch")
        self._jobs: collections.deque[tuple[int, Future]] = collections.deque()  # consecutive frames

    def _read(self) -> None:
        if self.reader_nice > 0:
            lower_thread_priority(self.reader_nice)
        for i in range(self.n):
            try:
                item: tuple[FrameRecord | None, BaseException | None] = (self.sequence[i], None)
            except BaseException as exc:  # noqa: BLE001 - raised or reported where the frame is taken
                item = (None, exc)
            while not self._stop.is_set():
                try:
                    self._records.put(item, timeout=0.05)
                    break
                except queue.Full:
                    continue
            if (item[1] is not None and not isinstance(item[1], DatasetError)) or self._stop.is_set():
                return

    def _job(self, i: int) -> tuple[FrameRecord, Features] | Skipped:
        while True:
            try:
                rec, exc = self._records.get(timeout=0.05)
                break
            except queue.Empty:
                # The reader ended on an earlier frame's error: that frame's job raises it,
                # which ends the run; this frame is never read.
                if not self._reader.is_alive() and self._records.empty():
                    raise SequenceEnded(f"frame {i} was not read: reading ended before it") from None
        if isinstance(exc, DatasetError):
            return Skipped(i, float(self._timestamps[i]), exc)
        if exc is not None:
            raise exc  # SequenceEnded: the sequence ends before its announced length
        self.pacer.wait(rec.timestamp)
        extractor = self.system._extractor_now()
        t0 = time.perf_counter()
        kps = self.system._extract(rec.image, extractor, remote=True)
        return rec, Features(extractor, kps, t0, 1000.0 * (time.perf_counter() - t0))

    def _get(self, i: int) -> tuple[FrameRecord, Features] | Skipped:
        """Frame ``i``'s job: the one started ahead, else run here."""
        if self._jobs and self._jobs[0][0] == i:
            return self._jobs.popleft()[1].result()
        return self._job(i)

    def _fill(self, i: int) -> None:
        """Start the jobs of the frames after ``i``: ``depth`` of them while the tracker
        tracks (its extractor stays), one while it initialises or relocalises (the
        extractor may change with the next frame)."""
        tracking = self.system.tracker.state == TrackingState.OK
        last = min(self.n - 1, i + (self.depth if tracking else 1))
        nxt = self._jobs[-1][0] + 1 if self._jobs else i + 1
        for j in range(nxt, last + 1):
            self._jobs.append((j, self._pool.submit(self._job, j)))

    def take(self, i: int) -> tuple[int, FrameRecord | None, Features | None, list[Skipped]]:
        """The next frame to process, from position ``i`` on: its position, record and
        features, and the frames skipped before it in order (dropped, see the class text,
        or unreadable); starts the jobs of the frames after it. The record is None when
        frame ``i`` is unreadable: the caller decides whether to go on (:meth:`take` of
        ``i + 1``). Raises SequenceEnded when the sequence ends before ``i``."""
        job = self._get(i)
        skipped: list[Skipped] = []
        while True:
            if isinstance(job, Skipped):
                skipped.append(job)
                self._fill(i)
                return i, None, None, skipped
            rec, features = job
            if not (self.buffer_s > 0 and i + 1 < self.n and self.pacer.delivered(self._timestamps[i] + self.buffer_s)):
                break
            skipped.append(Skipped(rec.index, rec.timestamp))
            i += 1
            job = self._get(i)
        self._fill(i)
        return i, rec, features, skipped

    def close(self) -> None:
        self.pacer.halt.set()  # a job waiting for its frame's time goes on at once
        for _, job in self._jobs:
            job.cancel()
        self._jobs.clear()
        self._pool.shutdown(wait=True)  # a running job still gets its frame from the reader
        self._stop.set()
        while True:
            try:
                self._records.get_nowait()
            except queue.Empty:
                break
        self._reader.join()


@dataclass
class RunSummary:
    """Outcome of :meth:`System.run`: frames seen, whether it was interrupted (and how:
    ``"interrupted (Ctrl-C)"``, ``"terminated (SIGTERM)"``; None when it was not)."""

    frames: int
    interrupted: bool
    wall_s: float
    stop_reason: str | None = None


class System:
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

    def _mapping_idle(self) -> bool:
        # With mapping_sync "due" a keyframe waits for mapping to finish the previous one,
        # local BA included: cut short by every keyframe that found it running, BA was
        # aborted on 64 of 66 keyframes of a loaded KITTI run (keyframe ATE 138 cm, 39 cm
        # with the BAs finished).
        if self.tracker.starved_on_interval:
            return self.stages.mapping_done()
        # With mapping_sync "points" a mapping held after a keyframe's new points
        # takes the next keyframe once released, as an idle one (the keyframes made do not
        # depend on how far it got).
        if self._hold_points and self.stages.holding:
            return True
        return self.stages.mapping_idle()

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

    def _map_due_keyframe(self, result: TrackResult, stages: SequentialStages | ThreadedStages) -> None:
        """threads.mapping_sync "due": a keyframe is due on this frame and local mapping is
        still busy with the previous one: wait for mapping to take one (within
        threads.sync_mapping_s, and with drop_late until the next frame's resume time)
        and make it from this frame. Timed as mapping_sync."""
        t0 = time.perf_counter()
        limit = min(self.configs.threads.sync_mapping_s, self._resume_by - t0)
        if limit > 0 and stages.wait_for_mapping(limit, done=True):
            # The frame was tracked without the points mapping made meanwhile; the keyframe
            # made from it observes them as one made after the mapping would.
            self._keyframe_after_wait(result, retrack=True)
        self.timings["mapping_sync"].append(1000.0 * (time.perf_counter() - t0))

    def _pipeline_mapping(self, result: TrackResult, stages: ThreadedStages, submitted: int) -> None:
        """threads.mapping_sync "points", after the frame's pose is out: local mapping holds
        after the new points (triangulated and fused) of the keyframes handed over before
        this frame (the first ``submitted``); release them (local BA and culling now run).
        If this frame made a keyframe, wait until its new points are made and fused
        (mapping finishes the released keyframes first), so that the next frame is tracked
        against them; else wait until mapping has finished the released keyframes, so that
        the next frame sees their local BA. Each wait is bounded by threads.sync_mapping_s (and
        with drop_late by the next frame's resume time) and timed as mapping_sync. Mapping
        thus works while the frames arrive, and when it keeps up, every frame is tracked
        against the same map whatever the machine's load."""
        released = stages.release_points(submitted)
        if not (result.new_keyframes or released):
            return
        t0 = time.perf_counter()
        limit = min(self.configs.threads.sync_mapping_s, self._resume_by - t0)
        if limit > 0:
            if result.new_keyframes:
                stages.wait_for_points(limit)
            else:
                stages.wait_for_mapping(limit, done=True)
        self.timings["mapping_sync"].append(1000.0 * (time.perf_counter() - t0))

    def _keyframe_after_wait(self, result: TrackResult, retrack: bool = False) -> KeyFrame | None:
        """Make the keyframe that was due on ``result``'s frame now that mapping takes it
        (``retrack``: after searching the local map again), and hand it over; None when
        the rules no longer ask for it."""
        with self.stages.handover():
            with first(self.tracker.map.lock):
                kf = self.tracker.keyframe_now(result.frame, result.n_inliers, retrack)
            if kf is not None:
                result.new_keyframes.append(kf)
                self._on_keyframe(kf)
        return kf

    def _map_starved_frame(self, result: TrackResult, stages: SequentialStages | ThreadedStages) -> None:
        """A keyframe was due on this frame but local mapping was busy (result.keyframe_starved):
        wait for mapping to take one, make it from this frame, and wait for mapping to
        triangulate its points, all within threads.keyframe_wait_s, so that the next frame
        finds a local map. The frames that arrive meanwhile wait (with threads.drop_late,
        a paced run drops those beyond its frame queue)."""
        t0 = time.perf_counter()
        deadline = t0 + self.configs.threads.keyframe_wait_s
        if stages.wait_for_mapping(self.configs.threads.keyframe_wait_s):
            if self._keyframe_after_wait(result) is not None:
                stages.wait_for_mapping(max(0.0, deadline - time.perf_counter()))
        self.timings["keyframe_wait"].append(1000.0 * (time.perf_counter() - t0))

    def _on_keyframe(self, kf: KeyFrame) -> None:
        if not self.configs.system.local_mapping:
            self.map.update_points(kf.observed_points()[1])
            self.map.update_connections(kf.id)
            return
        self.stages.submit(kf)

    def use_map(self, m: Map) -> None:
        """Make ``m`` (already the tracker's map) the map of every stage: the stages first
        finish the keyframes of the previous map, then the local mapper, loop closer and
        relocaliser are reset onto ``m``."""
        if self._stages is not None:
            self._stages.sync()
        if not self.sequential:
            self._share_map()
        self.map = m
        self.mapper.reset(m)
        if self.loop_closer is not None and hasattr(self.loop_closer, "reset"):
            self.loop_closer.reset(m, keep_database=True)
        if self.relocalizer is not None and hasattr(self.relocalizer, "reset"):
            self.relocalizer.reset(m)

    def install_atlas(self, atlas: Atlas, m: Map) -> None:
        """Use ``atlas`` (a loaded one) instead of the system's own, ``m`` its active map;
        before the first frame (then :meth:`use_map`)."""
        if self.sequential is False and isinstance(self.atlas.lock, TrackingFirstLock):
            atlas.lock = TrackingFirstLock()
        atlas.set_active(m)
        atlas.merge_hooks = [self.tracker.rescale_records]
        self.atlas = atlas
        self.tracker.atlas = atlas

    def _map_changed(self, frame_id: int, timestamp: float, result: TrackResult) -> None:
        """The tracker discarded its map, started a new one or relocalised into another:
        the stages follow it to the active map (the keyframe database keeps every map's
        keyframes, less those of a discarded map)."""
        if result.reset:
            self.n_resets += 1
        self.use_map(self.tracker.map)
        if self.database is not None:
            for k in self.database.keyframes():
                if self.atlas.map_of(k) is None:
                    self.database.erase(k)
        event = "reset" if result.reset else "new_map" if result.new_map else "map_switched"
        self.events.append({"frame": frame_id, "t": timestamp, "event": event, "map": self.map.map_id,
                            **({"why": result.why} if result.why else {})})

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

    # --- results -------------------------------------------------------------------------
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
