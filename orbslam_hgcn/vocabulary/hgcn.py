"""Hyperbolic graph convolutional network (HGCN) for semi-supervised node labelling.

Architecture (Chami, Ying, Re & Leskovec, "Hyperbolic Graph Convolutional Neural Networks",
NeurIPS 2019, section 4, on the Poincare ball as in their code's ``PoincareBall``):

* input: Euclidean node features ``x`` (scaled to unit mean norm), mapped onto the ball of
  curvature ``c0`` by the exponential map at the origin;
* two HGCN layers, each: hyperbolic linear transform (Mobius matrix-vector product, then
  Mobius addition of a bias ``exp_0(b)``), neighbourhood aggregation in the tangent space at
  the origin (``exp_0(A_hat log_0(h))``), hyperbolic activation (``exp_0^{c_out}(sigma(
  log_0^{c_in}(h)))``); every ball has its own trainable curvature ``c = softplus(raw) > 0``;
* output ("decoder", a choice of this implementation): one trainable prototype ``p_k`` per
  class, kept inside the ball as ``p_k = exp_0(v_k)``, and logits ``-s * d_c(h, p_k)^2`` with
  a trainable scale ``s > 0``. Distances to prototypes are the natural classifier of a
  metric space and need only one matrix product (closed-form distance, see
  :func:`~orbslam_hgcn.vocabulary.hyperbolic.sq_dist_matrix`). The prototypes start at
  the class means (in the tangent space at the origin) of the labelled nodes' initial
  embeddings, so training starts from a nearest-class-mean classifier.

Training is cross-entropy on the labelled nodes, in mini-batches: each step takes a batch
of labelled seed nodes and computes their outputs from their 2-hop neighbourhoods
(:func:`~orbslam_hgcn.vocabulary.graph.two_hop_blocks`): the second layer aggregates over
all neighbours of the seeds, the first over each node's self loop and a few sampled
neighbours (``sample_neighbours``; scaled to keep the expected aggregation; 0 = exact), so
memory and time per step do not grow with the graph. When K exceeds
``candidate_classes``, each step's softmax runs over a subset of the classes (see
:func:`_step_classes`). Inference runs layer by layer over the whole graph, exactly.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import scipy.sparse as sp
import torch
from torch import nn
from torch.nn import functional as F
from tqdm import tqdm

from orbslam_hgcn.config import HgcnTrainConfig
from orbslam_hgcn.vocabulary import hyperbolic as hyp
from orbslam_hgcn.vocabulary.graph import two_hop_blocks

log = logging.getLogger(__name__)

_ACTS = {"relu": F.relu, "leaky_relu": F.leaky_relu, "elu": F.elu, "tanh": torch.tanh}
_INFER_CHUNK = 4096  # rows per block of the decoder at inference


def _softplus_inv(y: float) -> float:
    return y + math.log(-math.expm1(-y))


def sparse_tensor(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray, shape: tuple[int, int]) -> torch.Tensor:
    """A coalesced torch COO matrix from row-sorted (rows, cols, vals) entries."""
    idx = torch.from_numpy(np.stack([rows, cols]).astype(np.int64))
    return torch.sparse_coo_tensor(
        idx, torch.from_numpy(np.asarray(vals, np.float32)), shape, is_coalesced=True, check_invariants=False
    )


def csr_to_torch(adj: sp.csr_matrix) -> torch.Tensor:
    coo = adj.tocoo()
    return sparse_tensor(coo.row, coo.col, coo.data, adj.shape)


class HypLinear(nn.Module):
    """Hyperbolic linear layer: ``(W (x)_c x) (+)_c exp_0^c(b)``."""

    def __init__(self, d_in: int, d_out: int, dropout: float) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(d_out, d_in))
        self.bias = nn.Parameter(torch.zeros(d_out))
        self.dropout = dropout
        nn.init.xavier_uniform_(self.weight, gain=math.sqrt(2))

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        """x: (N, d_in) points on ball c. Returns (N, d_out) points on ball c."""
        w = F.dropout(self.weight, self.dropout, training=self.training)
        mv = hyp.proj(hyp.mobius_matvec(w, x, c), c)
        return self._add_bias(mv, c)

    def forward_tangent(self, v: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        """The same map from the input's tangent vector v = log_0(x): since
        ``W (x)_c x = exp_0(W log_0(x))``, the Mobius product is one exponential map."""
        w = F.dropout(self.weight, self.dropout, training=self.training)
        return self._add_bias(hyp.proj(hyp.expmap0(v @ w.T, c), c), c)

    def _add_bias(self, mv: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        b = hyp.proj(hyp.expmap0(self.bias.view(1, -1), c), c)
        return hyp.proj(hyp.mobius_add(mv, b, c), c)


class HGCNLayer(nn.Module):
    """One HGCN layer: hyperbolic linear, tangent-space aggregation, hyperbolic activation."""

    def __init__(self, d_in: int, d_out: int, dropout: float, act: str) -> None:
        super().__init__()
        self.linear = HypLinear(d_in, d_out, dropout)
        self.act = _ACTS[act]

    def forward(self, x: torch.Tensor, adj: torch.Tensor, c_in: torch.Tensor, c_out: torch.Tensor) -> torch.Tensor:
        """x: (N_in, d_in) points on ball c_in. adj: (N_out, N_in) sparse propagation block.
        Returns (N_out, d_out) points on ball c_out."""
        h = self.linear(x, c_in)
        h = hyp.proj(hyp.expmap0(torch.sparse.mm(adj, hyp.logmap0(h, c_in)), c_in), c_in)
        return hyp.proj(hyp.expmap0(self.act(hyp.logmap0(h, c_in)), c_out), c_out)

    def forward_tangent(
        self, v: torch.Tensor, adj: torch.Tensor, c_in: torch.Tensor, c_out: torch.Tensor
    ) -> torch.Tensor:
        """:meth:`forward` on tangent vectors at the origin: v = log_0(x) in, log_0(output)
        out. Equal to ``log_0(forward(exp_0(v)))`` (``log_0(proj(exp_0(s)))`` is the norm
        cap :func:`~orbslam_hgcn.vocabulary.hyperbolic.clip_tangent`) with half the
        element-wise operations, which dominate the training time on a CPU."""
        h = self.linear.forward_tangent(v, c_in)
        s = torch.sparse.mm(adj, hyp.logmap0(h, c_in))
        return hyp.clip_tangent(self.act(hyp.clip_tangent(s, c_in)), c_out)


class HGCN(nn.Module):
    """Two HGCN layers and a hyperbolic prototype decoder over ``n_classes`` classes."""

    def __init__(self, d_in: int, hidden: int, n_classes: int, cfg: HgcnTrainConfig) -> None:
        super().__init__()
        self.layers = nn.ModuleList(
            [
                HGCNLayer(d_in, hidden, cfg.dropout, cfg.activation),
                HGCNLayer(hidden, hidden, cfg.dropout, cfg.activation),
            ]
        )
        self.raw_c = nn.Parameter(torch.full((3,), _softplus_inv(cfg.init_curvature)))
        self.prototypes = nn.Parameter(torch.randn(n_classes, hidden) * 1e-2)  # tangent vectors at 0
        self.raw_scale = nn.Parameter(torch.tensor(_softplus_inv(1.0)))

    @property
    def curvatures(self) -> torch.Tensor:
        """(3,) c of the input ball and of each layer's output ball."""
        return F.softplus(self.raw_c)

    def embed_input(self, x: torch.Tensor) -> torch.Tensor:
        """Euclidean features (N, d) onto the input ball."""
        c0 = self.curvatures[0]
        return hyp.proj(hyp.expmap0(x, c0), c0)

    def _forward_tangent(self, x: torch.Tensor, adj1: torch.Tensor, adj2: torch.Tensor) -> torch.Tensor:
        c = self.curvatures
        v = hyp.clip_tangent(x, c[0])  # log_0 of embed_input(x)
        v = self.layers[0].forward_tangent(v, adj1, c[0], c[1])
        v = self.layers[1].forward_tangent(v, adj2, c[1], c[2])
        return hyp.proj(hyp.expmap0(v, c[2]), c[2])

    def forward_reference(self, x: torch.Tensor, adj1: torch.Tensor, adj2: torch.Tensor) -> torch.Tensor:
        """Final embeddings computed on the ball, operation by operation as in HGCN (the
        training and inference paths use the equal tangent-space form)."""
        c = self.curvatures
        h = self.layers[0](self.embed_input(x), adj1, c[0], c[1])
        return self.layers[1](h, adj2, c[1], c[2])

    def prototype_points(self, classes: torch.Tensor | None = None) -> torch.Tensor:
        """(K, hidden) prototypes on the output ball (all, or the given class ids)."""
        c = self.curvatures[2]
        v = self.prototypes if classes is None else self.prototypes[classes]
        return hyp.proj(hyp.expmap0(v, c), c)

    def logits(self, h: torch.Tensor, classes: torch.Tensor | None = None) -> torch.Tensor:
        """(N, K') logits ``-s d(h, p_k)^2`` of final embeddings h (N, hidden) against all
        prototypes, or against the prototypes of ``classes`` (K',)."""
        c = self.curvatures[2]
        return -F.softplus(self.raw_scale) * hyp.sq_dist_matrix(h, self.prototype_points(classes), c)

    @torch.no_grad()
    def nearest_prototype(self, h: torch.Tensor) -> torch.Tensor:
        """(N,) argmax class of embeddings h, without evaluating the distances.

        ``d`` grows with ``z = 1 + 2c|h-p|^2 / ((1-c|h|^2)(1-c|p|^2))``, so the nearest
        prototype minimises ``|h-p|^2 / (1 - c|p|^2)``: one matrix product and two
        element-wise operations per pair instead of the full distance.
        """
        c = self.curvatures[2]
        p = self.prototype_points()
        w = 1.0 / (1.0 - c * p.pow(2).sum(-1)).clamp_min(1e-15)
        q = torch.addmm(p.pow(2).sum(-1)[None, :], h, p.T, alpha=-2)  # |p|^2 - 2 h.p
        return ((q + h.pow(2).sum(-1, keepdim=True)) * w).argmin(1)

    def forward_blocks(self, x_hop2: torch.Tensor, adj1: torch.Tensor, adj2: torch.Tensor) -> torch.Tensor:
        """(B, hidden) final embeddings (ball points) of a batch's seeds from their 2-hop
        inputs x_hop2 (N2, d) and propagation blocks (see two_hop_blocks)."""
        return self._forward_tangent(x_hop2, adj1, adj2)

    @torch.no_grad()
    def embed_all(self, x: torch.Tensor, adj: torch.Tensor) -> torch.Tensor:
        """(N, hidden) final embeddings of all nodes, layer by layer over the whole graph."""
        return self._forward_tangent(x, adj, adj)

    @torch.no_grad()
    def predict(self, x: torch.Tensor, adj: torch.Tensor) -> np.ndarray:
        """(N,) int64 argmax class of every node."""
        h = self.embed_all(x, adj)
        out = np.empty(len(h), np.int64)
        for s in range(0, len(h), _INFER_CHUNK):
            out[s : s + _INFER_CHUNK] = self.nearest_prototype(h[s : s + _INFER_CHUNK]).numpy()
        return out


