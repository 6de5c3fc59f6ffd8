"""Coarse-to-fine nearest-word search for one frame's descriptors (compiled).

The flat vocabularies' words are found by this search at run time (the k-means
vocabulary's centroids, the HGCN vocabulary's lifted prototypes): the W points are grouped
into round(2 sqrt(W)) lists by a seeded k-means done when the vocabulary loads
(nothing is added to the file; on a thread of its own, about 0.13 s for 8000 words, which the
first search waits for: a run's start-up goes on meanwhile, the k-means kernel releasing the
GIL); a query's ``probe`` nearest list centres are chosen, and the
nearest point among those lists' points is its word. Probing every list is the exact
search.

Why not one exhaustive faiss search: for a 2000-feature KITTI keyframe against 8000 words
in 20-D, faiss's flat search (BLAS products, then the minimum over the 2000 x 8000
distance table) took 18-19 ms CPU on one thread; this search, 28 of 179 lists probed, about
8 ms (same process, machine load 8-11). It finds the exact nearest word for 99.5% of the
descriptors of 2000-feature KITTI frames, 99.7-99.8% of TUM and EuRoC ones and 99.3% of the
synthetic offices' (asserted >= 99% on TUM and EuRoC by ``tests/test_vocabulary_probe.py``);
where it misses, its word's squared distance is a median 1.1-1.2 times the nearest one's.
(24 lists probed: 7 ms, 99.2% on KITTI but 98.9% on the offices.) Since then the list
selection takes 1.3 ms and the list search 4.0 ms CPU per 2000-feature KITTI keyframe (2.4
and 5.8 ms before the branch-free gathering and minimum and the four-point passes, same
words; one process, machine load 7-12).

Exact pruning does not pay in 20-D: skipping a probed list whose lower bound (the ball
bound ``(|q - centre| - radius)^2`` or the Voronoi bound of the list's cell against the
query's nearest list) exceeds the distance found in the nearest list would skip fewer than
one of the 27 further lists per query on KITTI descriptors.

How: every query picks its lists (squared distances to the list centres, then the
``probe``-th smallest by bisection on the value); the (query, list) pairs are grouped by
list, and each list's points, four at a time, are compared with all queries that probe
it at once, in loops over the queries that the compiler vectorises. Distances are
computed, as faiss does, as ``|p|^2 - 2 q.p`` (|q|^2 is the same for every word) in
float32; ties go to the lower word id.
"""

from __future__ import annotations

import threading

import numpy as np

from orbslam_hgcn.compiled import jit

# The distance kernel may fuse its products and sums into FMA instructions (and only that).
_jit_fma = jit(fastmath={"contract"})

PROBE = 28  # lists probed per query
KMEANS_ITERS = 10  # Lloyd iterations of the list centres (at load time)


def n_lists(n_points: int) -> int:
    """Lists of a search over ``n_points`` points: round(2 sqrt(W)), at most W."""
    return max(1, min(n_points, int(round(2 * np.sqrt(n_points)))))


