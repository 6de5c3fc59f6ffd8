"""Synthetic bundle-adjustment and pose-graph problems with known ground truth.

Used by the backend tests and benchmarks: cameras along a gently curving path looking at a
box of points, observations with octave-dependent pixel noise (sigma = 1.2 ** octave, the
ORB pyramid's scale), and drifted Sim(3) chains around a loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from orbslam_hgcn.geometry.se3 import inv_T, make_T

SCALE_FACTOR = 1.2
N_LEVELS = 8


@dataclass(frozen=True)
class SyntheticScene:
    """Ground truth and observations: T_cw (K, 4, 4), points (P, 3), obs_kf/obs_pt (O,),
    uv (O, 2) noisy undistorted pixels, octave (O,), inv_sigma2 (O,), K (3, 3)."""

    T_cw: np.ndarray
    points: np.ndarray
    obs_kf: np.ndarray
    obs_pt: np.ndarray
    uv: np.ndarray
    octave: np.ndarray
    inv_sigma2: np.ndarray
    K: np.ndarray


def default_K() -> np.ndarray:
    return np.array([[520.0, 0.0, 320.0], [0.0, 520.0, 240.0], [0.0, 0.0, 1.0]])


def perturb_pose(T_cw: np.ndarray, rot_deg: float, trans: float, rng: np.random.Generator) -> np.ndarray:
    """Left-multiply a random rotation of ``rot_deg`` degrees and a translation of norm ``trans``."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    d = rng.normal(size=3)
    d *= trans / np.linalg.norm(d)
    return make_T(Rotation.from_rotvec(np.radians(rot_deg) * axis).as_matrix(), d) @ T_cw


def make_scene(
    n_kf: int, n_points: int, obs_prob: float, rng: np.random.Generator, K: np.ndarray | None = None,
    pixel_noise: float = 1.0,
) -> SyntheticScene:  # fmt: skip
    """Cameras 0.3 apart on a line x in world, yawing slightly, seeing points in a box 4-8 m
    ahead; each visible point is observed with probability ``obs_prob`` (at least twice).
    Pixel noise has sigma ``pixel_noise`` * 1.2 ** octave."""
    K = default_K() if K is None else K
    T_wc = []
    for i in range(n_kf):
        yaw = np.radians(2.0 * (i - n_kf / 2))
        R_wc = Rotation.from_euler("y", yaw).as_matrix()
        T_wc.append(make_T(R_wc, [0.3 * i - 0.15 * n_kf, 0.05 * np.sin(i), 0.0]))
    T_cw = inv_T(np.stack(T_wc))
    half = 0.15 * n_kf + 2.0
    P = np.column_stack(
        [rng.uniform(-half, half, n_points), rng.uniform(-1.5, 1.5, n_points), rng.uniform(4.0, 8.0, n_points)]
    )
    o_kf, o_pt, uv, octv = [], [], [], []
    level_p = SCALE_FACTOR ** -np.arange(N_LEVELS, dtype=float)
    level_p /= level_p.sum()
    for i in range(n_kf):
        Xc = P @ T_cw[i, :3, :3].T + T_cw[i, :3, 3]
        u = K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2]
        v = K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]
        vis = (Xc[:, 2] > 0.1) & (u >= 0) & (u < 2 * K[0, 2]) & (v >= 0) & (v < 2 * K[1, 2])
        take = np.flatnonzero(vis & (rng.random(n_points) < obs_prob))
        lv = rng.choice(N_LEVELS, size=len(take), p=level_p)
        sigma = pixel_noise * SCALE_FACTOR**lv
        o_kf.append(np.full(len(take), i))
        o_pt.append(take)
        uv.append(np.column_stack([u[take], v[take]]) + rng.normal(size=(len(take), 2)) * sigma[:, None])
        octv.append(lv)
    o_kf_a, o_pt_a = np.concatenate(o_kf), np.concatenate(o_pt)
    counts = np.bincount(o_pt_a, minlength=n_points)
    keep_pt = np.flatnonzero(counts >= 2)
    remap = -np.ones(n_points, dtype=np.int64)
    remap[keep_pt] = np.arange(len(keep_pt))
    keep = counts[o_pt_a] >= 2
    octave = np.concatenate(octv)[keep]
    return SyntheticScene(
        T_cw=T_cw,
        points=P[keep_pt],
        obs_kf=o_kf_a[keep].astype(np.int64),
        obs_pt=remap[o_pt_a[keep]],
        uv=np.concatenate(uv)[keep],
        octave=octave.astype(np.int64),
        inv_sigma2=SCALE_FACTOR ** (-2.0 * octave),
        K=K,
    )


def drifted_loop(
    n: int, rng: np.random.Generator, rot_drift_deg: float = 0.3, trans_drift: float = 0.01,
    scale_drift: float = 0.005, noise: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Poses on a circle of radius 5 and their drifted odometry chain.

    Returns (S_cw_true (n, 4, 4), S_cw_drift (n, 4, 4) chained from drifted relative
    motions, edges (n - 1, 2) consecutive pairs, S_ji (n - 1, 4, 4) the drifted relative
    measurements). Each relative motion picks up a rotation of ``rot_drift_deg`` about a fixed
    axis, ``trans_drift`` of translation and a scale factor 1 + ``scale_drift`` (plus
    Gaussian ``noise`` on each), as monocular visual odometry drifts.
    """
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    T_wc = []
    for a in ang:
        R = Rotation.from_euler("y", -a).as_matrix()
        T_wc.append(make_T(R, [5 * np.cos(a), 0.2 * np.sin(3 * a), 5 * np.sin(a)]))
    S_cw_true = inv_T(np.stack(T_wc))
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    edges = np.column_stack([np.arange(n - 1), np.arange(1, n)])
    S_ji = np.zeros((n - 1, 4, 4))
    S_drift = [S_cw_true[0]]
    for k, (i, j) in enumerate(edges):
        rel = S_cw_true[j] @ inv_T(S_cw_true[i])
        rv = np.radians(rot_drift_deg) * axis + noise * rng.normal(size=3) * 0.01
        D = np.eye(4)
        s = 1.0 + scale_drift + noise * 0.001 * rng.normal()
        D[:3, :3] = s * Rotation.from_rotvec(rv).as_matrix()
        D[:3, 3] = trans_drift * np.array([1.0, 0.5, -0.3]) + noise * 0.01 * rng.normal(size=3)
        S_ji[k] = D @ rel
        S_drift.append(S_ji[k] @ S_drift[-1])
    return S_cw_true, np.stack(S_drift), edges, S_ji
