"""The Map: keyframes, map points and the links between them, behind one lock.

The Map is the only mutator of links. Adding an observation sets both ends (the point's
observation dict and the keyframe's feature slot) in one method, and keeps the shared-point
counts between keyframes (the covisibility weights) exact at every moment, so covisibility
queries never see stale weights. The policies follow ORB-SLAM (Mur-Artal, Montiel & Tardos,
T-RO 2015): covisibility edges from 15 shared points, the spanning tree grown from each new
keyframe's best covisible keyframe and re-linked when a keyframe is culled, points discarded
when left with two observations or fewer.

Every public method takes :attr:`Map.lock` (a re-entrant lock); hold it yourself to make a
sequence of calls atomic.
"""

from __future__ import annotations

import itertools
import logging
import threading
from collections import Counter
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from orbslam_hgcn.config import MapConfig
from orbslam_hgcn.map.frame import Frame
from orbslam_hgcn.map.keyframe import KeyFrame
from orbslam_hgcn.map.mappoint import MapPoint, PointStore, refresh_points

log = logging.getLogger(__name__)


class PointArrays(NamedTuple):
    """Copies of the per-point arrays of a set of ids (all indexed like the ids)."""

    position: np.ndarray  # (M, 3) float64
    normal: np.ndarray  # (M, 3) float64 unit mean viewing direction
    min_dist: np.ndarray  # (M,) float64
    max_dist: np.ndarray  # (M,) float64
    desc: np.ndarray  # (M, 32) uint8
    bad: np.ndarray  # (M,) bool


