"""The compiled (numba) kernels of a run: whether they are in numba's cache, and warming
them all at once.

The first run after an install compiles them (40 to 60 s on a 2-core machine: tracking
and local mapping's kernels, local BA's, ORB extraction's); later runs load them from the
cache in about a second (see :mod:`orbslam_hgcn.compiled`). A run says so before it
compiles (:func:`announce_compile`). ``python -m orbslam_hgcn.runtime.kernels`` (run by
``tools/setup.sh``) builds them ahead of time (:mod:`orbslam_hgcn.aot`; runs then load
them without numba), or, where that build fails, compiles every one that is not in numba's
cache; it returns at once when the build is up to date.
"""

from __future__ import annotations

import importlib
import logging
import sys
import time

log = logging.getLogger(__name__)

# The modules whose kernels a run compiles: tracking and local mapping's (warm_up_kernels),
# local BA's (in the solver), ORB extraction's (in the extractor or its process), and the
# vocabularies' word search and HGCN layers (when the vocabulary is loaded and first used).
RUN_KERNEL_MODULES = (
    "orbslam_hgcn.backend.pose_only",
    "orbslam_hgcn.match.projection_search",
    "orbslam_hgcn.match.matching",
    "orbslam_hgcn.geometry.triangulation",
    "orbslam_hgcn.map.mappoint",
    "orbslam_hgcn.map.database",
    "orbslam_hgcn.datasets.png",
    "orbslam_hgcn.backend.schur_ba",
    "orbslam_hgcn.features.fast",
    "orbslam_hgcn.features.distribute",
    "orbslam_hgcn.features.rbrief",
    "orbslam_hgcn.vocabulary.probe",
    "orbslam_hgcn.vocabulary.graph",
    "orbslam_hgcn.vocabulary.ball",
)
FIRST_COMPILE_S = "40 to 60"  # seconds, on a 2-core machine


def _cached(dispatcher) -> bool:
    """Whether numba's cache holds a compiled version of ``dispatcher`` for its source as
    it is now (numba's own index check; True when that cannot be told)."""
    cache = getattr(dispatcher, "_cache", None)
    cache_file = getattr(cache, "_cache_file", None)
    if cache_file is None or not hasattr(cache_file, "_load_index"):
        return True
    try:
        return bool(cache_file._load_index())
    except Exception:  # noqa: BLE001 - an unreadable index: numba compiles again
        return False


def cold_modules(modules: tuple[str, ...] = RUN_KERNEL_MODULES) -> list[str]:
    """The modules of ``modules`` with a kernel that numba's cache does not hold (they are
    compiled on first use); cheap: reads the cache's index files. None while the kernels
    built ahead of time are in use (numba is not even imported then)."""
    from orbslam_hgcn import compiled

    if compiled.BUILT is not None:
        return []
    from numba.core.registry import CPUDispatcher

    cold = []
    for name in modules:
        module = importlib.import_module(name)
        kernels = [v for v in vars(module).values() if isinstance(v, CPUDispatcher) and v.__module__ == name]
        if not all(_cached(k) for k in kernels):
            cold.append(name)
    return cold


def announce_compile(modules: tuple[str, ...] = RUN_KERNEL_MODULES) -> list[str]:
    """Log, before compiling, that the kernels not in the cache are compiled now, once;
    returns those modules (none: nothing logged)."""
    cold = cold_modules(modules)
    if cold:
        log.info(
            "compiling the numba kernels of %d modules (%s): the first run after an install compiles them "
            "once, %s s in all on a 2-core machine; later runs load them from the cache in about a "
            "second (tools/setup.sh compiles them ahead)",
            len(cold), ", ".join(n.rsplit(".", 1)[-1] for n in cold), FIRST_COMPILE_S,
        )  # fmt: skip
    return cold


def warm_up_tracking() -> float:
    """Compile (first run after an install) or load from numba's cache the compiled kernels
    of tracking and local mapping (pose-only optimisation, projection search and fusion,
    triangulation search and checks, map point refresh), the keyframe database's query and
    the readers' PNG rows, each
    module warming its own; returns the seconds it took. When numba's cache lacks a run's
    kernels (these, local BA's, extraction's) it says first that they are compiled now, once."""
    from orbslam_hgcn.backend import pose_only
    from orbslam_hgcn.datasets import png
    from orbslam_hgcn.geometry import triangulation
    from orbslam_hgcn.map import database, mappoint
    from orbslam_hgcn.match import matching, projection_search

    announce_compile()
    t0 = time.perf_counter()
    for module in (pose_only, projection_search, matching, triangulation, mappoint, database, png):
        module.warm_up()
    seconds = time.perf_counter() - t0
    if seconds > 2.0:
        log.info("compiled the tracking kernels in %.1f s (cached for later runs)", seconds)
    return seconds


def warm_vocabularies() -> float:
    """Load every shipped vocabulary and give it descriptors to quantise, which compiles
    (or loads) the kernels of their word search and HGCN layers; returns the seconds."""
    import numpy as np

    from orbslam_hgcn.vocabulary.loading import SHIPPED, load_vocabulary

    t0 = time.perf_counter()
    desc = np.random.default_rng(0).integers(0, 256, (500, 32), dtype=np.uint8)
    loading = logging.getLogger("orbslam_hgcn.vocabulary.loading")
    level = loading.level
    loading.setLevel(logging.WARNING)  # not a line per vocabulary
    try:
        for name in SHIPPED:
            load_vocabulary(name).transform(desc)
    finally:
        loading.setLevel(level)
    return time.perf_counter() - t0


def warm_all() -> float:
    """Compile (or load) every kernel of a run: tracking and local mapping's, local BA's,
    ORB extraction's and the vocabularies'; returns the seconds it took."""
    from orbslam_hgcn.backend import schur_ba
    from orbslam_hgcn.features.orb import ORBExtractor
    from orbslam_hgcn.geometry.camera import PinholeCamera
    from orbslam_hgcn.runtime.extraction import warm_up_extractors

    t0 = time.perf_counter()
    warm_up_tracking()
    schur_ba.warm_up()
    camera = PinholeCamera(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
    warm_up_extractors([ORBExtractor()], camera)
    warm_vocabularies()
    return time.perf_counter() - t0


def build_ahead() -> bool:
    """Build every kernel ahead of time (:mod:`orbslam_hgcn.runtime.aot_build`, in a
    process of its own with numba compiling the originals); True when the build is in
    place and passed its check."""
    import os
    import subprocess

    from orbslam_hgcn import aot

    env = {**os.environ, aot.ENV_SWITCH: "0"}
    return subprocess.run([sys.executable, "-m", "orbslam_hgcn.runtime.aot_build"], env=env).returncode == 0


def main() -> int:
    """Build the kernels ahead of time when they are not (numba never loaded by a run);
    when that cannot be done, compile them into numba's cache (the first run then loads
    them from there)."""
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logging.getLogger("orbslam_hgcn").setLevel(logging.INFO)
    from orbslam_hgcn import aot, compiled

    if compiled.BUILT is not None:
        print(f"compiled kernels: built ahead of time in {compiled.BUILT.folder}, up to date")
        return 0
    if not aot.turned_off():
        print(f"building the compiled kernels ahead of time ({aot.status})", flush=True)
        if build_ahead():
            return 0
        print("runs will load the kernels from numba's cache instead (about 0.5 s more start-up)", flush=True)
    if not cold_modules():
        print("compiled kernels: all in numba's cache")
        return 0
    seconds = warm_all()
    print(f"compiled kernels: compiled in {seconds:.0f} s and cached for later runs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
