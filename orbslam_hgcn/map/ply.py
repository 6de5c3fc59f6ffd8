"""A map as PLY files, for MeshLab, Open3D, CloudCompare and other point-cloud tools.

Two binary little-endian PLY 1.0 files, each one ``vertex`` element:

* the map points (:func:`write_points_ply`): float ``x, y, z`` (world frame), uchar
  ``red, green, blue`` and int ``observations`` (keyframes observing the point);
* the keyframes (:func:`write_keyframes_ply`): float ``x, y, z`` (camera centre in the
  world), float ``nx, ny, nz`` (the optical axis: the camera's z axis in the world, a unit
  vector), uchar ``red, green, blue`` and int ``frame`` (the keyframe's frame id, the index
  of its image in the sequence).

Both headers say ``comment orbslam_hgcn map <map_id>`` and the unit: the map's own, an
arbitrary scale for a monocular map. Only good points and keyframes are written, read
under the map's lock in one go. :func:`export_map_ply` writes both beside each other,
after checking the path; :func:`point_colours_from_images` samples point colours from the
keyframes' images. A file that cannot be written (or a path that is no ``.ply`` file, a map
without points) is a :class:`PlyExportError`, one line naming the file.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from orbslam_hgcn.errors import DatasetError, OrbslamError
from orbslam_hgcn.map.map import Map
from orbslam_hgcn.outputs import check_output_file

log = logging.getLogger(__name__)

UNITS_COMMENT = "units: map units (monocular: arbitrary scale)"

# The observation-count ramp of points without a colour: matplotlib's viridis at five stops
# (as the rerun view colours points), linear in between; OBS_DARK observations (the fewest
# a point keeps) are the darkest, OBS_BRIGHT or more the brightest.
_RAMP_STOPS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float64)
OBS_DARK, OBS_BRIGHT = 2, 15

KEYFRAME_RGB = (255, 0, 0)

POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                        ("observations", "<i4")])
KEYFRAME_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                           ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("frame", "<i4")])
_PLY_TYPES = {"<f4": "float", "u1": "uchar", "<i4": "int"}

Colours = Mapping[int, Any] | np.ndarray


class PlyExportError(OrbslamError):
    """A PLY export that cannot be made: a path that is no ``.ply`` file or cannot be
    written, or a map with nothing to export."""


def observation_colours(n_obs: np.ndarray) -> np.ndarray:
    """(M,) observation counts -> (M, 3) uint8 RGB on the fixed viridis-like ramp:
    ``OBS_DARK`` (2) observations or fewer dark purple, ``OBS_BRIGHT`` (15) or more bright
    yellow, linear in between."""
    t = np.clip((np.asarray(n_obs, np.float64) - OBS_DARK) / (OBS_BRIGHT - OBS_DARK), 0.0, 1.0)
    stops = np.linspace(0.0, 1.0, len(_RAMP_STOPS))
    return np.stack([np.interp(t, stops, _RAMP_STOPS[:, c]) for c in range(3)], axis=1).round().astype(np.uint8)


def _header(element_counts: list[tuple[str, int, np.dtype]], comments: list[str]) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments)]
    for name, count, dtype in element_counts:
        lines.append(f"element {name} {count}")
        lines.extend(f"property {_PLY_TYPES[dtype[f].str.lstrip('|')]} {f}" for f in dtype.names)
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def _write_ply(path: Path, vertices: np.ndarray, comments: list[str]) -> Path:
    """Write one ``vertex`` element (a structured array) as a binary little-endian PLY,
    through a temporary file beside ``path`` and a rename; OSError -> PlyExportError."""
    data = _header([("vertex", len(vertices), vertices.dtype)], comments) + vertices.tobytes()
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        raise PlyExportError(f"{path}: cannot write the PLY file ({exc.strerror or exc})") from None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _map_comments(m: Map) -> list[str]:
    return [f"orbslam_hgcn map {m.map_id}", UNITS_COMMENT]


def _point_rgb(pids: np.ndarray, n_obs: np.ndarray, colours: Colours | None) -> np.ndarray:
    """(M, 3) uint8 colours of the points ``pids``: ``colours`` where it gives one, the
    observation ramp elsewhere."""
    rgb = observation_colours(n_obs)
    if colours is None:
        return rgb
    if isinstance(colours, Mapping):
        rows = [i for i, p in enumerate(pids.tolist()) if p in colours]
        given = np.array([tuple(colours[int(pids[i])]) for i in rows], dtype=np.int64).reshape(-1, 3)
    else:
        given = np.asarray(colours)
        if given.shape != (len(pids), 3):
            raise ValueError(f"colours: an array must be ({len(pids)}, 3), one row per point of the map, "
                             f"found {given.shape}")
        rows = list(range(len(pids)))
    if given.size and (given.min() < 0 or given.max() > 255):
        raise ValueError("colours: RGB values must lie in 0-255")
    rgb[rows] = given.astype(np.uint8)
    return rgb


def write_points_ply(path: str | Path, m: Map, colours: Colours | None = None) -> Path:
    """Write the good map points of ``m`` to ``path``: float x, y, z (world), uchar red,
    green, blue, int observations (keyframes observing the point), in ascending point id.

    colours: {point id: (r, g, b)} (points missing from it, and all points without it, are
    coloured by their observation count on a fixed viridis-like ramp: 2 observations dark
    purple, 15 or more bright yellow; see :func:`observation_colours`), or an (N, 3) array
    of 0-255 values, one row per point of ``m.point_ids()`` in that order (for a map that
    does not change meanwhile). Returns ``path``.
    """
    path = Path(path)
    with m.lock:
        pids = m.point_ids()
        position = m.positions(pids)
        n_obs = m.n_observations(pids)
    v = np.zeros(len(pids), POINT_DTYPE)
    v["x"], v["y"], v["z"] = position.T.astype(np.float32)
    rgb = _point_rgb(pids, n_obs, colours)
    v["red"], v["green"], v["blue"] = rgb.T
    v["observations"] = n_obs
    return _write_ply(path, v, _map_comments(m))


def keyframe_axes(m: Map) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """((K, 3) camera centres, (K, 3) unit optical axes, (K,) frame ids) of the good
    keyframes of ``m`` in id order, world frame: the centre is T_wc's translation, the
    axis T_wc's third column (the camera's z axis; KeyFrame stores T_cw, T_wc its
    inverse)."""
    with m.lock:
        kfs = m.keyframes()
        T_wc = np.stack([kf.T_wc for kf in kfs]) if kfs else np.zeros((0, 4, 4))
        frames = np.array([kf.frame_id for kf in kfs], np.int64)
    axis = T_wc[:, :3, 2]
    axis = axis / np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    return T_wc[:, :3, 3].copy(), axis, frames


def write_keyframes_ply(path: str | Path, m: Map) -> Path:
    """Write the good keyframes of ``m`` to ``path``: float x, y, z (camera centre, world),
    float nx, ny, nz (the optical axis: the camera's z axis in the world), uchar red, green,
    blue (all red), int frame (the keyframe's frame id), in keyframe id order."""
    path = Path(path)
    centre, axis, frames = keyframe_axes(m)
    v = np.zeros(len(frames), KEYFRAME_DTYPE)
    v["x"], v["y"], v["z"] = centre.T.astype(np.float32)
    v["nx"], v["ny"], v["nz"] = axis.T.astype(np.float32)
    v["red"], v["green"], v["blue"] = KEYFRAME_RGB
    v["frame"] = frames
    return _write_ply(path, v, _map_comments(m))


def keyframes_path(path: str | Path) -> Path:
    """The keyframes file written beside the points file ``path``: ``<stem>_keyframes.ply``."""
    path = Path(path)
    return path.with_name(f"{path.stem}_keyframes.ply")


def check_ply_path(path: str | Path) -> Path:
    """The points file ``path`` of an export, checked before any work: a ``.ply`` name,
    neither it nor its keyframes file an existing folder, and its folder writable (or
    creatable under a writable one). PlyExportError for the name, else OrbslamError."""
    p = Path(path).expanduser()
    if p.suffix.lower() != ".ply":
        raise PlyExportError(f"{p}: the output must be a .ply file")
    check_output_file(keyframes_path(p), "the keyframes PLY")
    return check_output_file(p, "the PLY file")


def export_map_ply(m: Map, path: str | Path, colours: Colours | None = None) -> dict[str, Path]:
    """Write map ``m`` as ``path`` (its points, :func:`write_points_ply` with ``colours``)
    and ``<stem>_keyframes.ply`` beside it (:func:`write_keyframes_ply`).

    Returns {"points": path, "keyframes": keyframes path}. PlyExportError (one line) for a
    path without the ``.ply`` suffix, a folder that cannot be written, or a map without
    points (nothing is written then)."""
    p = check_ply_path(path)
    if m.n_points() == 0:
        raise PlyExportError(f"{p}: the map has no points; nothing to export")
    points = write_points_ply(p, m, colours)
    keyframes = write_keyframes_ply(keyframes_path(p), m)
    return {"points": points, "keyframes": keyframes}


def _pixel_rgb(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(M, 3) uint8 RGB of the pixels nearest (M, 2) ``uv`` (x right, y down; pixel
    centres at integers) of an (H, W) grey or (H, W, 3) BGR image."""
    h, w = image.shape[:2]
    col = np.clip(np.floor(uv[:, 0] + 0.5).astype(np.int64), 0, w - 1)
    row = np.clip(np.floor(uv[:, 1] + 0.5).astype(np.int64), 0, h - 1)
    px = image[row, col]
    return np.repeat(px[:, None], 3, axis=1) if image.ndim == 2 else px[:, ::-1]


def point_colours_from_images(
    m: Map, image_of: Callable[[int], np.ndarray | None]
) -> dict[int, tuple[int, int, int]]:
    """{point id: (r, g, b)} of the good points of ``m``, sampled from the keyframes'
    images: ``image_of(frame_id)`` gives a keyframe's image ((H, W, 3) uint8 BGR or (H, W)
    uint8 grey, the camera's size) or None when it has none.

    Each point takes the pixel nearest its keypoint (as detected, ``uv_raw``) in the oldest
    observing keyframe whose image is there; a grey pixel g gives (g, g, g). Keyframes are
    visited in id order and each image is asked for at most once (not at all once every
    point it observes has a colour); points seen in no available image get no entry. The
    keyframes' observations are read under the map's lock first, the images outside it.
    A wrong-sized image (another dataset's) is a DatasetError."""
    with m.lock:
        views = []
        for kf in m.keyframes():
            idx, pids = kf.observed_points()
            views.append((kf.frame_id, kf.camera, kf.keypoints.uv_raw[idx].astype(np.float64), pids.copy()))
    out: dict[int, tuple[int, int, int]] = {}
    for frame_id, camera, uv, pids in views:
        todo = np.array([p not in out for p in pids.tolist()], dtype=bool)
        if not todo.any():
            continue
        image = image_of(frame_id)
        if image is None:
            continue
        image = np.asarray(image)
        if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
            raise ValueError(f"image of frame {frame_id}: expected (H, W) or (H, W, 3) uint8, "
                             f"found {image.shape} {image.dtype}")
        if image.shape[:2] != (camera.height, camera.width):
            raise DatasetError(f"image of frame {frame_id} is {image.shape[1]}x{image.shape[0]}, but the map's "
                               f"camera is {camera.width}x{camera.height}: not the images the map was made from")
        rgb = _pixel_rgb(image, uv[todo])
        for p, c in zip(pids[todo].tolist(), rgb.tolist()):
            out[p] = (c[0], c[1], c[2])
    return out
