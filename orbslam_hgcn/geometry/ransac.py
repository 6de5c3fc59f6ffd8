"""The RANSAC iteration count shared by the solvers (Fischler & Bolles, CACM 1981)."""

from __future__ import annotations

import math


def ransac_iterations(probability: float, inlier_ratio: float, sample_size: int, max_iterations: int) -> int:
    """Iterations needed to draw one all-inlier sample with the given probability.

    ``log(1 - p) / log(1 - w**k)`` capped to [1, max_iterations]; max_iterations when the
    inlier ratio w is too small for the formula.
    """
    if inlier_ratio >= 1.0:
        return 1
    miss = math.log1p(-(inlier_ratio**sample_size)) if inlier_ratio > 0 else 0.0
    if miss == 0.0:
        return max_iterations
    return max(1, min(max_iterations, int(math.ceil(math.log(1.0 - probability) / miss))))
