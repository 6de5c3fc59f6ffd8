"""The loop closer: one entry, :meth:`LoopCloser.process`, per keyframe from local mapping.

ORB-SLAM's loop closing thread as a plain class (Mur-Artal, Montiel & Tardos, T-RO 2015,
Sec. VII; LoopClosing::Run of ORB-SLAM2): detect (:mod:`.detector`), verify with a
similarity (:mod:`.sim3_check`), correct (:mod:`.corrector`), then, by default, a global
bundle adjustment (:mod:`.global_ba`). Every keyframe is indexed in the keyframe database,
which relocalisation shares; with ``LoopClosingConfig.enabled`` False that indexing is all
it does. In an atlas the database holds the keyframes of every map, and a verified match
with a keyframe of another map merges that map into the active one (:mod:`.merge`).

The map must stay still while a loop is corrected. ``pause_mapping`` (optional) is called
with True before the correction and False after it, so a threaded system can stop local
mapping there (ORB-SLAM RequestStop / Release); run in order, local mapping is idle anyway.
The map lock is held during detection, the similarity check and the correction itself,
not while the global BA is solved (a ``solver``, :mod:`orbslam_hgcn.backend.solver`, may
solve it in another process); local mapping is paused again while its result is written.

Per keyframe checked for a loop, :attr:`LoopCloser.series` keeps the keyframe id, the
detection's wall time (ms: purge, database query, consistency, indexing; as
``timings["detect"]``), the keyframe database query's (ms; NaN when detection was skipped
and no query made) and the keyframes in the database after it: a run writes them to
``series.npz`` (:mod:`orbslam_hgcn.runtime.results`).
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from orbslam_hgcn.config import BackendConfig, LoopClosingConfig
from orbslam_hgcn.loop.corrector import Correction, correct_loop
from orbslam_hgcn.loop.detector import Detection, LoopDetector
from orbslam_hgcn.loop.global_ba import GlobalBAResult, run_global_ba
from orbslam_hgcn.loop.merge import MergeEvent, merge_maps
from orbslam_hgcn.loop.sim3_check import LoopMatch, Sim3Attempt, compute_sim3
from orbslam_hgcn.map import KeyFrame, Map
from orbslam_hgcn.map.database import KeyframeDatabase

log = logging.getLogger(__name__)


@dataclass
class LoopEvent:
    """One closed loop: keyframes, frames and times of both ends, the similarity S_cm (4, 4)
    (loop camera -> current camera, at the time of the check) and its scale, match counts,
    the correction's counts and per-step times (ms)."""

    kf_id: int
    loop_kf_id: int
    frame_id: int
    loop_frame_id: int
    timestamp: float
    loop_timestamp: float
    S_cm: np.ndarray
    scale: float
    n_sim3_inliers: int
    n_matches: int
    correction: Correction
    global_ba: GlobalBAResult | None
    time_ms: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = {k: getattr(self, k) for k in ("kf_id", "loop_kf_id", "frame_id", "loop_frame_id", "timestamp",
                                           "loop_timestamp", "scale", "n_sim3_inliers", "n_matches")}  # fmt: skip
        d["S_cm"] = self.S_cm.tolist()
        d["correction"] = vars(self.correction)
        d["global_ba"] = vars(self.global_ba) if self.global_ba is not None else None
        d["time_ms"] = dict(self.time_ms)
        return d


