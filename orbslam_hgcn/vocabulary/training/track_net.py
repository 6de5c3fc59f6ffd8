"""Training the graph network over causal feature tracks (torch).

The model is :class:`~orbslam_hgcn.vocabulary.track_network.TrackNetwork` (its docstring
gives the layer); this module holds its torch form and the training.

Objective, one the identity does not solve: a node is a tracked descriptor (the centre)
with a partial, causal track: its ``L`` most recent earlier track members, ``L`` drawn
uniformly from 1..min(W, members before it) anew every epoch (L = 0 is the lone
descriptor, which the network leaves unchanged by construction, so it carries no
gradient); the target is the seed word of the full track's mean (the nearest seed centre
of the mean of all the track's reduced descriptors). The untrained network (gate 0) gives
the centre's lone word.

Training: Adam (lr ``lr``, 0.01 as the reference HGCN), minibatches over at most
``max_nodes`` centres drawn from the training tracks (a subsample when there are more),
softmax over the target and the ``candidates`` seed centres nearest to each output
(hard negatives, refreshed every step), a trainable logit scale started at the best value of a line
search. Held-out tracks (``holdout`` of them, whole tracks) with cuts drawn once give the
validation accuracy after every epoch; the best epoch is chosen among epochs 1.. only (the
untrained state is never a candidate), and training stops when it has not improved for
``patience`` epochs, never before ``min_epochs``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from orbslam_hgcn.vocabulary.track_network import AGGREGATIONS, HAM_SCALE, POPCOUNT, TrackNetwork
from orbslam_hgcn.vocabulary.training import hyperbolic as hyp

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class TrackNetConfig:
    """Settings of :func:`train_track_network`."""

    window: int = 8  # mates at most (the most recent earlier track members)
    aggregation: str = "attention"  # or "mean" (all attention logits 0)
    input_radius: float = 0.5  # mean norm of the scaled input
    init_curvature: float = 1.0
    lr: float = 0.01
    epochs: int = 40
    min_epochs: int = 20
    patience: int = 10
    batch: int = 2048
    max_nodes: int = 60_000  # training centres at most (subsampled)
    max_validation: int = 10_000
    holdout: float = 0.1  # share of the tracks held out for validation
    candidates: int = 32  # hard negatives per centre (nearest to its output); 0: every seed centre
    seed: int = 0


def _softplus_inv(y: float) -> float:
    return y + math.log(-math.expm1(-y))


class TorchTrackNet(nn.Module):
    """The track network in torch (the same operations as :meth:`TrackNetwork.embed`)."""

    def __init__(self, d: int, cfg: TrackNetConfig, input_scale: float) -> None:
        super().__init__()
        if cfg.aggregation not in AGGREGATIONS:
            raise ValueError(f"aggregation must be one of {AGGREGATIONS}, found {cfg.aggregation!r}")
        self.aggregation = cfg.aggregation
        self.window = cfg.window
        self.input_scale = float(input_scale)
        self.weight = nn.Parameter(torch.eye(d))
        self.bias = nn.Parameter(torch.zeros(d))
        self.gate = nn.Parameter(torch.zeros(d))
        att = cfg.aggregation == "attention"
        self.att = nn.Parameter(torch.zeros(2 * d + 1), requires_grad=att)
        self.att_bias = nn.Parameter(torch.zeros(()), requires_grad=att)
        self.att_self = nn.Parameter(torch.zeros(()), requires_grad=att)
        self.raw_c = nn.Parameter(torch.tensor(_softplus_inv(cfg.init_curvature)))
        self.raw_scale = nn.Parameter(torch.tensor(0.0))

    @property
    def c(self) -> torch.Tensor:
        return F.softplus(self.raw_c)

    @property
    def scale(self) -> torch.Tensor:
        """The logit scale, ``exp(raw)``: Adam's steps change it by a share of its value, so
        it can grow by orders of magnitude as the outputs near their targets."""
        return torch.exp(self.raw_scale)

    def forward(self, x: torch.Tensor, mates: torch.Tensor, mask: torch.Tensor, ham: torch.Tensor) -> torch.Tensor:
        """(N, d) outputs in scaled PCA units (``log_0(o)``) of centres x (N, d) and mates
        (N, W, d) in scaled PCA units, mask (N, W) bool, Hamming distances ham (N, W)."""
        c = self.c
        u = hyp.clip_tangent(x, c)
        um = hyp.clip_tangent(mates, c)
        p = hyp.proj(hyp.expmap0(u, c), c)
        q = hyp.proj(hyp.expmap0(um @ self.weight.T + self.bias, c), c)
        t = hyp.logmap(p[:, None, :], q, c)
        e = torch.zeros(len(x), 1 + mask.shape[1], dtype=x.dtype, device=x.device)
        if self.aggregation == "attention":
            d = x.shape[1]
            f = ((u[:, None, :] - um).abs() @ self.att[:d] + (u[:, None, :] * um) @ self.att[d : 2 * d]
                 + ham / HAM_SCALE * self.att[2 * d])
            e = torch.cat([self.att_self.expand(len(x), 1), f + self.att_bias], 1)
        e = e.masked_fill(torch.cat([torch.zeros_like(mask[:, :1]), ~mask], 1), -math.inf)
        alpha = torch.softmax(e, 1)
        z = self.gate * torch.einsum("nw,nwd->nd", alpha[:, 1:], t)
        o = hyp.proj(hyp.expmap(p, z, c), c)
        y = hyp.logmap0(o, c)
        return torch.where(mask.any(1, keepdim=True), y, x)

    def to_numpy(self) -> TrackNetwork:
        def arr(t: torch.Tensor) -> np.ndarray:
            return t.detach().cpu().numpy().astype(np.float64)

        return TrackNetwork(arr(self.weight), arr(self.bias), arr(self.gate), arr(self.att),
                            float(self.att_bias.detach()), float(self.att_self.detach()), float(self.c.detach()),
                            self.input_scale, self.window, self.aggregation)


@dataclasses.dataclass
class TrackNodes:
    """Centres with their causal mates: centre rows (N,), mates (N, W) rows (-1 padding),
    available (N,) earlier members (capped at W), Hamming distances (N, W), target (N,)."""

    centre: np.ndarray
    mates: np.ndarray
    available: np.ndarray
    ham: np.ndarray
    target: np.ndarray
    track: np.ndarray


def track_nodes(track_ids: np.ndarray, desc: np.ndarray | None, window: int, track_target: np.ndarray,
                centre_ok: np.ndarray | None = None) -> TrackNodes:
    """Every tracked row with at least one earlier member (rows in causal order) as a
    centre: its ``window`` most recent earlier members, their Hamming distances to it
    (desc (M, B) uint8; None: zeros), and its track's target ``track_target[track]``.
    centre_ok: optional (M,) rows allowed as centres."""
    track_ids = np.asarray(track_ids, np.int64)
    rows = np.flatnonzero(track_ids >= 0)
    order = rows[np.argsort(track_ids[rows], kind="stable")]
    t = track_ids[order]
    start = np.r_[0, np.flatnonzero(t[1:] != t[:-1]) + 1]
    first = np.repeat(start, np.diff(np.r_[start, len(order)]))
    pos = np.arange(len(order)) - first
    keep = pos >= 1
    if centre_ok is not None:
        keep &= np.asarray(centre_ok, bool)[order]
    k = np.flatnonzero(keep)
    back = k[:, None] - 1 - np.arange(window)[None, :]
    valid = back >= first[k][:, None]
    mates = np.where(valid, order[np.maximum(back, 0)], -1)
    centre = order[k]
    if desc is not None:
        ham = POPCOUNT[np.bitwise_xor(desc[centre][:, None, :], desc[np.maximum(mates, 0)])].sum(-1, dtype=np.int64)
        ham = np.where(valid, ham, 0).astype(np.float32)
    else:
        ham = np.zeros(mates.shape, np.float32)
    return TrackNodes(centre, mates, np.minimum(pos[k], window), ham, np.asarray(track_target)[t[k]], t[k])


def full_track_targets(x: np.ndarray, track_ids: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(T,) the nearest seed centre of each track's mean of x."""
    from orbslam_hgcn.vocabulary.flat import nearest

    tr = np.asarray(track_ids, np.int64)
    ok = tr >= 0
    n = int(tr.max()) + 1 if ok.any() else 0
    sums = np.zeros((n, x.shape[1]))
    np.add.at(sums, tr[ok], x[ok])
    means = sums / np.maximum(np.bincount(tr[ok], minlength=n), 1)[:, None]
    return nearest(means.astype(np.float32), centres).astype(np.int64)


