"""ORB extraction in a child process (threaded runs of :class:`~orbslam_hgcn.runtime.system.System`).

Extraction is a chain of OpenCV calls with Python between them (reading the FAST corner
scores, the quadtree, the keypoint objects handed to the descriptor). OpenCV releases the
GIL, the Python parts hold it, so on a thread of the tracking process extraction slows
tracking and local mapping down and is slowed down by them. In a child process
(:class:`~orbslam_hgcn.childprocess.ChildProcess`) it runs beside them; only the image
goes in and the keypoint arrays come back (about 0.3 MB and 60 kB per frame).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable

import cv2
import numpy as np

from orbslam_hgcn.childprocess import ChildProcess
from orbslam_hgcn.config import ORBConfig
from orbslam_hgcn.errors import StageError
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.features.orb import ORBExtractor
from orbslam_hgcn.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)


class ExtractionError(StageError):
    """The extraction process failed or died (``lost``); the message carries its traceback."""

    stage = "extraction process"


def warm_up_extractors(extractors: Iterable[ORBExtractor], camera: PinholeCamera) -> None:
    """Run each extractor once on an image of the camera's size: this loads the compiled
    kernels and builds the pyramid tables of that size (about 60 ms at 640x480, once per
    process) before the first frame rather than inside it."""
    h, w = (camera.height, camera.width) if camera.width > 0 and camera.height > 0 else (120, 160)
    # A few bright squares on grey: corners on every level, so that every kernel runs, but
    # not the thousands of noise (a quarter of a second at KITTI's size for two extractors).
    image = np.full((h, w), 60, np.uint8)
    for k in range(1, 8):
        y, x, r = h * k // 8, w * k // 8, max(4, min(h, w) // 12)
        image[max(0, y - r):y + r, max(0, x - r):x + r] = 200
    for extractor in extractors:
        extractor.extract(image)


class Extractors:
    """ORB extractors by name over one camera: the object the child process serves."""

    def __init__(self, configs: dict[str, ORBConfig], camera: PinholeCamera) -> None:
        # One OpenCV thread: its parallel loops (resizing, blurring) only add switches when
        # every core is busy with tracking, mapping and BA.
        cv2.setNumThreads(1)
        self.extractors = {name: ORBExtractor(c) for name, c in configs.items()}
        self.camera = camera
        warm_up_extractors(self.extractors.values(), camera)

    def extract(self, name: str, image: np.ndarray) -> tuple[KeypointSet, float]:
        """Keypoints of a (H, W) uint8 image by extractor ``name``, and the time it took (ms)."""
        t0 = time.perf_counter()
        kps = self.extractors[name].extract(image, self.camera)
        return kps, 1000.0 * (time.perf_counter() - t0)


class ExtractionProcess:
    """Extract with the extractors ``configs`` ({name: ORBConfig}) in a child process.

    The process starts on :meth:`start` or the first request and lives until :meth:`close`;
    ``nice`` is added to its niceness (see :class:`~orbslam_hgcn.childprocess.ChildProcess`).
    """

    def __init__(self, configs: dict[str, ORBConfig], camera: PinholeCamera, nice: int = 0) -> None:
        self._child = ChildProcess("extraction", Extractors, (dict(configs), camera), ExtractionError, nice=nice)

    def start(self) -> None:
        """Start the process without waiting for it: it takes about a second (imports,
        compiled kernels) to build its extractors; :attr:`starting` says when it has not yet."""
        self._child.start()

    @property
    def starting(self) -> bool:
        """Started but not ready for requests yet (does not block): the caller extracts
        the frame itself meanwhile rather than wait."""
        return self._child.starting

    def extract(self, name: str, image: np.ndarray) -> tuple[KeypointSet, float]:
        """As :meth:`Extractors.extract`, in the child process. Raises ExtractionError."""
        return self._child.call("extract", (name, np.ascontiguousarray(image)))

    @property
    def alive(self) -> bool:
        return self._child.alive

    def close(self) -> None:
        self._child.close()
