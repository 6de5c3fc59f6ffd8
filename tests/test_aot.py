"""The kernels built ahead of time (orbslam_hgcn.aot): built into a folder of the test's
own, loaded without numba, given only the arguments they were built for, refused when
they no longer match, and computing what numba computes on a real run."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from orbslam_hgcn import aot
from orbslam_hgcn.backend import pose_only

REPO = Path(__file__).resolve().parents[1]
OPTIMIZE = "orbslam_hgcn.backend.pose_only._optimize"


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    """A build of every kernel of a run, as tools/setup.sh makes it, in a folder of its own."""
    folder = tmp_path_factory.mktemp("aot")
    env = {**os.environ, aot.ENV_DIR: str(folder)}
    env.pop(aot.ENV_SWITCH, None)
    r = subprocess.run([sys.executable, "-m", "orbslam_hgcn.runtime.kernels"], env=env, capture_output=True,
                       text=True, timeout=900, cwd=REPO)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert "kernel signatures ahead of time" in r.stdout, r.stdout
    return folder


def _load(folder: Path, monkeypatch) -> aot.Built | None:
    monkeypatch.setenv(aot.ENV_DIR, str(folder))
    monkeypatch.delenv(aot.ENV_SWITCH, raising=False)
    return aot.load()


def _pose_problem(n: int = 300):
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(4, 20, n)])
    K = np.array([[700.0, 0.0, 600.0], [0.0, 700.0, 180.0], [0.0, 0.0, 1.0]])
    uv = X[:, :2] / X[:, 2:] * 700.0 + [600.0, 180.0] + rng.normal(0.0, 1.0, (n, 2))
    T0 = np.eye(4)
    T0[0, 3] = 0.2
    return [T0, X, uv, np.ones(n), K, 4, 10, 3, 5.991]


def test_the_build_runs_its_kernels_and_hands_other_types_to_numba(built, monkeypatch):
    monkeypatch.setattr(aot, "fallbacks", {})
    b = _load(built, monkeypatch)
    assert b is not None, aot.status
    kernel = aot.Kernel(pose_only._optimize.py_func, {}, b.exports(OPTIMIZE))
    assert len(kernel.exports) == 1
    args = _pose_problem()
    T, inliers = kernel(*args)
    assert aot.fallbacks == {}
    T_ref, inliers_ref = kernel.dispatcher(*args)  # numba's own, compiled or from its cache
    np.testing.assert_array_equal(T, T_ref)
    np.testing.assert_array_equal(inliers, inliers_ref)
    assert abs(T[0, 3]) < 0.05  # the offset of the start removed
    # A view that is not C-ordered, a read-only array, float32 points: each goes to numba
    # (the built code would read them wrongly) and gives numba's result.
    for i, value in ((1, np.hstack([args[1], args[1]])[:, :3]), (2, args[2].copy()), (1, args[1].astype(np.float32))):
        other = list(args)
        other[i] = value
        if i == 2:
            value.setflags(write=False)
        monkeypatch.setattr(aot, "fallbacks", {})
        T2, _ = kernel(*other)
        assert list(aot.fallbacks) == [OPTIMIZE]
        np.testing.assert_allclose(T2, T, atol=1e-5)
    monkeypatch.setattr(aot, "fallbacks", {})
    kernel(*args[:-1], 5)  # an int where the build takes a float
    assert "int" in aot.fallbacks[OPTIMIZE].split(", ")[-1]


def test_argument_checks_take_exactly_the_built_types():
    check = aot.make_check(("int64", "float64", "bool", "array:float64:2:C:w", "array:uint8:1:A:r"))
    a, b = np.zeros((3, 2)), np.zeros(5, np.uint8)
    assert check(1, 1.0, True, a, b)
    assert check(np.int64(1), np.float64(1.0), np.bool_(False), a, b[::2])  # layout A: any strides
    bad = [
        (True, 1.0, True, a, b),  # a bool is not an int64
        (np.int32(1), 1.0, True, a, b),
        (1, 1, True, a, b),  # an int is not a float64
        (1, 1.0, 1, a, b),
        (1, 1.0, True, a.astype(np.float32), b),
        (1, 1.0, True, a.T, b),  # Fortran order
        (1, 1.0, True, a[:, :1], b),  # not contiguous
        (1, 1.0, True, a.ravel(), b),  # wrong dimensions
        (1, 1.0, True, a.astype(">f8"), b),  # other byte order
        (1, 1.0, True, np.frombuffer(bytes(49), np.uint8)[1:].view(np.float64).reshape(3, 2), b),  # unaligned
        (1, 1.0, True, a.tolist(), b),
    ]
    for args in bad:
        assert not check(*args), args
    ro = a.copy()
    ro.setflags(write=False)
    assert not check(1, 1.0, True, ro, b)  # written by the kernel: must be writable
    b_ro = b.copy()
    b_ro.setflags(write=False)
    assert check(1, 1.0, True, a, b_ro)  # "r": read-only allowed
    with pytest.raises(ValueError, match="unknown argument spec"):
        aot.make_check(("tuple",))


def test_a_build_that_no_longer_matches_is_not_used(built, tmp_path, monkeypatch):
    assert _load(built, monkeypatch) is not None, aot.status
    cases = {
        "source": lambda m: m["sources"].__setitem__("map/database.py", "0" * 64),
        "cpu": lambda m: m.__setitem__("cpu", "another"),
        "python": lambda m: m.__setitem__("python", [3, 99]),
        "format": lambda m: m.__setitem__("format", 0),
    }
    expected = {"source": "orbslam_hgcn/map/database.py changed", "cpu": "another CPU", "python": "another Python",
                "format": "another version of the builder"}  # fmt: skip
    for name, change in cases.items():
        folder = tmp_path / name
        shutil.copytree(built, folder)
        manifest = json.loads((folder / aot.MANIFEST).read_text())
        change(manifest)
        (folder / aot.MANIFEST).write_text(json.dumps(manifest))
        assert _load(folder, monkeypatch) is None
        assert expected[name] in aot.status, aot.status
    folder = tmp_path / "corrupt"
    shutil.copytree(built, folder)
    (folder / aot.MANIFEST).write_text("{not json")
    assert _load(folder, monkeypatch) is None and "unreadable manifest" in aot.status
    folder = tmp_path / "no_module"
    shutil.copytree(built, folder)
    for so in folder.glob(aot.MODULE_NAME + "*"):
        so.unlink()
    assert _load(folder, monkeypatch) is None and "does not load" in aot.status
    assert _load(tmp_path / "empty", monkeypatch) is None and "not built yet" in aot.status
    monkeypatch.setenv(aot.ENV_DIR, str(built))
    monkeypatch.setenv(aot.ENV_SWITCH, "0")
    assert aot.load() is None and "turned off" in aot.status


def _run(kitti_sample: Path, out: Path, env: dict[str, str]) -> dict:
    r = subprocess.run([sys.executable, "-m", "orbslam_hgcn", "run", str(kitti_sample), "--out", str(out),
                        "--max-frames", "40", "--no-progress", "--speed", "0"],
                       env=env, capture_output=True, text=True, timeout=300, cwd=REPO)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads((out / "stats.json").read_text())


def test_a_run_on_the_build_never_loads_numba_and_gives_numbas_poses(built, tmp_path, kitti_sample):
    """Real KITTI frames (initialisation, tracking, keyframes, local mapping and BA in their
    threads and processes): every kernel comes from the build, numba is never imported,
    and the poses are byte for byte those of the same run with numba's kernels."""
    env = {**os.environ, aot.ENV_DIR: str(built)}
    env.pop(aot.ENV_SWITCH, None)
    ahead = _run(kitti_sample, tmp_path / "ahead", env)
    assert ahead["kernels"] == {"built_ahead": True, "not_built_why": None, "numba_imported": False, "fallbacks": {}}
    assert ahead["keyframes"] >= 8 and ahead["timing_ms"]["local_ba_per_keyframe"]["count"] >= 5
    jit = _run(kitti_sample, tmp_path / "jit", {**env, aot.ENV_SWITCH: "0"})
    assert jit["kernels"]["built_ahead"] is False and jit["kernels"]["numba_imported"] is True
    for name in ("CameraTrajectory.txt", "KeyFrameTrajectory.txt"):
        assert (tmp_path / "ahead" / name).read_bytes() == (tmp_path / "jit" / name).read_bytes()
