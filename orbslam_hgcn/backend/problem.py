"""The arrays of one bundle adjustment and its result, shared by the gtsam solver
(:mod:`.bundle_adjustment`) and the compiled Schur-complement solver (:mod:`.schur_ba`),
which import them from here (numpy only, no gtsam).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class BAResult(NamedTuple):
    """T_cw (K, 4, 4) poses; points (P, 3); outlier (O,) bool per observation (chi2 above
    the threshold or behind the camera, evaluated at the returned estimates)."""

    T_cw: np.ndarray
    points: np.ndarray
    outlier: np.ndarray


class BAProblem(NamedTuple):
    """Input arrays of one bundle adjustment (see :func:`.bundle_adjustment.bundle_adjustment`)."""

    T_cw: np.ndarray
    fixed: np.ndarray
    points: np.ndarray
    obs_kf: np.ndarray
    obs_pt: np.ndarray
    uv: np.ndarray
    inv_sigma2: np.ndarray
    K: np.ndarray


def as_problem(T_cw, fixed, points, obs_kf, obs_pt, uv, inv_sigma2, K) -> BAProblem:
    """A :class:`BAProblem` of contiguous arrays with the dtypes the backend expects."""
    return BAProblem(
        np.ascontiguousarray(T_cw, dtype=np.float64).reshape(-1, 4, 4),
        np.ascontiguousarray(fixed, dtype=bool).reshape(-1),
        np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3),
        np.ascontiguousarray(obs_kf, dtype=np.int64).reshape(-1),
        np.ascontiguousarray(obs_pt, dtype=np.int64).reshape(-1),
        np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 2),
        np.ascontiguousarray(inv_sigma2, dtype=np.float64).reshape(-1),
        np.ascontiguousarray(K, dtype=np.float64).reshape(3, 3),
    )
