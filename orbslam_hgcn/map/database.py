"""Keyframe database: the keyframes' BoW vectors, and ORB-SLAM's queries.

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, sections VI-A and III-F, and its
``KeyFrameDatabase``) finds loop and relocalisation candidates in four steps:

1. every keyframe sharing a word with the query (ORB-SLAM: through its inverted index) is a
   candidate, except the query's connected keyframes (loop detection);
2. only candidates sharing more than ``0.8 x`` the largest number of shared words are
   scored (L1 score), and, for loops, only those scoring at least ``min_score`` are kept
   (optionally, ``per_word``, the shared words are counted as a fraction of each
   keyframe's words: see :meth:`KeyframeDatabase._detect`);
3. each kept candidate's score is accumulated over its group: itself and those of its
   best covisible keyframes that were scored in step 2; the group is represented by its
   best-scoring keyframe;
4. groups scoring more than ``0.75 x`` the best accumulated score are returned.

The database stores keyframe ids and BoW vectors only: the covisibility graph is reached
through a function passed to the queries (``kf_id -> best covisible kf ids``), so it does
not depend on the map. (In step 3 ORB-SLAM's relocalisation query also adds neighbours
that were not scored in step 2, with a stale score; here both queries use scored
neighbours only.)

Each loop query (:meth:`KeyframeDatabase.detect_loop_candidates`) is timed: the loop
closer reads ``loop_queries`` and ``last_loop_query_ms`` into its per-keyframe series (a
run's ``series.npz``, :mod:`orbslam_hgcn.runtime.results`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.compiled import jit
from orbslam_hgcn.vocabulary.bow import BowVector

log = logging.getLogger(__name__)

# The postings are made again when the entries added since outgrow this share of them (plus
# POSTINGS_MIN): each entry is then bucketed a bounded number of times on average, and a
# query walks at most that share of the entries one by one.
POSTINGS_TAIL = 0.125
POSTINGS_MIN = 8192

CovisibleFn = Callable[[int], Sequence[int]]


@dataclass(frozen=True)
class Candidate:
    """A query answer: ``kf_id`` (best keyframe of its group), its own L1 ``score``, the
    group's accumulated score ``group_score`` and ``common_words`` shared with the query."""

    kf_id: int
    score: float
    group_score: float
    common_words: int


