"""Vectorised pinhole reprojection errors (numpy): the outlier test shared by the pose-only
optimiser and bundle adjustment.
"""

from __future__ import annotations

import numpy as np


def reprojection_chi2(
    T_cw: np.ndarray, points_w: np.ndarray, uv: np.ndarray, inv_sigma2: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Whitened squared reprojection errors and depths.

    T_cw: (4, 4) one pose, or (M, 4, 4) one per observation; points_w (M, 3);
    uv (M, 2) undistorted observations; inv_sigma2 (M,); K (3, 3).
    Returns ((M,) chi2 = inv_sigma2 * |uv - project(T_cw X)|^2, (M,) depth in the camera).
    Points at depth <= 0 get chi2 = inf.
    """
    T_cw = np.asarray(T_cw, dtype=np.float64)
    X = np.asarray(points_w, dtype=np.float64)
    if T_cw.ndim == 2:
        Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    else:
        Xc = np.einsum("mij,mj->mi", T_cw[:, :3, :3], X) + T_cw[:, :3, 3]
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = 1.0 / z
        du = uv[:, 0] - (K[0, 0] * Xc[:, 0] * inv_z + K[0, 2])
        dv = uv[:, 1] - (K[1, 1] * Xc[:, 1] * inv_z + K[1, 2])
        chi2 = inv_sigma2 * (du * du + dv * dv)
    chi2 = np.where(z > 0, chi2, np.inf)
    return chi2, z
