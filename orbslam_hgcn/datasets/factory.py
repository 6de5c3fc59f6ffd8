"""Open any supported sequence by kind, or tell the kind from the folder's contents."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from orbslam_hgcn.errors import DatasetError
from orbslam_hgcn.geometry.camera import PinholeCamera

from .base import IMAGE_SUFFIXES, Sequence
from .euroc import EurocSequence
from .folder import FolderSequence
from .kitti import KittiSequence
from .tum import TumSequence
from .video import VIDEO_SUFFIXES, VideoSequence

log = logging.getLogger(__name__)

READERS: dict[str, type[Sequence]] = {
    "tum": TumSequence,
    "euroc": EurocSequence,
    "kitti": KittiSequence,
    "folder": FolderSequence,
    "video": VideoSequence,
}
KINDS = tuple(READERS)


def detect_kind(path: str | Path) -> str:
    """The reader kind for ``path`` from what it holds.

    A video file -> ``video``; a folder with ``rgb.txt`` -> ``tum``; with ``mav0/`` (or a
    camera folder with ``data.csv`` and ``sensor.yaml``) -> ``euroc``; with ``times.txt``
    and ``image_0/`` -> ``kitti``; with image files -> ``folder``.
    """
    p = Path(path).expanduser()
    if not p.exists():
        raise DatasetError(f"{p}: no such file or folder")
    if p.is_file():
        if p.suffix.lower() in VIDEO_SUFFIXES:
            return "video"
        raise DatasetError(f"{p}: not a video file ({', '.join(VIDEO_SUFFIXES)}) nor a dataset folder")
    if (p / "rgb.txt").is_file():
        return "tum"
    if (p / "mav0").is_dir() or (p.name == "mav0" and (p / "cam0").is_dir()) or (
        (p / "data.csv").is_file() and (p / "sensor.yaml").is_file()
    ):
        return "euroc"
    if (p / "times.txt").is_file() and (p / "image_0").is_dir():
        return "kitti"
    if any(c.is_file() and c.suffix.lower() in IMAGE_SUFFIXES for c in p.iterdir()):
        return "folder"
    if (p / "sequences").is_dir():  # the root of the KITTI odometry download
        seqs = sorted(c.name for c in (p / "sequences").iterdir() if (c / "times.txt").is_file())
        if seqs:
            raise DatasetError(f"{p}: a KITTI odometry folder holding sequences {', '.join(seqs)}; "
                               f"run one of them, e.g. {p / 'sequences' / seqs[0]}")
    raise DatasetError(
        f"{p}: cannot tell the dataset kind (no rgb.txt, mav0/, times.txt + image_0/ or images); "
        f"name it: one of {', '.join(KINDS)}"
    )


def open_sequence(
    kind: str | None, path: str | Path, camera: PinholeCamera | str | Path | None = None, **kw: Any
) -> Sequence:
    """Open a sequence.

    kind: ``tum``, ``euroc``, ``kitti``, ``folder``, ``video``, or None to detect it.
    camera: PinholeCamera, camera YAML path or shipped config name; required for
        ``folder`` and ``video``, optional elsewhere (the dataset's own calibration).
    kw: passed to the reader (e.g. ``color=True``, ``max_gap``, ``fps``, ``poses``).
    """
    if kind is None:
        kind = detect_kind(path)
        log.info("%s: reading as a %s sequence", path, kind)
    reader = READERS.get(kind.lower())
    if reader is None:
        raise DatasetError(f"unknown dataset kind {kind!r}; use one of {', '.join(KINDS)}")
    return reader(path, camera, **kw)
