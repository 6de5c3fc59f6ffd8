"""The Chow-Liu tree learned row by row against the dense mutual-information matrix."""

import re

import numpy as np
import pytest
import scipy.sparse as sp

from orbslam_hgcn.errors import OrbslamError
from orbslam_hgcn.placerec import chow_liu
from orbslam_hgcn.placerec.chow_liu import (
    MutualInformationRows,
    learn_chow_liu_tree,
    maximum_spanning_tree,
    strongest_edge_root,
    varying_words,
)
from orbslam_hgcn.placerec.memory import chow_liu_bytes, fabmap_bytes

from placerec_fixtures import dense_chow_liu_tree, dense_mutual_information_matrix


def _tie_rich_words(seed: int, n_images: int = 60, n_words: int = 300) -> sp.csr_matrix:
    """Sparse occurrences full of equal mutual informations: words seen once, copies and
    complements of a few patterns, words never or always seen, and independent words."""
    rng = np.random.default_rng(seed)
    X = np.zeros((n_images, n_words), dtype=bool)
    X[rng.integers(0, n_images, 100), np.arange(100)] = True  # seen once: few distinct MI values
    patterns = rng.random((n_images, 10)) < 0.3
    X[:, 100:200] = patterns[:, np.arange(100) % 10]  # ten copies of each pattern
    X[:, 200:280] = rng.random((n_images, 80)) < rng.uniform(0.02, 0.5, 80)
    X[:, 290:295] = True  # seen everywhere; 280..289 never seen
    X[:, 295:300] = ~patterns[:, :5]  # complements: the same MI as the copies
    return sp.csr_matrix(X[:, rng.permutation(n_words)])


@pytest.mark.parametrize("seed", range(6))
def test_rows_are_the_dense_matrix_rows(seed):
    X = _tie_rich_words(seed)
    keep = varying_words(X)
    Xk = X[:, keep]
    dense = dense_mutual_information_matrix(Xk, block_rows=7)
    rows = MutualInformationRows(Xk)
    for u in range(len(keep)):
        row = rows.row(u)
        assert row.dtype == np.float32
        np.testing.assert_array_equal(row, dense[u])
        assert rows.row_max(u) == dense[u].max()
    assert np.all(rows.entropy() + 1e-6 >= dense.max(axis=1))  # the bound the root search prunes with
    assert strongest_edge_root(rows) == np.unravel_index(np.argmax(dense), dense.shape)[0]


@pytest.mark.parametrize("seed", range(6))
def test_streamed_tree_equals_the_dense_tree(seed):
    X = _tie_rich_words(seed)
    tree, ref = learn_chow_liu_tree(X), dense_chow_liu_tree(X)
    assert tree.root == ref.root
    np.testing.assert_array_equal(tree.parent, ref.parent)
    for a in ("p_z", "p_z_given_p", "p_z_given_not_p", "mi"):
        np.testing.assert_array_equal(getattr(tree, a), getattr(ref, a))


def test_the_root_decides_the_tree_among_ties():
    """Among equal weights Prim's tree depends on where it starts, so matching the dense
    tree needs the dense root: growing from another vertex gives other edges here."""
    differs = 0
    for seed in range(6):
        X = _tie_rich_words(seed)
        keep = varying_words(X)
        rows = MutualInformationRows(X[:, keep])
        ref = dense_chow_liu_tree(X)
        root = strongest_edge_root(rows)
        other = (root + len(keep) // 2) % len(keep)
        for start, same in ((root, True), (other, False)):
            parent_k = maximum_spanning_tree(rows.row, len(keep), root=start)
            q = np.flatnonzero(parent_k >= 0)
            edges = {frozenset((int(keep[a]), int(keep[b]))) for a, b in zip(q, parent_k[q], strict=True)}
            inner = {e for e in ref.edges() if e <= set(keep.tolist())}
            if same:
                assert edges == inner
            else:
                differs += edges != inner
    assert differs >= 3


def test_streamed_tree_equals_the_dense_tree_on_orb_like_occurrences():
    """Images of 40-80 distinct words drawn with Zipf-like popularity from 3000 words."""
    rng = np.random.default_rng(4)
    popularity = rng.permutation(1.0 / np.arange(1, 3001) ** 0.6)
    popularity /= popularity.sum()
    rows = [np.unique(rng.choice(3000, size=rng.integers(40, 80), p=popularity)) for _ in range(80)]
    lens = [len(r) for r in rows]
    X = sp.csr_matrix((np.ones(sum(lens)), (np.repeat(np.arange(80), lens), np.concatenate(rows))), shape=(80, 3000))
    tree, ref = learn_chow_liu_tree(X), dense_chow_liu_tree(X)
    assert len(varying_words(X)) > 1000
    np.testing.assert_array_equal(tree.parent, ref.parent)
    for a in ("p_z", "p_z_given_p", "p_z_given_not_p", "mi"):
        np.testing.assert_array_equal(getattr(tree, a), getattr(ref, a))


def test_memory_estimate_is_linear_in_the_words():
    """44,000 varying words of 150 training images (at most 1000 words each): the dense
    matrix alone was 7.2 GiB; the tree now needs tens of megabytes, FAB-MAP far below 4 GB."""
    v_occ, nnz = 44_004, 150 * 1000
    assert chow_liu_bytes(v_occ, nnz) < 20 * 2**20
    assert fabmap_bytes(v_occ, nnz, 99_047, 150) < 0.1 * 2**30
    assert chow_liu_bytes(2 * v_occ, 2 * nnz) == 2 * chow_liu_bytes(v_occ, nnz)


def test_memory_estimate_bounds_what_learning_allocates():
    import tracemalloc

    rng = np.random.default_rng(2)
    X = sp.random(150, 20000, density=0.02, format="csr", random_state=rng, dtype=np.float32)
    v_occ = len(varying_words(X))
    need = chow_liu_bytes(v_occ, X[:, varying_words(X)].nnz)
    tracemalloc.start()
    try:
        learn_chow_liu_tree(X)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    per_word = 120 * X.shape[1]  # the tree's own (V,) arrays (counted with FAB-MAP's tables)
    assert peak < need + per_word, (peak, need)
    assert need < 4 * v_occ**2 / 20  # nothing like the (V_occ, V_occ) float32 matrix


def test_chow_liu_stops_before_allocating_beyond_the_memory_limit(monkeypatch):
    rng = np.random.default_rng(0)
    X = sp.random(200, 20000, density=0.02, format="csr", random_state=rng)
    built = []
    monkeypatch.setattr(chow_liu, "MutualInformationRows", lambda *a, **k: built.append(1))
    with pytest.raises(OrbslamError) as err:
        learn_chow_liu_tree(X, memory_limit_mb=1)
    msg = str(err.value)
    v_occ = len(varying_words(X))
    assert 19000 < v_occ < 20000
    assert f"over the {v_occ} varying words" in msg, msg
    need = float(re.search(r"needs about ([0-9.]+) MiB of memory but 1 MiB is available", msg).group(1))
    assert need == pytest.approx(chow_liu_bytes(v_occ, X.nnz) / 2**20, abs=0.5)
    assert "smaller vocabulary" in msg
    assert not built
    monkeypatch.setenv("ORBSLAM_HGCN_MEMORY_LIMIT_MB", "0.5")
    with pytest.raises(OrbslamError, match="but 0 MiB is available"):
        learn_chow_liu_tree(X)
