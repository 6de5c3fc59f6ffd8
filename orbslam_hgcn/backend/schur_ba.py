"""Bundle adjustment by Levenberg-Marquardt on the Schur complement, compiled with numba.

The same problem and scheme as :func:`orbslam_hgcn.backend.bundle_adjustment.bundle_adjustment`
(ORB-SLAM's local BA: Huber kernel of delta = sqrt(5.991) on the whitened error, robust
iterations, observations over the chi-square gate or behind their camera dropped, more
iterations without the kernel), solved the way g2o solves it for ORB-SLAM: every point
is eliminated first, which leaves the reduced camera system (Triggs et al., "Bundle
adjustment - a modern synthesis", 2000, Sec. 6.1)

    S = H_cc - sum_p H_cp H_pp^-1 H_pc,

a dense (6F, 6F) matrix over the F free keyframes, solved by Cholesky; the point steps
follow by back-substitution, one 3x3 system each. Steps are damped as in g2o's
Levenberg-Marquardt (lambda added to the diagonal, starting at 1e-5 times its largest
entry, Nielsen's update, up to 10 tries per iteration), poses move by a left
perturbation ``T_cw <- exp(xi) T_cw`` with xi = (omega, upsilon).

Why not gtsam here: on local-BA windows of real KITTI frames (41 keyframes, 28 free, 4,000
points, 25,000 observations) one gtsam LM iteration took about 100 ms, 119 ms of which
was the multifrontal elimination of the 4,000 point cliques (the linearisation took
18 ms; the sequential Cholesky solver was no faster, QR ten times slower), so local BA
alone took 0.65-0.75 s against ORB-SLAM's 0.30 s. Compiled, one iteration costs a few
milliseconds. gtsam stays the reference the result is checked against (tests), and the
solver of global BA, the pose graph and the two-view BA; ``BackendConfig.local_ba_solver``
chooses it for local BA too.

Each LM iteration is one compiled call without the GIL; the Python driver polls a stop
request and a deadline between iterations, as the gtsam driver does.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import numpy as np

from orbslam_hgcn.backend.pose_only import se3_compose, se3_exp
from orbslam_hgcn.backend.problem import BAResult, as_problem
from orbslam_hgcn.backend.projection import reprojection_chi2
from orbslam_hgcn.compiled import jit
from orbslam_hgcn.config import BackendConfig

log = logging.getLogger(__name__)

@jit
def _camera_point(T, X):
    """(x, y, z): point X (3,) in the camera of pose T (4, 4); a depth of exactly 0 is
    nudged to 1e-12 (points behind the camera keep their meaningless error, as in g2o)."""
    x = T[0, 0] * X[0] + T[0, 1] * X[1] + T[0, 2] * X[2] + T[0, 3]
    y = T[1, 0] * X[0] + T[1, 1] * X[1] + T[1, 2] * X[2] + T[1, 3]
    z = T[2, 0] * X[0] + T[2, 1] * X[1] + T[2, 2] * X[2] + T[2, 3]
    if z == 0.0:
        z = 1e-12
    return x, y, z


@jit
def _cost(T, X, obs_kf, obs_pt, uv, info, order, fx, fy, cx, cy, delta, robust):
    """Sum over the observations ``order`` of the (Huber-robust when ``robust``) whitened
    squared errors; Huber rho(s) = s - max(sqrt(s) - delta, 0) ** 2."""
    total = 0.0
    for o in order:
        x, y, z = _camera_point(T[obs_kf[o]], X[obs_pt[o]])
        eu = uv[o, 0] - (fx * x / z + cx)
        ev = uv[o, 1] - (fy * y / z + cy)
        s = info[o] * (eu * eu + ev * ev)
        if robust:
            d = math.sqrt(s) - delta
            if d > 0.0:
                s -= d * d
        total += s
    return total


@jit
def _linearise(T, X, obs_kf, obs_pt, uv, info, order, pt_start, cam_var, n_var, fx, fy, cx, cy, delta, robust):
    """Normal equations of the observations ``order`` (sorted by point, point p's in
    order[pt_start[p]:pt_start[p + 1]]): H_cc (6F, 6F) and g_c (6F,) of the free cameras,
    H_pp (P, 3, 3) and g_p (P, 3) of the points, W (O, 6, 3) = H_cp block of each
    observation (zero when its camera is fixed). J is d(error)/d(variable), so the
    Gauss-Newton step solves H dx = -g."""
    n_pt = len(pt_start) - 1
    Hcc = np.zeros((6 * n_var, 6 * n_var))
    gc = np.zeros(6 * n_var)
    Hpp = np.zeros((n_pt, 3, 3))
    gp = np.zeros((n_pt, 3))
    W = np.zeros((len(obs_kf), 6, 3))
    jc = np.empty((2, 6))
    jp = np.empty((2, 3))
    for p in range(n_pt):
        for k in range(pt_start[p], pt_start[p + 1]):
            o = order[k]
            i = obs_kf[o]
            Ti = T[i]
            x, y, z = _camera_point(Ti, X[p])
            iz = 1.0 / z
            xz, yz = x * iz, y * iz
            eu = uv[o, 0] - (fx * xz + cx)
            ev = uv[o, 1] - (fy * yz + cy)
            w = info[o]
            if robust:  # IRLS weight of the Huber kernel: 1 inside, delta / |e| outside
                w *= delta / max(math.sqrt(w * (eu * eu + ev * ev)), delta)
            # d(proj)/d(camera point): [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]];
            # the error is observed - projected, hence the signs.
            a0, a2 = -fx * iz, fx * xz * iz
            b1, b2 = -fy * iz, fy * yz * iz
            for c in range(3):  # d(error)/dX = -d(proj)/d(Xc) R
                jp[0, c] = a0 * Ti[0, c] + a2 * Ti[2, c]
                jp[1, c] = b1 * Ti[1, c] + b2 * Ti[2, c]
            for a in range(3):
                gp[p, a] += w * (jp[0, a] * eu + jp[1, a] * ev)
                for b in range(3):
                    Hpp[p, a, b] += w * (jp[0, a] * jp[0, b] + jp[1, a] * jp[1, b])
            ci = cam_var[i]
            if ci < 0:
                continue
            # d(Xc)/d(omega, upsilon) = [-[Xc]x, I] for T <- exp(xi) T.
            jc[0, 0], jc[0, 1], jc[0, 2] = fx * xz * yz, -(fx * xz * xz + fx), fx * yz
            jc[0, 3], jc[0, 4], jc[0, 5] = a0, 0.0, a2
            jc[1, 0], jc[1, 1], jc[1, 2] = fy * yz * yz + fy, -fy * yz * xz, -fy * xz
            jc[1, 3], jc[1, 4], jc[1, 5] = 0.0, b1, b2
            r0 = 6 * ci
            for a in range(6):
                gc[r0 + a] += w * (jc[0, a] * eu + jc[1, a] * ev)
                for b in range(a, 6):
                    Hcc[r0 + a, r0 + b] += w * (jc[0, a] * jc[0, b] + jc[1, a] * jc[1, b])
                for b in range(3):
                    W[o, a, b] = w * (jc[0, a] * jp[0, b] + jc[1, a] * jp[1, b])
    for r in range(6 * n_var):  # mirror the upper triangles of the diagonal blocks
        for c in range(r - r % 6, r):
            Hcc[r, c] = Hcc[c, r]
    return Hcc, gc, Hpp, gp, W


@jit
def _inv3(A: np.ndarray) -> tuple[np.ndarray, bool]:
    """Inverse of a (3, 3) symmetric matrix by cofactors; False when it is not positive definite."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    out = np.empty((3, 3))
    if not (det > 0.0 and A[0, 0] > 0.0 and c00 > 0.0):
        return out, False
    inv = 1.0 / det
    out[0, 0], out[1, 0], out[2, 0] = c00 * inv, c01 * inv, c02 * inv
    out[0, 1] = (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) * inv
    out[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) * inv
    out[2, 1] = (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) * inv
    out[0, 2] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) * inv
    out[1, 2] = (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) * inv
    out[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) * inv
    return out, True


