"""The DBoW2-style vocabulary tree: structure, quantisation, centres, and place similarity
on real images (both vocabulary kinds)."""

import numpy as np
import pytest
import vocab_fixtures as vf

from orbslam_hgcn.compiled import descriptor_words
from orbslam_hgcn.match.hamming import hamming_matrix
from orbslam_hgcn.vocabulary.descriptors import segment_centres
from orbslam_hgcn.vocabulary.orb_tree import train_tree_vocabulary


def test_bitwise_majority_centres():
    rows = np.array([[0b1011_0001] + [0] * 7, [0b0011_0011] + [0] * 7, [0b1001_0000] + [0] * 7,
                     [0b1111_1111] + [255] * 7, [0b0000_0000] + [0] * 7], np.uint8)
    # Segments: rows 0-2 (majority of three) and rows 3-4 (a tie sets the bit).
    c = segment_centres(descriptor_words(rows), np.array([0, 3]), "binary").view(np.uint8)
    assert c[0, 0] == 0b1011_0001 and not c[0, 1:].any()
    assert (c[1] == 255).all()
    m = segment_centres(np.array([[1.0, 2.0], [3.0, 6.0], [5.0, 5.0]], np.float32), np.array([0, 2]), "float")
    np.testing.assert_allclose(m, [[2.0, 4.0], [5.0, 5.0]])


def test_hamming_matrix_matches_bit_counting():
    rng = np.random.default_rng(0)
    a, b = rng.integers(0, 256, (7, 32), dtype=np.uint8), rng.integers(0, 256, (5, 32), dtype=np.uint8)
    expected = np.unpackbits(a[:, None, :] ^ b[None], axis=-1).sum(-1)
    np.testing.assert_array_equal(hamming_matrix(a, b), expected)


def test_tree_structure_and_greedy_descent():
    vocab = vf.small_orb_vocab()
    k, L = 10, 3
    n_children = np.bincount(vocab.parent[1:], minlength=len(vocab.parent))
    assert n_children.max() <= k and vocab.depth.max() <= L
    assert vocab.n_words == int((n_children == 0).sum()) and vocab.n_words > 500
    assert np.all(vocab.idf >= 0) and np.any(vocab.idf > 0)
    # Quantisation = descending to the nearest child at every level (checked by brute force).
    desc = vf.descriptors("tum", 0)[:60]
    words = vocab.transform_words(desc)
    for d, w in zip(desc, words):
        node = 0
        while (children := vocab.children[node][vocab.children[node] >= 0]).size:
            node = children[np.argmin(hamming_matrix(d[None], vocab.centres[children])[0])]
        assert vocab.node_word[node] == w
    # FeatureVector nodes: the ancestor at depth L - levels_up (the root when above the tree).
    nodes = vocab.word_nodes(words, levels_up=2)
    assert np.all(vocab.depth[nodes] == 1)
    assert np.all(vocab.parent[nodes] == 0)
    assert np.all(vocab.word_nodes(words, levels_up=4) == 0)
    np.testing.assert_array_equal(vocab.word_nodes(words, levels_up=0), vocab.word_node[words])


@pytest.mark.skipif(not (vf.REAL_TUM_RGB.is_dir() and vf.REAL_EUROC_RGB.is_dir()),
                    reason="needs the real TUM and EuRoC samples: the rendered stand-ins share their texture "
                    "statistics across places (scores 0.55 against 0.29 with the ORB tree)")
@pytest.mark.parametrize("kind", ["orb", "hgcn"])
def test_same_place_scores_higher_than_different_place(kind):
    vocab = vf.small_orb_vocab() if kind == "orb" else vf.small_hgcn_vocab()
    tum0, tum1 = vocab.bow(vf.descriptors("tum", 0)), vocab.bow(vf.descriptors("tum", 1))
    euroc0 = vocab.bow(vf.descriptors("euroc", 0))
    same = vocab.score(tum0, tum1)
    different = max(vocab.score(tum0, euroc0), vocab.score(tum1, euroc0))
    assert same > 2 * different and same > 0.1
    bow, fv = vocab.transform(vf.descriptors("tum", 0))
    assert sum(bow.values()) == pytest.approx(1.0, abs=1e-5)
    words = vocab.transform_words(vf.descriptors("tum", 0))
    assert fv.n_features() == int((vocab.idf[words] > 0).sum()) > 0


def test_tree_on_float_descriptors():
    # SIFT-like float descriptors around 30 centres grouped in 6 families: a k=6, L=2 tree
    # must never put two centres' descriptors in one word, and keeps most of each together.
    rng = np.random.default_rng(1)
    families = rng.normal(0, 30, (6, 1, 64))
    centres = (families + rng.normal(0, 5, (6, 5, 64))).reshape(30, 64).astype(np.float32)
    labels = rng.integers(0, 30, 3000)
    desc = centres[labels] + rng.normal(0, 0.5, (3000, 64)).astype(np.float32)
    vocab = train_tree_vocabulary(desc, np.arange(3000) // 100, k=6, levels=2, progress=False)
    assert vocab.descriptor_type == "float" and vocab.centres.dtype == np.float32
    words = vocab.transform_words(desc)
    word_purity = sum(np.bincount(labels[words == w]).max() for w in np.unique(words)) / len(desc)
    centre_purity = sum(np.bincount(words[labels == c]).max() for c in range(30)) / len(desc)
    assert word_purity == 1.0 and centre_purity > 0.85
    with pytest.raises(ValueError):
        vocab.transform_words(desc.astype(np.uint8))
