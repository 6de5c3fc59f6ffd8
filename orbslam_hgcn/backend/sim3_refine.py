"""Refinement of the similarity between two keyframes from their matched points, with gtsam.

ORB-SLAM's Optimizer::OptimizeSim3 (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. VII-B):
one Sim(3) variable S_12 (camera 2 -> camera 1); the matched points stay fixed in their own
camera frames; each match contributes two reprojection errors, point 2 mapped by S_12 into
keyframe 1 and point 1 mapped by S_12^-1 into keyframe 2, whitened by their keypoints'
level, with a Huber kernel of delta sqrt(chi2). Five LM iterations, then the matches whose
error exceeds chi2 in either keyframe are dropped and 10 more iterations run (5 when none
was dropped); the matches within the gate in both keyframes are the inliers.

gtsam has no factor projecting a point through a Similarity3, so all errors live in one
:class:`gtsam.CustomFactor` with analytic, vectorised Jacobians; each error is whitened by
its keypoint's level and Huber-weighted on its own, exactly as gtsam's robust noise models
whiten a system (error scaled to the Huber cost, Jacobian by the IRLS weight). The variable
holds S_12 as gtsam's ``Similarity3`` (``p -> s (R p + t)``); gtsam retracts on the right,
``X Exp(xi)`` with ``xi = (omega, u, lambda)`` and ``Exp(xi) p ~ p + omega x p + u +
lambda p`` to first order, which gives the Jacobians.

One addition to ORB-SLAM's problem: a weak prior (sigma 0.05 in log scale by default) on
the scale at the closed-form estimate. Reprojection errors hardly constrain the scale when
the two keyframes see the place from nearby (scaling S_12 about camera 1 leaves every
projection into keyframe 1 unchanged, and with a short baseline nearly every projection
into keyframe 2), and LM then follows the noise far along that direction (measured on the
synthetic ring: scale 1.12 from Horn's 3D alignment, true 1.12, 0.19 after unconstrained
refinement). The 3D alignment does fix the scale, and the prior keeps it; with a wide
baseline the reprojection terms outweigh the prior.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from orbslam_hgcn.backend.pose_graph import from_gtsam, to_gtsam

# gtsam is imported inside the functions that solve with it: a run that never does (no loop,
# local BA compiled) does not spend its start-up importing it.
if TYPE_CHECKING:
    import gtsam

log = logging.getLogger(__name__)


class Sim3Refinement(NamedTuple):
    """S_12 (4, 4) ``[[s R, t], [0, 1]]``; inliers (M,) bool; n_inliers."""

    S_12: np.ndarray
    inliers: np.ndarray
    n_inliers: int


def _residuals(S: np.ndarray, X: np.ndarray, uv: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M, 2) errors uv - project(S X), (M, 3) mapped points, (M, 2, 3) projection Jacobians."""
    Y = X @ S[:3, :3].T + S[:3, 3]
    x, y, z = Y.T
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = 1.0 / z
        e = uv - np.stack([K[0, 0] * x * iz + K[0, 2], K[1, 1] * y * iz + K[1, 2]], axis=1)
        P = np.zeros((len(X), 2, 3))
        P[:, 0, 0] = K[0, 0] * iz
        P[:, 0, 2] = -K[0, 0] * x * iz * iz
        P[:, 1, 1] = K[1, 1] * iz
        P[:, 1, 2] = -K[1, 1] * y * iz * iz
    return e, Y, P


