"""The frame feed of :meth:`System.run <orbslam_hgcn.runtime.system.System.run>`: frames
taken no faster than a camera delivers them (:class:`_Pacer`), read and extracted ahead of
tracking (:class:`_Prefetch`: a reader thread, extraction on a thread of its own or in the
system's extraction process), the features handed to the tracker with their frame
(:class:`Features`), the frames skipped on the way (:class:`Skipped`: dropped behind the
camera, or unreadable), and the garbage collector kept off the objects alive at start-up
(:func:`_freeze_startup_objects`).
"""

from __future__ import annotations

import collections
import gc
import queue
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from orbslam_hgcn.datasets import Sequence
from orbslam_hgcn.datasets.base import FrameRecord, SequenceEnded
from orbslam_hgcn.errors import DatasetError
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.features.orb import ORBExtractor
from orbslam_hgcn.runtime.worker import lower_thread_priority
from orbslam_hgcn.tracking.tracker import TrackingState


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
    or in the extraction process of ``system`` (the
    :class:`~orbslam_hgcn.runtime.system.System` that runs) when it has one. The extractor is chosen from the
    tracker's state when the job starts; if the state has changed when the frame is
    processed, :meth:`System.process` extracts again.

    With ``buffer_s`` > 0 (``threads.drop_late``: a live source), a paced run behind its
    camera drops frames as a camera driver whose queue holds ``buffer_s`` seconds of frames
    does: a frame is dropped, unprocessed, when the camera would already have delivered the
    frames of the next ``buffer_s`` seconds by the time the system is ready for it. 0 (a
    recorded sequence): no frame is dropped.
    """

    def __init__(
        self, system: Any, sequence: Sequence, n: int, pacer: _Pacer, ahead: int = 4, buffer_s: float = 0.0,
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
