"""Bag-of-words loop-closure detection: TF-IDF vectors and their cosine similarities.

Each image is the vector of its word counts weighted TF-IDF as DBoW2 does (Galvez-Lopez &
Tardos, T-RO 2012: ``tf = n_iq / n_i``, ``idf = log(N / N_q)`` over the N training images,
N_q of which contain word q); the training sequence supplies the IDF weights, so the
detector is trained on one dataset and tested on another. Vectors are L2-normalised and
compared by dot product (cosine similarity in [0, 1]); the matrix has the same shape and
comparison window as FAB-MAP's confusion matrix (:class:`PlaceMatches`).
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp

from orbslam_hgcn.placerec.metrics import candidate_mask
from orbslam_hgcn.placerec.sequence import PlaceMatches

log = logging.getLogger(__name__)


def idf_weights(train_counts: sp.spmatrix) -> np.ndarray:
    """(V,) float64 ``log(N / N_q)`` from (N, V) training counts; a word absent from
    training weighs as one seen once (the rarest)."""
    X = sp.csr_matrix(train_counts)
    n = X.shape[0]
    if n == 0:
        raise ValueError("idf needs at least one training image")
    df = np.bincount(X.indices[X.data > 0], minlength=X.shape[1]).astype(np.float64)
    return np.log(n / np.maximum(df, 1.0))


def tfidf_vectors(counts: sp.spmatrix, idf: np.ndarray) -> sp.csr_matrix:
    """(n, V) L2-normalised TF-IDF vectors of (n, V) word counts."""
    X = sp.csr_matrix(counts, dtype=np.float64, copy=True)
    totals = np.asarray(X.sum(axis=1)).ravel()
    rows = np.repeat(np.arange(X.shape[0]), np.diff(X.indptr))
    X.data *= idf[X.indices] / np.maximum(totals[rows], 1e-300)
    norms = np.sqrt(np.asarray(X.multiply(X).sum(axis=1)).ravel())
    X.data /= np.maximum(norms[rows], 1e-300)
    return X


def similarity_matrix(vectors: sp.csr_matrix, min_gap: int = 1) -> np.ndarray:
    """(n, n) float64 cosine similarities ``s[i, j]`` for ``j <= i - min_gap``, 0 elsewhere."""
    n = vectors.shape[0]
    S = np.asarray((vectors @ vectors.T).todense(), dtype=np.float64)
    S[~candidate_mask(n, min_gap)] = 0.0
    return S


def run_bow(train_counts: sp.spmatrix, test_counts: sp.spmatrix, min_gap: int = 1) -> PlaceMatches:
    """BoW detection over a test sequence: IDF from training, best earlier match per image.

    train_counts, test_counts: (N, V) and (n, V) word counts (same vocabulary).
    """
    idf = idf_weights(train_counts)
    S = similarity_matrix(tfidf_vectors(test_counts, idf), min_gap)
    n = S.shape[0]
    mask = candidate_mask(n, min_gap)
    has = mask.any(axis=1)
    best = np.where(mask, S, -np.inf).argmax(axis=1)
    matched = np.where(has & (S[np.arange(n), best] > 0), best, -1).astype(np.int64)
    return PlaceMatches(scores=S, p_new=np.full(n, np.nan), matched=matched, min_gap=max(1, min_gap))
