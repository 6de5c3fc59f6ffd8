"""The package as a user installs it: a wheel built from the sources, installed into a fresh
virtual environment, runs ``orbslam-hgcn run --config tum_fr3`` (a shipped camera, package
data) on a short render, from a folder outside the checkout.

For that run the fresh environment gets the wheel only; its dependencies (numpy, OpenCV,
gtsam, torch, ...) are the test environment's, reached through a ``.pth`` file, so nothing
is downloaded and the test takes seconds. The dependencies the wheel declares are checked
apart: pip, in another fresh environment, resolves the wheel against the package index
(``--dry-run --report``: every version chosen, nothing installed; torch pinned to 2.13.0, the
CPU build, as a full resolution would otherwise pick the CUDA build and its gigabytes), and
every third-party module the package imports must come from a declared dependency. The compiled kernels' numba cache of the checkout is copied
beside the installed modules when it is there (the same sources), so that the run loads
them instead of compiling them again (about 30 s on a 2-core machine).
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "orbslam_hgcn"


def _setuptools_builds_here() -> bool:
    """The test environment's setuptools can build the wheel without an isolated build
    environment (pyproject.toml asks for setuptools>=77), so nothing is downloaded."""
    try:
        major = int(importlib.metadata.version("setuptools").split(".")[0])
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return False
    return major >= 77


def _build_wheel(work: Path) -> Path:
    """Build the wheel from a copy of the sources (an in-tree build would leave build/ and
    could pack files left there by an earlier build)."""
    src = work / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    shutil.copytree(PACKAGE, src / "orbslam_hgcn", ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(work / "dist"), str(src)]
    if _setuptools_builds_here():
        cmd.insert(5, "--no-build-isolation")
    subprocess.run(cmd, check=True, cwd=work, timeout=300)
    wheels = list((work / "dist").glob("orbslam_hgcn-*.whl"))
    assert len(wheels) == 1
    return wheels[0]


def _fresh_venv(work: Path, wheel: Path) -> tuple[Path, Path]:
    """A venv holding the wheel only, its dependencies reached through a .pth file;
    returns (its bin folder, its site-packages)."""
    venv = work / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps",
                    "--no-index", str(wheel)], check=True, timeout=300)  # fmt: skip
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())  # fmt: skip
    # Only the folders: the test environment's own .pth files (its editable install of
    # this checkout among them) are not read from a folder named in a .pth file.
    deps = dict.fromkeys(sysconfig.get_paths()[k] for k in ("purelib", "platlib"))
    (site / "test_environment_dependencies.pth").write_text("\n".join(deps) + "\n")
    return venv / "bin", site


def _seed_numba_cache(site: Path) -> int:
    """Copy the checkout's numba cache beside the installed modules, with the installed
    sources given their checkout timestamps (numba checks them); returns the files copied."""
    copied = 0
    installed = site / "orbslam_hgcn"
    for cache in PACKAGE.rglob("__pycache__"):
        files = [p for p in cache.iterdir() if p.suffix in (".nbi", ".nbc")]
        if not files:
            continue
        rel = cache.parent.relative_to(PACKAGE)
        for source in cache.parent.glob("*.py"):
            target = installed / rel / source.name
            if target.is_file() and target.read_bytes() == source.read_bytes():
                st = source.stat()
                os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))
        (installed / rel / "__pycache__").mkdir(exist_ok=True)
        for f in files:
            shutil.copy2(f, installed / rel / "__pycache__" / f.name)
            copied += 1
    return copied


@pytest.mark.slow
def test_the_wheel_installs_and_runs_with_a_shipped_camera(synth_replay_100, tmp_path):
    wheel = _build_wheel(tmp_path)
    names = zipfile.ZipFile(wheel).namelist()
    for shipped in ("orbslam_hgcn/configs/tum_fr3.yaml", "orbslam_hgcn/data/vocab_orb_default.npz",
                    "orbslam_hgcn/data/vocab_hgcn_default.npz", "orbslam_hgcn/synth/sequence.py"):  # fmt: skip
        assert shipped in names
    assert not [n for n in names if n.startswith(("tests/", "bench/")) or "__pycache__" in n]
    bin_dir, site = _fresh_venv(tmp_path, wheel)
    _seed_numba_cache(site)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    work = tmp_path / "elsewhere"  # not the checkout: nothing resolves to its sources
    work.mkdir()
    where = subprocess.run([str(bin_dir / "python"), "-c", "import orbslam_hgcn; print(orbslam_hgcn.__file__)"],
                           check=True, capture_output=True, text=True, cwd=work, env=env).stdout  # fmt: skip
    assert Path(where.strip()).is_relative_to(site)
    cli = str(bin_dir / "orbslam-hgcn")
    synth = subprocess.run([cli, "synth", "--out", "s", "--frames", "2", "--texel-scale", "8"], cwd=work, env=env,
                           capture_output=True, text=True, timeout=300)  # fmt: skip
    assert synth.returncode == 0, synth.stderr
    # The frames as a plain image folder: the camera can only come from --config.
    run = subprocess.run([cli, "run", str(synth_replay_100 / "rgb"), "--dataset", "folder", "--config", "tum_fr3",
                          "--out", "out", "--vocab", "orb", "--no-loop", "--max-frames", "40", "--no-progress"],
                         cwd=work, env=env, capture_output=True, text=True, timeout=600)  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr
    stats = json.loads((work / "out" / "stats.json").read_text())
    assert Path(stats["settings"]["config"]).is_relative_to(site / "orbslam_hgcn" / "configs")
    assert stats["complete"] is True and stats["frames"]["frames"] == 40 and stats["frames"]["tracked"] > 0


# Third-party modules the package imports only behind a guard, from its optional extras.
OPTIONAL_MODULES = {"ray": "cluster", "pyorbslam3": "peer"}


def _imported_modules() -> set[str]:
    """Top-level names of the third-party modules the package's sources import."""
    import ast

    names: set[str] = set()
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n not in ("orbslam_hgcn", "__future__")}


