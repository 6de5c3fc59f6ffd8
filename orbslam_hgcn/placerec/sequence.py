"""Sequential FAB-MAP localisation over a test sequence: prior, posterior, confusion matrix.

Every test image becomes a place (openFABMAP's "add all" policy). Query ``i`` is compared
with the places ``j <= i - min_gap``; its posterior over those places and a new place is

    p(L_j | Z^i) ∝ p(Z_i | L_j) p(L_j | Z^{i-1}),   p(L_new | Z^i) ∝ p(Z_i | L_new) p_new

with a motion-model prior (FAB-MAP, Cummins & Newman IJRR 2008 sec. 4; the kernel as in
openFABMAP): the previous posterior mass at place ``j`` moves to ``j + 1`` with weight
``2 (1 - bias) / 3``, stays with ``1 / 3`` and moves to ``j - 1`` with ``2 bias / 3``; mass
that was on a new place or lands on a place not yet comparable is spread uniformly, as is a
``prior_spread`` share of the whole; ``p_new`` goes to a new place.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.special import logsumexp
from tqdm import tqdm

from orbslam_hgcn.config import FabmapConfig
from orbslam_hgcn.errors import ConfigError
from orbslam_hgcn.placerec.fabmap import FabMap2, detector_table
from orbslam_hgcn.placerec.words import as_binary_csr

log = logging.getLogger(__name__)


def check_config(cfg: FabmapConfig) -> FabmapConfig:
    """A ConfigError (naming the ``fabmap.<key>``) for out-of-range settings."""
    problems = {
        "new_place": cfg.new_place not in ("mean_field", "sampled"),
        "p_new": not 0.0 < cfg.p_new < 1.0,
        "motion_bias": not 0.0 <= cfg.motion_bias <= 1.0,
        "prior_spread": not 0.0 <= cfg.prior_spread <= 1.0,
        "smoothing": not 0.0 < cfg.smoothing < 0.5,
        "min_gap": cfg.min_gap < 0,
        "num_samples": cfg.num_samples < 1,
    }
    for key, bad in problems.items():
        if bad:
            raise ConfigError(f"fabmap.{key}: value {getattr(cfg, key)!r} out of range")
    detector_table(cfg.p_z_given_e, cfg.p_z_given_not_e)
    return cfg


def motion_prior(prev: np.ndarray, n_cand: int, cfg: FabmapConfig) -> tuple[np.ndarray, float]:
    """Prior over ``n_cand`` known places and a new place.

    prev: (n_prev,) the previous query's posterior over its candidate places (its
    remaining mass was on a new place). Returns ((n_cand,) prior of the places, prior of a
    new place); they sum to 1.
    """
    if n_cand == 0:
        return np.zeros(0), 1.0
    known = 1.0 - cfg.p_new
    if not cfg.motion_model or len(prev) == 0:
        return np.full(n_cand, known / n_cand), cfg.p_new
    b = cfg.motion_bias
    m = np.zeros(n_cand + 1)
    k = min(len(prev), n_cand)
    m[:k] += prev[:k] / 3.0  # stay
    m[1 : k + 1] += prev[:k] * (2.0 * (1.0 - b) / 3.0)  # forward
    m[: k - 1] += prev[1:k] * (2.0 * b / 3.0)  # backward
    m = m[:n_cand]  # forward mass off the end lands on a place not yet comparable
    eps = cfg.prior_spread
    uniform = (eps + (1.0 - eps) * max(0.0, 1.0 - m.sum())) / n_cand
    return known * ((1.0 - eps) * m + uniform), cfg.p_new


@dataclass(frozen=True, eq=False)
class PlaceMatches:
    """Output of a loop-closure detector over one test sequence of n images.

    scores:  (n, n) float64; ``scores[i, j]`` for ``j <= i - min_gap`` is the detector's
             belief that image i shows the place of image j (FAB-MAP: p(L_j | Z^i); BoW:
             similarity); 0 elsewhere
    p_new:   (n,) float64 probability of a new place (NaN for detectors without one)
    matched: (n,) int64 the matched earlier image, -1 when none (new place / no candidate)
    min_gap: the comparison window used
    log_scores: (n, n) float64 ``log p(L_j | Z^i)`` (-inf outside the window) for detectors
             with a posterior, else None; it keeps the ranking of posteriors that underflow
    """

    scores: np.ndarray
    p_new: np.ndarray
    matched: np.ndarray
    min_gap: int
    log_scores: np.ndarray | None = None


def run_fabmap(
    fabmap: FabMap2, test: sp.spmatrix | np.ndarray, cfg: FabmapConfig, *, progress: bool = False
) -> PlaceMatches:
    """Localise each test image against the earlier ones; returns the confusion matrix.

    test: (n, V) binary occurrences of the test images, in sequence order.
    """
    check_config(cfg)
    X = as_binary_csr(test)
    n = X.shape[0]
    index = fabmap.build_index(X)
    log_scores = np.full((n, n), -np.inf)
    p_new = np.ones(n)
    matched = np.full(n, -1, dtype=np.int64)
    prev = np.zeros(0)
    gap = max(1, cfg.min_gap)
    for i in tqdm(range(n), desc="FAB-MAP 2.0", unit="img", disable=not progress):
        n_cand = max(0, i - gap + 1)
        if n_cand == 0:
            prev = np.zeros(0)
            continue
        obs = X.indices[X.indptr[i] : X.indptr[i + 1]]
        pat = fabmap.pattern(obs)
        ll = fabmap.log_likelihoods(pat, index)[:n_cand]
        ll_new = fabmap.new_place_log_likelihood(pat, cfg.new_place)
        prior, prior_new = motion_prior(prev, n_cand, cfg)
        with np.errstate(divide="ignore"):
            logp = np.concatenate([ll + np.log(prior), [ll_new + np.log(prior_new)]])
        logp -= logsumexp(logp)
        post = np.exp(logp)
        log_scores[i, :n_cand] = logp[:n_cand]
        p_new[i] = post[-1]
        best = int(np.argmax(post))
        matched[i] = best if best < n_cand else -1
        prev = post[:n_cand]
    return PlaceMatches(scores=np.exp(log_scores), p_new=p_new, matched=matched, min_gap=gap, log_scores=log_scores)
