"""Loop detection: keyframe-database candidates filtered by covisibility consistency.

ORB-SLAM's LoopClosing::DetectLoop (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. VII-A):

* no detection until ``min_keyframes_between`` keyframes exist after the map's start or the
  last loop (the keyframe is still indexed);
* the lowest BoW score between the keyframe and its covisible keyframes is the minimum
  score a candidate must reach; the keyframe database returns candidates that are not
  connected to the keyframe (:meth:`KeyframeDatabase.detect_loop_candidates`);
* each candidate forms a group with its connected keyframes. A group is consistent with a
  group of the previous keyframe when they share a keyframe; its consistency is then the
  previous group's plus one (a group consistent with none starts at 0). A candidate whose
  group reaches ``consistency_threshold`` (3) is accepted for geometric verification. Only
  the groups of the last keyframe are kept, so one keyframe without consistent candidates
  breaks every chain; with the threshold 3 a place must be retrieved by four keyframes in a
  row (consistency 0, 1, 2, 3).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

from orbslam_hgcn.config import LoopClosingConfig
from orbslam_hgcn.map import KeyFrame, Map
from orbslam_hgcn.vocabulary.bow import l1_score
from orbslam_hgcn.map.database import KeyframeDatabase

log = logging.getLogger(__name__)


class ConsistencyFilter:
    """ORB-SLAM's consistent groups (mvConsistentGroups) as a plain object.

    threshold: consistency a candidate group needs (ORB-SLAM mnCovisibilityConsistencyTh).
    ``groups`` holds the previous keyframe's (group, consistency) pairs.
    """

    def __init__(self, threshold: int = 3) -> None:
        self.threshold = int(threshold)
        self.groups: list[tuple[frozenset[int], int]] = []

    def clear(self) -> None:
        self.groups = []

    def update(self, candidates: Sequence[tuple[int, frozenset[int] | set[int]]]) -> list[int]:
        """Feed one keyframe's candidates; returns those consistent enough, in order.

        candidates: (candidate id, its group: itself and its connected keyframes). An empty
        sequence clears the groups.
        """
        enough: list[int] = []
        current: list[tuple[frozenset[int], int]] = []
        extended = [False] * len(self.groups)
        for cand, group in candidates:
            group = frozenset(group) | {int(cand)}
            accepted = consistent_for_some = False
            for g, (previous, consistency) in enumerate(self.groups):
                if group.isdisjoint(previous):
                    continue
                consistent_for_some = True
                n = consistency + 1
                if not extended[g]:
                    current.append((group, n))
                    extended[g] = True
                if n >= self.threshold and not accepted:
                    enough.append(int(cand))
                    accepted = True
            if not consistent_for_some:
                current.append((group, 0))
        self.groups = current
        return enough


@dataclass
class Detection:
    """Outcome of :meth:`LoopDetector.detect` for one keyframe: ``candidates`` returned by
    the database, ``consistent`` ones accepted, the ``min_score`` used, ``skipped`` when
    too few keyframes passed since the start or the last loop."""

    kf_id: int
    candidates: list[int]
    consistent: list[int]
    min_score: float = 0.0
    skipped: bool = False


class LoopDetector:
    """Loop candidates of each new keyframe; indexes every keyframe in ``database``.

    m: the map; database: the keyframe database shared with relocalisation.
    """

    def __init__(self, m: Map, database: KeyframeDatabase, config: LoopClosingConfig | None = None) -> None:
        self.map = m
        self.database = database
        self.config = config or LoopClosingConfig()
        self.filter = ConsistencyFilter(self.config.consistency_threshold)
        self.last_loop_kf_id = 0

    def reset(self, m: Map, keep_database: bool = False) -> None:
        """Work on map ``m``: empty groups, and database unless ``keep_database``."""
        self.map = m
        if not keep_database:
            self.database.clear()
        self.filter.clear()
        # Keyframe ids run on across the maps of an atlas: count from the new map's first.
        self.last_loop_kf_id = m.atlas.next_keyframe_id() if m.atlas is not None and not m.n_keyframes() else 0

    def purge(self) -> None:
        """Drop culled keyframes, and those of discarded maps, from the database (ORB-SLAM
        erases them on SetBadFlag)."""
        m = self.map
        for k in self.database.keyframes():
            try:
                bad = m.keyframe(k).bad
            except KeyError:
                bad = True
            if bad:
                self.database.erase(k)

    def min_covisible_score(self, kf: KeyFrame) -> tuple[float, list[int]]:
        """(lowest BoW score against the connected keyframes (1 when none), their ids)."""
        connected = [int(k) for k in self.map.covisible_keyframes(kf.id)]
        scores = [
            l1_score(kf.bow, self.map.keyframe(k).bow)
            for k in connected
            if not self.map.keyframe(k).bad and self.map.keyframe(k).bow is not None
        ]
        return (min(scores) if scores else 1.0), connected

    def _group(self, kf_id: int) -> frozenset[int]:
        return frozenset(int(k) for k in self.map.covisible_keyframes(kf_id)) | {kf_id}

    def detect(self, kf: KeyFrame) -> Detection:
        """Candidates of ``kf`` that passed the consistency test; the keyframe is added to
        the database afterwards (whatever the outcome)."""
        m, cfg = self.map, self.config
        try:
            if kf.id < self.last_loop_kf_id + cfg.min_keyframes_between:
                return Detection(kf.id, [], [], skipped=True)
            min_score, connected = self.min_covisible_score(kf)
            exclude = set(connected) | {kf.id}
            found = self.database.detect_loop_candidates(
                kf.bow, exclude, min_score, covisible=lambda k: m.covisible_keyframes(int(k), self.database.n_covisible),
                per_word=cfg.common_words_per_word,
            )  # fmt: skip
            cands = [c.kf_id for c in found if not m.keyframe(c.kf_id).bad]
            if not cands:
                self.filter.clear()
                return Detection(kf.id, [], [], min_score)
            consistent = self.filter.update([(c, self._group(c)) for c in cands])
            log.debug("keyframe %d: candidates %s, consistent %s (min score %.3f)", kf.id, cands, consistent, min_score)
            return Detection(kf.id, cands, consistent, min_score)
        finally:
            self.database.add(kf.id, kf.bow)
