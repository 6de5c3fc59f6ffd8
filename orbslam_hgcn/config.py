"""Configuration: the camera YAML schema and frozen per-stage dataclasses.

Camera files (``configs/*.yaml``) use one flat schema::

    name: tum_fr3            # free text
    model: pinhole           # the only model supported
    width: 640               # image size in pixels
    height: 480
    fps: 30
    fx: 535.4                # focal lengths and principal point in pixels
    fy: 539.2
    cx: 320.1
    cy: 247.6
    distortion: [0, 0, 0, 0, 0]   # OpenCV radial-tangential k1 k2 p1 p2 [k3]

The same keys may instead sit under a ``camera:`` section of a larger file. Every value is
validated on load; an error names the file and the key.

Stage configs are frozen dataclasses defined below, each with its defaults beside their
meaning; :func:`section_from_yaml` fills one from a YAML section and rejects unknown keys.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, TypeVar

import yaml

from orbslam_hgcn.errors import ConfigError, where
from orbslam_hgcn.geometry.camera import PinholeCamera

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"

T = TypeVar("T")


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping; a missing, unreadable or non-mapping file is a ConfigError."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc.strerror})") from None
    # OpenCV FileStorage YAML (as ORB-SLAM ships) starts with a %YAML:1.0 directive that
    # PyYAML rejects; drop it so such files can at least be reported on clearly.
    if text.startswith("%YAML"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise ConfigError(f"{where(path, line)}: not valid YAML") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys at the top level")
    return data


def _number(data: dict, key: str, path: Path, *, positive: bool, integer: bool = False) -> float:
    if key not in data:
        raise ConfigError(f"{where(path, key=key)}: missing required key")
    val = data[key]
    if isinstance(val, bool) or not isinstance(val, (int, float)):
        raise ConfigError(f"{where(path, key=key)}: expected a number, found {val!r}")
    if not math.isfinite(val):
        raise ConfigError(f"{where(path, key=key)}: value must be finite, found {val!r}")
    if positive and val <= 0:
        raise ConfigError(f"{where(path, key=key)}: value must be positive, found {val!r}")
    if integer and int(val) != val:
        raise ConfigError(f"{where(path, key=key)}: expected a whole number, found {val!r}")
    return int(val) if integer else float(val)


def camera_from_dict(data: dict[str, Any], path: str | Path = "<camera>") -> PinholeCamera:
    """Validate a camera mapping (the flat schema above) and build a PinholeCamera."""
    path = Path(path)
    if "camera" in data and isinstance(data["camera"], dict):
        data = data["camera"]
    model = data.get("model", "pinhole")
    if model != "pinhole":
        raise ConfigError(f"{where(path, key='model')}: unsupported camera model {model!r}; use 'pinhole'")
    fx = _number(data, "fx", path, positive=True)
    fy = _number(data, "fy", path, positive=True)
    width = _number(data, "width", path, positive=True, integer=True)
    height = _number(data, "height", path, positive=True, integer=True)
    cx = _number(data, "cx", path, positive=False)
    cy = _number(data, "cy", path, positive=False)
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise ConfigError(
            f"{where(path, key='cx/cy')}: principal point ({cx}, {cy}) lies outside the "
            f"{width}x{height} image"
        )
    fps = _number(data, "fps", path, positive=True) if "fps" in data else 30.0
    dist = data.get("distortion", [0.0] * 5)
    if dist is None:
        dist = [0.0] * 5
    if (
        not isinstance(dist, list)
        or len(dist) not in (4, 5)
        or not all(isinstance(d, (int, float)) and not isinstance(d, bool) and math.isfinite(d) for d in dist)
    ):
        raise ConfigError(
            f"{where(path, key='distortion')}: expected a list of 4 or 5 numbers k1 k2 p1 p2 [k3], "
            f"found {dist!r}"
        )
    return PinholeCamera(
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        width=int(width),
        height=int(height),
        dist=tuple(float(d) for d in dist),
        fps=fps,
        name=str(data.get("name", path.stem)),
    )


def load_camera(path: str | Path) -> PinholeCamera:
    """Load and validate a camera YAML file.

    ``path`` may also be the bare name of a shipped config (``tum_fr3`` finds
    ``configs/tum_fr3.yaml``).
    """
    p = Path(path)
    if not p.is_file() and not p.suffix and (CONFIG_DIR / f"{p.name}.yaml").is_file():
        p = CONFIG_DIR / f"{p.name}.yaml"
    return camera_from_dict(load_yaml(p), p)


def camera_to_dict(cam: PinholeCamera) -> dict[str, Any]:
    """The flat YAML mapping of a camera (inverse of :func:`camera_from_dict`)."""
    return {
        "name": cam.name,
        "model": "pinhole",
        "width": cam.width,
        "height": cam.height,
        "fps": cam.fps,
        "fx": cam.fx,
        "fy": cam.fy,
        "cx": cam.cx,
        "cy": cam.cy,
        "distortion": [float(d) for d in cam.dist_coeffs],
    }


def save_camera(path: str | Path, cam: PinholeCamera) -> None:
    Path(path).write_text(yaml.safe_dump(camera_to_dict(cam), sort_keys=False), encoding="utf-8")


def section_from_yaml(cls: type[T], data: dict[str, Any] | None, path: str | Path, section: str) -> T:
    """Build the frozen dataclass ``cls`` from ``data[section]``, defaults for absent keys.

    Unknown keys, and values whose type does not match the default's, are ConfigErrors.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    values = (data or {}).get(section) or {}
    if not isinstance(values, dict):
        raise ConfigError(f"{where(path, key=section)}: expected a mapping")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, val in values.items():
        if key not in fields:
            raise ConfigError(
                f"{where(path, key=f'{section}.{key}')}: unknown key; known keys: {', '.join(sorted(fields))}"
            )
        default = fields[key].default
        if default is not dataclasses.MISSING and default is not None:
            if isinstance(default, bool) != isinstance(val, bool) or (
                isinstance(default, (int, float)) and not isinstance(val, (int, float))
            ) or (isinstance(default, str) and not isinstance(val, str)):
                raise ConfigError(
                    f"{where(path, key=f'{section}.{key}')}: expected {type(default).__name__}, found {val!r}"
                )
            if isinstance(default, float) and isinstance(val, int):
                val = float(val)
        kwargs[key] = val
    return cls(**kwargs)


# --- Stage configurations -------------------------------------------------------------
# Each stage appends its frozen dataclass below, defaults beside their meaning.
