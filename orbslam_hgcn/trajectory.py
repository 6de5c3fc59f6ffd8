"""Timestamped camera trajectories and the TUM text format.

A TUM trajectory file has one pose per line: ``timestamp tx ty tz qx qy qz qw``, the pose
being camera-to-world (``T_wc``). Lines starting with ``#`` are comments; commas are
accepted as separators (some tools write them). ORB-SLAM writes its results in this
format as ``KeyFrameTrajectory.txt`` and ``CameraTrajectory.txt``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from orbslam_hgcn.errors import DatasetError, where
from orbslam_hgcn.geometry.se3 import R_to_quat, quat_to_R


@dataclass
class Trajectory:
    """timestamps: (N,) float64 seconds, strictly increasing; poses: (N, 4, 4) float64 ``T_wc``."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise ValueError("timestamps and poses differ in length")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame."""
        return self.poses[:, :3, 3]

    def nearest(self, t: float, max_diff: float) -> int | None:
        """Index of the pose nearest in time to ``t``, or None when the gap exceeds ``max_diff``."""
        if len(self) == 0:
            return None
        i = int(np.searchsorted(self.timestamps, t))
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(self) and (best is None or abs(self.timestamps[j] - t) < abs(self.timestamps[best] - t)):
                best = j
        if best is None or abs(self.timestamps[best] - t) > max_diff:
            return None
        return best


def _parse_tum_values(text: str, path: str | Path, lineno: int) -> np.ndarray | None:
    """The 8 numbers of one TUM line, or None for comments and blank lines."""
    s = text.strip()
    if not s or s.startswith("#"):
        return None
    fields = s.replace(",", " ").split()
    if len(fields) != 8:
        raise DatasetError(
            f"{where(path, lineno)}: expected 8 values 'timestamp tx ty tz qx qy qz qw', "
            f"found {len(fields)}"
        )
    try:
        vals = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{where(path, lineno)}: not a number in {s!r}") from None
    if not np.all(np.isfinite(vals)) or np.linalg.norm(vals[4:8]) < 1e-6:
        raise DatasetError(f"{where(path, lineno)}: non-finite value or zero quaternion")
    return vals


def _poses_from_values(vals: np.ndarray) -> np.ndarray:
    """(N, 8) rows ``t tx ty tz qx qy qz qw`` -> (N, 4, 4) ``T_wc``."""
    T = np.tile(np.eye(4), (len(vals), 1, 1))
    q = vals[:, 4:8] / np.linalg.norm(vals[:, 4:8], axis=1, keepdims=True)
    T[:, :3, :3] = quat_to_R(q)
    T[:, :3, 3] = vals[:, 1:4]
    return T


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file; poses are sorted by timestamp."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: trajectory file not found")
    rows = []
    with path.open("r", encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, start=1):
            vals = _parse_tum_values(line, path, lineno)
            if vals is not None:
                rows.append(vals)
    if not rows:
        raise DatasetError(f"{path}: no poses in trajectory file")
    vals = np.stack(rows)
    order = np.argsort(vals[:, 0], kind="stable")
    vals = vals[order]
    return Trajectory(vals[:, 0], _poses_from_values(vals))


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write a trajectory in TUM format (6 decimals for time, 9 for pose values)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    q = R_to_quat(traj.poses[:, :3, :3]) if len(traj) else np.zeros((0, 4))
    with path.open("w", encoding="utf-8") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, T, qi in zip(traj.timestamps, traj.poses, q):
            x, y, z = T[:3, 3]
            fh.write(
                f"{t:.6f} {x:.9f} {y:.9f} {z:.9f} {qi[0]:.9f} {qi[1]:.9f} {qi[2]:.9f} {qi[3]:.9f}\n"
            )