class Map:
    """Keyframes, map points, covisibility graph, spanning tree and loop edges.

    atlas: the :class:`~orbslam_hgcn.map.atlas.Atlas` the map belongs to (its maps share
    one lock, one keyframe id counter and one point store), or None for a map on its own;
    map_id: the map's id in the atlas.
    """

    def __init__(self, config: MapConfig | None = None, atlas: Any = None, map_id: int = 0) -> None:
        self.config = config or MapConfig()
        self.atlas = atlas
        self.map_id = int(map_id)
        self.dropped = False  # discarded from its atlas (Atlas.drop): its keyframes and points are bad
        self._own_lock: Any = threading.RLock() if atlas is None else None
        self._kfs: dict[int, KeyFrame] = {}  # every keyframe ever added, bad ones included
        self._pts = atlas.points if atlas is not None else PointStore()
        self._next_kf_id = 0
        self.origin_id = -1  # the first keyframe: never culled, root of the spanning tree

    @property
    def lock(self) -> Any:
        """The map's re-entrant lock (its atlas's, when it has one)."""
        return self.atlas.lock if self.atlas is not None else self._own_lock

    @lock.setter
    def lock(self, lock: Any) -> None:
        if self.atlas is not None:
            self.atlas.lock = lock
        else:
            self._own_lock = lock

    def _own_points(self, ids: np.ndarray) -> np.ndarray:
        """The ids of ``ids`` (a prefix range of the store) that belong to this map."""
        if self.atlas is None:
            return ids
        return ids[self._pts.owner[ids] == self.map_id]

    # --- creation ----------------------------------------------------------------------
    def add_keyframe(self, frame: Frame) -> KeyFrame:
        """Make a keyframe from a tracked frame (empty point slots) and insert it."""
        with self.lock:
            if self.atlas is not None:
                kf_id = self.atlas.next_keyframe_id()
            else:
                kf_id = self._next_kf_id
                self._next_kf_id += 1
            kf = KeyFrame.from_frame(frame, kf_id)
            self._kfs[kf.id] = kf
            if self.origin_id < 0:
                self.origin_id = kf.id
                kf.first_connection = False
            return kf

    def add_map_point(self, position: np.ndarray, ref_kf_id: int) -> int:
        """New point at (3,) ``position`` created by keyframe ``ref_kf_id``; returns its id."""
        return int(self.add_map_points(np.reshape(position, (1, 3)), ref_kf_id)[0])

    def add_map_points(self, positions: np.ndarray, ref_kf_id: int) -> np.ndarray:
        """New points at (K, 3) ``positions`` created by keyframe ``ref_kf_id``; returns
        their (K,) int64 ids."""
        with self.lock:
            self._good_kf(ref_kf_id)
            return self._pts.new(positions, ref_kf_id, self.map_id)

    # --- observations ------------------------------------------------------------------
    def add_observation(self, kf_id: int, pid: int, idx: int) -> bool:
        """Link feature ``idx`` of keyframe ``kf_id`` with point ``pid`` (both ends at once).

        Returns False when exactly this link exists already. Raises ValueError when the slot
        holds another point or the point is already observed at another slot of the keyframe
        (erase or replace first).
        """
        with self.lock:
            kf = self._good_kf(kf_id)
            before = self._link(kf, pid, idx)
            if before is None:
                return False
            self._bump_shared(kf, dict.fromkeys(before, 1))
            return True

    def add_observations(self, kf_id: int, pids: np.ndarray, idxs: np.ndarray) -> int:
        """Add many links of one keyframe; existing identical links are skipped. Returns count
        added. As :meth:`add_observation` for each pair in order (a conflicting pair raises
        ValueError after the pairs before it are added), with the shared-point counts
        updated once per other keyframe."""
        with self.lock:
            kf = self._good_kf(kf_id)
            observers: list[tuple[int, ...]] = []  # keyframes observing each added point before the link
            try:
                for p, i in zip(np.asarray(pids).tolist(), np.asarray(idxs).tolist()):
                    before = self._link(kf, p, i)
                    if before is not None:
                        observers.append(before)
            finally:
                # One count per other keyframe, in the order add_observation would have met them.
                self._bump_shared(kf, Counter(itertools.chain.from_iterable(observers)))
            return len(observers)

    def _link(self, kf: KeyFrame, pid: int, idx: int) -> tuple[int, ...] | None:
        """Link slot ``idx`` of ``kf`` with point ``pid`` without touching the shared-point
        counts. Returns the keyframes that observed the point before, or None when exactly
        this link exists already; raises ValueError on a conflicting link."""
        self._good_point(pid)
        obs = self._pts.obs[pid]
        if kf.id in obs:
            if obs[kf.id] == idx:
                return None
            raise ValueError(f"point {pid} is already observed by keyframe {kf.id} at slot {obs[kf.id]}")
        cur = int(kf._point_ids[idx])
        if cur >= 0:
            raise ValueError(f"slot {idx} of keyframe {kf.id} already holds point {cur}")
        before = tuple(obs)
        obs[kf.id] = int(idx)
        kf._point_ids[idx] = pid
        return before

    def observer_counts(self, pids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((K,) int64 keyframes observing any of the points ``pids``, ascending; (K,) int64
        how many of the points each observes)."""
        with self.lock:
            obs, ids = self._pts.obs, np.asarray(pids, dtype=np.int64).tolist()
            total = sum(map(len, map(obs.__getitem__, ids)))
            kfs = np.fromiter(itertools.chain.from_iterable(map(obs.__getitem__, ids)), np.int64, total)
        return np.unique(kfs, return_counts=True)

    def erase_observation(self, kf_id: int, pid: int) -> None:
        """Unlink point ``pid`` from keyframe ``kf_id`` (both ends); a point left with too few
        observations (MapConfig.min_observations_after_erase) is set bad."""
        with self.lock:
            if kf_id not in self._pts.obs[pid]:
                return
            self._unlink(kf_id, pid)
            if len(self._pts.obs[pid]) < self.config.min_observations_after_erase:
                self.set_bad_point(pid)

    def erase_keyframe_slot(self, kf_id: int, idx: int) -> None:
        """Unlink whatever point feature ``idx`` of keyframe ``kf_id`` holds."""
        with self.lock:
            pid = int(self._kfs[kf_id]._point_ids[idx])
            if pid >= 0:
                self.erase_observation(kf_id, pid)

    def _unlink(self, kf_id: int, pid: int) -> None:
        obs = self._pts.obs[pid]
        idx = obs.pop(kf_id)
        kf = self._kfs[kf_id]
        kf._point_ids[idx] = -1
        self._bump_shared(kf, dict.fromkeys(obs, -1))
        if self._pts.ref_kf[pid] == kf_id:
            self._pts.ref_kf[pid] = next(iter(obs)) if obs else -1

    def _bump_shared(self, kf: KeyFrame, deltas: Mapping[int, int]) -> None:
        """Add ``deltas[other]`` to the shared-point count between ``kf`` and each other
        keyframe, both ways (a count reaching 0 drops the link); their covisibility orders
        are recomputed on next use. This runs for every observation added or removed."""
        if not deltas:
            return
        shared, kf_id = kf.shared, kf.id
        for other, delta in deltas.items():
            o = self._kfs[other]
            n = shared.get(other, 0) + delta
            if n > 0:
                shared[other] = n
            else:
                shared.pop(other, None)
            n = o.shared.get(kf_id, 0) + delta
            if n > 0:
                o.shared[kf_id] = n
            else:
                o.shared.pop(kf_id, None)
            o._invalidate_covisibility()
        kf._invalidate_covisibility()

    # --- points ------------------------------------------------------------------------
    def set_bad_point(self, pid: int) -> None:
        """Discard a point: unlink every observation and flag it bad."""
        with self.lock:
            self._pts.bad[pid] = True
            for kf_id in list(self._pts.obs[pid]):
                self._unlink(kf_id, pid)

    def replace_point(self, old: int, new: int, refresh: bool = True) -> None:
        """Fuse ``old`` into ``new``: move old's observations to new (dropping those in
        keyframes that already see new), add its counters, flag old bad and replaced by new
        (ORB-SLAM MapPoint::Replace); new's descriptor and viewing range are recomputed
        (``refresh``; a caller merging many points may refresh the survivors at once)."""
        with self.lock:
            if old == new:
                return
            self._good_point(new)
            s = self._pts
            moved = list(s.obs[old].items())
            for kf_id, _ in moved:
                self._unlink(kf_id, old)
            for kf_id, idx in moved:
                if kf_id not in s.obs[new]:
                    self.add_observation(kf_id, new, idx)
            s.found[new] += s.found[old]
            s.visible[new] += s.visible[old]
            s.bad[old] = True
            s.replaced_by[old] = new
            if refresh:
                self.update_points(np.array([new]))

    def fuse_points(self, kf_id: int, pids: np.ndarray, idxs: np.ndarray) -> tuple[int, int, list[int]]:
        """Write the matches of a fusion into keyframe ``kf_id`` (ORB-SLAM ORBmatcher::Fuse),
        point ``pids[i]`` onto slot ``idxs[i]``, in order: a point that is bad or already
        seen by the keyframe is skipped; a slot holding another good point merges the two
        (the point with more observations survives, :meth:`replace_point` without
        refresh); a free slot gains the observation.

        The shared-point counts of the added observations are applied together before each
        merge and at the end: the same counts as adding them one by one (covisibility
        orders do not depend on the order of a keyframe's links). Returns (points merged,
        observations added, the surviving point of each merge)."""
        with self.lock:
            kf, s = self._kfs[int(kf_id)], self._pts
            merged = added = 0
            survivors: list[int] = []
            pending: list[tuple[int, ...]] = []  # keyframes observing each added point before

            def flush() -> None:
                if pending:
                    self._bump_shared(kf, Counter(itertools.chain.from_iterable(pending)))
                    pending.clear()

            try:
                for pid, idx in zip(np.asarray(pids).tolist(), np.asarray(idxs).tolist()):
                    if kf.bad or s.bad[pid] or kf.id in s.obs[pid]:
                        continue
                    other = int(kf._point_ids[idx])
                    if other < 0:
                        pending.append(self._link(kf, pid, idx))
                        added += 1
                        continue
                    if other == pid or s.bad[other]:
                        continue
                    flush()
                    if len(s.obs[other]) > len(s.obs[pid]):
                        self.replace_point(pid, other, refresh=False)
                        survivors.append(other)
                    else:
                        self.replace_point(other, pid, refresh=False)
                        survivors.append(pid)
                    merged += 1
            finally:
                flush()
            return merged, added, survivors

    def set_point_positions(self, pids: np.ndarray, positions: np.ndarray) -> None:
        """Write (M, 3) positions of points ``pids``."""
        with self.lock:
            self._pts.position[np.asarray(pids, dtype=np.int64)] = np.asarray(positions, dtype=np.float64)

    def update_points(self, pids: np.ndarray, descriptors: bool = True) -> None:
        """Recompute mean viewing direction and distance range (ORB-SLAM
        UpdateNormalAndDepth) and, with ``descriptors``, the representative descriptor
        (ComputeDistinctiveDescriptors) of each good point in ``pids``."""
        with self.lock:
            refresh_points(self._pts, self._kfs, pids, descriptors)

    def increase_visible(self, pids: np.ndarray, n: int = 1) -> None:
        with self.lock:
            np.add.at(self._pts.visible, np.asarray(pids, dtype=np.int64), n)

    def increase_found(self, pids: np.ndarray, n: int = 1) -> None:
        with self.lock:
            np.add.at(self._pts.found, np.asarray(pids, dtype=np.int64), n)

    def point(self, pid: int) -> MapPoint:
        return MapPoint(self._pts, int(pid))

    def point_ids(self) -> np.ndarray:
        """(P,) int64 ids of all good points."""
        with self.lock:
            return self._own_points(np.flatnonzero(~self._pts.bad[: self._pts.n]).astype(np.int64))

    def n_points(self) -> int:
        with self.lock:
            return len(self.point_ids())

    def positions(self, pids: np.ndarray) -> np.ndarray:
        """(M, 3) float64 copy of the positions of ``pids``."""
        with self.lock:
            return self._pts.position[np.asarray(pids, dtype=np.int64)]

    def descriptors(self, pids: np.ndarray) -> np.ndarray:
        """(M, 32) uint8 copy of the representative descriptors of ``pids``."""
        with self.lock:
            return self._pts.desc[np.asarray(pids, dtype=np.int64)]

    def point_arrays(self, pids: np.ndarray) -> PointArrays:
        """Every per-point array for ``pids`` in one locked gather."""
        with self.lock:
            s, ids = self._pts, np.asarray(pids, dtype=np.int64)
            return PointArrays(s.position[ids], s.normal[ids], s.min_dist[ids], s.max_dist[ids], s.desc[ids], s.bad[ids])

    def point_counters(self, pids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M,) int64 copies for ``pids`` in one locked gather: times found, times visible,
        first keyframe."""
        with self.lock:
            s, ids = self._pts, np.asarray(pids, dtype=np.int64)
            return s.found[ids].astype(np.int64), s.visible[ids].astype(np.int64), s.first_kf[ids].astype(np.int64)

    def bad_points(self, pids: np.ndarray) -> np.ndarray:
        """(M,) bool copy: whether each point of ``pids`` has been discarded."""
        with self.lock:
            return self._pts.bad[np.asarray(pids, dtype=np.int64)]

    def n_observations(self, pids: np.ndarray) -> np.ndarray:
        """(M,) int64 number of keyframes observing each point."""
        with self.lock:
            obs, ids = self._pts.obs, np.asarray(pids, dtype=np.int64).tolist()
            return np.fromiter(map(len, map(obs.__getitem__, ids)), np.int64, len(ids))

    # --- keyframes ---------------------------------------------------------------------
    def keyframe(self, kf_id: int) -> KeyFrame:
        """The keyframe with this id (bad ones included). In an atlas, the keyframes of its
        other maps are found too (for reading: place recognition across maps)."""
        kf = self._kfs.get(kf_id)
        if kf is None:
            if self.atlas is None:
                raise KeyError(kf_id)
            return self.atlas.keyframe(kf_id)
        return kf

    def owns(self, kf_id: int) -> bool:
        """Whether keyframe ``kf_id`` (culled or not) belongs to this map."""
        return int(kf_id) in self._kfs

    def keyframes(self) -> list[KeyFrame]:
        """All good keyframes in id order."""
        with self.lock:
            return [kf for kf in self._kfs.values() if not kf.bad]

    def keyframe_ids(self) -> np.ndarray:
        with self.lock:
            return np.array([kf.id for kf in self._kfs.values() if not kf.bad], dtype=np.int64)

    def n_keyframes(self, limit: int | None = None) -> int:
        """Good keyframes in the map; with ``limit``, counted only up to it (the count
        then costs at most ``limit`` good keyframes' worth, not the whole map's)."""
        with self.lock:
            if limit is None:
                return sum(not kf.bad for kf in self._kfs.values())
            n = 0
            for kf in self._kfs.values():
                if n >= limit:
                    break
                n += not kf.bad
            return n

    def set_keyframe_pose(self, kf_id: int, T_cw: np.ndarray) -> None:
        with self.lock:
            self._kfs[kf_id]._set_pose(T_cw)

    def set_keyframe_poses(self, kf_ids: np.ndarray, T_cw: np.ndarray) -> None:
        """Write (K, 4, 4) poses of keyframes ``kf_ids``."""
        with self.lock:
            for k, T in zip(np.asarray(kf_ids).reshape(-1), T_cw):
                self._kfs[int(k)]._set_pose(T)

    def tracked_points(self, kf_id: int, min_obs: int = 1) -> int:
        """Points of the keyframe observed by at least ``min_obs`` keyframes (ORB-SLAM
        TrackedMapPoints, used by the keyframe decision)."""
        with self.lock:
            _, pids = self.keyframe(kf_id).observed_points()
            return int(np.count_nonzero(self.n_observations(pids) >= min_obs))

    # --- covisibility and spanning tree ------------------------------------------------
    def covisible_keyframes(self, kf_id: int, n: int | None = None) -> np.ndarray:
        """(C,) int64 covisibility neighbours of ``kf_id`` by descending weight (the best n)."""
        with self.lock:
            ids, _ = self.keyframe(kf_id).covisible(self.config.covisibility_min_weight)
            return ids[:n].copy() if n is not None else ids.copy()

    def covisible_by_weight(self, kf_id: int, min_weight: int) -> np.ndarray:
        """(C,) int64 keyframes sharing at least ``min_weight`` points, by descending weight."""
        with self.lock:
            kf = self.keyframe(kf_id)
            ids, w = kf.covisible(self.config.covisibility_min_weight)
            if min_weight >= self.config.covisibility_min_weight:
                return ids[w >= min_weight].copy()
            shared = kf.shared
            cand = sorted((k for k, c in shared.items() if c >= min_weight), key=lambda k: (-shared[k], k))
            return np.array(cand, dtype=np.int64)

    def covisibility_weight(self, a: int, b: int) -> int:
        """Number of map points keyframes ``a`` and ``b`` both observe."""
        with self.lock:
            return self.keyframe(a).shared.get(b, 0)

    def update_connections(self, kf_id: int) -> None:
        """Recount the keyframe's shared points from its slots (fixing both directions if
        they disagree) and, on its first connection, hang it in the spanning tree under its
        best covisible keyframe (ORB-SLAM KeyFrame::UpdateConnections)."""
        with self.lock:
            kf = self._good_kf(kf_id)
            counts: Counter[int] = Counter()
            for pid in kf._point_ids[kf._point_ids >= 0]:
                counts.update(k for k in self._pts.obs[pid] if k != kf_id)
            if counts != Counter(kf.shared):
                log.warning("keyframe %d: shared counts out of date; recounted", kf_id)
                for other in set(counts) | set(kf.shared):
                    delta = counts.get(other, 0) - kf.shared.get(other, 0)
                    if delta:
                        self._bump_shared(kf, {other: delta})
            if kf.first_connection and kf.id != self.origin_id:
                # The best covisible keyframe already in the tree (in ORB-SLAM's order of
                # events every neighbour is older, hence in the tree; this also holds when
                # keyframes are linked in another order, and never closes a cycle).
                ids, _ = kf.covisible(self.config.covisibility_min_weight)
                ranked = list(ids) + sorted(kf.shared, key=lambda k: (-kf.shared[k], k))
                for k in ranked:
                    other = self._kfs[int(k)]
                    if other.id == self.origin_id or not other.first_connection:
                        self.change_parent(kf_id, other.id)
                        kf.first_connection = False
                        break

    def change_parent(self, kf_id: int, parent_id: int) -> None:
        with self.lock:
            kf = self._kfs[kf_id]
            if kf.parent >= 0:
                self._kfs[kf.parent].children.discard(kf_id)
            kf.parent = int(parent_id)
            self._kfs[parent_id].children.add(kf_id)

    def add_loop_edge(self, a: int, b: int) -> None:
        """Record a loop closure between keyframes ``a`` and ``b`` (both ends); such keyframes
        are protected from culling."""
        with self.lock:
            ka, kb = self._good_kf(a), self._good_kf(b)
            ka.loop_edges.add(b)
            kb.loop_edges.add(a)
            ka.not_erase = kb.not_erase = True

    def _owner(self, kf_id: int) -> Map:
        """The map holding ``kf_id``: this one, or another map of the atlas."""
        if kf_id in self._kfs or self.atlas is None:
            return self
        other = self.atlas.map_of(kf_id)
        return other if other is not None else self

    def set_not_erase(self, kf_id: int) -> None:
        """Protect a keyframe from culling while the loop closer uses it (in an atlas, a
        keyframe of another map too)."""
        with self.lock:
            owner = self._owner(kf_id)
            owner._kfs[kf_id].not_erase = True

    def set_erase(self, kf_id: int) -> None:
        """Lift the protection (kept while the keyframe has loop edges); a cull requested
        meanwhile happens now (ORB-SLAM KeyFrame::SetErase)."""
        with self.lock:
            owner = self._owner(kf_id)
            if owner is not self:
                owner.set_erase(kf_id)
                return
            kf = self._kfs[kf_id]
            if not kf.loop_edges:
                kf.not_erase = False
            if kf.to_be_erased and not kf.not_erase:
                self.set_bad_keyframe(kf_id)

    def set_bad_keyframe(self, kf_id: int) -> bool:
        """Cull a keyframe (ORB-SLAM KeyFrame::SetBadFlag): unlink its observations, then give
        each child a new parent among {old parent, re-linked siblings} with the strongest
        covisibility, the rest to the old parent. Returns False when the keyframe is the
        origin or protected (then it is culled when the protection is lifted)."""
        with self.lock:
            kf = self._kfs[kf_id]
            if kf.bad or kf_id == self.origin_id:
                return False
            if kf.not_erase:
                kf.to_be_erased = True
                return False
            for pid in kf._point_ids[kf._point_ids >= 0].tolist():
                self.erase_observation(kf_id, pid)
            candidates = {kf.parent} if kf.parent >= 0 else set()
            children = {c for c in kf.children if not self._kfs[c].bad}
            min_w = self.config.covisibility_min_weight
            while children and candidates:
                best, best_w = None, -1
                for c in sorted(children):
                    for n, w in zip(*self._kfs[c].covisible(min_w)):
                        if int(n) in candidates and w > best_w:
                            best, best_w = (c, int(n)), int(w)
                if best is None:
                    break
                self.change_parent(*best)
                candidates.add(best[0])
                children.discard(best[0])
            for c in children:
                if kf.parent >= 0:
                    self.change_parent(c, kf.parent)
                else:
                    log.warning("culled keyframe %d had no parent; child %d left as a root", kf_id, c)
                    self._kfs[c].parent = -1
            kf.children.clear()
            if kf.parent >= 0:
                self._kfs[kf.parent].children.discard(kf_id)
                kf.T_cp = kf.T_cw @ self._kfs[kf.parent].T_wc
            for other in kf.loop_edges:
                self._kfs[other].loop_edges.discard(kf_id)
            kf.loop_edges.clear()
            kf.bad = True
            return True

    # --- helpers -----------------------------------------------------------------------
    def _good_kf(self, kf_id: int) -> KeyFrame:
        kf = self._kfs.get(kf_id)
        if kf is None or kf.bad:
            raise ValueError(f"keyframe {kf_id} does not exist or is bad")
        return kf

    def _good_point(self, pid: int) -> None:
        if not 0 <= pid < self._pts.n or self._pts.bad[pid]:
            raise ValueError(f"map point {pid} does not exist or is bad")
