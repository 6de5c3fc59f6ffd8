"""Sim(3) pose-graph optimisation of the essential graph, with gtsam.

Follows ORB-SLAM's loop correction (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. VII-B;
Optimizer::OptimizeEssentialGraph in ORB-SLAM2): one Sim(3) per keyframe, one relative
Sim(3) constraint per essential-graph edge (identity information unless weighted), the loop
keyframe fixed, Levenberg-Marquardt for 20 iterations. Afterwards each keyframe pose becomes
the rigid part [R, t / s] of its corrected similarity, and each map point moves with its
reference keyframe's correction.

Conventions: ``S_cw`` is a similarity (4, 4) ``[[s R, t], [0, 1]]`` mapping world points
into the camera (x_c = s R x_w + t), as ORB-SLAM's g2o::Sim3. gtsam's Similarity3(R, t, s)
maps p to s (R p + t) and its matrix() is ``[[R, t], [0, 1/s]]``; :func:`to_gtsam` and
:func:`from_gtsam` convert. Variables hold S_wc (gtsam's pose convention), so the edge
between keyframes i and j measures S_ij = S_iw S_wj, which BetweenFactorSimilarity3(i, j)
compares with X_i^-1 X_j.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from orbslam_hgcn.config import BackendConfig
from orbslam_hgcn.geometry.se3 import inv_S

# gtsam is imported inside the functions that solve with it: a run that never does (no loop,
# local BA compiled) does not spend its start-up importing it.
if TYPE_CHECKING:
    import gtsam

log = logging.getLogger(__name__)


def to_gtsam(S: np.ndarray) -> gtsam.Similarity3:
    """gtsam Similarity3 of a (4, 4) ``[[s R, t], [0, 1]]`` (p -> s R p + t)."""
    import gtsam
    S = np.asarray(S, dtype=np.float64)
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    R = S[:3, :3] / s
    # Re-orthonormalise against round-off before handing it to Rot3.
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    return gtsam.Similarity3(gtsam.Rot3(R), S[:3, 3] / s, s)


def from_gtsam(g: gtsam.Similarity3) -> np.ndarray:
    """(4, 4) ``[[s R, t], [0, 1]]`` of a gtsam Similarity3 (inverse of :func:`to_gtsam`)."""
    M = g.matrix()
    return M / M[3, 3]


def sim3_scale(S: np.ndarray) -> float:
    """Scale s of a (4, 4) similarity ``[[s R, t], [0, 1]]``."""
    return float(np.cbrt(np.linalg.det(np.asarray(S)[:3, :3])))


def sim3_to_se3(S_cw: np.ndarray) -> np.ndarray:
    """Rigid pose(s) T_cw = [R, t / s] of similarity pose(s) (4, 4) or (K, 4, 4) (ORB-SLAM's
    conversion of corrected keyframe similarities)."""
    S = np.asarray(S_cw, dtype=np.float64)
    s = np.cbrt(np.linalg.det(S[..., :3, :3]))[..., None, None]
    T = S / s
    T[..., 3, :] = np.array([0.0, 0.0, 0.0, 1.0])
    return T


def relative_sim3(S_cw_i: np.ndarray, S_cw_j: np.ndarray) -> np.ndarray:
    """(4, 4) S_ji = S_jw S_iw^-1: the measurement of edge (i, j) from two poses."""
    return np.asarray(S_cw_j) @ inv_S(np.asarray(S_cw_i))


def optimize_essential_graph(
    S_cw: np.ndarray,
    edges: np.ndarray,
    S_ji: np.ndarray,
    fixed: np.ndarray | int,
    weights: np.ndarray | None = None,
    config: BackendConfig | None = None,
) -> np.ndarray:
    """Optimise keyframe similarities under relative Sim(3) constraints.

    S_cw: (K, 4, 4) initial world-to-camera similarities (rigid poses are similarities of
    scale 1; the loop closer passes the corrected ones around the loop).
    edges: (E, 2) int rows (i, j) into S_cw; S_ji: (E, 4, 4) measured S_jw S_iw^-1 of each
    edge (spanning tree, strong covisibility and loop edges alike; see
    :func:`relative_sim3`). fixed: index of the fixed keyframe, or (K,) bool mask.
    weights: (E,) information scale per edge (default 1: ORB-SLAM's identity information).
    Returns (K, 4, 4) optimised S_cw.
    """
    import gtsam
    cfg = config or BackendConfig()
    S_cw = np.asarray(S_cw, dtype=np.float64).reshape(-1, 4, 4)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    S_ji = np.asarray(S_ji, dtype=np.float64).reshape(-1, 4, 4)
    n = len(S_cw)
    if isinstance(fixed, (int, np.integer)):
        mask = np.zeros(n, dtype=bool)
        mask[int(fixed)] = True
    else:
        mask = np.asarray(fixed, dtype=bool).reshape(-1)
    if len(edges) != len(S_ji):
        raise ValueError("edges and S_ji must have the same length")
    w = np.ones(len(edges)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k in range(n):
        values.insert(k, to_gtsam(inv_S(S_cw[k])))
    tight = gtsam.noiseModel.Isotropic.Sigma(7, 1e-6)
    for k in np.flatnonzero(mask):
        graph.add(gtsam.PriorFactorSimilarity3(int(k), to_gtsam(inv_S(S_cw[k])), tight))
    models: dict[float, gtsam.noiseModel.Base] = {}
    for (i, j), S, wk in zip(edges, S_ji, w):
        if wk not in models:
            models[wk] = gtsam.noiseModel.Isotropic.Sigma(7, 1.0 / np.sqrt(wk))
        # X_i^-1 X_j = S_iw S_wj = (S_ji)^-1
        graph.add(gtsam.BetweenFactorSimilarity3(int(i), int(j), to_gtsam(inv_S(S)), models[wk]))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.pose_graph_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    out = np.stack([inv_S(from_gtsam(result.atSimilarity3(k))) for k in range(n)])
    out[mask] = S_cw[mask]
    return out


def correct_points(
    points_w: np.ndarray, ref_index: np.ndarray, T_cw_before: np.ndarray, S_cw_after: np.ndarray
) -> np.ndarray:
    """Move each point with its reference keyframe's correction.

    points_w: (P, 3); ref_index: (P,) row of each point's reference keyframe;
    T_cw_before: (K, 4, 4) poses (or similarities) before the optimisation; S_cw_after:
    (K, 4, 4) optimised similarities. Returns (P, 3) S_wc_after (T_cw_before x), as ORB-SLAM:
    the point keeps its place in the reference camera, which moves.
    """
    X = np.asarray(points_w, dtype=np.float64).reshape(-1, 3)
    ref = np.asarray(ref_index, dtype=np.int64).reshape(-1)
    before = np.asarray(T_cw_before, dtype=np.float64)
    after_inv = np.stack([inv_S(S) for S in np.asarray(S_cw_after, dtype=np.float64)])
    C = np.einsum("kij,kjl->kil", after_inv, before)  # (K, 4, 4) per-keyframe correction
    Cr = C[ref]
    return np.einsum("pij,pj->pi", Cr[:, :3, :3], X) + Cr[:, :3, 3]
