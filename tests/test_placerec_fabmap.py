"""Chow-Liu tree learning and FAB-MAP 2.0 inference against brute-force evaluations."""

import itertools
import math

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import minimum_spanning_tree

from orbslam_hgcn.config import FabmapConfig
from orbslam_hgcn.placerec.chow_liu import (
    MutualInformationRows,
    learn_chow_liu_tree,
    maximum_spanning_tree,
    mutual_information_from_counts,
)
from orbslam_hgcn.placerec.fabmap import FabMap2
from orbslam_hgcn.placerec.sequence import motion_prior, run_fabmap
from orbslam_hgcn.placerec.words import occurrence_matrix

from placerec_fixtures import WordWorld, dense_chow_liu_tree, random_tree_model, route_sequence, sample_tree


def test_chow_liu_recovers_known_tree():
    rng = np.random.default_rng(3)
    model = random_tree_model(12, rng, rate=0.3, strength=0.7)
    z = sample_tree(model, 20000, rng)
    tree = learn_chow_liu_tree(z)
    true_edges = {frozenset((int(q), int(p))) for q, p in enumerate(model.parent) if p >= 0}
    assert len(true_edges) == 11
    assert tree.edges() == true_edges
    # the learned conditionals match the generating ones (smoothing 0.98 f + 0.01)
    q = np.flatnonzero(tree.parent >= 0)
    child_is_child = model.parent[q] == tree.parent[q]  # edge oriented as generated
    expect = 0.98 * model.p1_given_1[q] + 0.01
    np.testing.assert_allclose(tree.p_z_given_p[q][child_is_child], expect[child_is_child], atol=0.02)


def test_mutual_information_matches_direct_formula():
    rng = np.random.default_rng(0)
    z = rng.random((300, 6)) < np.array([0.1, 0.5, 0.5, 0.9, 0.0, 1.0])
    z[:, 2] = z[:, 1] ^ (rng.random(300) < 0.1)
    rows = MutualInformationRows(sp.csr_matrix(z))
    mi = np.array([rows.row(u) for u in range(6)])
    for a, b in itertools.combinations(range(6), 2):
        direct = 0.0
        for va, vb in itertools.product((0, 1), repeat=2):
            pab = np.mean((z[:, a] == va) & (z[:, b] == vb))
            pa, pb = np.mean(z[:, a] == va), np.mean(z[:, b] == vb)
            if pab > 0:
                direct += pab * math.log(pab / (pa * pb))
        assert mi[a, b] == pytest.approx(direct, abs=1e-6)
        assert mi[b, a] == pytest.approx(direct, abs=1e-6)
    assert mutual_information_from_counts(0, 0, 0, 10) == 0.0


def test_prim_equals_scipy_maximum_spanning_tree():
    rng = np.random.default_rng(1)
    w = rng.random((60, 60))
    w = (w + w.T) / 2
    np.fill_diagonal(w, 0)
    parent = maximum_spanning_tree(lambda u: w[u], 60, root=5)
    assert parent[5] == -1 and np.sum(parent < 0) == 1
    ours = sum(w[q, p] for q, p in enumerate(parent) if p >= 0)
    ref = -minimum_spanning_tree(sp.csr_matrix(np.triu(-w, 1))).sum()
    assert ours == pytest.approx(ref, rel=1e-12)


def _brute_log_likelihood(tree, pzge, pzgne, pe1_of_word, query):
    """log p(Z | L) as the product over all words of sum_e p(z_q | e_q, z_p) p(e_q | L)."""
    total = 0.0
    for q in range(tree.n_words):
        m = tree.p_z[q]
        par = tree.parent[q]
        zq = bool(query[q])
        if par < 0:
            c1 = m
        else:
            c1 = tree.p_z_given_p[q] if query[par] else tree.p_z_given_not_p[q]

        def cond(z, c1=c1):
            return c1 if z else 1.0 - c1

        def marg(z, m=m):
            return m if z else 1.0 - m

        def det(z, e):
            p1 = pzge if e else pzgne
            return p1 if z else 1.0 - p1

        p = 0.0
        for e, pe in ((True, pe1_of_word[q]), (False, 1.0 - pe1_of_word[q])):
            a = marg(zq) * det(not zq, e) * cond(not zq)
            b = marg(not zq) * det(zq, e) * cond(zq)
            p += pe * b / (a + b)
        total += math.log(p)
    return total