class LoopCloser:
    """Loop closing over one :class:`Map`.

    database: the keyframe database (shared with relocalisation); vocabulary: optional,
    computes a keyframe's BoW vectors when local mapping has not (``transform(desc) ->
    (BowVector, FeatureVector)``); pause_mapping: optional callback (see module docs);
    solver: runs the global BA (default: in the calling thread).
    """

    def __init__(
        self,
        m: Map,
        database: KeyframeDatabase,
        config: LoopClosingConfig | None = None,
        backend: BackendConfig | None = None,
        vocabulary: Any = None,
        pause_mapping: Callable[[bool], None] | None = None,
        solver: Any = None,
    ) -> None:
        self.solver = solver
        self.config = config or LoopClosingConfig()
        self.backend = backend or BackendConfig()
        self.vocabulary = vocabulary
        self.pause_mapping = pause_mapping
        self.database = database
        self.detector = LoopDetector(m, database, self.config)
        self.rng = np.random.default_rng(self.config.seed)
        self.loops: list[LoopEvent] = []
        self.merges: list[MergeEvent] = []
        self.detections: list[Detection] = []  # keyframes with database candidates
        self.attempts: list[Sim3Attempt] = []
        self.timings: dict[str, list[float]] = defaultdict(list)
        self.counts: dict[str, int] = defaultdict(int)
        # Per keyframe detected on: (kf id, detection ms, database query ms, database keyframes).
        self.series: list[tuple[int, float, float, int]] = []
        self.map = m

    def reset(self, m: Map, keep_database: bool = False) -> None:
        """Work on map ``m`` from now on (the database is emptied unless ``keep_database``:
        the maps of an atlas share it)."""
        self.map = m
        self.detector.reset(m, keep_database)

    # --- the entry -----------------------------------------------------------------------
    def process(self, kf: KeyFrame) -> LoopEvent | MergeEvent | None:
        """Index ``kf`` and look for a loop; close it when found. In an atlas the place may
        be one of another map: the maps are then merged. Returns the loop or the merge,
        or None."""
        m = self.map
        with m.lock:
            found = self._find(kf)
        if found is None:
            return None
        try:
            if not m.owns(found[0].loop_kf_id):
                return self._merge(kf, *found)
            return self._close(kf, *found)
        finally:
            m.set_erase(kf.id)

    def _merge(self, kf: KeyFrame, match: LoopMatch, time_ms: dict[str, float]) -> MergeEvent:
        """Merge the matched keyframe's map into this one (:mod:`.merge`)."""
        if self.pause_mapping is not None:
            self.pause_mapping(True)
        try:
            event = merge_maps(self.map, match, self.config, self.backend, self.solver)
        finally:
            if self.pause_mapping is not None:
                self.pause_mapping(False)
        event.time_ms.update(time_ms)
        if self.config.global_ba:
            t = time.perf_counter()
            run_global_ba(self.map, self.config.global_ba_iterations, self.backend, self.config.global_ba_time_budget_s,
                          solver=self.solver, pause_mapping=self.pause_mapping)  # fmt: skip
            event.time_ms["global_ba"] = 1000.0 * (time.perf_counter() - t)
        self.detector.last_loop_kf_id = kf.id
        self.detector.filter.clear()
        self.merges.append(event)
        self.counts["merges"] += 1
        return event

    def _find(self, kf: KeyFrame) -> tuple[LoopMatch, dict[str, float]] | None:
        """Index ``kf``, detect and verify a loop: (match, step times) or None. With a
        match, ``kf`` is left protected from culling (the caller releases it)."""
        m, cfg = self.map, self.config
        if kf.bad:
            return None
        if kf.bow is None:
            if self.vocabulary is None:
                log.debug("keyframe %d has no BoW vector and no vocabulary is given; skipped", kf.id)
                return None
            kf.bow, kf.featvec = self.vocabulary.transform(kf.keypoints.desc)
        self.counts["keyframes"] += 1
        if not cfg.enabled:
            self.database.add(kf.id, kf.bow)
            return None
        t0 = time.perf_counter()
        m.set_not_erase(kf.id)
        found = None
        try:
            queries = getattr(self.database, "loop_queries", 0)
            self.detector.purge()
            det = self.detector.detect(kf)
            t1 = time.perf_counter()
            self.timings["detect"].append(1000.0 * (t1 - t0))
            queried = getattr(self.database, "loop_queries", 0) > queries
            query_ms = self.database.last_loop_query_ms if queried else float("nan")
            self.series.append((kf.id, 1000.0 * (t1 - t0), query_ms, len(self.database)))
            if det.candidates:
                self.detections.append(det)
            if not det.consistent:
                return None
            self.counts["consistent_keyframes"] += 1
            for c in det.consistent:
                m.set_not_erase(c)
            match: LoopMatch | None = None
            try:
                attempts: list[Sim3Attempt] = []
                match = compute_sim3(m, kf, det.consistent, cfg, self.rng, attempts)
                self.attempts.extend(attempts)
            finally:
                for c in det.consistent:
                    if match is None or c != match.loop_kf_id:
                        m.set_erase(c)
            t2 = time.perf_counter()
            self.timings["sim3"].append(1000.0 * (t2 - t1))
            if match is None:
                return None
            found = match, {"detect": 1000.0 * (t1 - t0), "sim3": 1000.0 * (t2 - t1)}
            return found
        finally:
            if found is None:
                m.set_erase(kf.id)

    # --- correction ----------------------------------------------------------------------
    def _close(self, kf: KeyFrame, match: LoopMatch, time_ms: dict[str, float]) -> LoopEvent:
        m, cfg = self.map, self.config
        t0 = time.perf_counter()
        if self.pause_mapping is not None:
            self.pause_mapping(True)
        try:
            corr = correct_loop(m, match, cfg, self.backend)
        finally:
            if self.pause_mapping is not None:
                self.pause_mapping(False)
        t1 = time.perf_counter()
        time_ms["correct"] = 1000.0 * (t1 - t0)
        gba = None
        if cfg.global_ba:
            gba = run_global_ba(m, cfg.global_ba_iterations, self.backend, cfg.global_ba_time_budget_s,
                                solver=self.solver, pause_mapping=self.pause_mapping)  # fmt: skip
            time_ms["global_ba"] = 1000.0 * (time.perf_counter() - t1)
        self.detector.last_loop_kf_id = kf.id
        self.detector.filter.clear()
        loop_kf = m.keyframe(match.loop_kf_id)
        event = LoopEvent(
            kf.id, loop_kf.id, kf.frame_id, loop_kf.frame_id, kf.timestamp, loop_kf.timestamp, match.S_cm.copy(),
            float(np.cbrt(np.linalg.det(match.S_cm[:3, :3]))), match.n_sim3_inliers, match.n_matches,
            corr, gba, time_ms,
        )  # fmt: skip
        self.loops.append(event)
        for k, v in time_ms.items():
            self.timings[k].append(v)
        self.counts["loops"] += 1
        log.info("loop closed: keyframe %d (frame %d) with keyframe %d (frame %d), scale %.3f",
                 kf.id, kf.frame_id, loop_kf.id, loop_kf.frame_id, event.scale)  # fmt: skip
        return event

    def stats(self) -> dict[str, Any]:
        """Counts, loops and timings (ms) for a run's stats.json."""
        stages: dict[str, int] = defaultdict(int)
        for a in self.attempts:
            stages[a.stage] += 1
        return {
            "counts": dict(self.counts),
            "loops": [e.to_dict() for e in self.loops],
            "merges": [e.to_dict() for e in self.merges],
            "candidate_outcomes": dict(stages),
            "timing_ms": {k: float(np.mean(v)) if v else 0.0 for k, v in self.timings.items()},
        }
