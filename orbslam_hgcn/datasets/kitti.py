"""KITTI odometry sequences (Geiger et al., "Are we ready for Autonomous Driving? The KITTI
Vision Benchmark Suite", CVPR 2012), read as a monocular sequence of the left grayscale camera.

Layout (as unpacked from ``data_odometry_gray.zip`` and ``data_odometry_poses.zip``)::

    dataset/sequences/NN/image_0/000000.png ...   # rectified grayscale images (or .jpg)
    dataset/sequences/NN/times.txt                # one timestamp (s) per image
    dataset/sequences/NN/calib.txt                # "P0: p00 p01 ... p23" projection matrices
    dataset/poses/NN.txt                          # optional: 12 values per image

A poses line is the row-major 3x4 matrix ``[R | t]`` that maps points of camera 0 at that
image into the frame of camera 0 at the first image: ``T_wc`` with the world being the
first camera. The images are rectified, so the camera has no distortion; ``fx fy cx cy``
come from the projection matrix of the chosen camera (``P0`` for ``image_0``).
"""

from __future__ import annotations

import logging
import re
import struct
from pathlib import Path

import cv2
import numpy as np

from orbslam_hgcn.datasets.png import SIGNATURE
from orbslam_hgcn.errors import DatasetError, where
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.trajectory import Trajectory

from .base import ImageListSequence, data_lines, parse_floats, require_dir, resolve_camera

log = logging.getLogger(__name__)

DEFAULT_FPS = 10.0  # KITTI's cameras are triggered by the laser scanner at about 10 Hz
# The image files a sequence may hold, all of one format: KITTI's PNG, or JPEG (a camera's
# or a synthetic render's); suffix -> format name.
FRAME_SUFFIXES = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """Read a KITTI ``calib.txt``: key -> (3, 4) float64 matrix (P0..P3, Tr)."""
    if not path.is_file():
        raise DatasetError(f"{path}: calibration file not found")
    out: dict[str, np.ndarray] = {}
    for lineno, fields in data_lines(path):
        key = fields[0].rstrip(":")
        if not fields[0].endswith(":") or len(fields) != 13:
            raise DatasetError(f"{where(path, lineno)}: expected 'KEY: 12 numbers', found {' '.join(fields)!r}")
        out[key] = parse_floats(fields[1:], path, lineno).reshape(3, 4)
    return out


def read_times(path: Path) -> np.ndarray:
    """(N,) float64 timestamps in seconds from a KITTI ``times.txt`` (one per line)."""
    stamps: list[float] = []
    for lineno, fields in data_lines(path):
        if len(fields) != 1:
            raise DatasetError(f"{where(path, lineno)}: expected one timestamp, found {len(fields)} fields")
        stamps.append(float(parse_floats(fields, path, lineno)[0]))
    if not stamps:
        raise DatasetError(f"{path}: no timestamps listed")
    return np.asarray(stamps)


