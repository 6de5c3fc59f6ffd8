"""The common shape of every image sequence: :class:`FrameRecord` and :class:`Sequence`.

A reader opens a dataset, checks its listings up front (so a malformed line is reported
before any work starts) and loads images lazily, one at a time, while it is iterated.
Every user-facing failure is a :class:`~orbslam_hgcn.errors.DatasetError` whose message
names the file, and the line where one applies.
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from orbslam_hgcn.config import load_camera
from orbslam_hgcn.datasets.png import decode_png
from orbslam_hgcn.errors import DatasetError, OrbslamError, where
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.trajectory import Trajectory

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")


@dataclass(frozen=True, eq=False)
class FrameRecord:
    """One image of a sequence.

    index: position in the sequence (0-based).
    timestamp: seconds.
    image: (H, W) uint8 grayscale, or (H, W, 3) uint8 BGR when the reader was built with
        ``color=True``.
    T_wc: (4, 4) float64 ground-truth camera-to-world pose, or None where the sequence has
        no ground truth near this timestamp.
    """

    index: int
    timestamp: float
    image: np.ndarray
    T_wc: np.ndarray | None


class SequenceEnded(IndexError):
    """A reader was asked for a frame at or past the end of its sequence, an end found only
    while reading (a video whose container announced more frames than its stream holds):
    the sequence ends there, and its ``len`` is the true count from then on."""


class Sequence(abc.ABC):
    """A finite, ordered, re-iterable sequence of :class:`FrameRecord`.

    Subclasses provide ``__len__``, ``__getitem__`` and the ``name``, ``camera`` and
    ``ground_truth`` attributes; iteration loads one image at a time.
    """

    name: str
    camera: PinholeCamera
    ground_truth: Trajectory | None
    color: bool

    @abc.abstractmethod
    def __len__(self) -> int: ...

    @abc.abstractmethod
    def __getitem__(self, index: int) -> FrameRecord: ...

    def __iter__(self) -> Iterator[FrameRecord]:
        for i in range(len(self)):
            yield self[i]

    @property
    @abc.abstractmethod
    def timestamps(self) -> np.ndarray:
        """(N,) float64 frame timestamps in seconds."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, frames={len(self)}, camera={self.camera.name!r})"


class ImageListSequence(Sequence):
    """A sequence of image files with known timestamps and optional per-frame poses.

    paths: N image files. timestamps: (N,) float64 seconds. poses_wc: (N, 4, 4) float64
    ground-truth ``T_wc`` per frame with NaN where a frame has none, or None. sources: for
    each frame, the listing line it came from (``file:line``), quoted in image errors.
    """

    def __init__(
        self,
        *,
        name: str,
        camera: PinholeCamera,
        paths: list[Path],
        timestamps: np.ndarray,
        poses_wc: np.ndarray | None = None,
        ground_truth: Trajectory | None = None,
        sources: list[str] | None = None,
        color: bool = False,
    ) -> None:
        self.name = name
        self.camera = camera
        self.color = color
        self.ground_truth = ground_truth
        self._paths = list(paths)
        self._timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        if len(self._timestamps) != len(self._paths):
            raise ValueError("paths and timestamps differ in length")
        if poses_wc is not None:
            poses_wc = np.asarray(poses_wc, dtype=np.float64).reshape(-1, 4, 4)
            if len(poses_wc) != len(self._paths):
                raise ValueError("paths and poses differ in length")
        self._poses_wc = poses_wc
        self._sources = sources

    def __len__(self) -> int:
        return len(self._paths)

    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps

    @property
    def paths(self) -> list[Path]:
        """The N image files, in sequence order."""
        return list(self._paths)

    @property
    def has_pose(self) -> np.ndarray:
        """(N,) bool: which frames carry a ground-truth pose."""
        if self._poses_wc is None:
            return np.zeros(len(self), dtype=bool)
        return np.isfinite(self._poses_wc[:, 0, 0])

    def pose(self, index: int) -> np.ndarray | None:
        """(4, 4) float64 ground-truth ``T_wc`` of frame ``index``, or None."""
        if self._poses_wc is None or not np.isfinite(self._poses_wc[index, 0, 0]):
            return None
        return self._poses_wc[index].copy()

    def __getitem__(self, index: int) -> FrameRecord:
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for a sequence of {n} frames")
        index %= n
        source = self._sources[index] if self._sources is not None else None
        image = read_image(self._paths[index], color=self.color, source=source)
        check_image_size(image, self.camera, self._paths[index])
        return FrameRecord(index, float(self._timestamps[index]), image, self.pose(index))


