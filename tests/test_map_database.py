"""Keyframe database: inverted index and ORB-SLAM's loop / relocalisation queries on
hand-made BoW vectors with hand-computed answers."""

import pytest

from orbslam_hgcn.map.database import KeyframeDatabase
from orbslam_hgcn.vocabulary import BowVector


def _bow(words):
    return BowVector.from_dict({w: 1.0 / len(words) for w in words})


QUERY = _bow(range(10))  # words 0..9, 0.1 each
KFS = {
    1: _bow(range(10)),  # A: 10 shared words, score 1.0
    2: _bow([*range(9), 20]),  # B: 9 shared, 0.9
    3: _bow([*range(8), 20, 21]),  # C: 8 shared: not above 0.8 x 10, never scored
    4: _bow([*range(1, 10), 22]),  # D: 9 shared, 0.9
    5: _bow([*range(5), 30, 31, 32, 33, 34]),  # E: 5 shared, not scored
    6: _bow(range(40, 50)),  # F: no shared word
}
COVIS = {1: [3], 2: [4], 3: [1], 4: [2], 5: [], 6: []}


@pytest.fixture
def db():
    d = KeyframeDatabase()
    for kf, bow in KFS.items():
        d.add(kf, bow)
    return d


def test_inverted_index_and_shared_words(db):
    assert len(db) == 6 and 4 in db
    assert sorted(db.postings(0)) == [1, 2, 3, 5]
    ids, common, scores = db.shared(QUERY)
    assert ids.tolist() == [1, 2, 3, 4, 5]
    assert common.tolist() == [10, 9, 8, 9, 5]
    assert scores.tolist() == pytest.approx([1.0, 0.9, 0.8, 0.9, 0.5], abs=1e-6)
    assert db.query(QUERY, max_results=3) == [(1, pytest.approx(1.0)), (2, pytest.approx(0.9)), (4, pytest.approx(0.9))]


def test_loop_candidates_accumulate_over_covisible_groups(db):
    cands = db.detect_loop_candidates(QUERY, connected=[], min_score=0.0, covisible=COVIS.get)
    # Groups: A alone 1.0 (C unscored); B + D = 1.8; D + B = 1.8. Kept above 0.75 x 1.8 = 1.35.
    assert [c.kf_id for c in cands] == [2, 4]
    assert [c.group_score for c in cands] == pytest.approx([1.8, 1.8], abs=1e-6)
    assert [c.score for c in cands] == pytest.approx([0.9, 0.9], abs=1e-6)
    assert [c.common_words for c in cands] == [9, 9]


def test_loop_candidates_exclude_connected_keyframes(db):
    cands = db.detect_loop_candidates(QUERY, connected=[2], min_score=0.0, covisible=COVIS.get)
    # B is excluded: D's group is 0.9, A's 1.0; both above 0.75.
    assert [(c.kf_id, round(c.group_score, 6)) for c in cands] == [(1, 1.0), (4, 0.9)]


def test_min_score_filters_candidates_but_neighbours_still_count(db):
    covis = {1: [2], 2: [1], 3: [], 4: [], 5: [], 6: []}
    cands = db.detect_loop_candidates(QUERY, connected=[], min_score=0.95, covisible=covis.get)
    # Only A reaches 0.95; its group adds B's 0.9 (scored, though below min_score).
    assert [(c.kf_id, round(c.group_score, 6)) for c in cands] == [(1, 1.9)]
    assert db.detect_loop_candidates(QUERY, connected=[], min_score=1.01, covisible=covis.get) == []


def test_relocalisation_candidates_and_erase(db):
    assert [c.kf_id for c in db.detect_relocalization_candidates(QUERY, COVIS.get)] == [2, 4]
    db.erase(4)
    assert 4 not in db and 4 not in db.postings(1)
    cands = db.detect_relocalization_candidates(QUERY, COVIS.get)
    # A 1.0, B 0.9 (its neighbour D is gone): both above 0.75.
    assert [(c.kf_id, round(c.group_score, 6)) for c in cands] == [(1, 1.0), (2, 0.9)]
    db.erase(4)  # erasing twice is harmless
    db.add(2, _bow(range(40, 50)))  # re-adding replaces the old vector
    assert db.postings(0).keys() == {1, 3, 5}
    assert db.detect_relocalization_candidates(_bow([99])) == []


