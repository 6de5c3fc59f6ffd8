"""BoW vectors, TF-IDF weights, the L1 score and feature vectors."""

import math

import numpy as np
import pytest

from orbslam_hgcn.vocabulary.bow import BowVector, FeatureVector, idf_from_documents, l1_score


def test_idf_and_tfidf_match_hand_computed_values():
    # Three training images: words [0,0,1], [1,2], [2,2,2,3].
    docs = [[0, 0, 1], [1, 2], [2, 2, 2, 3]]
    words = np.concatenate(docs)
    doc_ids = np.repeat(np.arange(3), [len(d) for d in docs])
    idf = idf_from_documents(words, doc_ids, n_words=5)
    # n_w = 1, 2, 2, 1 images; word 4 never occurs (treated as n_w = 1).
    expected = [math.log(3 / 1), math.log(3 / 2), math.log(3 / 2), math.log(3 / 1), math.log(3 / 1)]
    np.testing.assert_allclose(idf, expected, rtol=1e-6)
    # Query image with words [0, 1, 1, 3, 3, 3]: tf = 1/6, 2/6, 3/6; weights tf * idf, L1-normalised.
    bow = BowVector.from_words(np.array([0, 1, 1, 3, 3, 3]), idf)
    raw = np.array([1 / 6 * math.log(3), 2 / 6 * math.log(1.5), 3 / 6 * math.log(3)])
    assert bow.keys() == [0, 1, 3]
    np.testing.assert_allclose(bow.values(), raw / raw.sum(), rtol=1e-6)
    assert math.isclose(sum(bow.values()), 1.0, rel_tol=1e-6)


def test_zero_idf_words_are_left_out():
    idf = np.array([0.0, 1.0, 2.0], np.float32)  # word 0 occurs in every training image
    bow = BowVector.from_words(np.array([0, 0, 1, 2]), idf)
    assert 0 not in bow and bow.keys() == [1, 2]
    np.testing.assert_allclose(bow.values(), [1 / 3, 2 / 3], rtol=1e-6)


def test_bow_vector_mapping_api():
    bow = BowVector.from_dict({7: 0.25, 2: 0.5, 11: 0.25})
    assert len(bow) == 3 and list(bow) == [2, 7, 11]
    assert bow[7] == 0.25 and bow.get(3) is None and bow.get(3, 0.0) == 0.0
    assert 11 in bow and 12 not in bow
    with pytest.raises(KeyError):
        bow[12]
    assert bow.to_dict() == {2: 0.5, 7: 0.25, 11: 0.25}
    assert bow.words.dtype == np.int32 and bow.weights.dtype == np.float32


def test_l1_score_equals_dbow2_definition():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = {int(w): float(v) for w, v in zip(rng.choice(50, 12, replace=False), rng.random(12))}
        b = {int(w): float(v) for w, v in zip(rng.choice(50, 9, replace=False), rng.random(9))}
        sa, sb = sum(a.values()), sum(b.values())
        a = {k: v / sa for k, v in a.items()}
        b = {k: v / sb for k, v in b.items()}
        dense_a, dense_b = np.zeros(50), np.zeros(50)
        dense_a[list(a)] = list(a.values())
        dense_b[list(b)] = list(b.values())
        expected = 1 - 0.5 * np.abs(dense_a - dense_b).sum()
        assert l1_score(BowVector.from_dict(a), BowVector.from_dict(b)) == pytest.approx(expected, abs=1e-6)
    same = BowVector.from_dict({1: 0.5, 2: 0.5})
    assert l1_score(same, same) == pytest.approx(1.0)
    assert l1_score(same, BowVector.from_dict({3: 1.0})) == 0.0
    assert l1_score(same, BowVector()) == 0.0


def test_feature_vector_groups_feature_indices_by_node():
    nodes = np.array([5, 3, 5, 9, 3, 5])
    keep = np.array([True, True, True, True, False, True])
    fv = FeatureVector.from_nodes(nodes, keep)
    assert sorted(fv) == [3, 5, 9]
    np.testing.assert_array_equal(fv[5], [0, 2, 5])
    np.testing.assert_array_equal(fv[3], [1])
    np.testing.assert_array_equal(fv[9], [3])
    assert fv.n_features() == 5