class KeyframeDatabase:
    """Every added keyframe's words and weights, scored against a query word by word.

    min_common_ratio: scored candidates share more than this x the most shared words (0.8).
    retain_ratio: groups scoring more than this x the best group are returned (0.75).
    n_covisible: best covisible keyframes forming a candidate's group (10).

    ORB-SLAM keeps an inverted index (word -> keyframes) and walks the postings of the
    query's words; so does this one, in two parts. The keyframes' sparse vectors are kept
    side by side in flat arrays, in the order they were added; the postings of the older
    entries are made from them in one compiled counting pass (:func:`_bucket_by_word`) and
    made again when the entries added since outgrow :data:`POSTINGS_TAIL` of them. A query
    walks the postings of its words (:func:`_postings_pass`) and then the newer entries one
    by one (:func:`_shared_pass`, a table lookup per entry). Both sum each keyframe's
    shared words in increasing word order, so the scores are the same as one pass over all
    the entries. On a 450 s rendered street (1057 keyframes, about a million entries) the
    last quarter's query took 2.4 ms instead of 9.0 ms with the one pass over all entries.
    :meth:`postings` answers the inverted index's question for one word. The arrays grow in
    place as keyframes are added (a replaced or erased keyframe's entries are marked dead
    and dropped at the next query, and the postings then made again), so adding a keyframe
    does not copy the others' entries.
    """

    def __init__(self, min_common_ratio: float = 0.8, retain_ratio: float = 0.75, n_covisible: int = 10) -> None:
        self.min_common_ratio = float(min_common_ratio)
        self.retain_ratio = float(retain_ratio)
        self.n_covisible = int(n_covisible)
        self._bows: dict[int, BowVector] = {}
        # Every entry's kf id, word and weight, keyframe after keyframe in the order they
        # were added, in arrays of spare capacity (the first _n rows are used); a keyframe's
        # rows in _rows; rows of replaced or erased keyframes are dead until compacted.
        self._ids = np.zeros(0, np.int64)
        self._words = np.zeros(0, np.int64)
        self._weights = np.zeros(0, np.float64)
        self._n = 0
        self._rows: dict[int, tuple[int, int]] = {}
        self._dead = np.zeros(0, bool)
        self._n_dead = 0
        # Bounds of the ids and words ever added (a dead entry's may be among them): the
        # sizes of a query's per-keyframe and per-word tables.
        self._min_id = 0
        self._max_id = -1
        self._max_word = -1
        # The inverted index (postings) of the first _base_n entries, word after word, each
        # word's entries in the order they were added: _base_ptr[w]:_base_ptr[w + 1] in
        # _base_ids / _base_weights. Made again (in one counting pass) when the entries added
        # since outgrow POSTINGS_TAIL of it, and after a compaction.
        self._base_n = 0
        self._base_ptr = np.zeros(1, np.int64)
        self._base_ids = np.zeros(0, np.int64)
        self._base_weights = np.zeros(0, np.float64)
        # Loop queries made so far and the wall time of the last one (ms), for the timings.
        self.loop_queries = 0
        self.last_loop_query_ms = 0.0

    # --- content --------------------------------------------------------------------------
    def add(self, kf_id: int, bow: BowVector) -> None:
        """Add keyframe ``kf_id``'s vector (re-adding replaces it)."""
        kf_id = int(kf_id)
        self._kill(kf_id)
        self._bows.pop(kf_id, None)
        self._bows[kf_id] = bow
        m = len(bow.words)
        if self._n + m > len(self._ids):
            cap = max(2 * len(self._ids), self._n + m, 4096)
            for name in ("_ids", "_words", "_weights", "_dead"):
                old = getattr(self, name)
                new = np.zeros(cap, old.dtype)
                new[: self._n] = old[: self._n]
                setattr(self, name, new)
        a, b = self._n, self._n + m
        self._ids[a:b] = kf_id
        self._words[a:b] = bow.words
        self._weights[a:b] = bow.weights
        self._dead[a:b] = False
        self._rows[kf_id] = (a, b)
        self._n = b
        self._min_id, self._max_id = min(self._min_id, kf_id), max(self._max_id, kf_id)
        if m:
            self._max_word = max(self._max_word, int(bow.words.max()))

    def erase(self, kf_id: int) -> None:
        """Remove keyframe ``kf_id`` (no effect if absent)."""
        if self._bows.pop(int(kf_id), None) is not None:
            self._kill(int(kf_id))

    def clear(self) -> None:
        self._bows.clear()
        self._rows.clear()
        self._n = self._n_dead = 0
        self._min_id, self._max_id, self._max_word = 0, -1, -1
        self._base_n = 0

    def _kill(self, kf_id: int) -> None:
        rows = self._rows.pop(kf_id, None)
        if rows is not None:
            self._dead[rows[0]:rows[1]] = True
            self._n_dead += rows[1] - rows[0]

    def __len__(self) -> int:
        return len(self._bows)

    def __contains__(self, kf_id: object) -> bool:
        return kf_id in self._bows

    def keyframes(self) -> list[int]:
        return list(self._bows)

    def bow(self, kf_id: int) -> BowVector:
        return self._bows[int(kf_id)]

    def postings(self, word: int) -> dict[int, float]:
        """{kf_id: weight} of the keyframes holding ``word``, in the order they were added."""
        ids, words, weights = self._entries()
        hit = np.flatnonzero(words == int(word))
        return dict(zip(ids[hit].tolist(), weights[hit].tolist()))

    def _entries(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(T,) int64 keyframe ids, (T,) int64 words, (T,) float64 weights of all entries
        (views of the store, keyframe after keyframe in the order they were added)."""
        if self._n_dead:
            keep = ~self._dead[: self._n]
            n = int(keep.sum())
            for name in ("_ids", "_words", "_weights"):
                arr = getattr(self, name)
                arr[:n] = arr[: self._n][keep]
            self._dead[:n] = False
            self._n, self._n_dead = n, 0
            self._base_n = 0  # the entries moved: the postings are made again
            # The live rows are the keyframes' vectors in _bows's order, one after the other.
            ends = np.cumsum([len(b.words) for b in self._bows.values()], dtype=np.int64)
            self._rows = {kf: (int(b - len(bow.words)), int(b)) for (kf, bow), b in zip(self._bows.items(), ends)}
        return self._ids[: self._n], self._words[: self._n], self._weights[: self._n]

    def _postings(self, words: np.ndarray, ids: np.ndarray, weights: np.ndarray) -> int:
        """Bring the postings up to date with the live entries (``_entries()``'s arrays) when
        the entries after them outgrow :data:`POSTINGS_TAIL` of them; returns how many
        entries (a prefix) they hold."""
        n = len(ids)
        if n - self._base_n > POSTINGS_TAIL * self._base_n + POSTINGS_MIN:
            self._base_ptr = np.zeros(self._max_word + 2, np.int64)
            self._base_ids = np.empty(n, np.int64)
            self._base_weights = np.empty(n, np.float64)
            _bucket_by_word(words, ids, weights, self._base_ptr, self._base_ids, self._base_weights)
            self._base_n = n
        return self._base_n

    def _sizes(self, ids: np.ndarray) -> np.ndarray:
        """(M,) float64 number of words of each keyframe of ``ids``."""
        return np.fromiter((len(self._bows[k].words) for k in ids.tolist()), np.float64, len(ids))

    # --- scoring --------------------------------------------------------------------------
    def shared(self, bow: BowVector, exclude: Collection[int] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keyframes sharing a word with ``bow``.

        Returns (kf_ids (M,) int64, common_words (M,) int64, scores (M,) float64), where
        ``scores`` is the L1 score ``sum_w min(q_w, v_w)`` (equal to DBoW2's
        ``1 - 0.5 |q - v|_1`` for L1-normalised vectors), summed in increasing word order.
        """
        ids, words, weights = self._entries()
        if len(ids) == 0 or len(bow.words) == 0:
            empty = np.zeros(0, np.int64)
            return empty, empty, np.zeros(0, np.float64)
        size = max(self._max_word, int(bow.words.max())) + 1
        held = np.zeros(size, bool)
        held[bow.words] = True
        query_weight = np.zeros(size, np.float64)
        query_weight[bow.words] = bow.weights
        if self._min_id >= 0:
            # One compiled pass: the sums below, in the same order, without the temporaries.
            excluded = np.zeros(self._max_id + 1, bool)
            out = [k for k in exclude if 0 <= k <= self._max_id]
            excluded[np.array(out, np.int64)] = True
            counts = np.zeros(self._max_id + 1, np.int64)
            sums = np.zeros(self._max_id + 1, np.float64)
            base = self._postings(words, ids, weights)
            q_words = np.ascontiguousarray(bow.words, dtype=np.int64)
            q_weights = np.ascontiguousarray(bow.weights, dtype=np.float64)
            # A keyframe's entries are all in the postings or all after them, and each is
            # summed in increasing word order either way, so the sums are the same.
            _postings_pass(q_words, q_weights, self._base_ptr, self._base_ids, self._base_weights, excluded,
                           counts, sums)
            _shared_pass(ids[base:], words[base:], weights[base:], held, query_weight, excluded, counts, sums)
            uniq = np.flatnonzero(counts)
            return uniq, counts[uniq], sums[uniq]
        hit = held[words]
        if exclude:
            hit &= ~np.isin(ids, np.fromiter(exclude, np.int64, len(exclude)))
        # Each keyframe's shared words in increasing word order, as the postings of the
        # query's words would give them.
        ids_a, kf_a, q_a = ids[hit], weights[hit], query_weight[words[hit]]
        if len(ids_a) == 0:
            empty = np.zeros(0, np.int64)
            return empty, empty, np.zeros(0, np.float64)
        uniq, inv = np.unique(ids_a, return_inverse=True)
        common = np.bincount(inv, minlength=len(uniq))
        scores = np.bincount(inv, weights=np.minimum(kf_a, q_a), minlength=len(uniq))
        return uniq, common, scores

    def query(
        self, bow: BowVector, max_results: int | None = None, exclude: Collection[int] = ()
    ) -> list[tuple[int, float]]:
        """Plain DBoW2 query: (kf_id, L1 score) of keyframes sharing a word, best first."""
        ids, _, scores = self.shared(bow, exclude)
        order = np.lexsort((ids, -scores))
        if max_results is not None:
            order = order[:max_results]
        return list(zip(ids[order].tolist(), scores[order].tolist()))

    def detect_loop_candidates(
        self, bow: BowVector, connected: Iterable[int], min_score: float, covisible: CovisibleFn | None = None,
        per_word: bool = False,
    ) -> list[Candidate]:  # fmt: skip
        """ORB-SLAM's ``DetectLoopCandidates``.

        bow: the query keyframe's vector. connected: its connected keyframes (excluded;
        include the query's own id if it is in the database). min_score: lowest L1 score of
        a candidate (ORB-SLAM: the lowest score between the query and its covisible
        keyframes). covisible: kf_id -> best covisible kf ids (None: no groups).
        per_word: step 2 compares the shared words divided by the keyframe's own number of
        words, instead of the shared words (see :meth:`_detect`). The query's wall time is
        kept in ``last_loop_query_ms`` (and counted in ``loop_queries``).
        """
        t0 = time.perf_counter()
        try:
            return self._detect(bow, set(int(k) for k in connected), float(min_score), covisible, per_word)
        finally:
            self.last_loop_query_ms = 1000.0 * (time.perf_counter() - t0)
            self.loop_queries += 1

    def detect_relocalization_candidates(
        self, bow: BowVector, covisible: CovisibleFn | None = None, per_word: bool = False
    ) -> list[Candidate]:
        """ORB-SLAM's ``DetectRelocalizationCandidates`` (no exclusion, no minimum score);
        ``per_word`` as in :meth:`detect_loop_candidates`."""
        return self._detect(bow, set(), None, covisible, per_word)

    def _detect(
        self, bow: BowVector, exclude: set[int], min_score: float | None, covisible: CovisibleFn | None,
        per_word: bool = False,
    ) -> list[Candidate]:  # fmt: skip
        """Steps 2 to 4 of the module's query.

        With ``per_word`` the step-2 filter is on the fraction of a keyframe's words that
        the query shares. With a small vocabulary (thousands of words against a million in
        ORB-SLAM's) most words of a 1000-feature query are shared by chance with any
        keyframe, in proportion to the keyframe's size, so the raw count favours the
        largest keyframes (the two initial ones, made with twice the features) over the
        ones that see the same place; the fraction does not.
        """
        ids, common, scores = self.shared(bow, exclude)
        if len(ids) == 0:
            return []
        share = common / self._sizes(ids) if per_word else common.astype(np.float64)
        scored = share > float(share.max()) * self.min_common_ratio
        kept = scored if min_score is None else scored & (scores >= min_score)
        if not kept.any():
            return []
        score_of = dict(zip(ids[scored].tolist(), scores[scored].tolist()))
        common_of = dict(zip(ids.tolist(), common.tolist()))
        groups: dict[int, float] = {}
        for kf, own in zip(ids[kept].tolist(), scores[kept].tolist()):
            best_kf, best, acc = kf, own, own
            if covisible is not None:
                for nb in list(covisible(kf))[: self.n_covisible]:
                    s = score_of.get(int(nb))
                    if s is None:
                        continue
                    acc += s
                    if s > best:
                        best_kf, best = int(nb), s
            groups[best_kf] = max(acc, groups.get(best_kf, -1.0))
        best_acc = max(groups.values())
        out = [
            Candidate(kf, score_of[kf], acc, int(common_of[kf]))
            for kf, acc in groups.items()
            if acc > self.retain_ratio * best_acc
        ]
        out.sort(key=lambda c: (-c.group_score, -c.score, c.kf_id))
        return out


@jit
def _shared_pass(ids, words, weights, held, query_weight, excluded, counts, sums):  # pragma: no cover - compiled
    """For every entry whose word the query holds and whose keyframe id is not excluded:
    counts[id] += 1 and sums[id] += min(weight, the query's weight), entry after entry
    (the order of a grouped sum over the entries)."""
    for k in range(len(ids)):
        w = words[k]
        if held[w]:
            i = ids[k]
            if not excluded[i]:
                counts[i] += 1
                q = query_weight[w]
                v = weights[k]
                sums[i] += v if v < q else q


@jit
def _bucket_by_word(words, ids, weights, ptr, out_ids, out_weights):  # pragma: no cover - compiled
    """The postings of the entries: ptr (W + 1,) the offsets of each word's run in out_ids
    and out_weights, each run in the entries' order (a stable counting sort by word)."""
    for w in range(len(ptr)):
        ptr[w] = 0
    for k in range(len(words)):
        ptr[words[k] + 1] += 1
    for w in range(len(ptr) - 1):
        ptr[w + 1] += ptr[w]
    fill = ptr[:-1].copy()
    for k in range(len(words)):
        w = words[k]
        j = fill[w]
        out_ids[j] = ids[k]
        out_weights[j] = weights[k]
        fill[w] = j + 1


@jit
def _postings_pass(q_words, q_weights, ptr, ids, weights, excluded, counts, sums):  # pragma: no cover - compiled
    """For each query word in turn (increasing), each of its postings whose keyframe id is
    not excluded: counts[id] += 1 and sums[id] += min(weight, the query's weight)."""
    for a in range(len(q_words)):
        w = q_words[a]
        if w + 1 >= len(ptr):
            continue  # a word no entry of the postings holds
        q = q_weights[a]
        for k in range(ptr[w], ptr[w + 1]):
            i = ids[k]
            if not excluded[i]:
                counts[i] += 1
                v = weights[k]
                sums[i] += v if v < q else q


def warm_up() -> None:
    """Compile (or load from numba's cache) the query's kernel."""
    db = KeyframeDatabase()
    db.add(0, BowVector(np.array([1, 2], np.int64), np.array([0.5, 0.5])))
    db.shared(BowVector(np.array([2], np.int64), np.array([1.0])), exclude={5})
    ptr, ids, weights = np.zeros(3, np.int64), np.zeros(2, np.int64), np.zeros(2, np.float64)
    _bucket_by_word(np.array([1, 0], np.int64), np.array([0, 0], np.int64), np.ones(2), ptr, ids, weights)