@jit
def _cholesky_solve(S: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, bool]:
    """x with S x = r for a symmetric positive definite S (n, n), in place on a copy;
    False when a pivot is not positive."""
    n = len(r)
    L = S.copy()
    for j in range(n):
        s = L[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return r, False
        d = math.sqrt(s)
        L[j, j] = d
        inv = 1.0 / d
        for i in range(j + 1, n):
            s = L[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s * inv
    y = r.copy()
    for i in range(n):
        s = y[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= L[k, i] * y[k]
        y[i] = s / L[i, i]
    return y, True


@jit
def _damped_step(Hcc, gc, Hpp, gp, W, obs_kf, order, pt_start, cam_var, pt_var, lam):
    """The LM step (dc (6F,), dp (P, 3)) of the damped system by the Schur complement, and
    whether it could be solved. Points with pt_var False get no step."""
    n_pt = len(pt_start) - 1
    S = Hcc.copy()
    r = -gc.copy()
    for a in range(len(r)):
        S[a, a] += lam
    Hinv = np.zeros((n_pt, 3, 3))
    Y = np.empty((6, 3))
    for p in range(n_pt):
        if not pt_var[p]:
            continue
        A = Hpp[p].copy()
        for a in range(3):
            A[a, a] += lam
        Ai, ok = _inv3(A)
        if not ok:
            return r, np.zeros((n_pt, 3)), False
        Hinv[p] = Ai
        for k in range(pt_start[p], pt_start[p + 1]):
            o = order[k]
            ca = cam_var[obs_kf[o]]
            if ca < 0:
                continue
            for a in range(6):  # Y = W_o H_pp^-1
                for b in range(3):
                    Y[a, b] = W[o, a, 0] * Ai[0, b] + W[o, a, 1] * Ai[1, b] + W[o, a, 2] * Ai[2, b]
            for a in range(6):  # r_c -= Y (-g_p)
                r[6 * ca + a] += Y[a, 0] * gp[p, 0] + Y[a, 1] * gp[p, 1] + Y[a, 2] * gp[p, 2]
            for k2 in range(pt_start[p], pt_start[p + 1]):
                o2 = order[k2]
                cb = cam_var[obs_kf[o2]]
                if cb < ca:  # the lower triangle is mirrored below
                    continue
                for a in range(6):
                    for b in range(6):
                        S[6 * ca + a, 6 * cb + b] -= Y[a, 0] * W[o2, b, 0] + Y[a, 1] * W[o2, b, 1] + Y[a, 2] * W[o2, b, 2]
    n = len(r)
    for a in range(n):
        for b in range(a):
            S[a, b] = S[b, a]
    dc, ok = _cholesky_solve(S, r)
    dp = np.zeros((n_pt, 3))
    if not ok:
        return dc, dp, False
    for p in range(n_pt):
        if not pt_var[p]:
            continue
        rhs0, rhs1, rhs2 = -gp[p, 0], -gp[p, 1], -gp[p, 2]
        for k in range(pt_start[p], pt_start[p + 1]):
            o = order[k]
            ca = cam_var[obs_kf[o]]
            if ca < 0:
                continue
            for a in range(6):
                d = dc[6 * ca + a]
                rhs0 -= W[o, a, 0] * d
                rhs1 -= W[o, a, 1] * d
                rhs2 -= W[o, a, 2] * d
        for a in range(3):
            dp[p, a] = Hinv[p, a, 0] * rhs0 + Hinv[p, a, 1] * rhs1 + Hinv[p, a, 2] * rhs2
    return dc, dp, True


@jit
def _apply(T, X, dc, dp, cam_var, pt_var):
    T_new = T.copy()
    for i in range(len(T)):
        c = cam_var[i]
        if c >= 0:
            T_new[i] = se3_compose(se3_exp(dc[6 * c : 6 * c + 6]), T[i])
    X_new = X.copy()
    for p in range(len(X)):
        if pt_var[p]:
            for a in range(3):
                X_new[p, a] += dp[p, a]
    return T_new, X_new


@jit
def lm_iteration(T, X, obs_kf, obs_pt, uv, info, order, pt_start, cam_var, n_var, pt_var, K, delta, robust, lam, nu, cost):
    """One g2o-style LM iteration: linearise once, then up to 10 damped steps until one
    lowers the cost (Nielsen's update of lambda and nu). lam < 0 starts lambda at 1e-5 x
    the largest diagonal entry. Returns (T, X, cost, lam, nu, accepted)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Hcc, gc, Hpp, gp, W = _linearise(
        T, X, obs_kf, obs_pt, uv, info, order, pt_start, cam_var, n_var, fx, fy, cx, cy, delta, robust
    )
    if lam < 0.0:
        top = 0.0
        for a in range(len(gc)):
            top = max(top, Hcc[a, a])
        for p in range(len(Hpp)):
            if pt_var[p]:
                for a in range(3):
                    top = max(top, Hpp[p, a, a])
        lam = 1e-5 * top if top > 0.0 else 1e-5
    for _try in range(10):
        dc, dp, ok = _damped_step(Hcc, gc, Hpp, gp, W, obs_kf, order, pt_start, cam_var, pt_var, lam)
        if ok:
            gain = 0.0  # predicted decrease of the (2x) cost: dx^T (lam dx - g)
            for a in range(len(dc)):
                gain += dc[a] * (lam * dc[a] - gc[a])
            for p in range(len(dp)):
                for a in range(3):
                    gain += dp[p, a] * (lam * dp[p, a] - gp[p, a])
            if gain <= 1e-12 * max(cost, 1e-300):
                return T, X, cost, lam, nu, False  # converged: no step lowers the cost measurably
            T_new, X_new = _apply(T, X, dc, dp, cam_var, pt_var)
            new_cost = _cost(T_new, X_new, obs_kf, obs_pt, uv, info, order, fx, fy, cx, cy, delta, robust)
            rho = (cost - new_cost) / (gain + 1e-3)
            if rho > 0.0 and math.isfinite(new_cost):
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                return T_new, X_new, new_cost, lam, 2.0, True
        lam *= nu
        nu *= 2.0
    return T, X, cost, lam, nu, False


def _optimise(
    T_cw: np.ndarray,
    fixed: np.ndarray,
    points: np.ndarray,
    obs_kf: np.ndarray,
    obs_pt: np.ndarray,
    uv: np.ndarray,
    info: np.ndarray,
    K: np.ndarray,
    active: np.ndarray,
    robust: bool,
    iterations: int,
    delta: float,
    deadline: float | None,
    should_stop: Callable[[], bool] | None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """LM over the active observations of points seen at least twice; returns (T_cw,
    points, iterations run). Stops early on gtsam's test (error decrease below 1e-5,
    absolute or relative), a failed iteration, the deadline or ``should_stop``."""
    n_kf, n_pt = len(T_cw), len(points)
    pt_count = np.bincount(obs_pt[active], minlength=n_pt)
    use = active & (pt_count[obs_pt] >= 2)
    if not use.any():
        return T_cw.copy(), points.copy(), 0
    sel = np.flatnonzero(use)
    order = sel[np.argsort(obs_pt[sel], kind="stable")].astype(np.int64)
    counts = np.bincount(obs_pt[order], minlength=n_pt)
    pt_start = np.zeros(n_pt + 1, dtype=np.int64)
    np.cumsum(counts, out=pt_start[1:])
    pt_var = counts > 0
    seen = np.zeros(n_kf, dtype=bool)
    seen[obs_kf[order]] = True
    free = seen & ~fixed
    cam_var = np.full(n_kf, -1, dtype=np.int64)
    cam_var[free] = np.arange(int(free.sum()))
    n_var = int(free.sum())
    T, X = T_cw.copy(), points.copy()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    cost = _cost(T, X, obs_kf, obs_pt, uv, info, order, fx, fy, cx, cy, delta, robust)
    lam, nu = -1.0, 2.0
    done = 0
    for _ in range(iterations):
        if (deadline is not None and time.perf_counter() > deadline) or (should_stop is not None and should_stop()):
            break
        T, X, new_cost, lam, nu, accepted = lm_iteration(
            T, X, obs_kf, obs_pt, uv, info, order, pt_start, cam_var, n_var, pt_var, K, delta, robust, lam, nu, cost
        )
        done += 1
        if not accepted:
            break
        # gtsam's test on its error (half this cost): absolute or relative decrease <= 1e-5.
        decrease = 0.5 * (cost - new_cost)
        cost = new_cost
        if decrease <= 1e-5 or decrease <= 1e-5 * 0.5 * (cost + 2.0 * decrease):
            break
    return T, X, done


def schur_bundle_adjustment(
    T_cw: np.ndarray,
    fixed: np.ndarray,
    points: np.ndarray,
    obs_kf: np.ndarray,
    obs_pt: np.ndarray,
    uv: np.ndarray,
    inv_sigma2: np.ndarray,
    K: np.ndarray,
    iterations: int,
    refine_iterations: int = 0,
    robust: bool = True,
    config: BackendConfig | None = None,
    should_stop: Callable[[], bool] | None = None,
    stop_first: bool = True,
):
    """:func:`orbslam_hgcn.backend.bundle_adjustment.bundle_adjustment` (same arguments,
    same result type) solved by the compiled Schur-complement LM of this module."""
    cfg = config or BackendConfig()
    p = as_problem(T_cw, fixed, points, obs_kf, obs_pt, uv, inv_sigma2, K)
    if len(p.fixed) != len(p.T_cw):
        raise ValueError("fixed must have one flag per pose")
    deadline = time.perf_counter() + cfg.ba_time_budget_s if cfg.ba_time_budget_s > 0 else None
    delta = float(np.sqrt(cfg.chi2_mono))
    args = (p.obs_kf, p.obs_pt, p.uv, p.inv_sigma2, p.K)
    active = np.ones(len(p.obs_kf), dtype=bool)
    T_new, X_new, _ = _optimise(
        p.T_cw, p.fixed, p.points, *args, active, robust, iterations, delta, deadline,
        should_stop if stop_first else None,
    )  # fmt: skip
    if refine_iterations > 0:
        chi2, z = reprojection_chi2(T_new[p.obs_kf], X_new[p.obs_pt], p.uv, p.inv_sigma2, p.K)
        active = (chi2 <= cfg.chi2_mono) & (z > 0)
        T_new, X_new, _ = _optimise(
            T_new, p.fixed, X_new, *args, active, False, refine_iterations, delta, deadline, should_stop
        )
    chi2, z = reprojection_chi2(T_new[p.obs_kf], X_new[p.obs_pt], p.uv, p.inv_sigma2, p.K)
    return BAResult(T_new, X_new, (chi2 > cfg.chi2_mono) | (z <= 0))


def warm_up() -> float:
    """Compile (first use after an install) or load from numba's cache every kernel of
    this module, on a tiny problem with the argument types of a real one; returns the
    seconds it took (about 12 s to compile on a 2-core machine, under 1 s to load)."""
    t0 = time.perf_counter()
    T = np.tile(np.eye(4), (3, 1, 1))
    T[1, 0, 3], T[2, 0, 3] = -0.1, -0.2
    grid = np.linspace(-1.0, 1.0, 4)
    X = np.array([[x, y, 4.0 + 0.1 * x] for x in grid for y in grid])
    obs_kf = np.repeat(np.arange(3), len(X))
    obs_pt = np.tile(np.arange(len(X)), 3)
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    Xc = np.einsum("oij,oj->oi", T[obs_kf, :3, :3], X[obs_pt]) + T[obs_kf, :3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] * 500.0 + np.array([320.0, 240.0])
    fixed = np.array([True, False, False])
    schur_bundle_adjustment(T, fixed, X + 0.01, obs_kf, obs_pt, uv, np.ones(len(uv)), K, 2, 2)
    seconds = time.perf_counter() - t0
    if seconds > 2.0:
        log.info("compiled the local BA kernels in %.1f s (cached for later runs)", seconds)
    return seconds
