"""What ``orbslam-hgcn run`` says before its first frame: where the camera and the stage
settings come from, and that the first run after an install compiles the kernels."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

from orbslam_hgcn.config import camera_to_dict
from orbslam_hgcn.geometry.camera import PinholeCamera

REPO = Path(__file__).resolve().parents[1]


class _Stop(Exception):
    """Raised where the system would be built: the test needs only what comes before."""


def _tum_folder(root: Path, camera: PinholeCamera, name: str = "seq") -> Path:
    """A TUM-layout folder (rgb.txt, two images) with ``camera`` in its camera.yaml."""
    import yaml

    folder = root / name
    (folder / "rgb").mkdir(parents=True)
    for i in range(2):
        cv2.imwrite(str(folder / "rgb" / f"{i}.png"), np.full((camera.height, camera.width), 100, np.uint8))
    (folder / "rgb.txt").write_text("0.000000 rgb/0.png\n0.033333 rgb/1.png\n")
    (folder / "camera.yaml").write_text(yaml.safe_dump(camera_to_dict(camera), sort_keys=False))
    return folder


def _settings_logged(folder: Path, out: Path, caplog, monkeypatch, config: str | None = None) -> str:
    import orbslam_hgcn.app.run as run_mod

    def stop(*a, **k):
        raise _Stop()

    monkeypatch.setattr(run_mod, "Slam", stop)
    caplog.set_level(logging.INFO, logger="orbslam_hgcn")
    with pytest.raises(_Stop):
        run_mod.run_dataset(folder, out, config=config, progress=False)
    lines = [r.getMessage() for r in caplog.records if "stage settings" in r.getMessage()]
    assert len(lines) == 1, [r.getMessage() for r in caplog.records]
    return lines[0]


def test_run_names_camera_yaml_and_why_the_settings(tmp_path, caplog, monkeypatch):
    """A TUM-layout folder whose camera.yaml holds a camera no shipped config has: the log
    names camera.yaml as the camera's source and says the stage settings are the TUM
    family's defaults, not those of "the dataset's camera"."""
    odd = PinholeCamera(fx=600.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480, name="rendered")
    folder = _tum_folder(tmp_path, odd, "rgbd_dataset_freiburg1_desk")  # the folder name says fr1: not used
    line = _settings_logged(folder, tmp_path / "out", caplog, monkeypatch)
    assert "the dataset's camera" not in line
    assert f"camera from {folder / 'camera.yaml'}" in line
    assert "stage settings of tum_fr1 (the defaults for this kind of dataset: the camera matches no shipped config)" \
        in line


def test_run_says_when_the_settings_follow_the_camera(tmp_path, caplog, monkeypatch):
    """camera.yaml with the freiburg3 camera: the settings of tum_fr3, chosen by the camera."""
    fr3 = PinholeCamera(fx=535.4, fy=539.2, cx=320.1, cy=247.6, width=640, height=480, name="fr3")
    folder = _tum_folder(tmp_path, fr3)
    line = _settings_logged(folder, tmp_path / "out", caplog, monkeypatch)
    assert line == f"camera from {folder / 'camera.yaml'}; stage settings of tum_fr3 (its camera is this camera)"


def test_run_names_config_as_the_cameras_source(tmp_path, caplog, monkeypatch):
    """--config with a camera wins over camera.yaml, and the log says so."""
    odd = PinholeCamera(fx=600.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480, name="rendered")
    folder = _tum_folder(tmp_path, odd)
    line = _settings_logged(folder, tmp_path / "out", caplog, monkeypatch, config="tum_fr2")
    assert line.startswith("camera from ") and "tum_fr2.yaml; stage settings of tum_fr2 (its camera" in line
    assert line.endswith("tum_fr2.yaml")  # then --config


_COLD_CACHE = textwrap.dedent("""
    import logging, sys
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s", stream=sys.stdout)
    import orbslam_hgcn.runtime.system as system
    from orbslam_hgcn.runtime import kernels
    for name in kernels.RUN_KERNEL_MODULES:  # the compile step stubbed: the message is the test
        __import__(name, fromlist=["warm_up"]).warm_up = lambda: 0.0
    system.warm_up_kernels()
    kernels.cold_modules = lambda *a: []  # as when every kernel is cached
    system.warm_up_kernels()
""")


def test_the_first_run_says_it_compiles_the_kernels_before_it_does(tmp_path):
    """Without the kernels built ahead of time and with numba's cache empty
    (NUMBA_CACHE_DIR), warming the kernels first logs that the first run after an install
    compiles them once and later runs load them; with every kernel cached it says nothing."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "ORBSLAM_HGCN_AOT": "0"}
    r = subprocess.run([sys.executable, "-c", _COLD_CACHE], env=env, capture_output=True, text=True, timeout=120,
                       cwd=REPO)  # fmt: skip
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stdout.splitlines() if "compiling the numba kernels" in ln]
    assert len(lines) == 1, r.stdout
    assert "first run after an install compiles them once" in lines[0] and "later runs load them" in lines[0]
    assert "pose_only" in lines[0] and "schur_ba" in lines[0] and "fast" in lines[0]


def _cache_files(folder: Path) -> dict[str, int]:
    """numba's cache files under ``folder`` (index and code) and their sizes and mtimes."""
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*") if p.suffix in (".nbi", ".nbc")}


def test_a_run_after_warming_the_kernels_compiles_nothing(tmp_path, kitti_sample):
    """Where the kernels cannot be built ahead of time (here: turned off),
    ``python -m orbslam_hgcn.runtime.kernels`` (tools/setup.sh) compiles them into numba's
    cache; a user's first run after it, on real KITTI frames with the default vocabulary
    (initialisation, tracking, keyframes, local mapping and BA), finds every kernel it needs
    in the cache: it writes nothing to numba's cache and does not say it compiles. (With
    the build, tests/test_aot.py.)"""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "ORBSLAM_HGCN_AOT": "0"}
    warm = subprocess.run([sys.executable, "-m", "orbslam_hgcn.runtime.kernels"], env=env, capture_output=True,
                          text=True, timeout=600, cwd=REPO)  # fmt: skip
    assert warm.returncode == 0, warm.stderr
    assert "compiled in" in warm.stdout
    before = _cache_files(tmp_path / "numba")
    assert len(before) > 40
    r = subprocess.run([sys.executable, "-m", "orbslam_hgcn", "run", str(kitti_sample), "--out", str(tmp_path / "run"),
                        "--max-frames", "30", "--no-progress", "--speed", "0"],
                       env=env, capture_output=True, text=True, timeout=300, cwd=REPO)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    stats = json.loads((tmp_path / "run" / "stats.json").read_text())
    assert stats["keyframes"] >= 5 and stats["timing_ms"]["local_ba_per_keyframe"]["count"] >= 3
    assert "compiling the numba kernels" not in r.stderr + r.stdout
    after = _cache_files(tmp_path / "numba")
    assert {k: v for k, v in after.items() if before.get(k) != v} == {}
