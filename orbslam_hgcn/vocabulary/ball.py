"""The trained HGCN's layers in numpy, for quantising descriptors at run time.

The same Poincare-ball operations as :mod:`orbslam_hgcn.vocabulary.training.hyperbolic` (Ganea et
al., NeurIPS 2018; the numerical guards of Chami et al.'s ``PoincareBall``) in float32
numpy, so that a vocabulary file can be used without torch. Only what the network needs
for one descriptor seen as a graph of its own (:class:`BallNetwork`): the hyperbolic
linear map, the exponential and logarithmic maps at the origin, Mobius addition and the
projections. Run time embeds descriptors as graphs of their own through one compiled
kernel per layer (:func:`_layer_rows`: the same operations row by row, after BLAS has done
the matrix products); numpy keeps the graph form (:meth:`BallNetwork.embed_graph`), which
training's checks use. The nearest prototype is found in a space where it is the nearest
point in L2 (:class:`PrototypeSearch`), by the coarse-to-fine search of :mod:`.probe`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.compiled import jit
from orbslam_hgcn.vocabulary.graph import configure_faiss, faiss_threads
from orbslam_hgcn.vocabulary.probe import ProbedSearch

log = logging.getLogger(__name__)

MIN_NORM = 1e-15
BALL_EPS = 4e-3  # float32 projection margin, as hyperbolic.BALL_EPS
ARTANH_CLIP = 1e-7  # float32 margin of artanh's argument from +-1
ACTIVATION_CODES = {"relu": 0, "leaky_relu": 1, "elu": 2, "tanh": 3}  # of the compiled kernel
ACTIVATIONS = {
    "relu": lambda v: np.maximum(v, 0.0),
    "leaky_relu": lambda v: np.where(v >= 0, v, 0.01 * v),
    "elu": lambda v: np.where(v > 0, v, np.expm1(np.minimum(v, 0.0))),
    "tanh": np.tanh,
}


def norm(x: np.ndarray) -> np.ndarray:
    """(..., 1) norms of the rows of x (..., d), at least MIN_NORM."""
    return np.maximum(np.sqrt(np.einsum("...i,...i->...", x, x))[..., None], MIN_NORM)


def artanh(x: np.ndarray, clip: float = ARTANH_CLIP) -> np.ndarray:
    """artanh of x clipped to [-1 + clip, 1 - clip]."""
    x = np.clip(x, -1 + clip, 1 - clip)
    return 0.5 * (np.log1p(x) - np.log1p(-x))


R_MAX_UNIT = float(artanh(np.float32(1 - BALL_EPS)))  # tangent radius of the projection ball at c = 1


def proj(x: np.ndarray, c: float, eps: float = BALL_EPS) -> np.ndarray:
    """x with rows beyond the radius (1 - eps) / sqrt(c) scaled back onto it."""
    maxnorm = (1 - eps) / np.sqrt(c)
    n = norm(x)
    return np.where(n > maxnorm, x / n * maxnorm, x)


def clip_tangent(v: np.ndarray, c: float, r_max_unit: float = R_MAX_UNIT) -> np.ndarray:
    """Tangent vectors v with rows longer than r_max_unit / sqrt(c) (the tangent radius of
    the projection ball; :data:`R_MAX_UNIT` for the default margin) scaled back to it."""
    r_max = r_max_unit / np.sqrt(c)
    return v * np.minimum(r_max / norm(v), 1.0)


def expmap0(u: np.ndarray, c: float) -> np.ndarray:
    sc = np.sqrt(c)
    n = norm(u)
    return np.tanh(sc * n) * u / (sc * n)


def logmap0(y: np.ndarray, c: float, clip: float = ARTANH_CLIP) -> np.ndarray:
    sc = np.sqrt(c)
    n = norm(y)
    return artanh(sc * n, clip) * y / (sc * n)


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
    """The trained layers of an HGCN (see :class:`orbslam_hgcn.vocabulary.training.hgcn.HGCN`).

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
        self._act_code = ACTIVATION_CODES[self.activation]
        self._layers = self._pack()

    def _pack(self) -> list[tuple]:
        """Per layer, what the lone-node pass needs: the transposed weights of both paths
        (float32, for BLAS), their biases as ball points ``proj(exp_0(b))`` and the input
        and output curvatures."""
        layers = []
        for k, w in enumerate(self.weights):
            c = float(self.curvatures[k])
            bias = proj(expmap0(self.biases[k][None, :].astype(np.float64), c), c)[0]
            if self.residual:
                sw = np.ascontiguousarray(self.self_weights[k].T)
                sbias = proj(expmap0(self.self_biases[k][None, :].astype(np.float64), c), c)[0]
            else:
                sw, sbias = np.zeros((w.shape[1], 0), np.float32), np.zeros(0)
            layers.append((np.ascontiguousarray(w.T), bias, sw, sbias, c, float(self.curvatures[k + 1])))
        return layers

    @property
    def residual(self) -> bool:
        return len(self.self_weights) > 0

    @property
    def out_dim(self) -> int:
        return self.weights[-1].shape[0]

    def embed_isolated(self, x: np.ndarray) -> np.ndarray:
        """(N, hidden) float32 output-ball points of PCA coordinates x (N, d), each descriptor
        a graph of its own (its normalised self loop has weight 1): :meth:`embed_graph`
        without a graph, in the compiled kernel."""
        x = np.ascontiguousarray(x, dtype=np.float32).reshape(-1, self.weights[0].shape[1])
        v = clip_tangent(x / np.float32(self.input_scale), float(self.curvatures[0]))
        for k, (wt, bias, swt, sbias, ci, co) in enumerate(self._layers):
            out = np.empty((len(v), wt.shape[1]), np.float32)
            if len(v):
                _layer_rows(v, wt, swt, bias, sbias, ci, co, self._act_code, self.residual, R_MAX_UNIT,
                            k == len(self._layers) - 1, out)
            v = out
        return v

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
    p = np.asarray(p, np.float64)
    return 1.0 / np.maximum(1.0 - c * np.einsum("kd,kd->k", p, p), MIN_NORM)


