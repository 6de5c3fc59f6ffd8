"""The trained HGCN's layers in numpy, for quantising descriptors at run time.

The same Poincare-ball operations as :mod:`orbslam_hgcn.vocabulary.hyperbolic` (Ganea et
al., NeurIPS 2018; the numerical guards of Chami et al.'s ``PoincareBall``) in float32
numpy, so that a vocabulary file can be used without torch. Only what the network needs
for one descriptor seen as a graph of its own (:class:`BallNetwork`): the hyperbolic
linear map, the exponential and logarithmic maps at the origin, Mobius addition and the
projections.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

MIN_NORM = 1e-15
BALL_EPS = 4e-3  # float32 projection margin, as hyperbolic.BALL_EPS
ACTIVATIONS = {
    "relu": lambda v: np.maximum(v, 0.0),
    "leaky_relu": lambda v: np.where(v >= 0, v, 0.01 * v),
    "elu": lambda v: np.where(v > 0, v, np.expm1(np.minimum(v, 0.0))),
    "tanh": np.tanh,
}


def _norm(x: np.ndarray) -> np.ndarray:
    return np.maximum(np.sqrt(np.einsum("...i,...i->...", x, x))[..., None], MIN_NORM)


def artanh(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, -1 + 1e-7, 1 - 1e-7)
    return 0.5 * (np.log1p(x) - np.log1p(-x))


def proj(x: np.ndarray, c: float) -> np.ndarray:
    maxnorm = (1 - BALL_EPS) / np.sqrt(c)
    n = _norm(x)
    return np.where(n > maxnorm, x / n * maxnorm, x)


def clip_tangent(v: np.ndarray, c: float) -> np.ndarray:
    r_max = artanh(np.float32(1 - BALL_EPS)) / np.sqrt(c)
    return v * np.minimum(r_max / _norm(v), 1.0)


def expmap0(u: np.ndarray, c: float) -> np.ndarray:
    sc = np.sqrt(c)
    n = _norm(u)
    return np.tanh(sc * n) * u / (sc * n)


def logmap0(y: np.ndarray, c: float) -> np.ndarray:
    sc = np.sqrt(c)
    n = _norm(y)
    return artanh(sc * n) * y / (sc * n)


def mobius_add(x: np.ndarray, y: np.ndarray, c: float) -> np.ndarray:
    x2 = np.einsum("...i,...i->...", x, x)[..., None]
    y2 = np.einsum("...i,...i->...", y, y)[..., None]
    xy = np.einsum("...i,...i->...", x, y)[..., None]
    num = (1 + 2 * c * xy + c * y2) * x + (1 - c * x2) * y
    den = 1 + 2 * c * xy + c * c * x2 * y2
    return num / np.maximum(den, MIN_NORM)


def hyp_linear(v: np.ndarray, weight: np.ndarray, bias: np.ndarray, c: float) -> np.ndarray:
    """``exp_0(W v) (+) exp_0(b)`` on the ball c, from tangent vectors v (N, d_in)."""
    mv = proj(expmap0(v @ weight.T, c), c)
    b = proj(expmap0(bias[None, :], c), c)
    return proj(mobius_add(mv, b, c), c)


@dataclass
class BallNetwork:
    """The trained layers of an HGCN (see :class:`orbslam_hgcn.vocabulary.hgcn.HGCN`).

    weights, biases: per layer, the neighbourhood path's (d_out, d_in) and (d_out,) arrays;
    self_weights, self_biases: the same for the residual self path (empty lists when the
    layers have none). curvatures: (3,) c of the input ball and of each layer's output.
    activation: name in :data:`ACTIVATIONS`. input_scale: descriptors' PCA coordinates are
    divided by it before the first layer.
    """

    weights: list[np.ndarray]
    biases: list[np.ndarray]
    self_weights: list[np.ndarray]
    self_biases: list[np.ndarray]
    curvatures: np.ndarray
    activation: str
    input_scale: float

    def __post_init__(self) -> None:
        f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
        self.weights = [f32(w) for w in self.weights]
        self.biases = [f32(b) for b in self.biases]
        self.self_weights = [f32(w) for w in self.self_weights]
        self.self_biases = [f32(b) for b in self.self_biases]
        self.curvatures = np.asarray(self.curvatures, np.float64)
        self._act = ACTIVATIONS[self.activation]

    @property
    def residual(self) -> bool:
        return len(self.self_weights) > 0

    @property
    def out_dim(self) -> int:
        return self.weights[-1].shape[0]

    def embed_isolated(self, x: np.ndarray) -> np.ndarray:
        """(N, hidden) float32 output-ball points of PCA coordinates x (N, d), each descriptor
        a graph of its own (its normalised self loop has weight 1)."""
        return self.embed_graph(x, None)

    def embed_graph(self, x: np.ndarray, adj) -> np.ndarray:
        """(N, hidden) float32 output-ball points of the nodes x (N, d) of a graph with the
        normalised propagation matrix adj ((N, N) scipy sparse; None: every node alone)."""
        c = [float(v) for v in self.curvatures]
        v = clip_tangent(np.asarray(x, np.float32) / np.float32(self.input_scale), c[0])
        for i in range(len(self.weights)):
            ci, co = c[i], c[i + 1]
            s = logmap0(hyp_linear(v, self.weights[i], self.biases[i], ci), ci)
            if adj is not None:
                s = np.asarray(adj @ s, np.float32)
            out = self._act(clip_tangent(s, ci))
            if self.residual:
                out = out + logmap0(hyp_linear(v, self.self_weights[i], self.self_biases[i], ci), ci)
            v = clip_tangent(out, co)
        c_out = c[-1]
        return proj(expmap0(v, c_out), c_out).astype(np.float32)

    def arrays(self) -> dict[str, np.ndarray]:
        """The network as named arrays (saved in the vocabulary file)."""
        out = {"net_curvatures": self.curvatures.astype(np.float64),
               "net_activation": np.array(self.activation), "net_input_scale": np.array(self.input_scale, np.float64)}
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            out[f"net_w{i}"], out[f"net_b{i}"] = w, b
        for i, (w, b) in enumerate(zip(self.self_weights, self.self_biases)):
            out[f"net_sw{i}"], out[f"net_sb{i}"] = w, b
        return out

    @classmethod
    def from_arrays(cls, a: dict[str, np.ndarray]) -> BallNetwork:
        """Inverse of :meth:`arrays` (KeyError or ValueError on missing or bad arrays)."""
        n = sum(1 for k in a if k.startswith("net_w"))
        ws = [a[f"net_w{i}"] for i in range(n)]
        bs = [a[f"net_b{i}"] for i in range(n)]
        m = sum(1 for k in a if k.startswith("net_sw"))
        sws = [a[f"net_sw{i}"] for i in range(m)]
        sbs = [a[f"net_sb{i}"] for i in range(m)]
        curv = np.asarray(a["net_curvatures"], np.float64)
        act = str(a["net_activation"])
        if n < 1 or m not in (0, n) or curv.shape != (n + 1,) or not np.all(curv > 0) or act not in ACTIVATIONS:
            raise ValueError("inconsistent network arrays")
        for i in range(n):
            if ws[i].ndim != 2 or bs[i].shape != (ws[i].shape[0],) or (i and ws[i].shape[1] != ws[i - 1].shape[0]):
                raise ValueError(f"bad shapes of layer {i}")
            if m and (sws[i].shape != ws[i].shape or sbs[i].shape != bs[i].shape):
                raise ValueError(f"bad self-path shapes of layer {i}")
        if not all(np.all(np.isfinite(t)) for t in ws + bs + sws + sbs):
            raise ValueError("non-finite network weights")
        return cls(ws, bs, sws, sbs, curv, act, float(a["net_input_scale"]))


def ball_weights(p: np.ndarray, c: float) -> np.ndarray:
    """(K,) ``1 / (1 - c |p|^2)`` of ball points p (K, d): the nearest point of a set to h
    in the hyperbolic distance minimises ``|h - p|^2 / (1 - c |p|^2)`` (the distance
    ``arcosh(1 + 2c|h-p|^2 / ((1-c|h|^2)(1-c|p|^2))) / sqrt(c)`` grows with it)."""
    return (1.0 / np.maximum(1.0 - c * np.einsum("kd,kd->k", p, p), MIN_NORM)).astype(np.float32)