class ProbedSearch:
    """Nearest of W points (W, d) by probing the ``probe`` nearest of round(2 sqrt(W)) lists.

    points: (W, d) float. probe: lists probed per query (None: :data:`PROBE`; at least the
    number of lists: exact). seed: of the lists' k-means (fixed: the same words every run).
    """

    def __init__(self, points: np.ndarray, probe: int | None = None, seed: int = 0) -> None:
        points = np.ascontiguousarray(points, dtype=np.float32)
        if points.ndim != 2 or len(points) == 0:
            raise ValueError("ProbedSearch needs a non-empty (W, d) array of points")
        self.dim = points.shape[1]
        if probe is not None and probe < 1:
            raise ValueError("probe must be at least 1")
        # The lists are built on a thread (see the module text); _built() waits for it.
        self._error: BaseException | None = None
        self._builder: threading.Thread | None = threading.Thread(
            target=self._build, args=(points, probe, seed), name="orbslam-probe-lists", daemon=True
        )
        self._builder.start()

    def _build(self, points: np.ndarray, probe: int | None, seed: int) -> None:
        try:
            self._make_lists(points, probe, seed)
        except BaseException as exc:  # noqa: BLE001 - raised by the first search
            self._error = exc

    def _built(self) -> None:
        """Wait for the lists (the first call only); raise what building them raised."""
        if self._builder is not None:
            self._builder.join()
            self._builder = None
        if self._error is not None:
            raise self._error

    def __getattr__(self, name: str) -> object:
        # An attribute the lists' thread has not set yet (ids, points, centres_t, ...): wait.
        if not name.startswith("__") and self.__dict__.get("_builder") is not None:
            self._built()
            return getattr(self, name)
        raise AttributeError(name)

    def __getstate__(self) -> dict:
        self._built()
        return {k: v for k, v in self.__dict__.items() if k != "_builder"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._builder = None

    def _make_lists(self, points: np.ndarray, probe: int | None, seed: int) -> None:
        centres, assign = list_kmeans(points, n_lists(len(points)), KMEANS_ITERS, seed)
        order = np.argsort(assign, kind="stable")
        self.ids = order.astype(np.int32)  # word of each reordered point, increasing within a list
        self.points = np.ascontiguousarray(points[order])
        self.scaled = -2 * self.points
        self.norms = np.einsum("wd,wd->w", self.points, self.points)
        self.starts = np.zeros(len(centres) + 1, np.int64)
        self.starts[1:] = np.cumsum(np.bincount(assign, minlength=len(centres)))
        self.centres_t = np.ascontiguousarray(centres.T)
        self._probe = min(PROBE if probe is None else int(probe), self.centres_t.shape[1])
        self._search(points[:1])  # compile or load the kernels now, not inside a frame

    @property
    def n_lists(self) -> int:
        self._built()
        return self.centres_t.shape[1]

    @property
    def probe(self) -> int:
        self._built()
        return self._probe

    @probe.setter
    def probe(self, value: int) -> None:
        if value < 1:
            raise ValueError("probe must be at least 1")
        self._probe = min(int(value), self.n_lists)

    def search(self, x: np.ndarray) -> np.ndarray:
        """(N,) int32 nearest point of every row of x (N, d) among the probed lists."""
        self._built()
        return self._search(x)

    def _search(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float32).reshape(-1, self.dim)
        out = np.empty(len(x), np.int32)
        if len(x):
            sel = np.empty((len(x), self._probe), np.int32)
            _select_lists(x, self.centres_t, sel)
            _search_lists(x, sel, self.scaled, self.norms, self.starts, self.ids, out)
        return out


def list_kmeans(points: np.ndarray, k: int, iters: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """((k, d) float32 centres, (W,) int64 nearest centre of every point): Lloyd's k-means
    from k points drawn with ``seed``, in float64 without BLAS, so the lists are the same
    whatever the thread settings."""
    p = np.asarray(points, np.float64)
    k = min(k, len(p))
    centres = p[np.random.default_rng(seed).choice(len(p), k, replace=False)]
    assign = np.empty(len(p), np.int64)
    for _ in range(iters):
        _assign(p, centres, assign)
        counts = np.bincount(assign, minlength=k)
        sums = np.zeros_like(centres)
        np.add.at(sums, assign, p)
        centres = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], centres)
    _assign(p, centres, assign)
    return centres.astype(np.float32), assign


@jit
def _assign(p, centres, out):
    """out[i] = the nearest centre of p[i] (lowest index on ties)."""
    for i in range(p.shape[0]):
        best = np.inf
        for c in range(centres.shape[0]):
            s = 0.0
            for t in range(p.shape[1]):
                e = p[i, t] - centres[c, t]
                s += e * e
            if s < best:
                best = s
                out[i] = c


@jit
def _select_lists(q, centres_t, sel):
    """sel[i] = the sel.shape[1] lists whose centres are nearest to q[i] (in list order):
    the squared distances, then the k-th smallest found by bisection on the value, then
    the lists below it gathered without branches (ties at the k-th value after them)."""
    d, n = centres_t.shape
    probe = sel.shape[1]
    dc = np.empty(n, np.float32)
    below = np.empty(n + 1, np.int32)
    for i in range(q.shape[0]):
        for c in range(n):
            dc[c] = 0
        for t in range(d):
            qt = q[i, t]
            for c in range(n):
                e = qt - centres_t[t, c]
                dc[c] += e * e
        hi = dc[0]  # count(dc <= hi) >= probe > count(dc <= lo)
        lo = dc[0]
        for c in range(n):
            hi = max(hi, dc[c])
            lo = min(lo, dc[c])
        lo -= np.float32(1.0)
        if probe < n:
            for _ in range(64):
                mid = np.float32(0.5) * (lo + hi)
                if mid <= lo or mid >= hi:
                    break
                cnt = 0
                for c in range(n):
                    cnt += np.int32(dc[c] <= mid)
                if cnt >= probe:
                    hi = mid
                    if cnt == probe:
                        break
                else:
                    lo = mid
        m = 0
        for c in range(n):  # fewer than probe lists lie below hi
            below[m] = c
            m += np.int32(dc[c] < hi)
        for k in range(m):
            sel[i, k] = below[k]
        for c in range(n):
            if m == probe:
                break
            if dc[c] == hi:
                sel[i, m] = c
                m += 1


