"""TUM RGB-D benchmark sequences (Sturm et al., "A Benchmark for the Evaluation of RGB-D
SLAM Systems", IROS 2012), monocular use of the RGB stream.

Layout of a sequence folder::

    rgb.txt           # "timestamp filename" per line, '#' comments
    rgb/<t>.png       # 640x480 colour images
    groundtruth.txt   # optional: "timestamp tx ty tz qx qy qz qw", camera-to-world
    camera.yaml       # optional: camera in the flat schema (written by the synthetic renderer)

TUM's ground truth runs at 100 Hz from a motion-capture system and is not synchronised with
the camera: each image takes the ground-truth pose nearest in time, within ``max_gap``
seconds (the benchmark's own ``associate.py`` uses 0.02 s), and none when there is none.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from orbslam_hgcn.errors import DatasetError, OrbslamError, where
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.trajectory import Trajectory, read_tum

from .base import ImageListSequence, associate, data_lines, parse_floats, poses_for, require_dir, resolve_camera

log = logging.getLogger(__name__)

DEFAULT_MAX_GAP = 0.02  # seconds between an image and its ground-truth pose
_FREIBURG = re.compile(r"(?:^|[_\-\s.])(?:freiburg|fr)([123])(?![0-9])")


def infer_tum_camera(folder: Path) -> str | None:
    """Shipped config name (tum_fr1/2/3) from a folder name such as ``rgbd_dataset_freiburg2_xyz``."""
    m = _FREIBURG.search(folder.name.lower())
    return f"tum_fr{m.group(1)}" if m else None


def read_image_list(path: Path) -> tuple[np.ndarray, list[str], list[int]]:
    """Parse a TUM image listing (``rgb.txt``).

    Returns ((N,) float64 timestamps, N relative file names, N line numbers). Commas are
    accepted as separators; timestamps must increase. An empty listing or a malformed line
    is a DatasetError naming the file and line.
    """
    stamps: list[float] = []
    names: list[str] = []
    lines: list[int] = []
    for lineno, fields in data_lines(path):
        if len(fields) != 2:
            raise DatasetError(
                f"{where(path, lineno)}: expected 'timestamp filename', found {len(fields)} fields"
            )
        stamps.append(float(parse_floats(fields[:1], path, lineno)[0]))
        names.append(fields[1])
        lines.append(lineno)
    if not stamps:
        raise DatasetError(f"{path}: no images listed")
    t = np.asarray(stamps)
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        raise DatasetError(
            f"{where(path, lines[bad[0] + 1])}: timestamp {t[bad[0] + 1]:.6f} does not increase "
            f"after {t[bad[0]]:.6f}"
        )
    return t, names, lines


class TumSequence(ImageListSequence):
    """A TUM RGB-D sequence folder, read as a monocular sequence.

    folder: the sequence folder (holding ``rgb.txt``).
    camera: a PinholeCamera, YAML path or shipped name; when None it comes from
        ``folder/camera.yaml``, else from the folder name (freiburg1/2/3), else an
        OrbslamError asks for ``--config``.
    max_gap: largest image-to-ground-truth time difference in seconds.
    groundtruth: ground-truth file; default ``folder/groundtruth.txt`` when present.
    color: yield (H, W, 3) BGR images instead of grayscale.
    """

    def __init__(
        self,
        folder: str | Path,
        camera: PinholeCamera | str | Path | None = None,
        *,
        max_gap: float = DEFAULT_MAX_GAP,
        groundtruth: str | Path | None = None,
        listing: str = "rgb.txt",
        color: bool = False,
    ) -> None:
        folder = require_dir(folder, "TUM sequence")
        listing_path = folder / listing
        if not listing_path.is_file():
            raise DatasetError(f"{listing_path}: image listing not found (is {folder} a TUM sequence?)")
        stamps, names, lines = read_image_list(listing_path)
        cam = self._camera(folder, camera)
        gt_path = Path(groundtruth) if groundtruth is not None else folder / "groundtruth.txt"
        if groundtruth is not None and not gt_path.is_file():
            raise DatasetError(f"{gt_path}: ground-truth file not found")
        gt: Trajectory | None = read_tum(gt_path) if gt_path.is_file() else None
        poses = None
        if gt is not None:
            idx = associate(stamps, gt.timestamps, max_gap)
            poses = poses_for(idx, gt)
            n_gt = int((idx >= 0).sum())
            log.debug("%s: %d of %d images have ground truth within %.3f s", folder, n_gt, len(stamps), max_gap)
        super().__init__(
            name=folder.resolve().name,
            camera=cam,
            paths=[folder / n for n in names],
            timestamps=stamps,
            poses_wc=poses,
            ground_truth=gt,
            sources=[where(listing_path, ln) for ln in lines],
            color=color,
        )

    @staticmethod
    def _camera(folder: Path, camera: PinholeCamera | str | Path | None) -> PinholeCamera:
        cam = resolve_camera(camera)
        if cam is not None:
            return cam
        if (folder / "camera.yaml").is_file():
            return resolve_camera(folder / "camera.yaml")
        name = infer_tum_camera(folder.resolve())
        if name is not None:
            log.info("%s: using camera %s inferred from the folder name", folder, name)
            return resolve_camera(name)
        raise OrbslamError(
            f"{folder}: cannot tell which TUM camera (freiburg1/2/3) took this sequence; "
            "give it with --config (e.g. tum_fr1, tum_fr2, tum_fr3 or a YAML file)"
        )
