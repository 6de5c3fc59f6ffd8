"""A video file taken as a sequence, decoded with OpenCV's ``cv2.VideoCapture``.

Frame ``i`` gets timestamp ``i / fps`` seconds. Iteration decodes frames one at a time in
order; indexing seeks (slower, and only as exact as the container allows). The camera
must be given, since video files carry no calibration.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from orbslam_hgcn.errors import DatasetError
from orbslam_hgcn.geometry.camera import PinholeCamera

from .base import FrameRecord, Sequence, check_image_size, require_camera

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv")


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
        rate = fps if fps is not None else (container_fps if container_fps > 0 else self.camera.fps)
        if not rate > 0:
            raise DatasetError(f"{self.path}: frame rate must be positive, got {rate}")
        self.fps = float(rate)
        self._seek_cap: cv2.VideoCapture | None = None

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
        cap = self._open()
        try:
            for i in range(self._n):
                ok, frame = cap.read()
                if not ok:
                    if i == 0:
                        raise DatasetError(f"{self.path}: cannot decode the first frame")
                    log.warning("%s: decoding stopped at frame %d of %d", self.path, i, self._n)
                    return
                yield self._record(i, frame)
        finally:
            cap.release()

    def __getitem__(self, index: int) -> FrameRecord:
        if not -self._n <= index < self._n:
            raise IndexError(f"frame {index} out of range for a video of {self._n} frames")
        index %= self._n
        if self._seek_cap is None:
            self._seek_cap = self._open()
        self._seek_cap.set(cv2.CAP_PROP_POS_FRAMES, index)
        ok, frame = self._seek_cap.read()
        if not ok:
            raise DatasetError(f"{self.path}: cannot decode frame {index}")
        return self._record(index, frame)

    def close(self) -> None:
        """Release the seeking decoder (iteration opens and closes its own)."""
        if self._seek_cap is not None:
            self._seek_cap.release()
            self._seek_cap = None