def read_image(path: Path, *, color: bool = False, source: str | None = None) -> np.ndarray:
    """Load one image: (H, W) uint8 grayscale, or (H, W, 3) uint8 BGR with ``color``.

    8-bit grey and RGB PNGs are decoded by :func:`~orbslam_hgcn.datasets.png.decode_png`
    (the same pixels, faster), every other image by OpenCV, which scales 16-bit images to
    8 bits. A missing, empty, unreadable or corrupt file is a DatasetError naming the file
    (and the listing line ``source`` it came from, where given).
    """
    flags = cv2.IMREAD_COLOR if color else cv2.IMREAD_GRAYSCALE
    listed = f" (listed at {source})" if source else ""
    if not path.is_file():
        raise DatasetError(f"{path}: image file not found{listed}")
    if path.stat().st_size == 0:
        raise DatasetError(f"{path}: empty image file (0 bytes){listed}")
    if path.suffix.lower() == ".png":  # the datasets' format: decoded here when it can be
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise DatasetError(f"{path}: cannot read image ({exc.strerror}){listed}") from None
        image = decode_png(data, color)
        if image is None:  # a PNG this decoder does not take: OpenCV's, from the same bytes
            image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    else:
        image = cv2.imread(str(path), flags)
    if image is None or image.size == 0:
        raise DatasetError(f"{path}: cannot read image (corrupt, truncated or unsupported format){listed}")
    return image


def check_image_size(image: np.ndarray, camera: PinholeCamera, path: Path | str) -> None:
    """A DatasetError when ``image`` is not ``camera.width`` x ``camera.height``."""
    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise DatasetError(
            f"{path}: image is {w}x{h} but camera {camera.name!r} expects "
            f"{camera.width}x{camera.height}; pass the matching camera config"
        )


def resolve_camera(camera: PinholeCamera | str | Path | None) -> PinholeCamera | None:
    """A PinholeCamera from a camera, a YAML path or a shipped config name (None stays None)."""
    if camera is None or isinstance(camera, PinholeCamera):
        return camera
    return load_camera(camera)


def require_camera(camera: PinholeCamera | str | Path | None, path: Path, kind: str) -> PinholeCamera:
    """Resolve ``camera``; a reader that cannot infer intrinsics asks for ``--config``."""
    cam = resolve_camera(camera)
    if cam is None:
        raise OrbslamError(
            f"{path}: a {kind} carries no calibration; give the camera with --config "
            "(a YAML file or a shipped name such as tum_fr3)"
        )
    return cam


def require_dir(path: str | Path, what: str) -> Path:
    """The folder ``path``, or a DatasetError saying it is missing."""
    p = Path(path).expanduser()
    if not p.exists():
        raise DatasetError(f"{p}: {what} folder not found")
    if not p.is_dir():
        raise DatasetError(f"{p}: expected a {what} folder, found a file")
    return p


def data_lines(path: Path) -> Iterable[tuple[int, list[str]]]:
    """Yield ``(line_number, fields)`` of a text listing, skipping blanks and ``#`` comments.

    Fields are separated by whitespace and/or commas. A missing file is a DatasetError.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read file ({exc.strerror})") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield lineno, s.replace(",", " ").split()


def parse_floats(fields: list[str], path: Path, lineno: int) -> np.ndarray:
    """(len(fields),) float64 values of one listing line; a bad number names file:line."""
    try:
        vals = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{where(path, lineno)}: not a number in {' '.join(fields)!r}") from None
    if not np.all(np.isfinite(vals)):
        raise DatasetError(f"{where(path, lineno)}: non-finite value in {' '.join(fields)!r}")
    return vals


def associate(query: np.ndarray, reference: np.ndarray, max_gap: float) -> np.ndarray:
    """Nearest-in-time association, vectorised.

    query: (N,) timestamps; reference: (M,) sorted timestamps (same unit as ``max_gap``).
    Returns (N,) int64 indices into ``reference``, -1 where the nearest is farther than
    ``max_gap`` or ``reference`` is empty.
    """
    query = np.asarray(query)
    reference = np.asarray(reference)
    out = np.full(len(query), -1, dtype=np.int64)
    if len(reference) == 0 or len(query) == 0:
        return out
    m = len(reference)
    pos = np.searchsorted(reference, query)
    lo = np.clip(pos - 1, 0, m - 1)
    hi = np.clip(pos, 0, m - 1)
    d_lo = np.abs(query - reference[lo])
    d_hi = np.abs(reference[hi] - query)
    best = np.where(d_hi < d_lo, hi, lo)
    gap = np.minimum(d_lo, d_hi)
    ok = gap <= max_gap
    out[ok] = best[ok]
    return out


def poses_for(index: np.ndarray, trajectory: Trajectory | None) -> np.ndarray | None:
    """(N, 4, 4) float64 poses of ``trajectory`` picked by ``index`` (NaN where index is -1)."""
    if trajectory is None:
        return None
    out = np.full((len(index), 4, 4), np.nan)
    ok = index >= 0
    out[ok] = trajectory.poses[index[ok]]
    return out