def _canonical(name: str) -> str:
    import re

    return re.sub(r"[-_.]+", "-", name).lower()


@pytest.mark.slow
def test_the_wheels_declared_dependencies_resolve_and_cover_its_imports(tmp_path):
    import tomllib

    from packaging.requirements import Requirement

    wheel = _build_wheel(tmp_path)
    declared = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]["dependencies"]
    venv = tmp_path / "resolve"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    pins = tmp_path / "pins.txt"
    pins.write_text("torch==2.13.0\n")
    report = tmp_path / "report.json"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    res = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", "--dry-run", "--ignore-installed",
                          "--report", str(report), "-c", str(pins), str(wheel)],
                         capture_output=True, text=True, timeout=900, env=env)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    install = {_canonical(i["metadata"]["name"]): i["metadata"] for i in json.loads(report.read_text())["install"]}
    # The wheel carries pyproject's dependencies, and each resolves to a version that satisfies it.
    own = [Requirement(r) for r in install["orbslam-hgcn"]["requires_dist"] if "extra ==" not in r]
    assert sorted(str(r) for r in own) == sorted(str(Requirement(d)) for d in declared)
    for req in own:
        got = install[_canonical(req.name)]["version"]
        assert req.specifier.contains(got, prereleases=True), (req, got)
    assert install["torch"]["version"].startswith("2.13.0")
    assert not [n for n in install if n.startswith("nvidia-")]  # the CPU build of torch
    # Every module the sources import comes from a declared dependency (or an optional extra).
    dists = importlib.metadata.packages_distributions()
    missing = {}
    for module in sorted(_imported_modules()):
        if module in OPTIONAL_MODULES:
            continue
        owners = {_canonical(d) for d in dists.get(module, [])}
        if not owners & set(install):
            missing[module] = sorted(owners) or "no installed distribution"
    assert not missing, f"imported but not declared in pyproject's dependencies: {missing}"
