"""A video file taken as a sequence, decoded with OpenCV's ``cv2.VideoCapture``.

Frame ``i`` gets timestamp ``i / fps`` seconds. The camera must be given, since video files
carry no calibration.

Frames are decoded in order by one decoder that stays open: asking for the frame after the
last one given reads on, a frame a few ahead decodes through the ones between, and only a
frame out of order seeks (``CAP_PROP_POS_FRAMES``, which on inter-coded video decodes
again from the last key frame, about ten times slower per frame; :attr:`VideoSequence.seeks`
counts them). The frame count the container announces is an upper bound: some containers
announce more frames than their stream holds (a truncated file, a writer that stopped
early). The stream's end, met while reading in order, gives the true count: asking for a
frame at or past it raises :class:`~orbslam_hgcn.datasets.base.SequenceEnded` (an IndexError), and :func:`len` tells the
true count from then on.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from orbslam_hgcn.errors import DatasetError
from orbslam_hgcn.geometry.camera import PinholeCamera

from .base import FrameRecord, Sequence, SequenceEnded, check_image_size, require_camera

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv")
# A frame at most this far ahead of the decoder is reached by decoding through the frames
# between (about a key-frame interval of common encoders) rather than by a seek.
READ_AHEAD_MAX = 30


class VideoSequence(Sequence):
    """Frames of one video file.

    camera: required (PinholeCamera, YAML path or shipped name).
    fps: frame rate for timestamps; default the container's rate, else the camera's.
    """

    ground_truth = None

    def __init__(
        self,
        path: str | Path,
        camera: PinholeCamera | str | Path | None = None,
        *,
        fps: float | None = None,
        color: bool = False,
    ) -> None:
        self.path = Path(path).expanduser()
        if not self.path.is_file():
            raise DatasetError(f"{self.path}: video file not found")
        self.camera = require_camera(camera, self.path, "video file")
        self.color = color
        self.name = self.path.stem
        cap = self._open()
        try:
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            container_fps = float(cap.get(cv2.CAP_PROP_FPS))
            if n <= 0:  # some containers do not record a frame count: count by decoding
                n = 0
                while cap.grab():
                    n += 1
        finally:
            cap.release()
        if n == 0:
            raise DatasetError(f"{self.path}: video holds no frames")
        self._n = n
        self.announced = n  # the count the container gave (or the one decoded without it)
        rate = fps if fps is not None else (container_fps if container_fps > 0 else self.camera.fps)
        if not rate > 0:
            raise DatasetError(f"{self.path}: frame rate must be positive, got {rate}")
        self.fps = float(rate)
        self._cap: cv2.VideoCapture | None = None
        self._pos: int | None = 0  # the frame the decoder gives next (None: unknown, after a failed seek)
        self._lock = threading.Lock()
        self.seeks = 0  # frames reached by seeking (out of order)

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            cap.release()
            raise DatasetError(f"{self.path}: cannot open video (corrupt or unsupported format)")
        return cap

    def __len__(self) -> int:
        return self._n

    @property
    def timestamps(self) -> np.ndarray:
        return np.arange(self._n, dtype=np.float64) / self.fps

    def _record(self, index: int, frame: np.ndarray) -> FrameRecord:
        image = frame if self.color or frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        if self.color and image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        check_image_size(image, self.camera, f"{self.path} frame {index}")
        return FrameRecord(index, index / self.fps, image, None)

    def __iter__(self) -> Iterator[FrameRecord]:
        i = 0
        while i < len(self):
            try:
                rec = self[i]
            except SequenceEnded:  # the stream ended before the announced count
                return
            yield rec
            i += 1

    def __getitem__(self, index: int) -> FrameRecord:
        if not -self._n <= index < self._n:
            raise IndexError(f"frame {index} out of range for a video of {self._n} frames")
        index %= self._n
        with self._lock:
            if self._cap is None:
                self._cap, self._pos = self._open(), 0
            pos = self._pos
            in_order = pos is not None and pos <= index <= pos + READ_AHEAD_MAX
            if in_order:
                while self._pos < index and self._cap.grab():
                    self._pos += 1
                ok, frame = self._cap.read() if self._pos == index else (False, None)
            else:
                self.seeks += 1
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, index)
                ok, frame = self._cap.read()
            if not ok:
                if in_order:
                    self._stream_ended(self._pos)
                    raise SequenceEnded(f"frame {index} is past the end of {self.path} ({self._n} frames)")
                self._pos = None  # the decoder's place is unknown: the next frame seeks
                raise DatasetError(f"{self.path}: cannot decode frame {index} (seeking)")
            self._pos = index + 1
        return self._record(index, frame)

    def _stream_ended(self, n: int) -> None:
        """The decoder met the stream's end at frame ``n``: the true frame count."""
        if n == 0:
            raise DatasetError(f"{self.path}: cannot decode the first frame")
        if n < self._n:
            log.warning("%s: the stream ends after %d frames (the container announced %d)", self.path, n, self._n)
            self._n = n

    def close(self) -> None:
        """Release the decoder (the next frame asked for opens it again)."""
        with self._lock:
            if self._cap is not None:
                self._cap.release()
                self._cap = None
