"""The graph network over a feature's causal track, at run time (numpy, no torch).

A keyframe's feature that is linked to a map point has a track: the point's observations
in earlier keyframes. The network (trained by
:mod:`orbslam_hgcn.vocabulary.training.track_net`) names the feature's word from its own
reduced descriptor and those of at most ``window`` of its most recent earlier track mates,
in one hyperbolic aggregation in the tangent space of the centre node (Chami et al.,
"Hyperbolic Graph Convolutional Neural Networks", NeurIPS 2019, section 4.2):

* the reduced descriptors (PCA coordinates) are scaled by ``input_scale`` and read as
  tangent vectors at the origin of the Poincare ball of curvature ``c``: the centre
  ``p = exp_0(u)``, each mate ``q_j = exp_0(W u_j + b)``;
* attention (``aggregation = "attention"``): the mate's logit is ``a . [|u - u_j|,
  u * u_j, hamming(centre, mate) / 32] + a_0``, the centre's own logit ``a_self``; a
  softmax over the centre and its mates makes the row-normalised weights ``alpha``
  (``"mean"``: all logits 0, the plain mean);
* the aggregate ``z = g * sum_j alpha_j log_p(q_j)`` (the centre's own term is zero: the
  self path is the centre point itself) moves the centre: ``o = exp_p(z)``;
* the word is the nearest seed centre (the k-means vocabulary's centroids) of
  ``log_0(o) * input_scale``, back in PCA space.

A feature without mates is its own point (``z = 0``): its word is its lone k-means word,
so frames described alone (relocalisation queries, the tracker's reference matching) and
keyframes share one word space. The gate ``g`` starts at zero: the untrained network is
the identity.

:class:`TrackNetworkWords` keeps per map point the reduced descriptors and binary
descriptors of its ``window`` most recent observations (bounded), so a keyframe's words
cost the same whatever the length of its tracks.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.vocabulary.ball import MIN_NORM, artanh, clip_tangent, expmap0, logmap0, mobius_add, norm, proj
from orbslam_hgcn.vocabulary.track_words import TrackWordsBase

# The Poincare-ball operations are those of :mod:`.ball`, in float64 with these margins.
BALL_EPS = 1e-5  # float64 projection margin, as training.hyperbolic.BALL_EPS[float64]
ARTANH_CLIP = 1e-15  # float64 margin of artanh's argument from +-1
R_MAX_UNIT = float(artanh(np.float64(1 - BALL_EPS), ARTANH_CLIP))  # tangent radius of the projection ball at c = 1
AGGREGATIONS = ("attention", "mean")
HAM_SCALE = 32.0  # Hamming distances enter the attention divided by this
POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.uint8)


def hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between binary descriptors a (..., B) and b (..., B) uint8
    (broadcast), as float64 (...)."""
    return POPCOUNT[np.bitwise_xor(a, b)].sum(-1, dtype=np.int64).astype(np.float64)


def _lambda(x: np.ndarray, c: float) -> np.ndarray:
    return 2.0 / np.maximum(1.0 - c * np.einsum("...i,...i->...", x, x)[..., None], MIN_NORM)


def _expmap(x: np.ndarray, u: np.ndarray, c: float) -> np.ndarray:
    sc, n = np.sqrt(c), norm(u)
    return mobius_add(x, np.tanh(sc * _lambda(x, c) * n / 2) * u / (sc * n), c)


def _logmap(x: np.ndarray, y: np.ndarray, c: float) -> np.ndarray:
    sc = np.sqrt(c)
    w = mobius_add(-x, y, c)
    wn = norm(w)
    return 2 / (sc * _lambda(x, c)) * artanh(sc * wn, ARTANH_CLIP) * w / wn


