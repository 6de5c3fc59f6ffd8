"""Memory estimates of the loop-closure detectors, checked before they allocate.

The big allocations of the detectors are the (n, n) matrices over the n test images (BoW
similarities, FAB-MAP posteriors, the metrics) and FAB-MAP's per-word tables. The Chow-Liu
tree computes its mutual information one row at a time, so it needs O(V_occ) over the V_occ
words that vary across the training images beside copies of the sparse training occurrences
(O(nnz), at most images x V_occ). :func:`check_memory` compares an estimate
with the memory available (``MemAvailable`` of ``/proc/meminfo``, else ``os.sysconf``), or
with the limit in megabytes given by the environment variable ``ORBSLAM_HGCN_MEMORY_LIMIT_MB``
or by the caller, and stops with an :class:`OrbslamError` before anything is allocated.
"""

from __future__ import annotations

import os

from orbslam_hgcn.errors import OrbslamError

LIMIT_ENV = "ORBSLAM_HGCN_MEMORY_LIMIT_MB"

# The Chow-Liu tree: per varying word, the counts, one mutual-information row and its
# temporaries, Prim's best/best_from/parent/in_tree arrays and the root search's entropy order;
# per stored occurrence, the CSR and CSC copies of the training matrix and one row's
# co-occurrence lists (at most every occurrence).
_CHOW_LIU_BYTES_PER_WORD = 160
_CHOW_LIU_BYTES_PER_ENTRY = 64
_FABMAP_BYTES_PER_WORD = 600  # FabMap2's (V, 2, 2, k) tables, d1..d4, parents, scratch
_NN_ARRAYS = 6  # (n, n) float64 matrices alive at once (scores, log scores, masks, metrics)


def chow_liu_bytes(v_occ: int, nnz: int) -> int:
    """Bytes the Chow-Liu tree over ``v_occ`` varying words, with ``nnz`` occurrences of
    them in the training images, needs at its peak."""
    return _CHOW_LIU_BYTES_PER_WORD * v_occ + _CHOW_LIU_BYTES_PER_ENTRY * nnz


def fabmap_bytes(v_occ: int, nnz: int, n_words: int, n_test: int) -> int:
    """Bytes of FAB-MAP 2.0 (tree learning, tables, confusion matrices) at its peak."""
    return chow_liu_bytes(v_occ, nnz) + _FABMAP_BYTES_PER_WORD * n_words + _NN_ARRAYS * 8 * n_test * n_test


def bow_bytes(n_test: int) -> int:
    """Bytes of the BoW detector: its (n, n) similarity matrix and the metrics' copies."""
    return _NN_ARRAYS * 8 * n_test * n_test


def available_bytes(limit_mb: float | None = None) -> int | None:
    """Memory the process may use: ``limit_mb`` if given, else ``$ORBSLAM_HGCN_MEMORY_LIMIT_MB``,
    else ``MemAvailable`` of ``/proc/meminfo``, else the free pages of ``os.sysconf``; None
    when none of them is known."""
    if limit_mb is None:
        env = os.environ.get(LIMIT_ENV, "").strip()
        if env:
            try:
                limit_mb = float(env)
            except ValueError:
                raise OrbslamError(f"{LIMIT_ENV}={env!r}: not a number of megabytes") from None
    if limit_mb is not None:
        return int(limit_mb * 2**20)
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (OSError, ValueError, AttributeError):
        return None


def format_bytes(n: float) -> str:
    if n >= 2**30:
        return f"{n / 2**30:.1f} GiB"
    return f"{n / 2**20:.0f} MiB"


def check_memory(needed: int, what: str, way_out: str, *, limit_mb: float | None = None) -> None:
    """An OrbslamError when ``needed`` bytes exceed the memory available (see
    :func:`available_bytes`); the message names both and ``way_out``."""
    avail = available_bytes(limit_mb)
    if avail is not None and needed > avail:
        raise OrbslamError(
            f"{what} needs about {format_bytes(needed)} of memory but {format_bytes(avail)} is available; {way_out}"
        )
