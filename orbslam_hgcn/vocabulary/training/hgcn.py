"""Hyperbolic graph convolutional network (HGCN) for semi-supervised node labelling.

Architecture (Chami, Ying, Re & Leskovec, "Hyperbolic Graph Convolutional Neural Networks",
NeurIPS 2019, section 4, on the Poincare ball as in their code's ``PoincareBall``):

* input: Euclidean node features ``x`` (scaled to a mean norm of ``input_radius``), mapped
  onto the ball of curvature ``c0`` by the exponential map at the origin;
* two HGCN layers, each: hyperbolic linear transform (Mobius matrix-vector product, then
  Mobius addition of a bias ``exp_0(b)``), neighbourhood aggregation in the tangent space at
  the origin (``A_hat log_0(h)``), activation in that tangent space, and the result read on
  the next ball (curvature ``c_out``); every ball has its own trainable curvature
  ``c = softplus(raw) > 0``;
* residual layers (``residual``, the default): a second hyperbolic linear map of the node's
  own input (the self path) is added, in the tangent space, to the activated aggregate.
  Separate self and neighbourhood weights are GraphSAGE's (Hamilton, Ying & Leskovec,
  NeurIPS 2017); as in GCNII's identity mapping (Chen et al., ICML 2020) the self path
  starts as the identity and the neighbourhood path at zero, so the untrained network
  passes every descriptor through unchanged. Without it (Chami et al.'s layer) the labels
  of k-means seeds are not learnt: on 80k KITTI descriptors and 1000 words the plain
  layers reached 80% on the training seeds and 37% on held-out ones;
* output: the class prototypes are the network's embeddings of the seed k-means centres,
  each passed through the layers as a graph of its own (its self loop only), and the
  logits are ``-s d_c(h, p_k)^2`` with a trainable scale ``s > 0``. Tying the prototypes to
  the centres leaves the training only the layers to change: free prototypes, a few seeds
  each, memorised their seeds (training accuracy up, held-out accuracy down).

Training (:func:`train_hgcn`) is full-batch cross-entropy on the labelled nodes, exact
over their 2-hop neighbourhoods (:func:`~orbslam_hgcn.vocabulary.graph.two_hop_blocks`);
each epoch's softmax runs over the seed's label and its ``candidate_classes`` nearest
prototypes (hard negatives), refreshed every epoch. The logit scale starts at the value
that minimises the initial loss (a line search), so the first steps do not just sharpen
the softmax by stretching the embedding. A share ``holdout`` of the seed groups (a track
is one group) is held out for early stopping, and as much again for the reported test
accuracy. Inference runs layer by layer over the whole graph, exactly.
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
from orbslam_hgcn.errors import ConfigError
from orbslam_hgcn.vocabulary.training import hyperbolic as hyp
from orbslam_hgcn.vocabulary.ball import BallNetwork
from orbslam_hgcn.vocabulary.graph import two_hop_blocks

log = logging.getLogger(__name__)

_ACTS = {"relu": F.relu, "leaky_relu": F.leaky_relu, "elu": F.elu, "tanh": torch.tanh}
_CHUNK = 4096  # rows per block of the prototype search


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
    """One HGCN layer: hyperbolic linear, tangent-space aggregation and activation, and
    (``residual``) the self path added to the activated aggregate."""

    def __init__(self, d_in: int, d_out: int, dropout: float, act: str, residual: bool = False) -> None:
        super().__init__()
        self.linear = HypLinear(d_in, d_out, dropout)
        self.act = _ACTS[act]
        self.self_linear = HypLinear(d_in, d_out, dropout) if residual else None
        if residual:
            with torch.no_grad():
                self.linear.weight.zero_()
                self.self_linear.weight.zero_()
                n = min(d_in, d_out)
                self.self_linear.weight[:n, :n] = torch.eye(n)

    @property
    def residual(self) -> bool:
        return self.self_linear is not None

    def forward(self, x: torch.Tensor, adj: torch.Tensor, c_in: torch.Tensor, c_out: torch.Tensor,
                self_rows: torch.Tensor | None = None) -> torch.Tensor:
        """Ball form, operation by operation. x: (N_in, d_in) points on ball c_in. adj:
        (N_out, N_in) sparse propagation block. self_rows: (N_out,) row of x of each output
        node (residual layers; None: the outputs are the inputs). Returns (N_out, d_out)
        points on ball c_out."""
        h = self.linear(x, c_in)
        s = hyp.proj(hyp.expmap0(torch.sparse.mm(adj, hyp.logmap0(h, c_in)), c_in), c_in)
        t = self.act(hyp.logmap0(s, c_in))
        if self.residual:
            xs = x if self_rows is None else x[self_rows]
            t = t + hyp.logmap0(self.self_linear(xs, c_in), c_in)
        return hyp.proj(hyp.expmap0(t, c_out), c_out)

    def forward_tangent(self, v: torch.Tensor, adj: torch.Tensor, c_in: torch.Tensor, c_out: torch.Tensor,
                        self_rows: torch.Tensor | None = None) -> torch.Tensor:
        """:meth:`forward` on tangent vectors at the origin: v = log_0(x) in, log_0(output)
        out (``log_0(proj(exp_0(s)))`` is the norm cap
        :func:`~orbslam_hgcn.vocabulary.training.hyperbolic.clip_tangent`), with half the
        element-wise operations, which dominate the training time on a CPU."""
        h = self.linear.forward_tangent(v, c_in)
        t = self.act(hyp.clip_tangent(torch.sparse.mm(adj, hyp.logmap0(h, c_in)), c_in))
        if self.residual:
            vs = v if self_rows is None else v[self_rows]
            t = t + hyp.logmap0(self.self_linear.forward_tangent(vs, c_in), c_in)
        return hyp.clip_tangent(t, c_out)

    def isolated_tangent(self, v: torch.Tensor, c_in: torch.Tensor, c_out: torch.Tensor) -> torch.Tensor:
        """:meth:`forward_tangent` of nodes that are graphs of their own (the normalised
        propagation matrix of a lone node with its self loop is 1)."""
        t = self.act(hyp.clip_tangent(hyp.logmap0(self.linear.forward_tangent(v, c_in), c_in), c_in))
        if self.residual:
            t = t + hyp.logmap0(self.self_linear.forward_tangent(v, c_in), c_in)
        return hyp.clip_tangent(t, c_out)


class HGCN(nn.Module):
    """Two HGCN layers; classes are scored against prototypes given as points of the output
    ball (:meth:`prototype_points` makes them from the seed centres)."""

    def __init__(self, d_in: int, hidden: int, cfg: HgcnTrainConfig) -> None:
        super().__init__()
        self.layers = nn.ModuleList([
            HGCNLayer(d_in, hidden, cfg.dropout, cfg.activation, cfg.residual),
            HGCNLayer(hidden, hidden, cfg.dropout, cfg.activation, cfg.residual),
        ])
        self.activation = cfg.activation
        self.raw_c = nn.Parameter(torch.full((3,), _softplus_inv(cfg.init_curvature)))
        self.raw_scale = nn.Parameter(torch.tensor(_softplus_inv(1.0)))

    @property
    def curvatures(self) -> torch.Tensor:
        """(3,) c of the input ball and of each layer's output ball."""
        return F.softplus(self.raw_c)

    @property
    def scale(self) -> torch.Tensor:
        return F.softplus(self.raw_scale)

    def embed_input(self, x: torch.Tensor) -> torch.Tensor:
        """Euclidean features (N, d) onto the input ball."""
        c0 = self.curvatures[0]
        return hyp.proj(hyp.expmap0(x, c0), c0)

    def forward_reference(self, x: torch.Tensor, adj1: torch.Tensor, adj2: torch.Tensor,
                          rows1: torch.Tensor | None = None, rows2: torch.Tensor | None = None) -> torch.Tensor:
        """Final embeddings computed on the ball, operation by operation as in HGCN (the
        training and inference paths use the equal tangent-space form)."""
        c = self.curvatures
        h = self.layers[0](self.embed_input(x), adj1, c[0], c[1], rows1)
        return self.layers[1](h, adj2, c[1], c[2], rows2)

    def forward_blocks(self, x_hop2: torch.Tensor, adj1: torch.Tensor, adj2: torch.Tensor,
                       rows1: torch.Tensor | None = None, rows2: torch.Tensor | None = None) -> torch.Tensor:
        """(B, hidden) final embeddings (ball points) of a batch's seeds from their 2-hop
        inputs x_hop2 (N2, d), propagation blocks and self rows (see :func:`blocks_for`)."""
        c = self.curvatures
        v = hyp.clip_tangent(x_hop2, c[0])  # log_0 of embed_input(x)
        v = self.layers[0].forward_tangent(v, adj1, c[0], c[1], rows1)
        v = self.layers[1].forward_tangent(v, adj2, c[1], c[2], rows2)
        return hyp.proj(hyp.expmap0(v, c[2]), c[2])

    @torch.no_grad()
    def embed_all(self, x: torch.Tensor, adj: torch.Tensor) -> torch.Tensor:
        """(N, hidden) final embeddings of all nodes, layer by layer over the whole graph."""
        return self.forward_blocks(x, adj, adj)

    def embed_isolated(self, x: torch.Tensor) -> torch.Tensor:
        """(N, hidden) final embeddings of nodes x (N, d) that are each a graph of its own."""
        c = self.curvatures
        v = hyp.clip_tangent(x, c[0])
        v = self.layers[0].isolated_tangent(v, c[0], c[1])
        v = self.layers[1].isolated_tangent(v, c[1], c[2])
        return hyp.proj(hyp.expmap0(v, c[2]), c[2])

    def prototype_points(self, centres: torch.Tensor) -> torch.Tensor:
        """(K, hidden) class prototypes: the seed centres (K, d) embedded as lone nodes."""
        return self.embed_isolated(centres)

    def candidate_logits(self, h: torch.Tensor, protos: torch.Tensor, cand: torch.Tensor) -> torch.Tensor:
        """(B, m) logits ``-s d(h_b, p_k)^2`` of embeddings h (B, hidden) against each row's
        candidate classes cand (B, m)."""
        c = self.curvatures[2]
        p = protos[cand]  # (B, m, hidden)
        h2 = h.pow(2).sum(-1, keepdim=True)
        p2 = p.pow(2).sum(-1)
        diff2 = (h[:, None, :] - p).pow(2).sum(-1)
        z = 1 + 2 * c * diff2 / ((1 - c * h2).clamp_min(hyp.MIN_NORM) * (1 - c * p2).clamp_min(hyp.MIN_NORM))
        return -self.scale * torch.acosh(z.clamp_min(1 + 1e-7)).pow(2) / c

    @torch.no_grad()
    def nearest(self, h: torch.Tensor, protos: torch.Tensor, k: int = 1) -> np.ndarray:
        """(N, k) int64 the k nearest prototypes of every embedding, nearest first.

        ``d`` grows with ``|h-p|^2 / (1 - c|p|^2)`` for a fixed h, so the search needs one
        matrix product and two element-wise operations per pair.
        """
        c = self.curvatures[2]
        p2 = protos.pow(2).sum(-1)
        w = 1.0 / (1.0 - c * p2).clamp_min(hyp.MIN_NORM)
        out = np.empty((len(h), k), np.int64)
        for s in range(0, len(h), _CHUNK):
            hh = h[s : s + _CHUNK]
            q = torch.addmm(p2[None, :], hh, protos.T, alpha=-2).add_(hh.pow(2).sum(-1, keepdim=True)).mul_(w)
            out[s : s + _CHUNK] = (q.argmin(1, keepdim=True) if k == 1 else q.topk(k, 1, largest=False)[1]).cpu().numpy()
        return out

    def to_numpy(self, input_scale: float) -> BallNetwork:
        """The trained layers for run-time use without torch."""
        def arr(t: torch.Tensor) -> np.ndarray:
            return t.detach().cpu().numpy().astype(np.float32)

        layers = list(self.layers)
        return BallNetwork(
            [arr(la.linear.weight) for la in layers], [arr(la.linear.bias) for la in layers],
            [arr(la.self_linear.weight) for la in layers if la.residual],
            [arr(la.self_linear.bias) for la in layers if la.residual],
            self.curvatures.detach().cpu().numpy().astype(np.float64), self.activation, float(input_scale))


