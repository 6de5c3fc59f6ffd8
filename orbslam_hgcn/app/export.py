"""``orbslam-hgcn map export-ply``: a saved map as PLY files for point-cloud tools.

Reads a map file (:func:`orbslam_hgcn.map.io.read_map`; no vocabulary is needed, the BoW
vectors are not used) and writes its active map's points and keyframes with
:func:`orbslam_hgcn.map.ply.export_map_ply`. With a dataset (the one the map was made
from), the points take their colours from the keyframes' images; a keyframe's ``frame_id``
is the index of its image in the sequence, and its timestamp must match that image's, so a
keyframe made from another sequence (a map extended on another dataset) keeps the
observation-count colours, and a dataset that matches no keyframe is an error.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from orbslam_hgcn.errors import DatasetError, FrameError
from orbslam_hgcn.map import Map
from orbslam_hgcn.map.io import read_map
from orbslam_hgcn.map.ply import check_ply_path, export_map_ply, point_colours_from_images

log = logging.getLogger(__name__)

# Largest difference, seconds, between a keyframe's timestamp and its frame's in the dataset.
TIMESTAMP_TOLERANCE_S = 1e-3


@dataclass
class PlyExport:
    """What :func:`export_ply` wrote: paths {"points", "keyframes"}, the counts, and how
    many points took their colour from an image (0 without a dataset); maps: how many maps
    the file holds (the active one, ``map_id``, is exported)."""

    paths: dict[str, Path]
    n_points: int
    n_keyframes: int
    n_coloured: int = 0
    map_id: int = 0
    maps: int = 1
    notes: list[str] = field(default_factory=list)


def export_ply(map_path: str | Path, out: str | Path, colour_from: str | Path | None = None) -> PlyExport:
    """Write the active map of the map file ``map_path`` as ``out`` (points) and
    ``<stem>_keyframes.ply``; ``colour_from``: the dataset the map was made from, to colour
    the points from its images. Every problem (the output path, a missing or corrupt map
    file, a dataset that does not fit the map) is an OrbslamError one-liner, found before
    anything is written."""
    out = check_ply_path(out)
    mf = read_map(map_path)
    m = mf.map
    notes: list[str] = []
    n_maps = len(mf.atlas.maps) if mf.atlas is not None else 1
    if n_maps > 1:
        notes.append(f"{mf.path} holds {n_maps} maps; exporting the active one (map {m.map_id})")
    colours = None
    if colour_from is not None:
        colours, note = _colours_from_dataset(m, colour_from)
        notes.append(note)
    paths = export_map_ply(m, out, colours)
    return PlyExport(paths, m.n_points(), m.n_keyframes(), len(colours or {}), m.map_id, n_maps, notes)


def _colours_from_dataset(m: Map, dataset: str | Path) -> tuple[dict[int, tuple[int, int, int]], str]:
    from orbslam_hgcn.datasets import open_sequence

    seq = open_sequence(None, dataset, None, color=True)
    kfs = m.keyframes()
    if not kfs:
        return {}, "the map has no keyframes to colour its points from"
    cam = kfs[0].camera
    if (seq.camera.width, seq.camera.height) != (cam.width, cam.height):
        raise DatasetError(f"{dataset}: its images are {seq.camera.width}x{seq.camera.height}, the map's camera "
                           f"{cam.width}x{cam.height}: not the dataset the map was made from")
    stamps = seq.timestamps
    matching = {kf.frame_id for kf in kfs
                if 0 <= kf.frame_id < len(seq) and abs(stamps[kf.frame_id] - kf.timestamp) <= TIMESTAMP_TOLERANCE_S}
    if not matching:
        raise DatasetError(f"{dataset}: no keyframe of the map has its frame here (frame index and timestamp): "
                           "not the dataset the map was made from")
    unreadable: list[int] = []

    def image_of(frame_id: int) -> np.ndarray | None:
        if frame_id not in matching:
            return None
        try:
            return seq[frame_id].image
        except FrameError as exc:
            log.warning("%s", exc)
            unreadable.append(frame_id)
            return None

    colours = point_colours_from_images(m, image_of)
    missed = len(kfs) - len(matching) + len(unreadable)
    note = f"coloured {len(colours)} of {m.n_points()} points from {dataset}"
    if missed:
        note += f" ({missed} of {len(kfs)} keyframes have no image there; their other points by observations)"
    return colours, note
