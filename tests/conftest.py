"""Shared test fixtures: paths to the real sample data beside the repository (tests that
need real images skip without it, saying so: ``pytest -rs``), and the renders the
end-to-end tests run on (made here, from tests/data, so that those tests never skip).

``ORBSLAM_HGCN_TEST_DATA`` names another folder for the real sample data (a folder that
does not exist shows what a checkout without it runs)."""

import atexit
import functools
import os
import shutil
import tempfile
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("ORBSLAM_HGCN_TEST_DATA") or REPO.parent / "shared" / "data")
TUM_SAMPLE = SHARED_DATA / "tum_fr3_long_office_household_sample"
EUROC_SAMPLE = SHARED_DATA / "euroc_V1_01_easy_first95"
KITTI_SAMPLE = SHARED_DATA / "kitti00_first160" / "sequences" / "00"
REAL_PHOTOS = SHARED_DATA / "real_photos"
# The whole suite's time budget, seconds (2 cores; each test also has pytest-timeout's limit).
SUITE_BUDGET_S = float(os.environ.get("ORBSLAM_HGCN_TEST_BUDGET_S", 1200))
# The real fr3 long-office camera path (ground truth only; tests/data/README.md).
REPLAY_GT = Path(__file__).resolve().parent / "data" / "tum_fr3_long_office_household_groundtruth.txt"


def load_bench(name: str):
    """The module of ``bench/NAME.py``, importable by its siblings (the bench folder goes on
    ``sys.path``, the module into ``sys.modules`` under NAME), for tests of a bench's
    arithmetic."""
    import importlib.util
    import sys

    bench = REPO / "bench"
    if str(bench) not in sys.path:
        sys.path.insert(0, str(bench))
    spec = importlib.util.spec_from_file_location(name, bench / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def real_photo_folder() -> Path:
    """The real photographs of the shared data (the held-out CamVid frames the benches judge
    vocabularies on among them); the calling test skips, saying why, without them."""
    if not (REAL_PHOTOS / "camvid_0620.jpg").is_file():
        pytest.skip(f"{REAL_PHOTOS}: no real photos")
    return REAL_PHOTOS


@functools.lru_cache(maxsize=None)
def stand_in(name: str) -> Path:
    """A synthetic stand-in for a real sample, rendered once per session in the TUM layout
    (its folder name gives the TUM fr3 camera, 640x480): ``tum``, the first 19 frames (as
    many as the real sample has) of the real fr3 camera path (tests/data) replayed in the
    synthetic office; ``euroc``, 85 frames at 20 Hz of a drive down the synthetic street, a
    place unlike the office as the real EuRoC room is unlike the TUM office."""
    from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence

    options = {
        "tum": SynthOptions(trajectory="replay", gt=str(REPLAY_GT), frames=19),
        "euroc": SynthOptions(scene="street", layout="tum", frames=85, fps=20),
    }[name]
    tmp = tempfile.mkdtemp(prefix=f"stand_in_{name}_")
    atexit.register(shutil.rmtree, tmp, True)
    return render_sequence(Path(tmp) / "rgbd_dataset_freiburg3_synthetic", options, progress=False)


@pytest.fixture
def tum_layout() -> Path:
    """A TUM-layout sequence for tests of what any such sequence shows (readers, features):
    the real TUM sample when it is there, else the rendered stand-in."""
    return TUM_SAMPLE if TUM_SAMPLE.is_dir() else stand_in("tum")


# The EuRoC cam0 calibration (sensor.yaml of every EuRoC MAV sequence), for the stand-in.
EUROC_SENSOR_YAML = """%YAML:1.0
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


@functools.lru_cache(maxsize=None)
def euroc_stand_in() -> Path:
    """An EuRoC-layout folder (mav0/cam0/data, data.csv, sensor.yaml, groundtruth_left_cam.csv)
    holding the ``euroc`` stand-in's frames at 752x480 and 20 Hz, with its camera path as the
    ground truth from frame 20 on (the real sample's first frames have none either)."""
    import cv2
    import numpy as np

    src = stand_in("euroc")
    root = src.parent / "euroc_layout"
    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    (cam / "sensor.yaml").write_text(EUROC_SENSOR_YAML)
    frames = sorted((src / "rgb").glob("*.png"))
    ns = 1403715273262142976 + 50_000_000 * np.arange(len(frames), dtype=np.int64)
    for t, f in zip(ns, frames):
        img = cv2.resize(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), (752, 480), interpolation=cv2.INTER_LINEAR)
        cv2.imwrite(str(cam / "data" / f"{t}.png"), img)
    (cam / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in ns))
    gt = np.loadtxt(src / "groundtruth.txt", comments="#")
    lines = ["#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"]
    for t, row in zip(ns[20:], gt[20:]):
        x, y, z, qx, qy, qz, qw = row[1:8]
        lines.append(f"{t},{x:.10f},{y:.10f},{z:.10f},{qw:.10f},{qx:.10f},{qy:.10f},{qz:.10f}")
    (root / "groundtruth_left_cam.csv").write_text("\n".join(lines) + "\n")
    return root


@pytest.fixture
def euroc_layout() -> Path:
    """An EuRoC-layout sequence for tests of what any such sequence shows (the reader, its
    checks): the real EuRoC sample when it is there, else the stand-in."""
    return EUROC_SAMPLE if EUROC_SAMPLE.is_dir() else euroc_stand_in()


@pytest.fixture
def tum_sample() -> Path:
    if not TUM_SAMPLE.is_dir():
        pytest.skip(f"real TUM sample not found at {TUM_SAMPLE}")
    return TUM_SAMPLE


@pytest.fixture
def euroc_sample() -> Path:
    if not EUROC_SAMPLE.is_dir():
        pytest.skip(f"real EuRoC sample not found at {EUROC_SAMPLE}")
    return EUROC_SAMPLE


@pytest.fixture
def kitti_sample() -> Path:
    """KITTI odometry 00, frames 0-159 (sequence folder; poses in ../../poses/00.txt)."""
    if not KITTI_SAMPLE.is_dir():
        pytest.skip(f"real KITTI sample not found at {KITTI_SAMPLE}")
    return KITTI_SAMPLE


@pytest.fixture
def replay_gt() -> Path:
    """The real fr3 long-office ground truth (TUM format), shipped with the tests."""
    return REPLAY_GT


@pytest.fixture(scope="session")
def synth_replay_100(tmp_path_factory) -> Path:
    """The first 100 frames of the real fr3 long-office camera path replayed in a synthetic
    room (rendered once per test session)."""
    from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence

    out = tmp_path_factory.mktemp("synth_replay_100")
    return render_sequence(out, SynthOptions(trajectory="replay", gt=str(REPLAY_GT), frames=100), progress=False)


def pytest_sessionstart(session) -> None:
    session.config._suite_t0 = time.monotonic()


def pytest_sessionfinish(session, exitstatus) -> None:
    """A whole run of the suite (not a selection) over its budget fails, saying by how much."""
    elapsed = time.monotonic() - session.config._suite_t0
    whole = not session.config.args or [str(a) for a in session.config.args] == ["tests"]
    if whole and session.testscollected > 100 and elapsed > SUITE_BUDGET_S and exitstatus == 0:
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            reporter.write_line(f"suite budget exceeded: {elapsed:.0f} s against {SUITE_BUDGET_S:.0f} s "
                                "(ORBSLAM_HGCN_TEST_BUDGET_S)", red=True)
        session.exitstatus = 1