def blocks_for(adj: sp.csr_matrix, seeds: np.ndarray):
    """Exact two-layer propagation blocks of ``seeds`` as torch tensors: (hop2 node ids,
    adj1, adj2, rows1, rows2); rows1 / rows2 give each layer's output nodes among its inputs."""
    hop2, (r1, c1, v1), hop1, (r2, c2, v2) = two_hop_blocks(adj, seeds)
    adj1 = sparse_tensor(r1, c1, v1, (len(hop1), len(hop2)))
    adj2 = sparse_tensor(r2, c2, v2, (len(seeds), len(hop1)))
    rows1 = torch.from_numpy(np.searchsorted(hop2, hop1).astype(np.int64))
    rows2 = torch.from_numpy(np.searchsorted(hop1, seeds).astype(np.int64))
    return torch.from_numpy(hop2.astype(np.int64)), adj1, adj2, rows1, rows2


def split_seeds(labels: np.ndarray, groups: np.ndarray | None, holdout: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(train, validation, test) labelled node ids. Seeds are split by group (nodes of one
    track together: a held-out track is unseen in training), ``holdout`` of the groups
    each for validation and test."""
    lab = np.flatnonzero(labels >= 0)
    g = lab.astype(np.int64) if groups is None else np.where(groups[lab] >= 0, groups[lab], -1 - lab)
    ug = np.unique(g)
    rng.shuffle(ug)
    n = int(round(holdout * len(ug)))
    if n == 0 or len(ug) < 3 * n:
        return lab, lab[:0], lab[:0]
    val, test = np.isin(g, ug[:n]), np.isin(g, ug[n : 2 * n])
    return lab[~(val | test)], lab[val], lab[test]


def _init_scale(model: HGCN, h: torch.Tensor, protos: torch.Tensor, target: np.ndarray, m: int) -> float:
    """Set the logit scale to the value (on a log grid) that minimises the initial loss."""
    cand, mask = _candidates(model, h, protos, target, m)
    zero = torch.zeros(len(target), dtype=torch.long, device=h.device)
    best = (math.inf, 1.0)
    with torch.no_grad():
        d2 = -model.candidate_logits(h, protos, cand) / model.scale
        for s in np.geomspace(1e-2, 1e5, 71):
            loss = F.cross_entropy((-s * d2).masked_fill(mask, -math.inf), zero).item()
            if loss < best[0]:
                best = (loss, float(s))
        model.raw_scale.fill_(_softplus_inv(best[1]))
    return best[1]


def _candidates(model: HGCN, h: torch.Tensor, protos: torch.Tensor, target: np.ndarray, m: int):
    """(B, 1 + m) target and hard-negative classes of every seed, and the mask of negatives
    equal to the target."""
    neg = model.nearest(h.detach(), protos.detach(), min(m, len(protos)))
    cand = np.concatenate([target[:, None], neg], axis=1)
    mask = np.concatenate([np.zeros((len(target), 1), bool), neg == target[:, None]], axis=1)
    return torch.from_numpy(cand).to(h.device), torch.from_numpy(mask).to(h.device)


def training_device(device: str | None = None) -> torch.device:
    """The device to train on: ``device`` as given, or for None / ``auto`` a GPU when
    torch sees one (CUDA), else the CPU."""
    if device in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except RuntimeError as exc:
        raise ConfigError(f"--device: {exc}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {device}: torch sees no CUDA GPU here; use cpu or auto")
    return dev


def train_hgcn(
    x: np.ndarray, adj: sp.csr_matrix, labels: np.ndarray, centres: np.ndarray, cfg: HgcnTrainConfig,
    groups: np.ndarray | None = None, progress: bool = True, device: str | None = None,
) -> tuple[HGCN, np.ndarray, dict]:
    """Train the HGCN on the labelled nodes and label every node.

    x: (N, d) float32 node features. adj: (N, N) normalised propagation matrix (CSR, self
    loops included). labels: (N,) int64 class in [0, K) or -1 (unlabelled). centres: (K, d)
    the seed centres (the classes' prototypes are their embeddings). groups: optional (N,)
    group of every node (-1: none; a track), kept together when seeds are held out.
    device: the torch device to train on (``cpu``, ``cuda``, ``cuda:1``, ...); None or
    ``auto``: a GPU when torch sees one, else the CPU (:func:`training_device`).
    Returns (model, (N,) int64 predicted class of every node, stats dict); the model (on
    the CPU)'s ``input_scale`` attribute holds the feature scale.
    """
    t0 = time.perf_counter()
    dev = training_device(device)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    if not np.any(labels >= 0):
        raise ValueError("no labelled node to train on")
    input_scale = float(np.mean(np.linalg.norm(x, axis=1))) / cfg.input_radius or 1.0
    xt = torch.from_numpy(np.ascontiguousarray(x / input_scale, dtype=np.float32)).to(dev)
    ct = torch.from_numpy(np.ascontiguousarray(centres / input_scale, dtype=np.float32)).to(dev)
    train, val, test = split_seeds(labels, groups, cfg.holdout, rng)
    model = HGCN(x.shape[1], cfg.hidden_dim, cfg).to(dev)
    model.input_scale = input_scale
    tb = tuple(t.to(dev) for t in blocks_for(adj, train))
    vb = tuple(t.to(dev) for t in blocks_for(adj, val)) if len(val) else None
    y = labels[train]

    def accuracy(blocks, nodes: np.ndarray) -> float:
        if blocks is None or len(nodes) == 0:
            return float("nan")
        model.eval()
        with torch.no_grad():
            h = model.forward_blocks(xt[blocks[0]], *blocks[1:])
            return float(np.mean(model.nearest(h, model.prototype_points(ct))[:, 0] == labels[nodes]))

    with torch.no_grad():
        model.eval()
        h0 = model.forward_blocks(xt[tb[0]], *tb[1:])
        scale0 = _init_scale(model, h0, model.prototype_points(ct), y, cfg.candidate_classes)
    opt = torch.optim.Adam([
        {"params": [p for n, p in model.named_parameters() if n != "raw_scale"]},
        {"params": [model.raw_scale], "lr": cfg.scale_lr},
    ], lr=cfg.lr, weight_decay=cfg.weight_decay)
    best = (accuracy(vb, val), 0, {k: v.detach().clone() for k, v in model.state_dict().items()})
    val_start = best[0]
    losses: list[float] = []
    bad, epoch = 0, 0
    bar = tqdm(range(1, cfg.epochs + 1), desc="HGCN training", unit="epoch", disable=not progress)
    for epoch in bar:
        model.train()
        protos = model.prototype_points(ct)
        h = model.forward_blocks(xt[tb[0]], *tb[1:])
        cand, mask = _candidates(model, h, protos, y, cfg.candidate_classes)
        logits = model.candidate_logits(h, protos, cand).masked_fill(mask, -math.inf)
        loss = F.cross_entropy(logits, torch.zeros(len(y), dtype=torch.long, device=dev))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        if epoch % cfg.eval_every == 0 and vb is not None:
            acc = accuracy(vb, val)
            bar.set_postfix(loss=f"{losses[-1]:.3f}", val=f"{acc:.3f}")
            if acc > best[0]:
                best, bad = (acc, epoch, {k: v.detach().clone() for k, v in model.state_dict().items()}), 0
            else:
                bad += 1
                if bad >= cfg.patience:
                    break
    if vb is not None:
        model.load_state_dict(best[2])
    model.eval()
    t_train = time.perf_counter() - t0
    adj_t = csr_to_torch(adj).to(dev)
    with torch.no_grad():
        protos = model.prototype_points(ct)
        pred = model.nearest(model.embed_all(xt, adj_t), protos)[:, 0]
        iso = model.nearest(model.embed_isolated(xt), protos)[:, 0]

    def acc_of(nodes: np.ndarray) -> float | None:
        return round(float(np.mean(pred[nodes] == labels[nodes])), 4) if len(nodes) else None

    stats = {
        "hgcn_epochs": epoch,
        "hgcn_best_epoch": best[1],
        "hgcn_train_seconds": round(t_train, 2),
        "hgcn_predict_seconds": round(time.perf_counter() - t0 - t_train, 2),
        "loss_first": round(losses[0], 4) if losses else None,
        "loss_last": round(losses[-1], 4) if losses else None,
        "logit_scale_start": round(scale0, 3),
        "seeds_train": int(len(train)), "seeds_validation": int(len(val)), "seeds_test": int(len(test)),
        "labelled_accuracy": acc_of(train),
        "validation_accuracy": acc_of(val),
        "validation_accuracy_untrained": None if val_start != val_start else round(val_start, 4),
        "heldout_accuracy": acc_of(test),
        "isolated_agreement": round(float(np.mean(iso == pred)), 4),
        "curvatures": [round(float(v), 4) for v in model.curvatures.detach()],
        "hgcn_device": str(dev),
    }
    model.to("cpu")
    log.info("HGCN: %d epochs (best %d) in %.1f s; seed accuracy train %s, validation %s, test %s",
             epoch, best[1], t_train, stats["labelled_accuracy"], stats["validation_accuracy"],
             stats["heldout_accuracy"])
    return model, pred, stats
