"""The local mapper: one entry, :meth:`LocalMapper.process`, per new keyframe.

ORB-SLAM's local mapping thread as a plain class (Mur-Artal, Montiel & Tardos, T-RO 2015,
Sec. VI; LocalMapping::Run of ORB-SLAM2), in its order:

1. keyframe insertion: BoW vector (with a vocabulary; outside the map lock, timed apart as
   ``words``, and as ``words_cpu``: CPU time of the mapping thread), descriptors and
   viewing ranges of the points the tracker linked, covisibility and spanning-tree links;
   points created with the keyframe enter the recent list;
2. recent map point culling (:mod:`orbslam_hgcn.mapping.culling`);
3. new points by triangulation (:mod:`orbslam_hgcn.mapping.triangulate`);
4. duplicate fusion with the neighbourhood (:mod:`orbslam_hgcn.mapping.fuse`); then, with
   ``track_words`` and a flat vocabulary, the keyframe's BoW vector is remade from its
   features' causal tracks (:mod:`orbslam_hgcn.vocabulary.track_words`; timed as
   ``track_words``; with ``track_words_by: network`` from the graph network over each
   feature's causal track mates, :mod:`orbslam_hgcn.vocabulary.track_network`) before the
   loop closer adds it to the keyframe database;
5. local bundle adjustment (the compiled solver or gtsam, via :mod:`orbslam_hgcn.backend`):
   the keyframe and its covisible keyframes free, every other keyframe seeing their points
   fixed, Huber kernel, 5 iterations, outliers out, 10 more, CPU time bounded, and stopped
   early when ``should_abort`` says so (ORB-SLAM's abort flag, raised when a new keyframe
   waits; by default it takes effect after the 5 robust iterations, see
   ``BackendConfig.local_ba_abort_robust``). With ``ba_beside_mapping`` (the default) its
   window is cut right after step 2 and solved in a thread of its own during steps 3 and 4,
   and written back here; otherwise it is cut and solved here (ORB-SLAM's order);
6. redundant keyframe culling.

Each step holds the map lock; local BA holds it only to cut its window from the map and
to write the results back (keyframes and points that became bad meanwhile are skipped),
not while it is solved, which a ``solver`` may do in another process
(:mod:`orbslam_hgcn.backend.solver`). When that process dies (killed, out of memory), the
keyframe's local BA is skipped with a warning and counted (``counts["ba_process_lost"]``):
the next keyframe's BA starts a new process and covers the same window. A process lost
more than :data:`MAX_LOST_SOLVERS` times, or an error the solver reports, stops the stage.

Stage timings of every call are kept in :attr:`LocalMapper.timings` (milliseconds).
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from orbslam_hgcn.backend.problem import as_problem
from orbslam_hgcn.backend.solver import InProcessSolver, SolverError
from orbslam_hgcn.config import BackendConfig, LocalMappingConfig
from orbslam_hgcn.errors import ConfigError
from orbslam_hgcn.map import KeyFrame, Map
from orbslam_hgcn.map.window import apply_window, local_window
from orbslam_hgcn.mapping.culling import cull_recent_points, redundant_keyframes
from orbslam_hgcn.mapping.fuse import search_in_neighbors
from orbslam_hgcn.mapping.triangulate import create_new_points
from orbslam_hgcn.vocabulary.track_network import TrackNetworkWords
from orbslam_hgcn.vocabulary.track_words import TrackWords

log = logging.getLogger(__name__)

MAX_LOST_SOLVERS = 3  # local BA processes a run may lose before local mapping gives up


class LocalMapper:
    """Local mapping over one :class:`Map`.

    vocabulary: optional (``transform(desc) -> (BowVector, FeatureVector)``); keyframes
    then get BoW vectors and triangulation matches features under one vocabulary node.
    should_abort: polled between local BA iterations; True stops the BA (a threaded system
    raises it when the tracker queues a new keyframe). Never, when None.
    solver: runs local BA (``local_ba(problem, config, cpu_budget_s, should_stop)``);
    default: in the calling thread. ``in_ba`` is True while a local BA runs.
    on_points: called with the keyframe once its new points are triangulated and fused
    with its neighbours', before local BA and culling (a threaded system lets the tracker
    go on from there); before_changes: called with it once after that, before local BA
    writes its result into the map or, without one, before culling (a threaded system may
    hold mapping there until the next frame is tracked; the BA is solved meanwhile).
    """

    def __init__(
        self,
        m: Map,
        config: LocalMappingConfig | None = None,
        backend: BackendConfig | None = None,
        vocabulary: Any = None,
        should_abort: Callable[[], bool] | None = None,
        solver: Any = None,
    ) -> None:
        self.config = config or LocalMappingConfig()
        self.backend = backend or BackendConfig()
        self.vocabulary = vocabulary
        self.should_abort = should_abort
        self.solver = solver if solver is not None else InProcessSolver()
        self.in_ba = False
        self.on_points: Callable[[KeyFrame], None] | None = None
        self.before_changes: Callable[[KeyFrame], None] | None = None
        self._changing = -1  # the keyframe before_changes was called for
        self._pool: ThreadPoolExecutor | None = None  # solves local BA beside triangulation (ba_beside_mapping)
        self.timings: dict[str, list[float]] = defaultdict(list)
        self.counts: dict[str, int] = defaultdict(int)
        self.reset(m)

    def reset(self, m: Map) -> None:
        """Work on map ``m`` from now on, forgetting the recent points (and the track sums)."""
        self.map = m
        self.recent = np.zeros(0, dtype=np.int64)
        self.track_words = None
        if self.config.track_words and self.vocabulary is not None:
            if self.config.track_words_by == "network":
                if getattr(self.vocabulary, "track_network", None) is None:
                    raise ConfigError("local_mapping.track_words_by: network needs a vocabulary holding a track "
                                      "network (--vocab hgcn_graph)")
                self.track_words = TrackNetworkWords(self.vocabulary)
            elif hasattr(self.vocabulary, "words_of_points"):
                self.track_words = TrackWords(self.vocabulary)
            else:
                log.warning("local_mapping.track_words needs a flat vocabulary (kmeans, hgcn): lone words")
        self._lone: tuple[int, np.ndarray, np.ndarray] | None = None  # (kf id, reduced descriptors, words)

    def process(self, kf: KeyFrame) -> KeyFrame | None:
        """Run every local mapping step for a new keyframe; returns it for the loop closer,
        or None when it was culled meanwhile."""
        t_all, c_all = time.perf_counter(), time.process_time()
        m, cfg = self.map, self.config
        with self._timed("insert"):
            if self.vocabulary is not None and kf.featvec is None:
                c = time.thread_time()
                with self._timed("words"):  # the descriptors never change: no map lock needed
                    self._lone_words(kf)
                self.timings["words_cpu"].append(1000.0 * (time.thread_time() - c))
            with m.lock:
                self._insert(kf)
        with self._timed("cull_points"), m.lock:
            self.recent, n_cull = cull_recent_points(m, self.recent, kf.id, cfg)
        # Local BA: (window, the future solving it beside triangulation and fusion, or None)
        ba = None
        if cfg.ba_beside_mapping and self._wants_ba(kf):
            window = self._window(kf)
            ba = (window, self._ba_pool().submit(self._solve, kf, window))
        # These two take the map lock per neighbour keyframe.
        with self._timed("triangulate"):
            new = create_new_points(m, kf, cfg)
            self.recent = np.concatenate([self.recent, new])
        with self._timed("fuse"):
            fused = search_in_neighbors(m, kf, cfg)
        # In ORB-SLAM's order local BA's window is cut from the map as fusion left it, before
        # on_points lets the tracker change it (a keyframe of the next frame adds observations).
        if ba is None and self._wants_ba(kf):
            ba = (self._window(kf), None)
        if self.on_points is not None:
            self.on_points(kf)
        if self.track_words is not None and self._lone is not None and self._lone[0] == kf.id:
            c = time.thread_time()
            with self._timed("track_words"):
                self._track_bow(kf)
            self.timings["track_words_cpu"].append(1000.0 * (time.thread_time() - c))
        ba_ms = ba_cpu_ms = 0.0
        if ba is not None:  # beside: the time left to wait for it; its CPU time either way
            t = time.perf_counter()
            window, solving = ba
            res, ba_cpu_ms = solving.result() if solving is not None else self._solve(kf, window)
            self._write_ba(kf, window, res)
            ba_ms = 1000.0 * (time.perf_counter() - t)
        self.timings["local_ba"].append(ba_ms)
        self.timings["local_ba_cpu"].append(ba_cpu_ms)
        self._changes(kf)
        culled: list[int] = []
        if cfg.keyframe_culling and not kf.bad:
            with self._timed("cull_keyframes"), m.lock:
                culled = redundant_keyframes(m, kf, cfg)
        self.timings["total"].append(1000.0 * (time.perf_counter() - t_all))
        self.timings["total_cpu"].append(1000.0 * (time.process_time() - c_all))
        self.counts["keyframes"] += 1
        self.counts["points_created"] += len(new)
        self.counts["points_culled"] += n_cull
        self.counts["points_merged"] += fused["merged"]
        self.counts["keyframes_culled"] += len(culled)
        log.debug(
            "keyframe %d: %d new points, %d culled, %d merged, %d keyframes culled, BA %.0f ms",
            kf.id, len(new), n_cull, fused["merged"], len(culled), ba_ms,
        )  # fmt: skip
        return None if kf.bad else kf

    # --- steps ---------------------------------------------------------------------------
    def _insert(self, kf: KeyFrame) -> None:
        """ORB-SLAM2 ProcessNewKeyFrame for a keyframe whose observations are linked."""
        m = self.map
        _, pids = kf.observed_points()
        m.update_points(pids)
        # Points created with this keyframe (the initial map) are on probation like
        # triangulated ones.
        if len(pids):
            first = np.array([m.point(int(p)).first_kf for p in pids], dtype=np.int64)
            self.recent = np.concatenate([self.recent, pids[first == kf.id]])
        m.update_connections(kf.id)

    def _lone_words(self, kf: KeyFrame) -> None:
        """The keyframe's lone BoW and feature vectors (kept for the track words)."""
        v = self.vocabulary
        if self.track_words is None:
            kf.bow, kf.featvec = v.transform(kf.keypoints.desc)
            return
        x = v.project(kf.keypoints.desc)
        words = v.words_of_points(x)
        kf.bow, kf.featvec = v.vectors(words)
        self._lone = (kf.id, x, words)

    def _track_bow(self, kf: KeyFrame) -> None:
        """Replace the keyframe's BoW vector by its track words' (the FeatureVector stays)."""
        m = self.map
        _, x, words = self._lone
        self._lone = None
        with m.lock:
            if kf.bad:
                return
            idx, pids = kf.observed_points()
            obs = [m.point(int(p)).observations for p in pids]
            kf_ids = {j for o in obs for j in o if j != kf.id}
            descs = {j: m.keyframe(j).keypoints.desc for j in kf_ids if m.owns(j)}
            obs = [{j: i for j, i in o.items() if j == kf.id or j in descs} for o in obs]
            if len(self.track_words) > 2 * m.n_points():  # drop the sums of culled and merged points
                cached = np.fromiter(self.track_words.points(), np.int64)
                self.track_words.forget(cached[m.bad_points(cached)])
        kf.bow, _ = self.track_words.keyframe_bow(kf.id, kf.keypoints.desc, words, idx, pids, obs,
                                                  descs.__getitem__, x=x)

    def _wants_ba(self, kf: KeyFrame) -> bool:
        return self.config.local_ba and self.map.n_keyframes() > 2 and not kf.bad

    def _window(self, kf: KeyFrame) -> Any:
        """Local BA's window around ``kf``, cut from the map under its lock."""
        with self.map.lock:
            return local_window(self.map, kf.id, self.config.ba_max_keyframes or None)

    def _ba_pool(self) -> ThreadPoolExecutor:
        """The thread that solves local BA beside triangulation and fusion, started by the
        mapping thread (so it inherits that thread's niceness) on first use."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="local-ba")
        return self._pool

    def _solve(self, kf: KeyFrame, w: Any) -> tuple[Any, float]:
        """Local BA over the window ``w`` (map.window.local_window of ``kf``), the map
        untouched: (the solver's result or None when there was nothing to solve or the
        solver process was lost, the CPU ms of the calling thread)."""
        c = time.thread_time()
        if w.n_observations == 0 or not (~w.fixed).any():
            return None, 0.0
        problem = as_problem(w.T_cw, w.fixed, w.points, w.obs_kf, w.obs_pt, w.uv, w.inv_sigma2, w.K)
        self.in_ba = True
        try:
            res, budget_hit = self.solver.local_ba(
                problem, self.backend, self.config.ba_cpu_budget_s, self.should_abort
            )
        except SolverError as exc:
            if not exc.lost or self.counts["ba_process_lost"] >= MAX_LOST_SOLVERS:
                raise
            self.counts["ba_process_lost"] += 1
            log.warning("local BA of keyframe %d skipped: %s; the next one starts a new process", kf.id, exc)
            return None, 1000.0 * (time.thread_time() - c)
        finally:
            self.in_ba = False
        self.counts["ba_budget_hit"] += int(budget_hit)
        self.counts["ba_aborted"] += int(self.should_abort is not None and bool(self.should_abort()))
        self.counts["ba_keyframes_free"] += int((~w.fixed).sum())
        return res, 1000.0 * (time.thread_time() - c)

    def _write_ba(self, kf: KeyFrame, w: Any, res: Any) -> None:
        """Write a local BA result over window ``w`` back into the map (keyframes and
        points that became bad meanwhile, fusion's merged points among them, are skipped)."""
        if res is None:
            return
        self._changes(kf)
        self.counts["ba_outliers_erased"] += apply_window(self.map, w, res.T_cw, res.points, res.outlier)

    def _changes(self, kf: KeyFrame) -> None:
        """Call before_changes once per keyframe, before its first change after fusion."""
        if self.before_changes is not None and self._changing != kf.id:
            self._changing = kf.id
            self.before_changes(kf)

    # --- timing --------------------------------------------------------------------------
    def _timed(self, name: str) -> _Timer:
        return _Timer(self.timings[name])


class _Timer:
    """Context manager appending the elapsed milliseconds to a list."""

    def __init__(self, sink: list[float]) -> None:
        self.sink = sink

    def __enter__(self) -> _Timer:
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        self.sink.append(1000.0 * (time.perf_counter() - self.t0))
