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

from orbslam_hgcn.memory import LIMIT_ENV, available_bytes, check_memory, format_bytes

__all__ = ["LIMIT_ENV", "available_bytes", "bow_bytes", "check_memory", "chow_liu_bytes", "fabmap_bytes",
           "format_bytes"]

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