@dataclass
class TrackNetwork:
    """The trained track network's parameters (see the module docstring).

    weight, bias: (d, d), (d,) the mates' map. gate: (d,). att: (2d + 1,) attention
    weights, att_bias and att_self: the mates' and the centre's logit offsets.
    curvature: c > 0. input_scale: PCA coordinates are divided by it. window: mates used
    at most. aggregation: ``attention`` or ``mean``.
    """

    weight: np.ndarray
    bias: np.ndarray
    gate: np.ndarray
    att: np.ndarray
    att_bias: float
    att_self: float
    curvature: float
    input_scale: float
    window: int
    aggregation: str

    def __post_init__(self) -> None:
        f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
        self.weight, self.bias, self.gate, self.att = f64(self.weight), f64(self.bias), f64(self.gate), f64(self.att)
        self.att_bias, self.att_self = float(self.att_bias), float(self.att_self)
        self.curvature, self.input_scale, self.window = float(self.curvature), float(self.input_scale), int(self.window)
        d = self.weight.shape[0]
        if (self.weight.shape != (d, d) or self.bias.shape != (d,) or self.gate.shape != (d,)
                or self.att.shape != (2 * d + 1,)):
            raise ValueError("inconsistent track network shapes")
        if not (self.curvature > 0 and self.input_scale > 0 and self.window >= 1):
            raise ValueError("track network curvature, input scale and window must be positive")
        if self.aggregation not in AGGREGATIONS:
            raise ValueError(f"track network aggregation must be one of {AGGREGATIONS}, found {self.aggregation!r}")
        if not all(np.all(np.isfinite(a)) for a in (self.weight, self.bias, self.gate, self.att)):
            raise ValueError("non-finite track network weights")

    @property
    def dim(self) -> int:
        return self.weight.shape[0]

    def embed(self, x: np.ndarray, mates: np.ndarray, mask: np.ndarray, ham: np.ndarray) -> np.ndarray:
        """(N, d) float32 PCA-space outputs of centre features x (N, d) with mates (N, W, d)
        (rows where mask (N, W) is False are padding) at Hamming distances ham (N, W) from
        their centre. Rows without a mate return x itself."""
        c, s = self.curvature, self.input_scale
        x = np.asarray(x, np.float64).reshape(-1, self.dim)
        mates = np.asarray(mates, np.float64).reshape(len(x), -1, self.dim)
        mask = np.asarray(mask, bool).reshape(len(x), -1)
        u = clip_tangent(x / s, c, R_MAX_UNIT)
        um = clip_tangent(mates / s, c, R_MAX_UNIT)
        p = proj(expmap0(u, c), c, BALL_EPS)
        q = proj(expmap0(um @ self.weight.T + self.bias, c), c, BALL_EPS)
        t = _logmap(p[:, None, :], q, c)  # (N, W, d)
        e = np.zeros((len(x), 1 + mask.shape[1]))
        if self.aggregation == "attention":
            d = self.dim
            f = (np.abs(u[:, None, :] - um) @ self.att[:d] + (u[:, None, :] * um) @ self.att[d : 2 * d]
                 + np.asarray(ham, np.float64).reshape(mask.shape) / HAM_SCALE * self.att[2 * d])
            e[:, 0] = self.att_self
            e[:, 1:] = f + self.att_bias
        e[:, 1:][~mask] = -np.inf
        e -= e.max(1, keepdims=True)
        w = np.exp(e)
        alpha = w / w.sum(1, keepdims=True)
        z = self.gate * np.einsum("nw,nwd->nd", alpha[:, 1:], t)
        o = proj(_expmap(p, z, c), c, BALL_EPS)
        y = logmap0(o, c, ARTANH_CLIP) * s
        none = ~mask.any(1)
        y[none] = x[none]
        return y.astype(np.float32)

    def arrays(self) -> dict[str, np.ndarray]:
        """The network as named arrays (saved in the vocabulary file)."""
        return {"tracknet_weight": self.weight, "tracknet_bias": self.bias, "tracknet_gate": self.gate,
                "tracknet_att": self.att,
                "tracknet_scalars": np.array([self.att_bias, self.att_self, self.curvature, self.input_scale,
                                              self.window], np.float64),
                "tracknet_aggregation": np.array(self.aggregation)}

    @classmethod
    def from_arrays(cls, a: dict[str, np.ndarray]) -> TrackNetwork:
        """Inverse of :meth:`arrays` (KeyError or ValueError on missing or bad arrays)."""
        sc = np.asarray(a["tracknet_scalars"], np.float64)
        if sc.shape != (5,):
            raise ValueError("bad track network scalars")
        return cls(a["tracknet_weight"], a["tracknet_bias"], a["tracknet_gate"], a["tracknet_att"],
                   sc[0], sc[1], sc[2], sc[3], int(sc[4]), str(a["tracknet_aggregation"]))


