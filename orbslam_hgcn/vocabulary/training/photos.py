"""The real photographs the shipped vocabularies are trained on, and the ones held out.

The folder (``shared/data/real_photos`` beside the project, or any folder laid out the same
way) holds grey JPEGs named ``<source>_<NNNN>.jpg``. Each file prefix is one source; it
becomes one :class:`~orbslam_hgcn.vocabulary.training.train.ImageSource`, so feature tracks
(matched between consecutive images of a source) never join two sources.

Two sources are video frames about a second apart (CamVid's drives and the ICDAR 2015
head-worn walks): neighbouring frames see the same place, which makes them the real test
of place recognition. Their last images are held out of every shipped vocabulary
(:data:`HOLDOUT`) and serve the real family of ``bench/bench_track_words.py`` and the real
check of ``bench/bench_lcd.py``.
"""

from __future__ import annotations

import re
from pathlib import Path

from orbslam_hgcn.datasets.base import read_image
from orbslam_hgcn.errors import DatasetError

# Source prefix -> first held-out index (every image from there on is held out).
HOLDOUT = {"camvid": 560, "icdar2015": 400}
_NAME = re.compile(r"^(?P<source>[a-z0-9]+(?:_[a-z]+)*)_(?P<index>\d+)\.(?:jpg|jpeg|png)$", re.IGNORECASE)


def default_photo_folder() -> Path:
    """``shared/data/real_photos`` beside the project checkout (may not exist)."""
    return Path(__file__).resolve().parents[3].parent / "shared" / "data" / "real_photos"


def photo_files(folder: str | Path, part: str = "train") -> dict[str, list[Path]]:
    """Photo files by source prefix, sorted by index.

    part: ``train`` (everything but :data:`HOLDOUT`), ``heldout`` (only the held-out images
    of the held-out sources) or ``all``.
    """
    if part not in ("train", "heldout", "all"):
        raise ValueError(f"part must be train, heldout or all, found {part!r}")
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such photo folder")
    out: dict[str, list[tuple[int, Path]]] = {}
    for f in folder.iterdir():
        m = _NAME.match(f.name)
        if not m or not f.is_file():
            continue
        source, index = m.group("source"), int(m.group("index"))
        held = source in HOLDOUT and index >= HOLDOUT[source]
        if part == "all" or (part == "train") != held:
            out.setdefault(source, []).append((index, f))
    if not out:
        raise DatasetError(f"{folder}: no photos named <source>_<number>.jpg ({part} part)")
    return {s: [f for _, f in sorted(v)] for s, v in sorted(out.items())}


def photo_sources(folder: str | Path, part: str = "train") -> list:
    """One ImageSource per source prefix of :func:`photo_files`."""
    from orbslam_hgcn.vocabulary.training.train import ImageSource

    return [ImageSource(f"real_photos/{s}", len(files), (lambda fs: lambda i: read_image(fs[i]))(files))
            for s, files in photo_files(folder, part).items()]


def describe(folder: str | Path, part: str = "train") -> str:
    """One line naming the photos of ``part``: sources and image counts."""
    files = photo_files(folder, part)
    total = sum(len(v) for v in files.values())
    held = ", ".join(f"{s} from #{i}" for s, i in HOLDOUT.items())
    what = "real photographs" if part != "heldout" else "held-out real photographs"
    return (f"{total} {what} of shared/data/real_photos (" + ", ".join(f"{s} {len(v)}" for s, v in files.items())
            + ")" + (f"; held out: {held}" if part == "train" else "") + "; no render, no benchmark sequence")
