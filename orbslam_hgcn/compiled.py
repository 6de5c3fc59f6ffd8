"""The numba settings of every compiled kernel: the :data:`jit` decorator.

A leaf module: it imports numpy, numba (when the kernels are not built ahead of time) and
:mod:`orbslam_hgcn.aot`, and the kernel modules import it. The kernels are compiled without
the GIL, so other threads run meanwhile, and cached on disk beside their modules (or in
numba's user cache when the package folder is read-only).

Two steps of tracking run on every frame over a few hundred points, where numpy's
per-call overhead on small arrays outweighs the arithmetic: the pose-only optimisation
(:mod:`orbslam_hgcn.backend.pose_only`) and the window search of projected points
(:mod:`orbslam_hgcn.match.projection_search`). Local mapping's triangulation search and
checks (:mod:`orbslam_hgcn.match.matching`, :mod:`orbslam_hgcn.geometry.triangulation`),
the refresh of map points' viewing ranges and descriptors (:mod:`orbslam_hgcn.map.mappoint`)
and local BA (:mod:`orbslam_hgcn.backend.schur_ba`) are compiled too, as are ORB
extraction's FAST detection, quadtree and descriptor loops
(:mod:`orbslam_hgcn.features.fast`, :mod:`~orbslam_hgcn.features.distribute`,
:mod:`~orbslam_hgcn.features.rbrief`), the HGCN vocabulary's run-time layers
(:mod:`orbslam_hgcn.vocabulary.ball`, warmed when a vocabulary with a network is built)
and the row filters of the dataset readers' PNG decoder (:mod:`orbslam_hgcn.datasets.png`).

The first run after an install compiles them (7-10 s for the tracking kernels and about
10 s for FAST and the quadtree on a 2-core machine); later runs load them from the cache
(about 0.5 s). Each kernel module warms itself: its ``warm_up()`` runs its kernels once on
a tiny problem with the argument types of a real run. The system calls them before the
first frame (:func:`orbslam_hgcn.runtime.system.warm_up_kernels`; local BA's in the
solver that runs it, extraction's in the extractor or its process), so that the time is
not spent inside a frame.

``tools/setup.sh`` builds them ahead of time as well (:mod:`orbslam_hgcn.aot`): while that
build matches the sources and the machine, :func:`jit` gives each kernel its built versions
and numba is not imported at all, unless a kernel is called with arguments of a type it was
not built for.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from orbslam_hgcn import aot

# The kernels built ahead of time (None: numba compiles them, or loads them from its cache).
BUILT = aot.load()


def jit(func: Callable[..., Any] | None = None, **options: Any) -> Any:
    """Compile ``func`` as a kernel: ``numba.njit(cache=True, nogil=True, **options)``, or
    its versions built ahead of time (:data:`BUILT`). ``@jit`` or ``@jit(fastmath=...)``."""

    def wrap(f: Callable[..., Any]) -> Any:
        if BUILT is not None:
            return aot.Kernel(f, options, BUILT.exports(f"{f.__module__}.{f.__qualname__}"))
        return aot.numba_kernel(f, options)

    return wrap if func is None else wrap(func)


@jit
def popcount64(x):
    """Set bits of one uint64 (the SWAR popcount); Hamming distances of ORB descriptors
    are sums of it over their four 64-bit words."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return int((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


def descriptor_words(desc: np.ndarray) -> np.ndarray:
    """(N, ceil(B / 8)) uint64 view of (N, B) uint8 packed-bit descriptors, zero-padded to
    8 bytes ((N, 4) for ORB's 32 bytes, a view without a copy): the input of
    :func:`popcount64` and of the vocabularies' Hamming distances."""
    desc = np.ascontiguousarray(desc, dtype=np.uint8)
    pad = (-desc.shape[1]) % 8
    if pad:
        desc = np.concatenate([desc, np.zeros((len(desc), pad), np.uint8)], axis=1)
    return desc.view(np.uint64)