class TrackNetworkWords(TrackWordsBase):
    """Causal track-network words of keyframes over a flat vocabulary holding a
    :class:`TrackNetwork` (``vocabulary.track_network``).

    Per map point it keeps the kf ids, reduced descriptors and binary descriptors of at
    most ``window + 1`` of its observations, the most recent ones (a keyframe needs
    ``window`` mates older than itself, and its own observation becomes a mate of the next).
    """

    def __init__(self, vocabulary) -> None:
        net = getattr(vocabulary, "track_network", None)
        if net is None or not hasattr(vocabulary, "words_of_points"):
            raise ValueError("track-network words need a vocabulary holding a track network (e.g. 'hgcn_graph')")
        self.network: TrackNetwork = net
        self._obs: dict[int, dict[int, tuple[np.ndarray, np.ndarray]]] = {}  # point -> kf -> (x, desc)
        super().__init__(vocabulary, self._obs)

    def inputs(
        self,
        kf_id: int,
        x: np.ndarray,
        desc: np.ndarray,
        idx: np.ndarray,
        pids: np.ndarray,
        observations: Sequence[dict[int, int]],
        descriptors_of: Callable[[int], np.ndarray],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The network's inputs for keyframe ``kf_id``'s tracked features.

        x, desc: (N, d) reduced and (N, B) binary descriptors of the keyframe. idx, pids,
        observations, descriptors_of: as for
        :meth:`~orbslam_hgcn.vocabulary.track_words.TrackWords.means`. Observations of
        keyframes after ``kf_id`` are ignored, and so is every point that the keyframe's
        own feature is not an observation of (a stale link).
        Returns ((K,) indices into idx of the features with at least one earlier mate,
        (K, W, d) mates (most recent first), (K, W) mask, (K, W) Hamming distances).
        """
        kf_id, w = int(kf_id), self.network.window
        need: list[tuple[int, int, int]] = []  # (point, kf, feature) observations to fetch
        live: list[int] = []
        for k, (pid, obs) in enumerate(zip(pids.tolist(), observations)):
            if obs.get(kf_id) != int(idx[k]):
                continue
            live.append(k)
            cached = self._obs.setdefault(pid, {})
            recent = sorted((j for j in obs if j <= kf_id), reverse=True)[: w + 1]
            need.extend((pid, j, obs[j]) for j in recent if j not in cached)
        self._fetch(kf_id, x, desc, need, descriptors_of)
        rows, mates, mask, ham = [], [], [], []
        for k in live:
            pid = int(pids[k])
            cached = self._obs[pid]
            older = sorted((j for j in cached if j < kf_id), reverse=True)[:w]
            for j in sorted(cached)[: max(0, len(cached) - (w + 1))]:
                del cached[j]  # bounded: the w + 1 most recent observations
            if not older:
                continue
            m = np.zeros((w, x.shape[1]), np.float32)
            b = np.zeros((w, desc.shape[1]), np.uint8)
            for r, j in enumerate(older):
                m[r], b[r] = cached[j]
            rows.append(k)
            mates.append(m)
            mask.append(np.arange(w) < len(older))
            ham.append(hamming_rows(desc[int(idx[k])][None, :], b))
        if not rows:
            d = x.shape[1]
            return np.zeros(0, np.int64), np.zeros((0, w, d), np.float32), np.zeros((0, w), bool), np.zeros((0, w))
        return np.array(rows, np.int64), np.stack(mates), np.stack(mask), np.stack(ham)

    def _fetch(self, kf_id: int, x: np.ndarray, desc: np.ndarray, need: list[tuple[int, int, int]],
               descriptors_of: Callable[[int], np.ndarray]) -> None:
        """Cache the reduced and binary descriptors of observations (point, kf, feature)."""
        by_kf: dict[int, list[tuple[int, int]]] = {}
        for pid, j, i in need:
            by_kf.setdefault(j, []).append((pid, i))
        for j, items in by_kf.items():
            feats = np.array([i for _, i in items], np.int64)
            if j == kf_id:
                xs, ds = x[feats], desc[feats]
            else:
                ds = descriptors_of(j)[feats]
                xs = self.vocabulary.project(ds)
            for (pid, _), xv, dv in zip(items, xs, ds):
                self._obs[pid][j] = (np.asarray(xv, np.float32), np.asarray(dv, np.uint8))

    def track_points(self, kf_id, x, desc, idx, pids, observations, descriptors_of):
        """The network's outputs for the features with at least one earlier mate (:meth:`inputs`)."""
        rows, mates, mask, ham = self.inputs(kf_id, x, desc, idx, pids, observations, descriptors_of)
        if not len(rows):
            return rows, np.zeros((0, x.shape[1]), np.float32)
        return rows, self.network.embed(x[idx[rows]], mates, mask, ham)


def window_inputs(x: list[np.ndarray], desc: list[np.ndarray], tracks: list[np.ndarray], window: int,
                  mates: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """The network's inputs for a sequence of keyframes given as per-keyframe reduced
    descriptors x, binary descriptors desc and track ids (-1: none), as
    :meth:`TrackNetworkWords.inputs` gives them: per keyframe k, (rows of its features
    with a track member in keyframes k - window + 1 .. k - 1, (R, mates, d) the ``mates``
    most recent such members, (R, mates) mask, (R, mates) Hamming distances)."""
    out = []
    d = x[0].shape[1] if x else 0
    for k in range(len(x)):
        latest: dict[int, list[tuple[int, int]]] = {}
        for j in range(k - 1, max(0, k - window + 1) - 1, -1):
            for i in np.flatnonzero(tracks[j] >= 0).tolist():
                lst = latest.setdefault(int(tracks[j][i]), [])
                if len(lst) < mates:
                    lst.append((j, i))
        rows = [r for r in np.flatnonzero(tracks[k] >= 0).tolist() if int(tracks[k][r]) in latest]
        m = np.zeros((len(rows), mates, d), np.float32)
        mask = np.zeros((len(rows), mates), bool)
        ham = np.zeros((len(rows), mates))
        for n, r in enumerate(rows):
            for s, (j, i) in enumerate(latest[int(tracks[k][r])]):
                m[n, s], mask[n, s] = x[j][i], True
                ham[n, s] = hamming_rows(desc[k][r], desc[j][i])
        out.append((np.array(rows, np.int64), m, mask, ham))
    return out


def window_words(vocabulary, desc: list[np.ndarray], tracks: list[np.ndarray], window: int) -> list[np.ndarray]:
    """Per keyframe of a sequence, its (N,) int32 words from the vocabulary's track network
    over the causal track mates of :func:`window_inputs` (features without one keep their
    lone words). desc: per keyframe (N, B) descriptors; tracks: per keyframe (N,) track ids."""
    net: TrackNetwork = vocabulary.track_network
    x = [vocabulary.project(d) for d in desc]
    out = []
    for xi, (rows, mates, mask, ham) in zip(x, window_inputs(x, desc, tracks, window, net.window)):
        w = vocabulary.words_of_points(xi)
        if len(rows):
            w[rows] = vocabulary.words_of_points(net.embed(xi[rows], mates, mask, ham))
        out.append(w)
    return out
