"""Operations on the Poincare ball of curvature -c (c > 0), in torch.

The ball is ``{x : c |x|^2 < 1}``. Formulas follow Ganea, Becigneul & Hofmann, "Hyperbolic
Neural Networks", NeurIPS 2018 (Mobius addition, scalar and matrix multiplication, exp/log
maps) and their use in Chami, Ying, Re & Leskovec, "Hyperbolic Graph Convolutional Neural
Networks", NeurIPS 2019 (HGCN), including the numerical guards of HGCN's ``PoincareBall``:
points are projected to radius ``(1 - eps) / sqrt(c)`` (eps = 4e-3 in float32, 1e-5 in
float64) and norms are clamped away from zero.

All functions broadcast over leading dimensions; the last dimension is the ball's. ``c``
is a positive scalar tensor (or float).
"""

from __future__ import annotations

import logging

import torch

log = logging.getLogger(__name__)

MIN_NORM = 1e-15
BALL_EPS = {torch.float32: 4e-3, torch.float64: 1e-5}


def _c(c: torch.Tensor | float, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(c, dtype=like.dtype, device=like.device)


def artanh(x: torch.Tensor) -> torch.Tensor:
    """Inverse hyperbolic tangent, clamped to stay finite at |x| -> 1."""
    eps = 1e-7 if x.dtype == torch.float32 else 1e-15
    x = x.clamp(-1 + eps, 1 - eps)
    return 0.5 * (torch.log1p(x) - torch.log1p(-x))


def _norm(x: torch.Tensor) -> torch.Tensor:
    return x.norm(dim=-1, keepdim=True).clamp_min(MIN_NORM)


def proj(x: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """Pull points back inside the ball: norm at most ``(1 - eps) / sqrt(c)``."""
    c = _c(c, x)
    maxnorm = (1 - BALL_EPS.get(x.dtype, 1e-5)) / c.sqrt()
    norm = _norm(x)
    return torch.where(norm > maxnorm, x / norm * maxnorm, x)


def clip_tangent(v: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """``log_0(proj(exp_0(v)))`` in closed form: v with its norm capped at
    ``artanh(1 - eps) / sqrt(c)`` (the tangent radius of the projection ball)."""
    c = _c(c, v)
    r_max = artanh(torch.tensor(1 - BALL_EPS.get(v.dtype, 1e-5), dtype=v.dtype)) / c.sqrt()
    return v * (r_max / _norm(v)).clamp(max=1.0)


def lambda_x(x: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """Conformal factor ``2 / (1 - c |x|^2)``, shape (..., 1)."""
    c = _c(c, x)
    return 2.0 / (1.0 - c * x.pow(2).sum(-1, keepdim=True)).clamp_min(MIN_NORM)


def mobius_add(x: torch.Tensor, y: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """Mobius addition ``x (+)_c y``:

    ``((1 + 2c<x,y> + c|y|^2) x + (1 - c|x|^2) y) / (1 + 2c<x,y> + c^2 |x|^2 |y|^2)``.
    """
    c = _c(c, x)
    x2 = x.pow(2).sum(-1, keepdim=True)
    y2 = y.pow(2).sum(-1, keepdim=True)
    xy = (x * y).sum(-1, keepdim=True)
    num = (1 + 2 * c * xy + c * y2) * x + (1 - c * x2) * y
    den = 1 + 2 * c * xy + c**2 * x2 * y2
    return num / den.clamp_min(MIN_NORM)


def expmap0(u: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """Exponential map at the origin: ``tanh(sqrt(c)|u|) u / (sqrt(c)|u|)``."""
    sqrt_c = _c(c, u).sqrt()
    un = _norm(u)
    return torch.tanh(sqrt_c * un) * u / (sqrt_c * un)


def logmap0(y: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """Logarithmic map at the origin: ``artanh(sqrt(c)|y|) y / (sqrt(c)|y|)``."""
    sqrt_c = _c(c, y).sqrt()
    yn = _norm(y)
    return artanh(sqrt_c * yn) * y / (sqrt_c * yn)


def expmap(x: torch.Tensor, u: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """Exponential map at x: ``x (+) tanh(sqrt(c) lambda_x |u| / 2) u / (sqrt(c)|u|)``."""
    sqrt_c = _c(c, x).sqrt()
    un = _norm(u)
    second = torch.tanh(sqrt_c * lambda_x(x, c) * un / 2) * u / (sqrt_c * un)
    return mobius_add(x, second, c)


def logmap(x: torch.Tensor, y: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """Logarithmic map at x: ``2 / (sqrt(c) lambda_x) artanh(sqrt(c)|w|) w / |w|``, w = -x (+) y."""
    sqrt_c = _c(c, x).sqrt()
    w = mobius_add(-x, y, c)
    wn = _norm(w)
    return 2 / (sqrt_c * lambda_x(x, c)) * artanh(sqrt_c * wn) * w / wn


def mobius_scalar_mul(r: torch.Tensor | float, x: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """Mobius scalar multiplication ``r (x)_c x = tanh(r artanh(sqrt(c)|x|)) x / (sqrt(c)|x|)``."""
    sqrt_c = _c(c, x).sqrt()
    xn = _norm(x)
    return torch.tanh(r * artanh(sqrt_c * xn)) * x / (sqrt_c * xn)


def mobius_matvec(m: torch.Tensor, x: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """Mobius matrix-vector product of rows: ``M (x)_c x``.

    m: (d_out, d_in). x: (..., d_in). Returns (..., d_out):
    ``tanh(|Mx| / |x| artanh(sqrt(c)|x|)) Mx / (sqrt(c)|Mx|)`` (zero where Mx = 0).
    """
    sqrt_c = _c(c, x).sqrt()
    xn = _norm(x)
    mx = x @ m.transpose(-1, -2)
    mxn = _norm(mx)
    res = torch.tanh(mxn / xn * artanh(sqrt_c * xn)) * mx / (mxn * sqrt_c)
    zero = (mx == 0).all(dim=-1, keepdim=True)
    return torch.where(zero, torch.zeros_like(res), res)


def dist(x: torch.Tensor, y: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """Geodesic distance ``2 / sqrt(c) artanh(sqrt(c) |-x (+) y|)``, shape (...)."""
    sqrt_c = _c(c, x).sqrt()
    return 2 / sqrt_c * artanh(sqrt_c * mobius_add(-x, y, c).norm(dim=-1))


def sq_dist_matrix(x: torch.Tensor, p: torch.Tensor, c: torch.Tensor | float) -> torch.Tensor:
    """(N, K) squared geodesic distances between rows of x (N, d) and p (K, d).

    Uses the closed form ``d = arcosh(1 + 2c|x-p|^2 / ((1 - c|x|^2)(1 - c|p|^2))) / sqrt(c)``,
    which needs only a matrix product for ``|x - p|^2``. The square keeps the gradient
    finite at zero distance.
    """
    c = _c(c, x)
    x2 = x.pow(2).sum(-1, keepdim=True)
    p2 = p.pow(2).sum(-1)
    diff2 = torch.addmm(p2[None, :], x, p.T, alpha=-2).add_(x2).clamp_min_(0)  # |x - p|^2
    a = 1.0 / (1 - c * x2).clamp_min(MIN_NORM)
    b = (2 * c) / (1 - c * p2).clamp_min(MIN_NORM)
    eps = 1e-7 if x.dtype == torch.float32 else 1e-12
    z = (diff2 * a * b[None, :]).add_(1).clamp_min_(1 + eps)
    return torch.acosh(z).pow_(2) / c