class PrototypeSearch:
    """Hyperbolic nearest prototype as a nearest point in L2.

    For a query h, the nearest of the ball points p (curvature c) minimises
    ``w_p |h - p|^2`` with ``w_p = 1 / (1 - c |p|^2)`` (:func:`ball_weights`): it has the
    largest inner product of ``q = [h, |h|^2, 1]`` with ``u_p = [2 w_p p, -w_p,
    -w_p |p|^2]``. Scaled to unit length, ``u_p / M`` completed by ``sqrt(1 - |u_p / M|^2)``
    (M the largest ``|u_p|``) and ``q / |q|`` completed by 0, the largest inner product is
    the nearest point in L2 (hidden width + 3 dimensions). Run time searches those lifted
    points with :class:`~.probe.ProbedSearch`; ``exact`` uses faiss's exhaustive search.
    """

    def __init__(self, prototypes: np.ndarray, c: float) -> None:
        p = np.asarray(prototypes, np.float64)
        w = ball_weights(p, c)[:, None]
        u = np.hstack([2 * w * p, -w, -w * np.einsum("kd,kd->k", p, p)[:, None]])
        u /= np.sqrt(np.einsum("kd,kd->k", u, u).max())
        self.dim = u.shape[1] + 1
        self.points = np.zeros((len(u), self.dim), np.float32)
        self.points[:, : u.shape[1]] = u
        self.points[:, u.shape[1]] = np.sqrt(np.maximum(1.0 - np.einsum("kd,kd->k", u, u), 0.0))
        self.probed = ProbedSearch(self.points)

    def lift(self, h: np.ndarray) -> np.ndarray:
        """(N, hidden + 3) float32 unit queries ``[h, |h|^2, 1, 0] / |.|`` of ball points h."""
        h = np.asarray(h, np.float32)
        q = np.zeros((len(h), self.dim), np.float32)
        q[:, : h.shape[1]] = h
        q[:, h.shape[1]] = np.einsum("nd,nd->n", h, h)
        q[:, h.shape[1] + 1] = 1.0
        q /= np.sqrt(np.einsum("nd,nd->n", q, q))[:, None]
        return q

    def search(self, h: np.ndarray, exact: bool = False) -> np.ndarray:
        """(N,) int32 nearest prototype of ball points h (N, hidden) (``exact``: faiss's
        exhaustive search, for comparisons)."""
        q = self.lift(h)
        if exact:
            configure_faiss()
            import faiss
            index = faiss.IndexFlatL2(self.dim)
            index.add(self.points)
            with faiss_threads(len(q)):
                return index.search(q, 1)[1][:, 0].astype(np.int32)
        return self.probed.search(q)