def _pe_given_place(tree, pzge, pzgne, place):
    m = tree.p_z
    out = np.empty(tree.n_words)
    for q in range(tree.n_words):
        d1 = pzge if place[q] else 1 - pzge
        d0 = pzgne if place[q] else 1 - pzgne
        out[q] = d1 * m[q] / (d1 * m[q] + d0 * (1 - m[q]))
    return out


@pytest.mark.parametrize("pzgne", [0.0, 0.05])
def test_inverted_index_equals_brute_force(pzgne):
    rng = np.random.default_rng(7)
    model = random_tree_model(8, rng, rate=0.35, strength=0.6)
    train = sample_tree(model, 400, rng)
    tree = learn_chow_liu_tree(train)
    pzge = 0.39
    fm = FabMap2(tree, pzge, pzgne, train=train, num_samples=5, seed=2)
    places = sample_tree(model, 6, rng)
    places[0] = False  # a place that saw nothing
    index = fm.build_index(places)
    queries = np.vstack([sample_tree(model, 5, rng), np.zeros(8, bool), np.ones(8, bool)])
    for z in queries:
        obs = np.flatnonzero(z)
        got = fm.log_likelihoods(obs, index, absolute=True)
        want = [_brute_log_likelihood(tree, pzge, pzgne, _pe_given_place(tree, pzge, pzgne, pl), z) for pl in places]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        # mean-field new place: every word's element at its prior p(e = 1) = p(z = 1)
        want_mf = _brute_log_likelihood(tree, pzge, pzgne, tree.p_z, z)
        assert fm.new_place_log_likelihood(obs, "mean_field", absolute=True) == pytest.approx(want_mf, abs=1e-9)
        # sampled new place: mean likelihood of the sampled training places
        sample_rows = fm.sample_index.postings.T.toarray().astype(bool)
        lls = [
            _brute_log_likelihood(tree, pzge, pzgne, _pe_given_place(tree, pzge, pzgne, pl), z) for pl in sample_rows
        ]
        want_s = math.log(np.mean(np.exp(lls)))
        assert fm.new_place_log_likelihood(obs, "sampled", absolute=True) == pytest.approx(want_s, abs=1e-9)


def test_likelihood_is_a_distribution_over_observations():
    rng = np.random.default_rng(11)
    model = random_tree_model(8, rng)
    tree = learn_chow_liu_tree(sample_tree(model, 300, rng))
    fm = FabMap2(tree, 0.39, 0.0)
    places = sample_tree(model, 3, rng)
    index = fm.build_index(places)
    all_z = np.array(list(itertools.product((0, 1), repeat=8)), dtype=bool)
    ll = np.array([fm.log_likelihoods(np.flatnonzero(z), index, absolute=True) for z in all_z])
    np.testing.assert_allclose(np.exp(ll).sum(axis=0), 1.0, atol=1e-12)
    mf = np.array([fm.new_place_log_likelihood(np.flatnonzero(z), absolute=True) for z in all_z])
    assert np.exp(mf).sum() == pytest.approx(1.0, abs=1e-12)


def test_motion_prior_sums_to_one_and_favours_neighbours():
    cfg = FabmapConfig(p_new=0.9, motion_bias=0.5, prior_spread=0.01)
    prev = np.zeros(9)
    prev[4] = 0.8
    prior, new = motion_prior(prev, 10, cfg)
    assert prior.sum() + new == pytest.approx(1.0)
    assert new == 0.9
    assert set(np.argsort(prior)[-3:]) == {3, 4, 5}
    flat, _ = motion_prior(prev, 10, FabmapConfig(motion_model=False))
    np.testing.assert_allclose(flat, 0.01)