@torch.no_grad()
def _init_prototypes(model: HGCN, x: torch.Tensor, adj_t: torch.Tensor, labels: np.ndarray, n_classes: int) -> None:
    """Prototypes at the tangent-space class means of the labelled nodes' embeddings, and
    the logit scale so that the mean squared distance to the own prototype maps to -1."""
    lab = np.flatnonzero(labels >= 0)
    h = model.embed_all(x, adj_t)[torch.from_numpy(lab)]
    c = model.curvatures[2]
    t = hyp.logmap0(h, c)
    y = torch.from_numpy(labels[lab])
    sums = torch.zeros(n_classes, t.shape[1]).index_add_(0, y, t)
    counts = torch.bincount(y, minlength=n_classes).clamp_min(1).unsqueeze(1)
    has = torch.bincount(y, minlength=n_classes) > 0
    model.prototypes[has] = (sums / counts)[has]
    p = hyp.proj(hyp.expmap0(model.prototypes[y], c), c)
    d2 = hyp.dist(h, p, c).pow(2).mean().clamp_min(1e-6)
    model.raw_scale.fill_(_softplus_inv(float(1.0 / d2)))


def _step_classes(labels: np.ndarray, seeds: np.ndarray, hop2: np.ndarray, n_classes: int, budget: int,
                  rng: np.random.Generator) -> tuple[torch.Tensor | None, torch.Tensor]:
    """Classes of one step's softmax and the seeds' targets among them.

    With K <= budget all classes are used. Otherwise (a sampled softmax): the seeds' own
    labels, the labels seeded anywhere in their 2-hop neighbourhood (the likeliest
    confusions) and random classes up to ``budget``. Returns (classes (K',) or None for
    all, (B,) target index of each seed).
    """
    y = labels[seeds]
    if n_classes <= budget:
        return None, torch.from_numpy(y)
    near = labels[hop2]
    cand = np.unique(np.concatenate([y, near[near >= 0]]))
    extra = budget - len(cand)
    if extra > 0:
        cand = np.unique(np.concatenate([cand, rng.integers(0, n_classes, extra)]))
    return torch.from_numpy(cand), torch.from_numpy(np.searchsorted(cand, y))


