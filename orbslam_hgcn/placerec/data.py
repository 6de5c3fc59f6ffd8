"""Inputs of loop-closure evaluation: image sequences and ground-truth loop matrices.

A ground-truth matrix is (n, n) for a sequence of n images, nonzero where images i and j
show the same place. Accepted files:

- ``.mat`` (MATLAB up to v7.2, via scipy): the variable named ``truth``, ``GroundTruth``,
  ``gt``, ``groundtruth`` or ``ground_truth`` (any case), or else the only 2-D numeric
  variable; the New College / City Centre files of Cummins & Newman (IJRR 2008) store it so;
- ``.txt`` / ``.csv``: one matrix row per line, numbers separated by whitespace or commas
  (``#`` and ``%`` comment lines skipped);
- ``.npy``: a 2-D numeric array.

Every problem (missing or unreadable file, wrong shape, not square, a count that differs
from the image count) is a :class:`DatasetError` naming the file.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import scipy.io

from orbslam_hgcn.errors import DatasetError, OrbslamError, where

log = logging.getLogger(__name__)

GT_SUFFIXES = (".mat", ".txt", ".csv", ".npy")
_MAT_NAMES = ("truth", "groundtruth", "ground_truth", "gt")


def _load_mat(path: Path) -> np.ndarray:
    try:
        data = scipy.io.loadmat(str(path))
    except NotImplementedError:
        raise DatasetError(f"{path}: MATLAB v7.3 (HDF5) files are not supported; save with -v7") from None
    except (scipy.io.matlab.MatReadError, ValueError, OSError, TypeError) as exc:
        raise DatasetError(f"{path}: not a readable MATLAB .mat file ({exc})") from None
    variables = {k: v for k, v in data.items() if not k.startswith("__")}
    for name in _MAT_NAMES:
        for key, val in variables.items():
            if key.lower() == name:
                return np.asarray(val)
    matrices = {
        k: v for k, v in variables.items()
        if isinstance(v, np.ndarray) and v.ndim == 2 and (v.dtype.kind in "biuf" or v.dtype == bool)
    }
    if len(matrices) == 1:
        return next(iter(matrices.values()))
    raise DatasetError(
        f"{path}: cannot tell which variable is the ground truth; found "
        f"{', '.join(sorted(variables)) or 'no variables'} (name it 'truth')"
    )


def _load_text(path: Path) -> np.ndarray:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read file ({exc.strerror})") from None
    rows: list[np.ndarray] = []
    first_line = 0
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith(("#", "%")):
            continue
        fields = s.replace(",", " ").split()
        try:
            row = np.array([float(f) for f in fields])
        except ValueError:
            raise DatasetError(f"{where(path, lineno)}: not a number in {s[:60]!r}") from None
        if rows and len(row) != len(rows[0]):
            raise DatasetError(
                f"{where(path, lineno)}: row has {len(row)} values, line {first_line} has {len(rows[0])}"
            )
        if not rows:
            first_line = lineno
        rows.append(row)
    if not rows:
        raise DatasetError(f"{path}: ground-truth file is empty")
    return np.vstack(rows)


def load_ground_truth(path: str | Path, n_images: int | None = None) -> np.ndarray:
    """(n, n) bool loop matrix from a .mat/.txt/.csv/.npy file, symmetrised (``gt | gt.T``).

    n_images: when given, the matrix must be n_images x n_images.
    """
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: ground-truth file not found")
    suffix = p.suffix.lower()
    if suffix == ".mat":
        gt = _load_mat(p)
    elif suffix in (".txt", ".csv"):
        gt = _load_text(p)
    elif suffix == ".npy":
        try:
            gt = np.load(p, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise DatasetError(f"{p}: not a readable .npy array ({exc})") from None
    else:
        raise DatasetError(f"{p}: unknown ground-truth format; use one of {', '.join(GT_SUFFIXES)}")
    gt = np.asarray(gt)
    if gt.dtype.kind not in "biuf":
        raise DatasetError(f"{p}: ground truth must be numeric, found {gt.dtype}")
    if gt.ndim != 2 or gt.shape[0] != gt.shape[1]:
        raise DatasetError(f"{p}: ground truth must be a square matrix, found shape {gt.shape}")
    if gt.dtype.kind == "f" and not np.all(np.isfinite(gt)):
        raise DatasetError(f"{p}: ground truth holds non-finite values")
    if n_images is not None and gt.shape[0] != n_images:
        raise DatasetError(
            f"{p}: ground truth is {gt.shape[0]}x{gt.shape[1]} but the test sequence has "
            f"{n_images} images"
        )
    gt = gt != 0
    return gt | gt.T


def save_ground_truth(path: str | Path, gt: np.ndarray) -> None:
    """Write an (n, n) loop matrix as .mat (variable ``truth``), .txt/.csv or .npy."""
    p = Path(path)
    gt = np.asarray(gt).astype(np.uint8)
    suffix = p.suffix.lower()
    if suffix == ".mat":
        scipy.io.savemat(str(p), {"truth": gt})
    elif suffix in (".txt", ".csv"):
        np.savetxt(p, gt, fmt="%d", delimiter="," if suffix == ".csv" else " ")
    elif suffix == ".npy":
        np.save(p, gt)
    else:
        raise DatasetError(f"{p}: unknown ground-truth format; use one of {', '.join(GT_SUFFIXES)}")


class ImageSource:
    """The images of a sequence for place recognition, loaded lazily in order.

    ``path``: a folder of images (natural name order, no calibration needed), or any
    sequence :func:`orbslam_hgcn.datasets.open_sequence` reads (TUM, EuRoC, KITTI, video
    with ``camera``). ``stride`` keeps every stride-th image, or ``indices`` the given
    frames; ``limit`` the first ones of those.
    """

    def __init__(
        self, path: str | Path, *, stride: int = 1, limit: int | None = None, camera: str | None = None,
        indices: np.ndarray | None = None,
    ) -> None:
        from orbslam_hgcn.datasets import detect_kind
        from orbslam_hgcn.datasets.folder import list_images

        self.path = Path(path)
        if stride < 1:
            raise OrbslamError(f"{self.path}: stride must be at least 1, found {stride}")
        kind = detect_kind(self.path)
        self.kind = kind
        if kind == "folder":
            self._paths: list[Path] | None = list_images(self.path)
            self._seq = None
            total = len(self._paths)
        else:
            from orbslam_hgcn.datasets import open_sequence

            self._paths = None
            self._seq = open_sequence(kind, self.path, camera)
            total = len(self._seq)
        self.total = total
        idx = np.arange(0, total, stride) if indices is None else np.asarray(indices, dtype=np.int64)
        self.indices = idx[:limit] if limit is not None else idx
        if len(self.indices) == 0:
            raise DatasetError(f"{self.path}: no images in the sequence")

    def __len__(self) -> int:
        return len(self.indices)

    def select(self, indices: np.ndarray, limit: int | None = None) -> ImageSource:
        """The same sequence restricted to the frames ``indices`` (of the whole sequence)."""
        other = object.__new__(ImageSource)
        other.__dict__.update(self.__dict__)
        idx = np.asarray(indices, dtype=np.int64)
        other.indices = idx[:limit] if limit is not None else idx
        if len(other.indices) == 0:
            raise DatasetError(f"{self.path}: no images selected")
        return other

    @property
    def all_timestamps(self) -> np.ndarray | None:
        """(total,) float64 seconds of every frame of the sequence; None for an image folder."""
        return None if self._seq is None else np.asarray(self._seq.timestamps, dtype=np.float64)

    @property
    def timestamps(self) -> np.ndarray | None:
        """(n,) float64 seconds of the selected frames; None for an image folder."""
        t = self.all_timestamps
        return None if t is None else t[self.indices]

    @property
    def all_poses(self) -> np.ndarray | None:
        """(total, 4, 4) float64 ground-truth ``T_wc`` of every frame, NaN where a frame has
        none; None when the sequence has no ground truth."""
        pose = getattr(self._seq, "pose", None)
        if pose is None:
            return None
        poses = np.full((self.total, 4, 4), np.nan)
        for i in range(self.total):
            p = pose(i)
            if p is not None:
                poses[i] = p
        return poses if np.isfinite(poses[:, 0, 0]).any() else None

    def names(self) -> list[str]:
        """The selected images' file names (relative to the sequence folder where it can)."""
        paths = self._paths if self._paths is not None else getattr(self._seq, "paths", None)
        if paths is None:
            return [f"frame {i}" for i in self.indices]
        out = []
        for i in self.indices:
            p = Path(paths[i])
            try:
                out.append(str(p.relative_to(self.path)))
            except ValueError:
                out.append(str(p))
        return out

    def __iter__(self) -> Iterator[np.ndarray]:
        """(H, W) uint8 grayscale images."""
        from orbslam_hgcn.datasets.base import read_image

        for i in self.indices:
            if self._paths is not None:
                yield read_image(self._paths[i])
            else:
                yield self._seq[int(i)].image
