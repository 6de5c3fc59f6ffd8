"""A folder of images taken as a sequence, in natural name order, at a given frame rate.

For image collections without timestamps (phone captures, extracted video frames, place
recognition sets): frame ``i`` gets timestamp ``i / fps`` seconds. The camera must be
given, since image files carry no calibration.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from orbslam_hgcn.errors import DatasetError
from orbslam_hgcn.geometry.camera import PinholeCamera

from .base import IMAGE_SUFFIXES, ImageListSequence, require_camera, require_dir

log = logging.getLogger(__name__)


def natural_key(name: str) -> list:
    """Sort key that orders embedded numbers by value: ``img2.png`` before ``img10.png``."""
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", name)]


def list_images(folder: Path) -> list[Path]:
    """Image files (png, jpg, jpeg, bmp, tif, tiff, ppm, pgm) of ``folder`` in natural order."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


class FolderSequence(ImageListSequence):
    """Images of one folder, in natural name order.

    camera: required (PinholeCamera, YAML path or shipped name).
    fps: frame rate giving the timestamps ``i / fps``; default the camera's ``fps``.
    start_time: timestamp of the first image in seconds.
    """

    def __init__(
        self,
        folder: str | Path,
        camera: PinholeCamera | str | Path | None = None,
        *,
        fps: float | None = None,
        start_time: float = 0.0,
        color: bool = False,
    ) -> None:
        folder = require_dir(folder, "image")
        cam = require_camera(camera, folder, "folder of images")
        paths = list_images(folder)
        if not paths:
            raise DatasetError(
                f"{folder}: no images found (looked for {', '.join(s.lstrip('.') for s in IMAGE_SUFFIXES)})"
            )
        rate = float(fps) if fps is not None else cam.fps
        if not rate > 0:
            raise DatasetError(f"{folder}: frame rate must be positive, got {rate}")
        super().__init__(
            name=folder.resolve().name,
            camera=cam,
            paths=paths,
            timestamps=start_time + np.arange(len(paths), dtype=np.float64) / rate,
            color=color,
        )
