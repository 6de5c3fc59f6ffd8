"""EuRoC MAV sequences in ASL format (Burri et al., "The EuRoC micro aerial vehicle
datasets", IJRR 2016), read as a monocular sequence from one camera.

Layout::

    <root>/mav0/cam0/data.csv        # "#timestamp [ns],filename"
    <root>/mav0/cam0/data/<ns>.png   # 752x480 grayscale, 20 Hz
    <root>/mav0/cam0/sensor.yaml     # OpenCV %YAML:1.0: intrinsics, distortion, T_BS
    <root>/mav0/state_groundtruth_estimate0/data.csv   # body (IMU) frame ground truth
    <root>/groundtruth_left_cam.csv  # optional: ground truth already in the cam0 frame

Ground-truth files hold ``ns, px, py, pz, qw, qx, qy, qz[, ...]`` per line. Body-frame
poses ``T_wb`` become camera poses ``T_wc = T_wb @ T_BS`` with ``T_BS`` (camera to body)
from ``sensor.yaml``. Timestamps are integer nanoseconds in the files; association is
done on the integers (exact), and frames report seconds.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from orbslam_hgcn.config import camera_from_dict
from orbslam_hgcn.errors import ConfigError, DatasetError, where
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import quat_to_R
from orbslam_hgcn.trajectory import Trajectory

from .base import ImageListSequence, associate, data_lines, poses_for, require_dir, resolve_camera

log = logging.getLogger(__name__)

DEFAULT_MAX_GAP = 0.02  # seconds between an image and its ground-truth pose

# Flat camera-schema keys and the sensor.yaml keys they come from.
_SENSOR_KEYS = {
    "fx": "intrinsics", "fy": "intrinsics", "cx": "intrinsics", "cy": "intrinsics", "cx/cy": "intrinsics",
    "width": "resolution", "height": "resolution", "fps": "rate_hz", "distortion": "distortion_coefficients",
}


class _OpenCVLoader(yaml.SafeLoader):
    """SafeLoader that reads OpenCV FileStorage tags (``!!opencv-matrix``) as plain mappings."""


def _construct_tagged(loader: yaml.SafeLoader, _suffix: str, node: yaml.Node) -> Any:
    if isinstance(node, yaml.MappingNode):
        return loader.construct_mapping(node, deep=True)
    if isinstance(node, yaml.SequenceNode):
        return loader.construct_sequence(node, deep=True)
    return loader.construct_scalar(node)


_OpenCVLoader.add_multi_constructor("tag:yaml.org,2002:opencv", _construct_tagged)
_OpenCVLoader.add_multi_constructor("!", _construct_tagged)


def load_opencv_yaml(path: Path) -> dict[str, Any]:
    """Parse an OpenCV-style YAML file (``%YAML:1.0`` header, ``!!opencv-matrix`` tags)."""
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    # Blank the directive lines rather than drop them, so YAML error lines stay true.
    text = "\n".join("" if ln.startswith("%") or ln.strip() == "---" else ln for ln in lines)
    try:
        data = yaml.load(text, Loader=_OpenCVLoader)  # noqa: S506 - SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise DatasetError(f"{where(path, mark.line + 1 if mark else None)}: not valid YAML") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a mapping of keys at the top level")
    return data


def _matrix(value: Any, path: Path, key: str, shape: tuple[int, int]) -> np.ndarray:
    """A matrix written as a flat list, a list of rows, or an OpenCV ``{rows, cols, data}``."""
    data = value.get("data") if isinstance(value, dict) else value
    try:
        arr = np.asarray(data, dtype=np.float64).reshape(shape)
    except (TypeError, ValueError):
        raise DatasetError(
            f"{where(path, key=key)}: expected a {shape[0]}x{shape[1]} matrix, found {value!r}"
        ) from None
    if not np.all(np.isfinite(arr)):
        raise DatasetError(f"{where(path, key=key)}: non-finite value")
    return arr


def read_sensor_yaml(path: Path) -> tuple[PinholeCamera, np.ndarray]:
    """Camera and ``T_BS`` ((4, 4) float64, camera to body) from an EuRoC ``sensor.yaml``."""
    data = load_opencv_yaml(path)
    for key in ("intrinsics", "resolution"):
        if key not in data:
            raise DatasetError(f"{where(path, key=key)}: missing required key")
    intr = _matrix(data["intrinsics"], path, "intrinsics", (1, 4)).ravel()
    res = _matrix(data["resolution"], path, "resolution", (1, 2)).ravel()
    model = str(data.get("distortion_model", "radial-tangential")).lower()
    if model not in ("radial-tangential", "radtan", "plumb_bob", "pinhole", "none"):
        raise DatasetError(
            f"{where(path, key='distortion_model')}: unsupported distortion model {model!r}; "
            "only radial-tangential is supported"
        )
    dist = data.get("distortion_coefficients", [0.0, 0.0, 0.0, 0.0])
    dist = dist.get("data") if isinstance(dist, dict) else dist
    cam_model = str(data.get("camera_model", "pinhole"))
    if cam_model != "pinhole":
        raise DatasetError(f"{where(path, key='camera_model')}: unsupported camera model {cam_model!r}")
    mapping = {
        "name": f"euroc_{path.parent.name}",
        "width": float(res[0]),
        "height": float(res[1]),
        "fps": data.get("rate_hz", 20.0),
        "fx": float(intr[0]),
        "fy": float(intr[1]),
        "cx": float(intr[2]),
        "cy": float(intr[3]),
        "distortion": list(dist) if isinstance(dist, (list, tuple)) else dist,
    }
    try:
        cam = camera_from_dict(mapping, path)
    except ConfigError as exc:
        # Report the sensor.yaml key, not the flat-schema key it was mapped to.
        msg = re.sub(r"\[([a-z/]+)\]", lambda m: f"[{_SENSOR_KEYS.get(m.group(1), m.group(1))}]", str(exc))
        raise DatasetError(msg) from None
    T_BS = _matrix(data["T_BS"], path, "T_BS", (4, 4)) if "T_BS" in data else np.eye(4)
    return cam, T_BS


def read_ns_listing(path: Path) -> tuple[np.ndarray, list[str], list[int]]:
    """Parse a camera ``data.csv``: ((N,) int64 ns timestamps, N file names, N line numbers)."""
    stamps: list[int] = []
    names: list[str] = []
    lines: list[int] = []
    for lineno, fields in data_lines(path):
        if len(fields) != 2:
            raise DatasetError(f"{where(path, lineno)}: expected 'timestamp_ns,filename', found {len(fields)} fields")
        stamps.append(_ns(fields[0], path, lineno))
        names.append(fields[1])
        lines.append(lineno)
    if not stamps:
        raise DatasetError(f"{path}: no images listed")
    t = np.asarray(stamps, dtype=np.int64)
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        raise DatasetError(f"{where(path, lines[bad[0] + 1])}: timestamp {t[bad[0] + 1]} does not increase")
    return t, names, lines


def _ns(text: str, path: Path, lineno: int) -> int:
    """Integer nanoseconds from ``1403715274312143104`` or ``1403715274312143104.0000``."""
    head, _, frac = text.partition(".")
    if not head.isdigit() or (frac and not frac.isdigit()):
        raise DatasetError(f"{where(path, lineno)}: not a nanosecond timestamp: {text!r}")
    return int(head)


def read_euroc_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read an EuRoC ground-truth CSV.

    Returns ((M,) int64 ns timestamps sorted, (M, 4, 4) float64 poses of the file's frame
    in the world). Extra columns (velocities, biases) are ignored.
    """
    stamps: list[int] = []
    rows: list[list[str]] = []
    lines: list[int] = []
    for lineno, fields in data_lines(path):
        if len(fields) < 8:
            raise DatasetError(
                f"{where(path, lineno)}: expected 'ns, px, py, pz, qw, qx, qy, qz', found {len(fields)} fields"
            )
        stamps.append(_ns(fields[0], path, lineno))
        rows.append(fields[1:8])
        lines.append(lineno)
    if not rows:
        raise DatasetError(f"{path}: no poses in ground-truth file")
    try:
        vals = np.array(rows, dtype=np.float64)
    except ValueError:
        for ln, row in zip(lines, rows):
            for f in row:
                try:
                    float(f)
                except ValueError:
                    raise DatasetError(f"{where(path, ln)}: not a number: {f!r}") from None
        raise
    q_wxyz = vals[:, 3:7]
    norm = np.linalg.norm(q_wxyz, axis=1)
    bad = np.flatnonzero(~np.isfinite(vals).all(axis=1) | (norm < 1e-6))
    if len(bad):
        raise DatasetError(f"{where(path, lines[bad[0]])}: non-finite value or zero quaternion")
    q_xyzw = np.concatenate([q_wxyz[:, 1:], q_wxyz[:, :1]], axis=1) / norm[:, None]
    poses = np.tile(np.eye(4), (len(vals), 1, 1))
    poses[:, :3, :3] = quat_to_R(q_xyzw)
    poses[:, :3, 3] = vals[:, :3]
    t = np.asarray(stamps, dtype=np.int64)
    order = np.argsort(t, kind="stable")
    return t[order], poses[order]