@_jit_fma
def _search_lists(q, sel, scaled, norms, starts, ids, out):
    """out[i] = the nearest point to q[i] among the lists sel[i], by ``|p|^2 - 2 q.p``
    (scaled: the points times -2, norms: their |p|^2): the (query, list) pairs grouped by
    list, each list's points against all its queries at once. Within a list the nearest
    point is kept by a branch-free select (the list's ids increase, so the first of equal
    distances has the lowest id); the lists' winners then meet with ties to the lower id."""
    n, d = q.shape
    n_lists = len(starts) - 1
    first = np.zeros(n_lists + 1, np.int64)
    for i in range(n):
        for j in range(sel.shape[1]):
            first[sel[i, j] + 1] += 1
    for c in range(n_lists):
        first[c + 1] += first[c]
    fill = first[:-1].copy()
    members = np.empty(first[-1], np.int64)
    for i in range(n):
        for j in range(sel.shape[1]):
            c = sel[i, j]
            members[fill[c]] = i
            fill[c] += 1
    best = np.full(n, np.inf, np.float32)
    best_id = np.full(n, -1, np.int32)
    qt = np.empty((d, n), np.float32)
    d0, d1 = np.empty(n, np.float32), np.empty(n, np.float32)  # distances to the pass's four points
    d2, d3 = np.empty(n, np.float32), np.empty(n, np.float32)
    pb = np.empty(n, np.float32)
    pid = np.empty(n, np.int32)
    for c in range(n_lists):
        a = first[c]
        m = first[c + 1] - a
        if m == 0:
            continue
        for j in range(m):
            i = members[a + j]
            for t in range(d):
                qt[t, j] = q[i, t]
            pb[j] = np.inf
            pid[j] = -1
        w, end = starts[c], starts[c + 1]
        while w < end:  # four points per pass (the last repeated to fill a pass: no change)
            w1, w2, w3 = min(w + 1, end - 1), min(w + 2, end - 1), min(w + 3, end - 1)
            e0, e1, e2, e3 = norms[w], norms[w1], norms[w2], norms[w3]
            for j in range(m):
                d0[j], d1[j], d2[j], d3[j] = e0, e1, e2, e3
            t = 0
            while t + 4 <= d:  # four dimensions per pass: each query load serves 16 products
                a0, a1, a2, a3 = scaled[w, t], scaled[w, t + 1], scaled[w, t + 2], scaled[w, t + 3]
                b0, b1, b2, b3 = scaled[w1, t], scaled[w1, t + 1], scaled[w1, t + 2], scaled[w1, t + 3]
                c0, c1, c2, c3 = scaled[w2, t], scaled[w2, t + 1], scaled[w2, t + 2], scaled[w2, t + 3]
                f0, f1, f2, f3 = scaled[w3, t], scaled[w3, t + 1], scaled[w3, t + 2], scaled[w3, t + 3]
                for j in range(m):
                    x0, x1, x2, x3 = qt[t, j], qt[t + 1, j], qt[t + 2, j], qt[t + 3, j]
                    d0[j] += x0 * a0 + x1 * a1 + x2 * a2 + x3 * a3
                    d1[j] += x0 * b0 + x1 * b1 + x2 * b2 + x3 * b3
                    d2[j] += x0 * c0 + x1 * c1 + x2 * c2 + x3 * c3
                    d3[j] += x0 * f0 + x1 * f1 + x2 * f2 + x3 * f3
                t += 4
            while t < d:
                a0, b0, c0, f0 = scaled[w, t], scaled[w1, t], scaled[w2, t], scaled[w3, t]
                for j in range(m):
                    x0 = qt[t, j]
                    d0[j] += x0 * a0
                    d1[j] += x0 * b0
                    d2[j] += x0 * c0
                    d3[j] += x0 * f0
                t += 1
            _keep_nearer(d0, ids[w], m, pb, pid)  # a list's ids increase: in this order, the
            _keep_nearer(d1, ids[w1], m, pb, pid)  # first of equal distances has the lowest id
            _keep_nearer(d2, ids[w2], m, pb, pid)
            _keep_nearer(d3, ids[w3], m, pb, pid)
            w += 4
        for j in range(m):
            i = members[a + j]
            if pb[j] < best[i] or (pb[j] == best[i] and pid[j] < best_id[i]):
                best[i] = pb[j]
                best_id[i] = pid[j]
    for i in range(n):
        out[i] = best_id[i]



@_jit_fma
def _keep_nearer(dist, wid, m, pb, pid):
    """pb[j], pid[j] = dist[j], wid where dist[j] < pb[j] (j < m), without branches."""
    for j in range(m):
        v = dist[j]
        nearer = v < pb[j]
        pb[j] = v if nearer else pb[j]
        pid[j] = wid if nearer else pid[j]
