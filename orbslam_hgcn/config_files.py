"""Config files: the camera YAML schema, the shipped configs, and reading a file's sections.

Camera files (the shipped ones in ``orbslam_hgcn/configs/*.yaml``) use one flat schema::

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
validated on load; an error names the file and the key. A file may also carry stage
sections (``orb:``, ``tracking:``, ...; see :class:`~orbslam_hgcn.runtime.system.Configs`):
each shipped camera carries the settings ORB-SLAM's example files use for it
(:func:`dataset_settings` picks them for a dataset's camera). A section that no stage reads
is refused (:func:`check_sections`), as an unknown key is: :func:`section_from_yaml` fills
a section's frozen dataclass (:mod:`orbslam_hgcn.config`, :mod:`orbslam_hgcn.tool_config`)
and rejects unknown keys. Every name here is also importable from :mod:`orbslam_hgcn.config`.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib.resources
import math
from pathlib import Path
from typing import Any, TypeVar

import yaml

from orbslam_hgcn.errors import ConfigError, where
from orbslam_hgcn.geometry.camera import PinholeCamera


# The shipped camera configs, package data (read the same from a checkout or a wheel).
CONFIG_DIR = Path(str(importlib.resources.files("orbslam_hgcn") / "configs"))


def resolve_config(path: str | Path) -> Path:
    """The file of a config argument: a path as given, or the bare name of a shipped config
    (``tum_fr3`` finds ``tum_fr3.yaml`` among the shipped configs) when no such file exists."""
    p = Path(path)
    if not p.is_file() and not p.suffix and (CONFIG_DIR / f"{p.name}.yaml").is_file():
        return CONFIG_DIR / f"{p.name}.yaml"
    return p


def shipped_configs() -> list[str]:
    """Names of the shipped configs."""
    return sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))

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

    ``path`` may also be the bare name of a shipped config (``tum_fr3``).
    """
    p = resolve_config(path)
    return camera_from_dict(load_yaml(p), p)


# A dataset of one of these kinds whose camera matches no shipped config takes the stage
# settings of the first shipped config of its family (ORB-SLAM's settings for that dataset).
KIND_FAMILIES = {"kitti": "kitti_", "tum": "tum_", "euroc": "euroc_"}


def _same_camera(a: PinholeCamera, b: PinholeCamera, tol_px: float = 0.5) -> bool:
    return (a.width, a.height) == (b.width, b.height) and all(
        abs(x - y) <= tol_px for x, y in ((a.fx, b.fx), (a.fy, b.fy), (a.cx, b.cx), (a.cy, b.cy))
    )


def stage_sections(data: dict[str, Any]) -> dict[str, Any]:
    """The stage sections (every mapping but ``camera``) of a config file's contents."""
    return {k: v for k, v in data.items() if isinstance(v, dict) and k != "camera"}


def dataset_settings(camera: PinholeCamera, kind: str | None = None) -> tuple[Path | None, dict[str, Any]]:
    """The stage settings a run on a dataset with ``camera`` starts from (before --config).

    The shipped config whose camera is ``camera`` (same size, focal lengths and principal
    point within 0.5 px); otherwise, for a dataset ``kind`` with a family of shipped
    configs (KITTI, TUM, EuRoC), the first of that family; otherwise none. Returns (the
    config's path or None, its stage sections)."""
    names = shipped_configs()
    for name in names:
        path = CONFIG_DIR / f"{name}.yaml"
        data = load_yaml(path)
        if _same_camera(camera_from_dict(data, path), camera):
            return path, stage_sections(data)
    prefix = KIND_FAMILIES.get((kind or "").lower())
    family = [n for n in names if prefix and n.startswith(prefix)]
    if family:
        path = CONFIG_DIR / f"{family[0]}.yaml"
        return path, stage_sections(load_yaml(path))
    return None, {}


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


# Sections a run's config file may hold besides the stages' (runtime.system.Configs): the
# camera, the live viewer's (viz), and those of the commands that may share a file with it
# (lcd's fabmap, vocab train's hgcn and vocab_tree).
OTHER_SECTIONS = ("camera", "viz", "fabmap", "hgcn", "vocab_tree")
# What to say, instead of a close match, of sections people write that are no settings.
NOT_SETTINGS = {"vocabulary": "the vocabulary is no config setting: choose it with --vocab NAME|FILE"}


def check_sections(data: dict[str, Any] | None, path: str | Path, stages: list[str]) -> None:
    """Raise ConfigError, naming the file, for a section (a mapping at the top of a config
    file) that neither a stage (``stages``, the section names) nor :data:`OTHER_SECTIONS`
    reads: a misspelt ``orbb:`` would otherwise be ignored without a word."""
    known = list(stages) + list(OTHER_SECTIONS)
    for key, value in (data or {}).items():
        if isinstance(value, dict) and key not in known:
            close = difflib.get_close_matches(str(key), known, n=1)
            hint = f"{NOT_SETTINGS[key]}; " if key in NOT_SETTINGS else f"did you mean {close[0]!r}? " if close else ""
            raise ConfigError(f"{where(path, key=str(key))}: unknown section; {hint}known sections: {', '.join(known)}")


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