def sim3_errors(
    G: gtsam.Similarity3, X1: np.ndarray, X2: np.ndarray, uv1: np.ndarray, uv2: np.ndarray,
    K1: np.ndarray, K2: np.ndarray, fix_scale: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Errors and Jacobians of every match at the similarity G (gtsam's S_12).

    Returns ((M, 2) e12 = uv1 - project(S_12 X2), (M, 2, 7) its Jacobian, (M, 2) e21 =
    uv2 - project(S_12^-1 X1), (M, 2, 7) its Jacobian), Jacobians in gtsam's tangent space
    (omega, u, lambda) of right perturbations: ``d Exp(xi) p / d xi = [-[p]x, I, p]``.
    """
    S = from_gtsam(G)
    e12, _, P1 = _residuals(S, X2, uv1, K1)
    A = P1 @ (G.scale() * G.rotation().matrix())  # (M, 2, 3): d pixel / d (Exp(xi) X2)
    J12 = np.empty((len(X2), 2, 7))
    J12[:, :, :3] = np.cross(A, X2[:, None, :])  # -A (-[p]x); row a of A [p]x is a x p
    J12[:, :, 3:6] = -A
    J12[:, :, 6] = -np.einsum("mij,mj->mi", A, X2)
    e21, R2, P2 = _residuals(np.linalg.inv(S), X1, uv2, K2)
    J21 = np.empty((len(X1), 2, 7))
    J21[:, :, :3] = -np.cross(P2, R2[:, None, :])  # -P [r]x
    J21[:, :, 3:6] = P2
    J21[:, :, 6] = np.einsum("mij,mj->mi", P2, R2)
    if fix_scale:
        J12[:, :, 6] = 0.0
        J21[:, :, 6] = 0.0
    return e12, J12, e21, J21


def sim3_chi2(
    S_12: np.ndarray, X1: np.ndarray, X2: np.ndarray, uv1: np.ndarray, uv2: np.ndarray,
    info1: np.ndarray, info2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Whitened squared errors ((M,) in keyframe 1, (M,) in keyframe 2) of every match
    (inf where the mapped point lies behind the camera)."""
    S_12 = np.asarray(S_12, dtype=np.float64)
    out = []
    for S, X, uv, info, K in ((S_12, X2, uv1, info1, K1), (np.linalg.inv(S_12), X1, uv2, info2, K2)):
        e, Y, _ = _residuals(S, X, uv, K)
        chi2 = info * np.sum(e * e, axis=1)
        out.append(np.where(Y[:, 2] > 0, np.nan_to_num(chi2, nan=np.inf), np.inf))
    return out[0], out[1]


def _huber(r: np.ndarray, J: np.ndarray, delta: float) -> tuple[np.ndarray, np.ndarray]:
    """Whitened (M, 2) errors and (M, 2, 7) Jacobians scaled so that the squared norm of
    each error is the Huber cost rho(|r|^2) and the Jacobian carries the IRLS weight
    sqrt(w) (as gtsam's robust noise models whiten a system)."""
    s = np.sum(r * r, axis=1)
    norm = np.sqrt(s)
    big = norm > delta
    w = np.where(big, delta / np.maximum(norm, 1e-300), 1.0)
    rho = np.where(big, 2.0 * delta * norm - delta * delta, s)
    scale_e = np.sqrt(np.where(s > 0, rho / np.maximum(s, 1e-300), 1.0))
    return r * scale_e[:, None], J * np.sqrt(w)[:, None, None]


def _optimise(S0: np.ndarray, sel: np.ndarray, data: tuple, cfg: tuple) -> np.ndarray:
    """LM over the matches ``sel``: one vectorised CustomFactor holding every error (each
    whitened by its keypoint's level and Huber-weighted on its own), plus the scale prior."""
    import gtsam
    X1, X2, uv1, uv2, info1, info2 = (a[sel] for a in data[:6])
    K1, K2 = data[6:]
    chi2, iterations, fix_scale, scale_sigma = cfg
    delta = float(np.sqrt(chi2))
    w1, w2 = np.sqrt(info1)[:, None], np.sqrt(info2)[:, None]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        e12, J12, e21, J21 = sim3_errors(values.atSimilarity3(0), X1, X2, uv1, uv2, K1, K2, fix_scale)
        r1, Jr1 = _huber(w1 * e12, w1[:, :, None] * J12, delta)
        r2, Jr2 = _huber(w2 * e21, w2[:, :, None] * J21, delta)
        if H is not None:
            H[0] = np.concatenate([Jr1.reshape(-1, 7), Jr2.reshape(-1, 7)])
        return np.nan_to_num(np.concatenate([r1.reshape(-1), r2.reshape(-1)]), nan=1e6)

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    G0 = to_gtsam(S0)
    values.insert(0, G0)
    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(4 * len(X1)), [0], error))
    if scale_sigma > 0 and not fix_scale:
        sig = np.array([1e3] * 6 + [scale_sigma])
        graph.add(gtsam.PriorFactorSimilarity3(0, G0, gtsam.noiseModel.Diagonal.Sigmas(sig)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return from_gtsam(result.atSimilarity3(0))


def optimize_sim3(
    S_12: np.ndarray,
    X1: np.ndarray,
    X2: np.ndarray,
    uv1: np.ndarray,
    uv2: np.ndarray,
    info1: np.ndarray,
    info2: np.ndarray,
    K1: np.ndarray,
    K2: np.ndarray,
    *,
    chi2: float = 10.0,
    iterations: int = 5,
    more_iterations: int = 10,
    fix_scale: bool = False,
    scale_prior_sigma: float = 0.05,
    min_remaining: int = 10,
) -> Sim3Refinement:
    """Refine the similarity S_12 (camera 2 -> camera 1) from matched points.

    S_12: (4, 4) initial ``[[s R, t], [0, 1]]``; X1, X2: (M, 3) the matched points in
    camera-1 and camera-2 coordinates; uv1, uv2: (M, 2) their keypoints in each keyframe;
    info1, info2: (M,) information of those keypoints (1 / sigma^2 of their level);
    K1, K2: (3, 3). scale_prior_sigma: sigma of a prior on log(scale) at the initial (3D,
    closed-form) estimate; 0 for none (see the module docstring). Returns the refined
    similarity and the inliers (both whitened errors within ``chi2``); zero inliers when
    fewer than ``min_remaining`` matches survive the first outlier test (ORB-SLAM's rule).
    """
    data = tuple(np.asarray(a, dtype=np.float64) for a in (X1, X2, uv1, uv2, info1, info2, K1, K2))
    n = len(data[0])
    S = np.asarray(S_12, dtype=np.float64)
    if n == 0:
        return Sim3Refinement(S.copy(), np.zeros(0, dtype=bool), 0)
    S = _optimise(S, np.arange(n), data, (chi2, iterations, fix_scale, scale_prior_sigma))
    c1, c2 = sim3_chi2(S, *data)
    keep = (c1 <= chi2) & (c2 <= chi2)
    n_bad = int(n - keep.sum())
    if n - n_bad < min_remaining:
        return Sim3Refinement(S, np.zeros(n, dtype=bool), 0)
    more = more_iterations if n_bad else iterations
    S = _optimise(S, np.flatnonzero(keep), data, (chi2, more, fix_scale, scale_prior_sigma))
    c1, c2 = sim3_chi2(S, *data)
    inliers = keep & (c1 <= chi2) & (c2 <= chi2)
    return Sim3Refinement(S, inliers, int(inliers.sum()))