def _nearest_rows(y: torch.Tensor, centres: torch.Tensor, k: int) -> np.ndarray:
    """(N, k) int64 the k nearest centres (Euclidean) of every row of y, nearest first."""
    out = []
    c2 = centres.pow(2).sum(1)
    with torch.no_grad():
        for s in range(0, len(y), 4096):
            d = torch.addmm(c2[None, :], y[s : s + 4096], centres.T, alpha=-2)
            out.append(d.topk(k, 1, largest=False)[1].cpu().numpy())
    return np.concatenate(out) if out else np.zeros((0, k), np.int64)


def _cut(nodes: TrackNodes, idx: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(n, W) mask of a random causal cut: the L most recent mates, L uniform in 1..available."""
    lengths = rng.integers(1, nodes.available[idx] + 1)
    return np.arange(nodes.mates.shape[1])[None, :] < lengths[:, None]


def _batch(nodes: TrackNodes, idx: np.ndarray, mask: np.ndarray, xt: torch.Tensor):
    m = torch.from_numpy(np.maximum(nodes.mates[idx], 0))
    return (xt[torch.from_numpy(nodes.centre[idx])], xt[m], torch.from_numpy(mask),
            torch.from_numpy(nodes.ham[idx]))


def train_track_network(
    x: np.ndarray, track_ids: np.ndarray, centres: np.ndarray, cfg: TrackNetConfig | None = None,
    desc: np.ndarray | None = None, track_target: np.ndarray | None = None, centre_ok: np.ndarray | None = None,
    device: str | None = None,
) -> tuple[TrackNetwork, dict]:
    """Train the track network.

    x: (M, d) reduced descriptors, rows in causal order within each track. track_ids: (M,)
    track of every row (-1: none). centres: (K, d) the seed centres (the words). desc:
    optional (M, B) uint8 binary descriptors (the attention's Hamming distances).
    track_target: optional (T,) word of every track (default: the nearest centre of the
    full track's mean). centre_ok: optional (M,) rows allowed as centres.
    device: torch device (None / ``auto``: a GPU when torch sees one).
    Returns the numpy network and the training figures.
    """
    from orbslam_hgcn.vocabulary.training.hgcn import training_device

    cfg = cfg or TrackNetConfig()
    t0 = time.perf_counter()
    dev = training_device(device)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    x = np.asarray(x, np.float32)
    if track_target is None:
        track_target = full_track_targets(x, track_ids, centres)
    nodes = track_nodes(track_ids, desc, cfg.window, track_target, centre_ok)
    if len(nodes.centre) == 0:
        raise ValueError("no tracked descriptor with an earlier track member to train on")
    utracks = np.unique(nodes.track)
    rng.shuffle(utracks)
    n_val = int(round(cfg.holdout * len(utracks)))
    is_val = np.isin(nodes.track, utracks[:n_val])
    train_idx, val_idx = np.flatnonzero(~is_val), np.flatnonzero(is_val)
    n_train_all = len(train_idx)
    if len(train_idx) > cfg.max_nodes:
        train_idx = np.sort(rng.choice(train_idx, cfg.max_nodes, replace=False))
    if len(val_idx) > cfg.max_validation:
        val_idx = np.sort(rng.choice(val_idx, cfg.max_validation, replace=False))
    input_scale = float(np.mean(np.linalg.norm(x, axis=1))) / cfg.input_radius or 1.0
    xt = torch.from_numpy(x / input_scale).to(dev)
    ct = torch.from_numpy(np.asarray(centres, np.float32) / input_scale).to(dev)
    model = TorchTrackNet(x.shape[1], cfg, input_scale).to(dev)
    n_cand = min(cfg.candidates, len(centres))
    val_mask = _cut(nodes, val_idx, rng)
    val_batches = [(val_idx[s : s + cfg.batch], val_mask[s : s + cfg.batch]) for s in range(0, len(val_idx), cfg.batch)]

    def predict(idx: np.ndarray, mask: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            y = model(*(t.to(dev) for t in _batch(nodes, idx, mask, xt)))
        return _nearest_rows(y, ct, 1)[:, 0]

    def val_accuracy() -> float:
        model.eval()
        hits = sum(int(np.sum(predict(i, m) == nodes.target[i])) for i, m in val_batches)
        return hits / max(len(val_idx), 1)

    c2 = ct.pow(2).sum(1)

    def logits_of(y: torch.Tensor, idx: np.ndarray):
        """(squared distances to the classes scored, mask of classes left out, column of the target)."""
        if cfg.candidates <= 0:  # the full softmax over every seed centre
            d2 = torch.addmm(c2[None, :], y, ct.T, alpha=-2).add(y.pow(2).sum(1, keepdim=True))
            return d2, torch.zeros_like(d2, dtype=torch.bool), torch.from_numpy(nodes.target[idx]).to(dev)
        target = nodes.target[idx]
        near = _nearest_rows(y.detach(), ct, n_cand)
        cand = torch.from_numpy(np.concatenate([target[:, None], near], 1)).to(dev)
        same = torch.from_numpy(np.concatenate([np.zeros((len(idx), 1), bool), near == target[:, None]], 1)).to(dev)
        d2 = (y[:, None, :] - ct[cand]).pow(2).sum(-1)
        return d2, same, torch.zeros(len(idx), dtype=torch.long, device=dev)

    # Figures of the validation nodes before training: lone word, the word of the partial
    # track's mean (what track averaging gives), the untrained network.
    vx = x[nodes.centre[val_idx]].astype(np.float64)
    vm = np.where(val_mask[:, :, None], x[np.maximum(nodes.mates[val_idx], 0)], 0.0).sum(1)
    partial_mean = ((vx + vm) / (1 + val_mask.sum(1))[:, None]).astype(np.float32)
    from orbslam_hgcn.vocabulary.flat import nearest

    lone_acc = float(np.mean(nearest(vx.astype(np.float32), centres) == nodes.target[val_idx]))
    mean_acc = float(np.mean(nearest(partial_mean, centres) == nodes.target[val_idx]))
    untrained = val_accuracy()
    # Logit scale: the best initial loss on a log grid.
    with torch.no_grad():
        i0 = train_idx[: cfg.batch]
        y0 = model(*(t.to(dev) for t in _batch(nodes, i0, _cut(nodes, i0, rng), xt)))
        d2, same, zero = logits_of(y0, i0)
        s0 = min(np.geomspace(1e-2, 1e4, 61),
                 key=lambda s: float(F.cross_entropy((-s * d2).masked_fill(same, -math.inf), zero)))
        model.raw_scale.fill_(math.log(float(s0)))
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=cfg.lr)
    best = (-1.0, 0, None)
    history: list[float] = []
    losses: list[float] = []
    epoch = 0
    for epoch in range(1, cfg.epochs + 1):
        model.train()
        perm = rng.permutation(train_idx)
        total = 0.0
        for s in range(0, len(perm), cfg.batch):
            idx = perm[s : s + cfg.batch]
            y = model(*(t.to(dev) for t in _batch(nodes, idx, _cut(nodes, idx, rng), xt)))
            d2, same, col = logits_of(y, idx)
            loss = F.cross_entropy((-model.scale * d2).masked_fill(same, -math.inf), col)
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        losses.append(total / len(perm))
        acc = val_accuracy()
        history.append(acc)
        if acc > best[0]:
            best = (acc, epoch, {k: v.detach().clone() for k, v in model.state_dict().items()})
        log.info("track network epoch %d: loss %.4f, validation %.4f (best %.4f at %d)", epoch, losses[-1], acc,
                 best[0], best[1])
        if epoch >= cfg.min_epochs and epoch - best[1] >= cfg.patience:
            break
    model.load_state_dict(best[2])
    model.to("cpu")
    stats = {
        "epochs": epoch, "best_epoch": best[1], "train_seconds": round(time.perf_counter() - t0, 1),
        "validation_accuracy": round(best[0], 4), "validation_accuracy_untrained": round(untrained, 4),
        "validation_lone_word": round(lone_acc, 4), "validation_partial_mean_word": round(mean_acc, 4),
        "loss_first": round(losses[0], 4), "loss_last": round(losses[-1], 4),
        "centres_train": int(len(train_idx)), "centres_train_available": int(n_train_all),
        "centres_validation": int(len(val_idx)), "curvature": round(float(model.c.detach()), 4),
        "gate_mean": round(float(model.gate.detach().mean()), 4), "device": str(dev),
        "logit_scale_start": round(float(s0), 3), "logit_scale": round(float(model.scale.detach()), 3),
        "validation_history": [round(a, 4) for a in history],
    }
    return model.to_numpy(), stats
