"""FAB-MAP 2.0 observation likelihoods over an inverted index.

Model (Cummins & Newman, IJRR 2008 "FAB-MAP: probabilistic localization and mapping in the
space of appearance", and IJRR 2011 "Appearance-only SLAM at large scale with FAB-MAP 2.0"):

- an observation is the binary vector ``Z = (z_1 .. z_V)`` of words seen in an image;
- each word has a hidden scene element ``e_q``; the detector model is
  ``p(z_q = 1 | e_q = 1) = PzGe`` and ``p(z_q = 1 | e_q = 0) = PzGNe``;
- words depend on one another through a Chow-Liu tree, and given ``e_q`` the observation
  follows ``p(z_q | e_q, z_p) = (1 + a / b)^-1`` with
  ``a = p(z_q) p(~z_q | e_q) p(~z_q | z_p)`` and ``b = p(~z_q) p(z_q | e_q) p(z_q | z_p)``
  (``p(z_q)`` the marginal, ``z_p`` the parent's state; the root uses its marginal);
- a place ``L`` is one stored observation; FAB-MAP 2.0 restricts its appearance model to
  ``p(e_q = 1 | L) = p(e_q = 1 | z_q^L)``, by Bayes from the detector model and the marginal,
  so it takes one of two values per word depending on whether ``L`` saw the word;
- ``p(Z | L) = prod_q sum_e p(z_q | e, z_p) p(e_q = e | L)``.

Because a place's model only depends on which words it saw, ``log p(Z | L)`` equals a
baseline common to all places (every word unseen) plus, for each word ``q`` the place saw,
``R_q(z_q, z_p) = log T_q(z_q, z_p, seen) - log T_q(z_q, z_p, unseen)``. Most words of a
query are ``(z_q, z_p) = (0, 0)``, so each place keeps the default ``sum_{q in L} d1_q`` with
``d1 = R(0, 0)``, and a query only corrects the places that saw one of its observed words
(``d3 = R(1, 0) - d1``, ``d4 = R(1, 1) - d1``) or an unobserved child of one of them
(``d2 = R(0, 1) - d1``), through the inverted index (FAB-MAP 2.0, sec. 3): the cost grows
with the number of observed words and their postings, not with the vocabulary size.

Defaults of the detector model follow openFABMAP (Glover et al., ICRA 2012; its
``samples/settings.yml``: PzGe 0.39, PzGNe 0).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.special import logsumexp

from orbslam_hgcn.errors import ConfigError
from orbslam_hgcn.placerec.chow_liu import ChowLiuTree
from orbslam_hgcn.placerec.words import as_binary_csr

log = logging.getLogger(__name__)


def detector_table(p_z_given_e: float, p_z_given_not_e: float) -> np.ndarray:
    """(2, 2) detector model ``D[z, e] = p(z_q = z | e_q = e)``."""
    if not (0.0 < p_z_given_e < 1.0) or not (0.0 <= p_z_given_not_e < p_z_given_e):
        raise ConfigError(
            f"fabmap: need 0 < p_z_given_e < 1 and 0 <= p_z_given_not_e < p_z_given_e, "
            f"found {p_z_given_e}, {p_z_given_not_e}"
        )
    return np.array([[1.0 - p_z_given_not_e, 1.0 - p_z_given_e], [p_z_given_not_e, p_z_given_e]])


def observation_tables(tree: ChowLiuTree, D: np.ndarray, p_e_given_place: np.ndarray) -> np.ndarray:
    """(V, 2, 2, K) ``T[q, z, zp, k] = p(z_q = z | z_p = zp, place model k)``.

    p_e_given_place: (V, K) ``p(e_q = 1 | place model k)`` for K place models.
    """
    m = tree.p_z  # (V,) marginal p(z_q = 1)
    cond = np.stack([tree.p_z_given_not_p, tree.p_z_given_p], axis=1)  # (V, 2): p(z_q = 1 | zp)
    v = tree.n_words
    # p(z_q = z | e, zp) for z, e, zp in {0, 1}: (V, z, e, zp)
    pz = np.empty((v, 2, 2, 2))
    for z in (0, 1):
        pm_z = m if z else 1.0 - m  # p(z_q = z)
        pm_nz = 1.0 - pm_z
        for e in (0, 1):
            for zp in (0, 1):
                pc_z = cond[:, zp] if z else 1.0 - cond[:, zp]  # p(z_q = z | zp)
                a = pm_z * D[1 - z, e] * (1.0 - pc_z)
                b = pm_nz * D[z, e] * pc_z
                pz[:, z, e, zp] = b / (a + b)
    pe1 = p_e_given_place[:, None, None, :]  # (V, 1, 1, K)
    return pz[:, :, 0, :, None] * (1.0 - pe1) + pz[:, :, 1, :, None] * pe1


@dataclass(frozen=True, eq=False)
class PlaceIndex:
    """Inverted index of places (each one binary observation).

    postings: (V, n_places) CSR, row q lists the places that saw word q
    defaults: (n_places,) float64 ``sum of d1`` over each place's words
    """

    postings: sp.csr_matrix
    defaults: np.ndarray

    @property
    def n_places(self) -> int:
        return len(self.defaults)


@dataclass(frozen=True, eq=False)
class QueryPattern:
    """The words of a query whose ``(z_q, z_p)`` is not ``(0, 0)``.

    words: (k,) int64 word ids; z: (k,) int8 ``z_q``; zp: (k,) int8 parent's ``z``.
    """

    words: np.ndarray
    z: np.ndarray
    zp: np.ndarray


def _gather_rows(csr: sp.csr_matrix, rows: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column indices of the given CSR rows, concatenated, with each row's weight repeated."""
    starts = csr.indptr[rows]
    lens = csr.indptr[rows + 1] - starts
    total = int(lens.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    offsets = np.repeat(starts - np.concatenate(([0], np.cumsum(lens)[:-1])), lens)
    pos = offsets + np.arange(total)
    return csr.indices[pos], np.repeat(weights, lens)


def _dependent_children(tree: ChowLiuTree) -> sp.csr_matrix:
    """(V, V) CSR: row p lists the children q of p with p(z_q | z_p) depending on z_p."""
    q = np.flatnonzero((tree.parent >= 0) & (tree.p_z_given_p != tree.p_z_given_not_p))
    data = np.ones(len(q), dtype=np.int8)
    return sp.csr_matrix((data, (tree.parent[q], q)), shape=(tree.n_words, tree.n_words))


class FabMap2:
    """FAB-MAP 2.0 likelihoods of observations against indexed places.

    tree: the Chow-Liu tree learned on training data; p_z_given_e / p_z_given_not_e: the
    detector model. ``train``: (N, V) training occurrences, needed for the sampled
    new-place model (openFABMAP's "Sampled": the mean likelihood of ``num_samples``
    training places drawn once with ``seed``). Queries use a scratch buffer: one instance
    serves one thread.
    """

    def __init__(
        self,
        tree: ChowLiuTree,
        p_z_given_e: float = 0.39,
        p_z_given_not_e: float = 0.0,
        *,
        train: sp.spmatrix | np.ndarray | None = None,
        num_samples: int = 1000,
        seed: int = 0,
    ) -> None:
        self.tree = tree
        self.D = detector_table(p_z_given_e, p_z_given_not_e)
        m = tree.p_z
        # p(e_q = 1 | place saw z_q^L), Bayes on the detector model with prior p(z_q): (V, 2)
        pe = np.empty((tree.n_words, 2))
        for zl in (0, 1):
            a = self.D[zl, 1] * m
            b = self.D[zl, 0] * (1.0 - m)
            pe[:, zl] = a / (a + b)
        self.p_e_given_seen = pe
        # Mean-field place (FAB-MAP 1, sec. 4.1; openFABMAP's MEAN_FIELD): every element at its
        # prior p(e_q = 1) = p(z_q), the prior the place model above uses; it is also the mean
        # of p(e_q | z_q^L) over places whose z_q^L follow the model's own predictive law.
        pe_avg = m
        T = observation_tables(tree, self.D, np.column_stack([pe[:, 0], pe[:, 1], pe_avg]))
        logT = np.log(T)  # (V, 2, 2, 3): place unseen, seen, mean field
        self.log_t0 = logT[..., 0]  # (V, 2, 2) baseline: the place did not see the word
        self.R = logT[..., 1] - logT[..., 0]  # (V, 2, 2) gain of a place that saw the word
        self.G_mf = logT[..., 2] - logT[..., 0]  # (V, 2, 2) mean-field place over baseline
        self.d1 = self.R[:, 0, 0].copy()
        self.d2 = self.R[:, 0, 1] - self.d1
        self.d3 = self.R[:, 1, 0] - self.d1
        self.d4 = self.R[:, 1, 1] - self.d1
        # Children whose conditional does not depend on their parent (words that never varied
        # in training hang under the root that way) contribute exactly nothing when the parent
        # is seen and they are not, so they are left out of the queries' patterns.
        self._children = _dependent_children(tree)
        self._parent = tree.parent
        self._mf_default = float(self.G_mf[:, 0, 0].sum())
        self._base_default = float(self.log_t0[:, 0, 0].sum())
        self._scratch = np.zeros(tree.n_words, dtype=bool)
        self.sample_index: PlaceIndex | None = None
        if train is not None:
            X = as_binary_csr(train)
            rng = np.random.default_rng(seed)
            k = min(num_samples, X.shape[0])
            pick = np.sort(rng.choice(X.shape[0], size=k, replace=False))
            self.sample_index = self.build_index(X[pick])

    @property
    def n_words(self) -> int:
        return self.tree.n_words

    # -- index ---------------------------------------------------------------------------

    def build_index(self, places: sp.spmatrix | np.ndarray) -> PlaceIndex:
        """Index places given as (n_places, V) binary occurrences (one image per place)."""
        X = as_binary_csr(places)
        if X.shape[1] != self.n_words:
            raise ValueError(f"places have {X.shape[1]} words, the tree has {self.n_words}")
        defaults = np.asarray(X @ self.d1).ravel()
        postings = X.T.tocsr()
        postings.sort_indices()
        return PlaceIndex(postings=postings, defaults=defaults)

    # -- queries -------------------------------------------------------------------------

    def pattern(self, observed: np.ndarray) -> QueryPattern:
        """The non-default words of a query given its observed word ids (any order, repeats ok)."""
        obs = np.unique(np.asarray(observed, dtype=np.int64))
        z = self._scratch
        z[obs] = True
        try:
            par = self._parent[obs]
            zp_obs = np.where(par >= 0, z[np.maximum(par, 0)], False)
            ch = _gather_rows(self._children, obs, np.zeros(len(obs)))[0]
            kids = ch[~z[ch]]
        finally:
            z[obs] = False
        words = np.concatenate([obs, kids])
        zq = np.concatenate([np.ones(len(obs), np.int8), np.zeros(len(kids), np.int8)])
        zp = np.concatenate([zp_obs.astype(np.int8), np.ones(len(kids), np.int8)])
        return QueryPattern(words, zq, zp)

    def _index_scores(self, pat: QueryPattern, index: PlaceIndex) -> np.ndarray:
        adj = self.R[pat.words, pat.z, pat.zp] - self.d1[pat.words]
        places, w = _gather_rows(index.postings, pat.words, adj)
        return index.defaults + np.bincount(places, weights=w, minlength=index.n_places)

    def baseline(self, pat: QueryPattern) -> float:
        """``log p(Z | L)`` of a place that saw none of the words (common to all places)."""
        t = self.log_t0[pat.words, pat.z, pat.zp] - self.log_t0[pat.words, 0, 0]
        return self._base_default + float(t.sum())

    def log_likelihoods(
        self, observed: np.ndarray | QueryPattern, index: PlaceIndex, *, absolute: bool = False
    ) -> np.ndarray:
        """(n_places,) ``log p(Z | L_i)`` of a query against every indexed place.

        Relative to the all-unseen baseline (which cancels in the posterior) unless
        ``absolute``. ``observed``: (k,) observed word ids, or a precomputed pattern.
        """
        pat = observed if isinstance(observed, QueryPattern) else self.pattern(observed)
        scores = self._index_scores(pat, index)
        return scores + self.baseline(pat) if absolute else scores

    def new_place_log_likelihood(
        self, observed: np.ndarray | QueryPattern, method: str = "mean_field", *, absolute: bool = False
    ) -> float:
        """``log p(Z | L_new)``: the mean-field average place, or the mean likelihood of
        sampled training places (``method="sampled"``, FAB-MAP 2.0's choice)."""
        pat = observed if isinstance(observed, QueryPattern) else self.pattern(observed)
        if method == "mean_field":
            g = self.G_mf[pat.words, pat.z, pat.zp] - self.G_mf[pat.words, 0, 0]
            rel = self._mf_default + float(g.sum())
        elif method == "sampled":
            if self.sample_index is None or self.sample_index.n_places == 0:
                raise ConfigError("fabmap: the sampled new-place model needs training images")
            ll = self._index_scores(pat, self.sample_index)
            rel = float(logsumexp(ll) - np.log(len(ll)))
        else:
            raise ConfigError(f"fabmap: unknown new-place model {method!r}; use mean_field or sampled")
        return rel + self.baseline(pat) if absolute else rel
