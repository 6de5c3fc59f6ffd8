"""One resolution of a run's settings, used by ``run``, ``compare``, ``sweep``, the Python API
(:class:`~orbslam_hgcn.app.slam.Slam`) and the benches.

Layers, each overriding the one before it key by key:

1. the defaults of each stage's config class (:mod:`orbslam_hgcn.config`);
2. the shipped settings of the camera (``configs/<name>.yaml`` whose camera is this one,
   else the default of the dataset kind's family: :func:`~orbslam_hgcn.config.dataset_settings`);
3. the user's config: ``--config`` / ``config=``, a YAML file, a shipped camera name such as
   ``tum_fr3``, or (API) a mapping of sections;
4. the arguments of the command or the API call (``--sequential``, ``--no-loop``,
   ``--speed``, ``--drop-late``; ``Slam(sequential=..., loop_closing=...)``), where None
   means "take the config".

Each layer is checked on its own: a section no stage reads, a key its section does not
have or a value of the wrong type is a :class:`~orbslam_hgcn.errors.ConfigError` that names
the file (one line and status 2 from the commands).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from orbslam_hgcn.config import dataset_settings, load_camera, load_yaml, resolve_config
from orbslam_hgcn.errors import ConfigError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.runtime.system import Configs

CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")


@dataclass(frozen=True)
class UserConfig:
    """The user's config layer: its sections, where it came from (a file, or ``<mapping>``)
    and its file (None for a mapping or no config)."""

    data: dict[str, Any]
    origin: str
    path: Path | None


def user_config(config: str | Path | Mapping[str, Any] | None) -> UserConfig:
    """Read the user's config: a YAML file, a shipped camera name, or a mapping of sections
    (the API's ``config=``); None: an empty layer."""
    if config is None:
        return UserConfig({}, "", None)
    if isinstance(config, Mapping):
        return UserConfig(dict(config), "<config mapping>", None)
    path = resolve_config(config)  # a path, or a shipped camera name such as tum_fr3
    return UserConfig(load_yaml(path), str(path), path)


def config_camera(user: UserConfig) -> PinholeCamera | None:
    """The camera the user's config holds (flat keys or a ``camera:`` section), else None."""
    data = user.data
    section = data.get("camera") if isinstance(data.get("camera"), dict) else data
    if not any(k in section for k in CAMERA_KEYS):
        return None
    if user.path is not None:
        return load_camera(user.path)
    from orbslam_hgcn.config import camera_from_dict

    return camera_from_dict(section, user.origin)


def camera_from_config(path: str | Path | None) -> PinholeCamera | None:
    """The camera of a config file when it holds one (flat keys or a ``camera:`` section)."""
    return None if path is None else config_camera(user_config(path))


def flag_layer(
    sequential: bool | None = None, loop_closing: bool | None = None, speed: float | None = None,
    drop_late: bool | None = None,
) -> dict[str, Any]:  # fmt: skip
    """Layer 4: the settings the command's flags or the API's arguments give (None: not given)."""
    layer: dict[str, dict[str, Any]] = {}
    threads = {k: v for k, v in (("sequential", sequential), ("speed", speed), ("drop_late", drop_late))
               if v is not None}  # fmt: skip
    if threads:
        layer["threads"] = threads
    if loop_closing is not None:
        layer["loop_closing"] = {"enabled": bool(loop_closing)}
    return layer


@dataclass(frozen=True)
class Settings:
    """A run's resolved settings, and where they came from."""

    configs: Configs
    settings_path: Path | None  # the shipped settings file of layer 2 (None: the defaults)
    chosen_by: str | None  # "camera": the shipped config has this camera; "kind": its family's
    user: UserConfig

    def line(self, camera_origin: str) -> str:
        """The log line that says where a run's camera and stage settings come from."""
        line = f"camera from {camera_origin}; "
        if self.settings_path is None:
            line += "stage settings: the defaults"
        elif self.chosen_by == "camera":
            line += f"stage settings of {self.settings_path.stem} (its camera is this camera)"
        else:
            line += (f"stage settings of {self.settings_path.stem} (the defaults for this kind of dataset: the "
                     "camera matches no shipped config)")  # fmt: skip
        return line + (f", then {self.user.origin}" if self.user.origin else "")


def resolve_settings(
    camera: PinholeCamera, kind: str | None = None, config: str | Path | Mapping[str, Any] | UserConfig | None = None,
    flags: Mapping[str, Any] | None = None,
) -> Settings:  # fmt: skip
    """The settings of a run of ``camera`` (layers 1-4 of the module text): ``kind`` the
    dataset kind (``tum``, ``kitti``, ``euroc``, ...; None: a camera match only), ``config``
    the user's config, ``flags`` layer 4 (:func:`flag_layer`)."""
    user = config if isinstance(config, UserConfig) else user_config(config)
    settings_path, shipped = dataset_settings(camera, kind)
    chosen_by = None
    if settings_path is not None:
        matched, _ = dataset_settings(camera, None)
        chosen_by = "camera" if matched == settings_path else "kind"
    layers = [(shipped, settings_path or ""), (user.data, user.origin or "")]
    if flags:
        layers.append((dict(flags), "<arguments>"))
    return Settings(Configs.from_layers(layers), settings_path, chosen_by, user)


def check_user_config(user: UserConfig) -> None:
    """Validate the user's config layer on its own (before a dataset is read)."""
    Configs.from_layers([(user.data, user.origin or "")])


def camera_argument(camera: PinholeCamera | str | Path | None, user: UserConfig) -> PinholeCamera:
    """The camera of the API's ``camera=``: a PinholeCamera, a shipped camera name
    (``tum_fr3``) or a YAML file with one; None: the camera of the user's config."""
    if isinstance(camera, PinholeCamera):
        return camera
    if camera is not None:
        return load_camera(resolve_config(camera))
    cam = config_camera(user)
    if cam is None:
        raise ConfigError("no camera: give camera= (a shipped name such as tum_fr3, a YAML file or a "
                          "PinholeCamera) or a config with fx, fy, cx, cy, width and height")  # fmt: skip
    return cam