@pytest.mark.parametrize(("new_place", "max_false"), [("mean_field", 0), ("sampled", 2)])
def test_fabmap_sequence_finds_revisits(new_place, max_false):
    """Revisits match their place; first visits stay new places. The sampled new-place
    likelihood (a mean over 300 training places) is a noisier estimate than the closed-form
    mean field and lets a first visit through now and then (0 to 2 of 30 over seeds 5-7)."""
    rng = np.random.default_rng(5)
    n_words = 1000
    world = WordWorld(n_words, rng, words_per_place=80)
    train = route_sequence(world, np.arange(100, 400), rng, clutter=20)
    route = np.r_[np.arange(30), np.arange(5, 20)]
    test = route_sequence(world, route, rng, clutter=20)
    Xtr = occurrence_matrix(train.word_ids, n_words)
    tree = learn_chow_liu_tree(Xtr)
    cfg = FabmapConfig(new_place=new_place)
    out = run_fabmap(FabMap2(tree, train=Xtr), occurrence_matrix(test.word_ids, n_words), cfg)
    revisits = np.arange(30, 45)
    assert np.mean(out.matched[revisits] == route[revisits]) >= 0.9
    assert np.all(out.p_new[revisits] < 0.5)
    assert np.sum(out.matched[:30] != -1) <= max_false
    rows = out.scores.sum(axis=1) + out.p_new
    np.testing.assert_allclose(rows[1:], 1.0)


def test_config_from_yaml_section_and_range_checks():
    from orbslam_hgcn.config import section_from_yaml
    from orbslam_hgcn.errors import ConfigError
    from orbslam_hgcn.placerec.sequence import check_config

    data = {"fabmap": {"new_place": "sampled", "p_new": 0.8, "min_gap": 3}}
    cfg = section_from_yaml(FabmapConfig, data, "x.yaml", "fabmap")
    assert check_config(cfg) is cfg and cfg.p_new == 0.8 and cfg.min_gap == 3
    with pytest.raises(ConfigError, match="fabmap.new_place"):
        check_config(FabmapConfig(new_place="average"))
    with pytest.raises(ConfigError, match="fabmap.p_new"):
        check_config(FabmapConfig(p_new=1.0))
    with pytest.raises(ConfigError, match="p_z_given_e"):
        check_config(FabmapConfig(p_z_given_e=0.2, p_z_given_not_e=0.3))


def _dense_reference_tree(X, smoothing=0.01):
    """The Chow-Liu tree as built before words were restricted: Prim's algorithm over the
    (V, V) mutual information of every word, rooted at an endpoint of the strongest edge."""
    return dense_chow_liu_tree(X, smoothing, restrict=False)


def _words_with_gaps(rng, n_images=400, n_words=40):
    """Tree samples over n_words columns of which some never occur and one always does."""
    model = random_tree_model(30, rng, rate=0.3, strength=0.7)
    z = sample_tree(model, n_images, rng)
    X = np.zeros((n_images, n_words), dtype=bool)
    cols = np.sort(rng.choice(n_words, size=30, replace=False))
    X[:, cols] = z
    never = np.setdiff1d(np.arange(n_words), cols)
    X[:, never[0]] = True  # seen in every training image
    return X, cols, never[1:]