def read_kitti_poses(path: Path) -> np.ndarray:
    """(N, 4, 4) float64 ``T_wc`` from a KITTI poses file (12 row-major values per line)."""
    rows: list[np.ndarray] = []
    for lineno, fields in data_lines(path):
        if len(fields) != 12:
            raise DatasetError(f"{where(path, lineno)}: expected 12 values of a 3x4 pose, found {len(fields)}")
        rows.append(parse_floats(fields, path, lineno))
    if not rows:
        raise DatasetError(f"{path}: no poses in file")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = np.stack(rows).reshape(-1, 3, 4)
    return poses


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image, from the PNG header when possible (no decoding)."""
    try:
        with path.open("rb") as fh:
            head = fh.read(24)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read image ({exc.strerror})") from None
    if head[:8] == SIGNATURE and head[12:16] == b"IHDR":
        w, h = struct.unpack(">II", head[16:24])
        return int(w), int(h)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{path}: cannot read image (corrupt or unsupported format)")
    return int(img.shape[1]), int(img.shape[0])


class KittiSequence(ImageListSequence):
    """A KITTI odometry sequence folder (``.../sequences/NN``).

    camera: overrides the calibration from ``calib.txt``.
    poses: a poses file; by default ``../../poses/NN.txt`` relative to the sequence folder
        when present. Poses are those of camera 0.
    image_dir: ``image_0`` (left grayscale, default) or ``image_1``..``image_3``; the
        matching ``P<k>`` of ``calib.txt`` gives the intrinsics.
    """

    def __init__(
        self,
        folder: str | Path,
        camera: PinholeCamera | str | Path | None = None,
        *,
        poses: str | Path | None = None,
        image_dir: str = "image_0",
        color: bool = False,
    ) -> None:
        folder = require_dir(folder, "KITTI sequence")
        img_dir = require_dir(folder / image_dir, "KITTI image")
        stamps = read_times(folder / "times.txt")
        n = len(stamps)
        suffix = self._frame_suffix(img_dir, folder / "times.txt", n)
        paths = [img_dir / f"{i:06d}{suffix}" for i in range(n)]

        cam = resolve_camera(camera)
        if cam is None:
            cam = self._calib_camera(folder / "calib.txt", image_dir, paths[0], stamps)

        seq_dir = folder.resolve()
        poses_path = Path(poses) if poses is not None else seq_dir.parent.parent / "poses" / f"{seq_dir.name}.txt"
        if poses is not None and not poses_path.is_file():
            raise DatasetError(f"{poses_path}: poses file not found")
        poses_wc = gt = None
        if poses_path.is_file():
            poses_wc = read_kitti_poses(poses_path)
            if len(poses_wc) != n:
                raise DatasetError(
                    f"{poses_path}: holds {len(poses_wc)} poses but {folder / 'times.txt'} lists {n} images"
                )
            gt = Trajectory(stamps, poses_wc)
        super().__init__(
            name=f"kitti_{folder.resolve().name}",
            camera=cam,
            paths=paths,
            timestamps=stamps,
            poses_wc=poses_wc,
            ground_truth=gt,
            color=color,
        )

    @staticmethod
    def _frame_suffix(img_dir: Path, times: Path, n: int) -> str:
        """The suffix of the sequence's images (.png, .jpg or .jpeg), which must be all of
        one kind and as many as ``times`` lists (``n``); a DatasetError otherwise."""
        counts: dict[str, int] = {}
        for p in img_dir.iterdir():
            if p.suffix in FRAME_SUFFIXES:
                counts[p.suffix] = counts.get(p.suffix, 0) + 1
        if not counts:
            raise DatasetError(f"{img_dir}: holds no PNG or JPEG images ({', '.join(FRAME_SUFFIXES)}) but {times} "
                               f"lists {n}")
        if len(counts) > 1:
            found = ", ".join(f"{c} {s}" for s, c in sorted(counts.items()))
            raise DatasetError(f"{img_dir}: mixes image formats ({found}); a sequence's images must be all PNG "
                               "or all JPEG")
        (suffix, n_files), = counts.items()
        if n_files != n:
            raise DatasetError(f"{img_dir}: holds {n_files} {FRAME_SUFFIXES[suffix]} images but {times} lists {n}")
        return suffix

    @staticmethod
    def _calib_camera(calib_path: Path, image_dir: str, first: Path, stamps: np.ndarray) -> PinholeCamera:
        m = re.fullmatch(r"image_(\d)", image_dir)
        key = f"P{m.group(1)}" if m else "P0"
        calib = read_calib(calib_path)
        if key not in calib:
            raise DatasetError(f"{where(calib_path, key=key)}: missing projection matrix for {image_dir}")
        P = calib[key]
        if P[0, 0] <= 0 or P[1, 1] <= 0:
            raise DatasetError(f"{where(calib_path, key=key)}: focal lengths must be positive")
        w, h = image_size(first)
        fps = DEFAULT_FPS
        if len(stamps) > 1:
            dt = float(np.median(np.diff(stamps)))
            if dt > 0:
                fps = 1.0 / dt
        return PinholeCamera(
            fx=float(P[0, 0]), fy=float(P[1, 1]), cx=float(P[0, 2]), cy=float(P[1, 2]),
            width=w, height=h, fps=fps, name=f"kitti_{calib_path.parent.name}",
        )