def test_per_word_filter_is_not_won_by_the_largest_keyframe():
    # G holds twice the words of the others and shares 12 of them with the query only
    # by chance (words 100..111); H sees the query's place (8 of its 10 words shared).
    # The raw count keeps G alone (8 < 0.8 x 12); per word H shares 0.8, G 0.6.
    query = _bow([*range(8), *range(100, 112)])
    d = KeyframeDatabase()
    d.add(7, _bow([*range(100, 112), *range(200, 208)]))  # G: 20 words
    d.add(8, _bow([*range(8), 300, 301]))  # H: 10 words
    assert [c.kf_id for c in d.detect_relocalization_candidates(query)] == [7]
    assert [c.kf_id for c in d.detect_relocalization_candidates(query, per_word=True)] == [8]
    loop = d.detect_loop_candidates(query, connected=[], min_score=0.0, per_word=True)
    assert [(c.kf_id, c.common_words) for c in loop] == [(8, 8)]


# The inverted index (postings) of the older entries: never made (every query walks all the
# entries), made of everything at each query, and made now and then, part of the entries
# after it (the split a growing database has).
POSTINGS = pytest.mark.parametrize("postings", [(0.125, 10**12), (0.0, -1), (0.5, 50)], ids=["none", "all", "part"])


def _set_postings(monkeypatch, postings) -> None:
    from orbslam_hgcn.map import database

    monkeypatch.setattr(database, "POSTINGS_TAIL", postings[0])
    monkeypatch.setattr(database, "POSTINGS_MIN", postings[1])


@POSTINGS
def test_the_growing_store_scores_as_a_database_built_afresh(monkeypatch, postings):
    """Keyframes added, replaced and erased in any order: every query scores as a database
    holding only the keyframes left, added in the same order, and the entries stay in that
    order (its sums run in the same order), whichever entries the postings hold."""
    import numpy as np

    _set_postings(monkeypatch, postings)
    rng = np.random.default_rng(0)

    def random_bow() -> BowVector:
        words = np.unique(rng.integers(0, 3000, rng.integers(0, 400)))
        weights = rng.random(len(words))
        return BowVector(words, weights / max(weights.sum(), 1e-9))

    grown: KeyframeDatabase = KeyframeDatabase()
    kept: dict[int, BowVector] = {}
    queries = 0
    for step in range(800):
        r = rng.random()
        if r < 0.65 or not kept:
            k, bow = int(rng.integers(0, 300)), random_bow()
            grown.add(k, bow)
            kept.pop(k, None)
            kept[k] = bow
        elif r < 0.85:
            k = int(rng.choice(list(kept)))
            grown.erase(k)
            del kept[k]
        else:
            fresh = KeyframeDatabase()
            for k, bow in kept.items():
                fresh.add(k, bow)
            query, connected = random_bow(), set(rng.choice(list(kept), 3).tolist())
            for a, b in zip(grown.shared(query, connected), fresh.shared(query, connected)):
                np.testing.assert_array_equal(a, b)
            loop = grown.detect_loop_candidates(query, connected, 0.0, per_word=True)
            assert loop == fresh.detect_loop_candidates(query, connected, 0.0, per_word=True)
            assert grown.keyframes() == list(kept)
            if len(query.words):
                assert grown.postings(int(query.words[0])) == fresh.postings(int(query.words[0]))
            queries += 1
    assert queries > 50 and len(kept) > 100


@POSTINGS
def test_shared_words_and_scores_match_a_direct_count(monkeypatch, postings):
    """The compiled passes (postings and entries) and the grouped fallback (negative ids)
    give, per keyframe, the words shared with the query and the sum of min(weights) in
    increasing word order, bit for bit, with excluded keyframes left out."""
    import numpy as np

    _set_postings(monkeypatch, postings)
    rng = np.random.default_rng(3)

    def random_bow() -> BowVector:
        words = np.unique(rng.integers(0, 2000, rng.integers(1, 300)))
        weights = rng.random(len(words))
        return BowVector(words, weights / weights.sum())

    for ids in (list(range(0, 120, 2)), list(range(-30, 30))):
        bows = {k: random_bow() for k in ids}
        db = KeyframeDatabase()
        for k, bow in bows.items():
            db.add(k, bow)
        query = random_bow()
        exclude = set(rng.choice(ids, 10).tolist())
        q = dict(zip(query.words.tolist(), query.weights.astype(np.float64).tolist()))
        want = {}
        for k, bow in bows.items():
            if k in exclude:
                continue
            common, score = 0, 0.0
            for w, v in sorted(zip(bow.words.tolist(), bow.weights.astype(np.float64).tolist())):
                if w in q:
                    common, score = common + 1, score + min(v, q[w])
            if common:
                want[k] = (common, score)
        got_ids, got_common, got_scores = db.shared(query, exclude)
        assert got_ids.tolist() == sorted(want)
        assert got_common.tolist() == [want[k][0] for k in sorted(want)]
        assert got_scores.tolist() == [want[k][1] for k in sorted(want)]  # exact
