"""Word-id lists of images as sparse (images x words) matrices.

Every detector in this package works on these matrices, never on descriptors: a
vocabulary turns each image's descriptors into an (N_i,) array of word ids, and these
helpers stack them into a CSR matrix of counts or of binary occurrences.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def count_matrix(word_ids: list[np.ndarray], n_words: int) -> sp.csr_matrix:
    """(n_images, n_words) float32 CSR matrix: how often each word occurs in each image.

    word_ids: per image, an (N_i,) int array of word ids in [0, n_words) (repeats allowed).
    """
    lens = [len(np.asarray(w).reshape(-1)) for w in word_ids]
    rows = np.repeat(np.arange(len(word_ids), dtype=np.int64), lens)
    cols = (
        np.concatenate([np.asarray(w, dtype=np.int64).reshape(-1) for w in word_ids])
        if sum(lens)
        else np.zeros(0, dtype=np.int64)
    )
    if len(cols) and (cols.min() < 0 or cols.max() >= n_words):
        raise ValueError(f"word ids must lie in [0, {n_words}); found {cols.min()}..{cols.max()}")
    data = np.ones(len(cols), dtype=np.float32)
    X = sp.csr_matrix((data, (rows, cols)), shape=(len(word_ids), n_words))
    X.sum_duplicates()
    return X


def occurrence_matrix(word_ids: list[np.ndarray], n_words: int) -> sp.csr_matrix:
    """(n_images, n_words) float32 CSR matrix of ones where a word occurs in an image."""
    return as_binary_csr(count_matrix(word_ids, n_words))


def as_binary_csr(X: np.ndarray | sp.spmatrix) -> sp.csr_matrix:
    """(N, V) occurrence data (dense bool/int or sparse) as a float32 0/1 CSR matrix."""
    X = sp.csr_matrix(X, dtype=np.float32, copy=True)
    X.eliminate_zeros()
    X.sum_duplicates()
    X.data[:] = 1.0
    return X
