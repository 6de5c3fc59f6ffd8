"""The compiled per-frame kernels: their numba settings and their warm-up.

Two steps of tracking run on every frame over a few hundred points, where numpy's
per-call overhead on small arrays outweighs the arithmetic: the pose-only optimisation
(:mod:`orbslam_hgcn.backend.pose_only`) and the window search of projected points
(:mod:`orbslam_hgcn.match.projection_search`). Local mapping's triangulation search
(:mod:`orbslam_hgcn.match.matching`) is warmed with them; local BA's kernels
(:mod:`orbslam_hgcn.backend.schur_ba`) are warmed by the solver that runs them. They are compiled with numba
(:data:`jit`): without the GIL, so other threads run meanwhile, and cached on disk beside
their modules (or in numba's user cache when the package folder is read-only). ORB
extraction's FAST detection (:mod:`orbslam_hgcn.features.fast`), quadtree
(:mod:`orbslam_hgcn.features.distribute`) and orientation and descriptor loops
(:mod:`orbslam_hgcn.features.rbrief`) use the same settings; they are
loaded by an extractor's first extraction (the descriptor loops when it is built) and, in
the extraction process, by one extraction before the first frame.

The first run after an install compiles them (7-10 s for the tracking kernels and about
10 s for FAST and the quadtree on a 2-core machine); later runs load them from the cache
(about 0.5 s). :func:`warm_up` does either for the tracking kernels before the first
frame, so that the time is not spent inside a frame's tracking.
"""

from __future__ import annotations

import logging
import time

import numba
import numpy as np

log = logging.getLogger(__name__)

jit = numba.njit(cache=True, nogil=True)


def warm_up() -> float:
    """Compile (or load from the cache) every kernel by running it on a tiny problem with
    the argument types of a real run. Returns the seconds it took."""
    from orbslam_hgcn.backend.pose_only import optimize_pose
    from orbslam_hgcn.features.keypoints import KeypointSet
    from orbslam_hgcn.geometry.camera import PinholeCamera
    from orbslam_hgcn.match.grid import FeatureGrid
    from orbslam_hgcn.match.matching import search_for_triangulation
    from orbslam_hgcn.match.projection_search import fuse_candidates, search_by_projection

    t0 = time.perf_counter()
    camera = PinholeCamera(100.0, 100.0, 50.0, 50.0, 100, 100)
    uv = np.array([[20.0, 30.0], [60.0, 40.0], [45.0, 70.0], [75.0, 75.0]])
    X = np.column_stack([(uv - 50.0) / 100.0 * 2.0, np.full(len(uv), 2.0)])
    optimize_pose(np.eye(4), X, uv, np.ones(len(uv)), camera.K)
    n = len(uv)
    kps = KeypointSet(
        uv_raw=uv.astype(np.float32), uv=uv, octave=np.zeros(n, np.int32), angle=np.zeros(n, np.float32),
        response=np.ones(n, np.float32), desc=np.zeros((n, 32), np.uint8), scale_factors=np.array([1.0, 1.2]),
    )  # fmt: skip
    grid = FeatureGrid(kps, camera)
    search_by_projection(kps, grid, uv, kps.octave, kps.desc, 2.0, ratio=0.8, available=np.ones(n, bool))
    fuse_candidates(
        kps, grid, camera, np.eye(4), X, kps.desc, X / np.linalg.norm(X, axis=1, keepdims=True),
        np.zeros(n), np.full(n, 10.0),
    )  # fmt: skip
    pairs = (np.arange(n, dtype=np.int64), np.arange(n, dtype=np.int64))
    search_for_triangulation(kps, kps, np.eye(3), np.array([500.0, 500.0]), pairs)
    seconds = time.perf_counter() - t0
    if seconds > 2.0:
        log.info("compiled the tracking kernels in %.1f s (cached for later runs)", seconds)
    return seconds