def test_tree_over_occurring_words_equals_the_full_tree():
    from orbslam_hgcn.placerec.chow_liu import varying_words

    rng = np.random.default_rng(21)
    X, cols, never = _words_with_gaps(rng)
    assert varying_words(X).tolist() == cols.tolist()
    new, ref = learn_chow_liu_tree(X), _dense_reference_tree(X)
    assert new.n_words == ref.n_words == 40
    assert new.root == ref.root and new.root in cols
    occurring = set(cols.tolist())
    edges_among = lambda t: {e for e in t.edges() if e <= occurring}  # noqa: E731
    assert len(edges_among(new)) == 29  # a spanning tree over the 30 varying words
    assert edges_among(new) == edges_among(ref)
    np.testing.assert_array_equal(new.parent[cols], ref.parent[cols])
    for a in ("p_z", "p_z_given_p", "p_z_given_not_p"):
        np.testing.assert_array_equal(getattr(new, a)[cols], getattr(ref, a)[cols])
    np.testing.assert_array_equal(new.mi[cols], ref.mi[cols])
    # every other word hangs under the root, its conditional its marginal (0.01 unseen, 0.99 always seen)
    rest = np.setdiff1d(np.arange(40), cols)
    assert np.all(new.parent[rest] == new.root)
    np.testing.assert_array_equal(new.p_z_given_p[rest], new.p_z[rest])
    np.testing.assert_array_equal(new.p_z_given_not_p[rest], new.p_z[rest])
    np.testing.assert_allclose(new.p_z[never], 0.01)
    np.testing.assert_allclose(new.p_z[rest[~np.isin(rest, never)]], 0.99)
    np.testing.assert_array_equal(new.p_z, ref.p_z)


def _fabmap_before(tree, X):
    """FabMap2 as it was: every child of a word in the query patterns."""
    fm = FabMap2(tree, train=X, num_samples=50, seed=1)
    fm._children = tree.children()
    return fm


def test_fabmap_scores_unchanged_when_every_word_varies():
    rng = np.random.default_rng(5)
    n_words = 300
    world = WordWorld(n_words, rng, words_per_place=30)
    train = route_sequence(world, np.arange(40, 240), rng, clutter=20)
    Xtr = occurrence_matrix(train.word_ids, n_words)
    counts = np.asarray(Xtr.sum(axis=0)).ravel()
    assert np.all((counts > 0) & (counts < Xtr.shape[0]))  # every word occurs, none everywhere
    tree, ref = learn_chow_liu_tree(Xtr), _dense_reference_tree(Xtr)
    np.testing.assert_array_equal(tree.parent, ref.parent)
    test = occurrence_matrix(route_sequence(world, np.r_[np.arange(15), np.arange(3, 10)], rng, clutter=10).word_ids,
                             n_words)
    for new_place in ("mean_field", "sampled"):
        cfg = FabmapConfig(new_place=new_place)
        got = run_fabmap(FabMap2(tree, train=Xtr, num_samples=50, seed=1), test, cfg)
        want = run_fabmap(_fabmap_before(ref, Xtr), test, cfg)
        np.testing.assert_array_equal(got.log_scores, want.log_scores)
        np.testing.assert_array_equal(got.p_new, want.p_new)
        np.testing.assert_array_equal(got.matched, want.matched)
        assert np.sum(got.matched[15:] >= 0) >= 5  # the revisits are found, so the comparison is not vacuous


def test_fabmap_with_words_missing_from_training_scores_as_the_full_tree():
    """Words that never occur in training (and one seen everywhere) drop out of the spanning
    tree; FAB-MAP over the full word range still scores test images that use them as the
    tree over all words does, to rounding."""
    rng = np.random.default_rng(8)
    X, cols, never = _words_with_gaps(rng, n_images=300)
    tree, ref = learn_chow_liu_tree(X), _dense_reference_tree(X)
    test = rng.random((25, 40)) < 0.3  # test images see the missing words too
    got = run_fabmap(FabMap2(tree, train=X, num_samples=50, seed=1), test, FabmapConfig(new_place="sampled"))
    want = run_fabmap(_fabmap_before(ref, X), test, FabmapConfig(new_place="sampled"))
    finite = np.isfinite(want.log_scores)
    np.testing.assert_array_equal(np.isfinite(got.log_scores), finite)
    np.testing.assert_allclose(got.log_scores[finite], want.log_scores[finite], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(got.p_new, want.p_new, rtol=1e-9, atol=1e-12)