@jit
def _norm1(v, n):
    s = 0.0
    for t in range(n):
        s += v[t] * v[t]
    return max(np.sqrt(s), MIN_NORM)


@jit
def _artanh1(x):
    x = min(max(x, -1.0 + 1e-7), 1.0 - 1e-7)
    return 0.5 * (np.log1p(x) - np.log1p(-x))


@jit
def _clip_tangent1(v, n, c, r_max_unit):
    f = min(r_max_unit / np.sqrt(c) / _norm1(v, n), 1.0)
    for t in range(n):
        v[t] *= f


@jit
def _exp0_scale(n, c):
    """The factor f with ``proj(exp_0(u)) = f u`` on the ball c, for |u| = n."""
    sc = np.sqrt(c)
    f = np.tanh(sc * n) / (sc * n)
    maxnorm = (1 - BALL_EPS) / sc
    return maxnorm / n if f * n > maxnorm else f


@jit
def _ball_linear_log(a, bias_pt, c, out):
    """out = log_0(proj(proj(exp_0(a)) (+) bias_pt)) on the ball c, for one row a = W v
    (the tangent result of the hyperbolic linear map)."""
    n_out = len(a)
    sc = np.sqrt(c)
    maxnorm = (1 - BALL_EPS) / sc
    f = _exp0_scale(_norm1(a, n_out), c)
    x2, y2, xy = 0.0, 0.0, 0.0
    for r in range(n_out):
        m = a[r] * f
        out[r] = m
        x2 += m * m
        y2 += bias_pt[r] * bias_pt[r]
        xy += m * bias_pt[r]
    p = 1 + 2 * c * xy + c * y2
    q = 1 - c * x2
    den = max(1 + 2 * c * xy + c * c * x2 * y2, MIN_NORM)
    for r in range(n_out):
        out[r] = (p * out[r] + q * bias_pt[r]) / den
    n = _norm1(out, n_out)
    if n > maxnorm:
        for r in range(n_out):
            out[r] *= maxnorm / n
        n = maxnorm
    f = _artanh1(sc * n) / (sc * n)  # log_0
    for r in range(n_out):
        out[r] *= f


@jit
def _row_product(v, i, wt, row):
    """row = V[i] W^T for the transposed weights wt (d_in, d_out)."""
    for t in range(wt.shape[1]):
        row[t] = 0.0
    for k in range(wt.shape[0]):
        e = v[i, k]
        for t in range(wt.shape[1]):
            row[t] += e * wt[k, t]


@jit
def _layer_rows(v, wt, swt, bias_pt, sbias_pt, ci, co, act, residual, r_max_unit, last, out):
    """One layer for lone nodes, row by row: the products V W^T and V W_self^T of both paths
    (wt, swt: transposed weights; the products are done here, not by BLAS, whose worker
    threads spin for a frame's 20 x 20 products), then the ball operations; out (N, d_out)
    receives the next layer's tangent input, or, for the last layer (``last``), the
    output-ball points."""
    n_out = wt.shape[1]
    s = np.empty(n_out)
    r = np.empty(n_out)
    row = np.empty(n_out)
    for i in range(v.shape[0]):
        _row_product(v, i, wt, row)
        _ball_linear_log(row, bias_pt, ci, s)
        _clip_tangent1(s, n_out, ci, r_max_unit)
        for t in range(n_out):
            e = s[t]
            if act == 0:
                e = max(e, 0.0)
            elif act == 1:
                e = e if e >= 0 else 0.01 * e
            elif act == 2:
                e = e if e > 0 else np.expm1(e)
            else:
                e = np.tanh(e)
            s[t] = e
        if residual:
            _row_product(v, i, swt, row)
            _ball_linear_log(row, sbias_pt, ci, r)
            for t in range(n_out):
                s[t] += r[t]
        _clip_tangent1(s, n_out, co, r_max_unit)
        if last:
            f = _exp0_scale(_norm1(s, n_out), co)
            for t in range(n_out):
                out[i, t] = s[t] * f
        else:
            for t in range(n_out):
                out[i, t] = s[t]
