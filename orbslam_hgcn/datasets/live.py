"""Live sources: a camera device or a network stream, read with OpenCV's ``cv2.VideoCapture``.

A source is named ``cam:N`` (device N: ``/dev/videoN`` on Linux) or by a stream URL
(``rtsp://``, ``rtmp://``, ``http://``, ``https://``, ``udp://``, ``tcp://``). Unlike a
:class:`~orbslam_hgcn.datasets.base.Sequence` it has no length and cannot be read again:
:class:`LiveSource` yields frames as they arrive, each stamped with the time it was grabbed
(seconds since the first frame, ``time.perf_counter``).

A reader thread grabs frames as the device delivers them. With ``drop_late`` (the default
for a live source) it keeps only the newest frame: a frame the system was too busy to take
before the next one arrived is dropped and counted (:attr:`LiveSource.dropped`), as a camera
driver with a one-frame queue does, so the system never falls behind the camera. Without it
every frame is kept (up to ``max_queue``, then the oldest is dropped).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import cv2
import numpy as np

from orbslam_hgcn.errors import DatasetError
from orbslam_hgcn.geometry.camera import PinholeCamera

from .base import FrameRecord

log = logging.getLogger(__name__)

STREAM_SCHEMES = ("rtsp://", "rtsps://", "rtmp://", "http://", "https://", "udp://", "tcp://")


def is_live(spec: Any) -> bool:
    """Whether ``spec`` names a live source (``cam:N`` or a stream URL) rather than a dataset."""
    s = str(spec)
    return s.startswith("cam:") or s.lower().startswith(STREAM_SCHEMES)


def capture_target(spec: str) -> int | str:
    """What ``cv2.VideoCapture`` opens for ``spec``: a device index for ``cam:N``, else the URL."""
    if spec.startswith("cam:"):
        index = spec[4:]
        if not index.isdigit():
            raise DatasetError(f"{spec}: a camera device is cam:N with N a number (cam:0 for the first)")
        return int(index)
    return spec


class LiveSource:
    """Frames of a camera device or stream, as they arrive (see the module text).

    camera: the calibration (a live source carries none); frames of another size are an
    error. open_capture: builds the capture object from :func:`capture_target`'s value
    (default ``cv2.VideoCapture``; anything with ``isOpened``, ``read``, ``release``).
    color: give (H, W, 3) BGR images instead of gray. max_frames: stop after this many.
    """

    def __init__(
        self,
        spec: str,
        camera: PinholeCamera,
        *,
        drop_late: bool = True,
        color: bool = False,
        open_capture: Callable[[int | str], Any] | None = None,
        max_queue: int = 64,
        open_timeout_s: float = 10.0,
    ) -> None:
        self.spec, self.camera, self.color = spec, camera, color
        self.name = spec.replace("://", "_").replace("/", "_").replace(":", "_")
        self.drop_late = bool(drop_late)
        target = capture_target(spec)
        opener = open_capture or _open_video_capture
        self._cap = opener(target)
        if self._cap is None or not self._cap.isOpened():
            if self._cap is not None:
                self._cap.release()
            what = f"camera device {target}" if isinstance(target, int) else f"stream {spec}"
            raise DatasetError(f"{spec}: cannot open the {what} (not connected, busy, or no permission)")
        self._frames: collections.deque[tuple[float, np.ndarray]] = collections.deque(
            maxlen=1 if self.drop_late else max_queue)
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._ended: str | None = None
        self.grabbed = 0  # frames the source delivered
        self.dropped = 0  # of them, replaced by a newer one before the system took them
        self._t0: float | None = None
        self._open_timeout_s = open_timeout_s
        self._reader = threading.Thread(target=self._read, name="orbslam-live", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                ok, frame = self._cap.read()
            except Exception as exc:  # noqa: BLE001 - the source's failure ends the stream
                ok, frame = False, None
                log.warning("%s: reading failed: %s", self.spec, exc)
            t = time.perf_counter()
            with self._cond:
                if not ok or frame is None:
                    self._ended = "the stream ended" if self.grabbed else "the source gave no frame"
                    self._cond.notify_all()
                    return
                self.grabbed += 1
                if len(self._frames) == self._frames.maxlen:
                    self.dropped += 1
                self._frames.append((t, frame))
                self._cond.notify_all()

    def _image(self, frame: np.ndarray) -> np.ndarray:
        if frame.ndim == 3 and not self.color:
            frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        elif frame.ndim == 2 and self.color:
            frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        h, w = frame.shape[:2]
        cam = self.camera
        if (w, h) != (cam.width, cam.height):
            raise DatasetError(f"{self.spec}: frames are {w}x{h}, the camera {cam.width}x{cam.height}: give the "
                               "calibration of this camera at this resolution (--config)")  # fmt: skip
        return frame

    def __iter__(self) -> Iterator[FrameRecord]:
        index = 0
        deadline = time.perf_counter() + self._open_timeout_s
        while not self._stop.is_set():
            with self._cond:
                while not self._frames and self._ended is None and not self._stop.is_set():
                    self._cond.wait(0.05)
                    if index == 0 and time.perf_counter() > deadline:
                        raise DatasetError(f"{self.spec}: no frame within {self._open_timeout_s:g} s")
                if not self._frames:
                    if self._ended is not None:
                        log.info("%s: %s after %d frames", self.spec, self._ended, self.grabbed)
                    return
                t, frame = self._frames.popleft()
            if self._t0 is None:
                self._t0 = t
            yield FrameRecord(index, t - self._t0, self._image(frame), None)
            index += 1

    @property
    def ended(self) -> str | None:
        """Why the stream ended (None while it delivers)."""
        return self._ended

    def close(self) -> None:
        self._stop.set()
        self._reader.join(timeout=2.0)
        self._cap.release()

    def __enter__(self) -> LiveSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _open_video_capture(target: int | str) -> Any:
    return cv2.VideoCapture(target)