def train_hgcn(
    x: np.ndarray, adj: sp.csr_matrix, labels: np.ndarray, n_classes: int, cfg: HgcnTrainConfig, progress: bool = True
) -> tuple[HGCN, np.ndarray, dict]:
    """Train the HGCN on the labelled nodes and label every node.

    x: (N, d) float32 node features. adj: (N, N) normalised propagation matrix (CSR, self
    loops included). labels: (N,) int64 class in [0, n_classes) or -1 (unlabelled).
    Returns (model, (N,) int64 predicted class of every node, stats dict).
    """
    t0 = time.perf_counter()
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    scale = float(np.mean(np.linalg.norm(x, axis=1))) or 1.0
    xt = torch.from_numpy(np.ascontiguousarray(x / scale, dtype=np.float32))
    adj_t = csr_to_torch(adj)
    labelled = np.flatnonzero(labels >= 0)
    if len(labelled) == 0:
        raise ValueError("no labelled node to train on")
    model = HGCN(x.shape[1], cfg.hidden_dim, n_classes, cfg)
    _init_prototypes(model, xt, adj_t, labels, n_classes)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps = int(np.clip(np.ceil(cfg.epochs * len(labelled) / cfg.batch_size), cfg.min_steps, cfg.max_steps))
    order = rng.permutation(labelled)
    pos = 0
    losses = []
    model.train()
    bar = tqdm(range(steps), desc="HGCN training", unit="step", disable=not progress)
    for _ in bar:
        if pos + cfg.batch_size > len(order):
            order, pos = rng.permutation(labelled), 0
        seeds = np.sort(order[pos : pos + cfg.batch_size])
        pos += cfg.batch_size
        hop2, (r1, c1, v1), hop1, (r2, c2, v2) = two_hop_blocks(adj, seeds, cfg.sample_neighbours, rng)
        adj1 = sparse_tensor(r1, c1, v1, (len(hop1), len(hop2)))
        adj2 = sparse_tensor(r2, c2, v2, (len(seeds), len(hop1)))
        h = model.forward_blocks(xt[torch.from_numpy(hop2)], adj1, adj2)
        classes, target = _step_classes(labels, seeds, hop2, n_classes, cfg.candidate_classes, rng)
        loss = F.cross_entropy(model.logits(h, classes), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        bar.set_postfix(loss=f"{losses[-1]:.3f}", nodes=len(hop2))
    model.eval()
    t_train = time.perf_counter() - t0
    pred = model.predict(xt, adj_t)
    acc = float(np.mean(pred[labelled] == labels[labelled]))
    stats = {
        "hgcn_steps": steps,
        "hgcn_train_seconds": round(t_train, 2),
        "hgcn_predict_seconds": round(time.perf_counter() - t0 - t_train, 2),
        "loss_first": round(losses[0], 4) if losses else None,
        "loss_last": round(float(np.mean(losses[-10:])), 4) if losses else None,
        "labelled_accuracy": round(acc, 4),
        "curvatures": [round(float(v), 4) for v in model.curvatures.detach()],
    }
    log.info("HGCN: %d steps in %.1f s, loss %.3f -> %.3f, labelled accuracy %.3f",
             steps, t_train, stats["loss_first"] or 0, stats["loss_last"] or 0, acc)
    return model, pred, stats