def find_euroc_camera_dir(path: Path, cam: str = "cam0") -> tuple[Path, Path]:
    """(sequence root, camera folder) from a sequence root, its ``mav0`` or the camera folder."""
    if (path / "mav0" / cam).is_dir():
        return path, path / "mav0" / cam
    if path.name == "mav0" and (path / cam).is_dir():
        return path.parent, path / cam
    if (path / "data.csv").is_file() and (path / "sensor.yaml").is_file():
        return path.parent.parent, path
    raise DatasetError(f"{path}: not an EuRoC sequence (expected mav0/{cam}/data.csv and sensor.yaml)")


class EurocSequence(ImageListSequence):
    """One camera of an EuRoC sequence.

    path: the sequence root (holding ``mav0/``), ``mav0/`` itself, or ``mav0/cam0``.
    camera: overrides the calibration read from ``sensor.yaml`` (PinholeCamera, YAML path
        or shipped name).
    groundtruth: a ground-truth CSV; ``groundtruth_frame`` says whether it gives camera
        poses (``"camera"``) or body poses (``"body"``, converted with ``T_BS``). By default
        ``<root>/groundtruth_left_cam.csv`` (camera frame, cam0 only) is used when present,
        else ``mav0/state_groundtruth_estimate0/data.csv`` (body frame).
    max_gap: largest image-to-ground-truth time difference in seconds.
    """

    def __init__(
        self,
        path: str | Path,
        camera: PinholeCamera | str | Path | None = None,
        *,
        cam: str = "cam0",
        groundtruth: str | Path | None = None,
        groundtruth_frame: str | None = None,
        max_gap: float = DEFAULT_MAX_GAP,
        color: bool = False,
    ) -> None:
        root, cam_dir = find_euroc_camera_dir(require_dir(path, "EuRoC sequence"), cam)
        ns, names, lines = read_ns_listing(cam_dir / "data.csv")
        sensor_cam, self.T_BS = read_sensor_yaml(cam_dir / "sensor.yaml")
        camera_obj = resolve_camera(camera) or sensor_cam
        self.timestamps_ns = ns

        gt_path, frame = self._groundtruth_source(root, cam_dir, cam, groundtruth, groundtruth_frame)
        gt = poses = None
        if gt_path is not None:
            gt_ns, gt_poses = read_euroc_groundtruth(gt_path)
            if frame == "body":
                gt_poses = gt_poses @ self.T_BS  # T_wc = T_wb @ T_bc
            gt = Trajectory(gt_ns.astype(np.float64) * 1e-9, gt_poses)
            idx = associate(ns, gt_ns, int(round(max_gap * 1e9)))
            poses = poses_for(idx, gt)
            log.debug("%s: %d of %d images have ground truth (%s)", root, int((idx >= 0).sum()), len(ns), gt_path)
        super().__init__(
            name=root.resolve().name,
            camera=camera_obj,
            paths=[cam_dir / "data" / n for n in names],
            timestamps=ns.astype(np.float64) * 1e-9,
            poses_wc=poses,
            ground_truth=gt,
            sources=[where(cam_dir / "data.csv", ln) for ln in lines],
            color=color,
        )

    @staticmethod
    def _groundtruth_source(
        root: Path, cam_dir: Path, cam: str, groundtruth: str | Path | None, frame: str | None
    ) -> tuple[Path | None, str]:
        if frame not in (None, "camera", "body"):
            raise ValueError(f"groundtruth_frame must be 'camera' or 'body', not {frame!r}")
        if groundtruth is not None:
            p = Path(groundtruth)
            if not p.is_file():
                raise DatasetError(f"{p}: ground-truth file not found")
            if frame is None:
                frame = "body" if p.parent.name.startswith("state_groundtruth") else "camera"
            return p, frame
        left = root / "groundtruth_left_cam.csv"
        if cam == "cam0" and left.is_file():
            return left, "camera"
        state = cam_dir.parent / "state_groundtruth_estimate0" / "data.csv"
        if state.is_file():
            return state, "body"
        return None, "camera"
