"""The Atlas: several maps, one of them active (ORB-SLAM3's Atlas; Campos et al., "ORB-SLAM3:
An Accurate Open-Source Library for Visual, Visual-Inertial and Multi-Map SLAM", T-RO 2021,
Sec. IV).

When tracking is lost and cannot be recovered, a new map is started and the old one kept,
inactive; place recognition covers every map, and a verified match between the active map
and an inactive one merges them (:mod:`orbslam_hgcn.loop.merge`).

The maps of an atlas share three things, so that keyframes and points keep their ids for
life, whichever map holds them and however maps are merged:

* one lock (a map's ``lock`` is the atlas's): a merge changes two maps at once;
* one keyframe id counter: ids are unique across the maps, so the keyframe database and
  the tracker's records name a keyframe without naming its map;
* one point store (:class:`~orbslam_hgcn.map.mappoint.PointStore`): each point records the
  map it belongs to, and a merge relabels the points it moves instead of renumbering them.

A map's own queries (keyframes, points, covisibility) stay within the map; ``keyframe(id)``
also finds the keyframes of the other maps, for the read-only uses of place recognition
across maps.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np

from orbslam_hgcn.config import MapConfig
from orbslam_hgcn.map.keyframe import KeyFrame
from orbslam_hgcn.map.map import Map
from orbslam_hgcn.map.mappoint import PointStore

log = logging.getLogger(__name__)


class Atlas:
    """The maps of one run: ``maps`` by id, ``active`` the one tracking works in."""

    def __init__(self, config: MapConfig | None = None) -> None:
        self.config = config or MapConfig()
        self._lock: Any = threading.RLock()
        self.points = PointStore()
        self.maps: dict[int, Map] = {}
        self.active: Map | None = None
        self._next_kf_id = 0
        self._next_map_id = 0
        self.n_dropped = 0  # maps discarded (too few keyframes when tracking was lost)
        self.merges: list[dict[str, Any]] = []  # one record per merge (see loop.merge)
        # Called as hook(moved keyframe ids, scale) under the lock when a merge moves a
        # map by a similarity of that scale (the tracker rescales the frame poses it keeps
        # relative to those keyframes).
        self.merge_hooks: list[Any] = []
        self.new_map()

    # --- shared state -----------------------------------------------------------------
    @property
    def lock(self) -> Any:
        return self._lock

    @lock.setter
    def lock(self, lock: Any) -> None:
        """Replace the lock of every map (a threaded system gives tracking priority)."""
        self._lock = lock

    def next_keyframe_id(self) -> int:
        with self._lock:
            k = self._next_kf_id
            self._next_kf_id += 1
            return k

    # --- maps -------------------------------------------------------------------------
    def new_map(self) -> Map:
        """Start an empty map and make it the active one (the previous stays, inactive)."""
        with self._lock:
            m = Map(self.config, atlas=self, map_id=self._next_map_id)
            self._next_map_id += 1
            self.maps[m.map_id] = m
            self.active = m
            log.debug("map %d started (%d maps)", m.map_id, len(self.maps))
            return m

    def set_active(self, m: Map) -> None:
        with self._lock:
            if self.maps.get(m.map_id) is not m:
                raise ValueError(f"map {m.map_id} is not in this atlas")
            self.active = m

    def drop(self, m: Map) -> None:
        """Discard a map: its keyframes and points are set bad and it leaves the atlas."""
        with self._lock:
            for kf in m._kfs.values():
                kf.bad = True
            own = np.flatnonzero((self.points.owner[: self.points.n] == m.map_id) & ~self.points.bad[: self.points.n])
            self.points.bad[own] = True
            m.dropped = True
            self.maps.pop(m.map_id, None)
            self.n_dropped += 1
            if self.active is m:
                self.active = None

    def remove(self, m: Map) -> None:
        """Take an emptied map (merged into another) out of the atlas."""
        with self._lock:
            self.maps.pop(m.map_id, None)
            if self.active is m:
                self.active = None

    def map_of(self, kf_id: int) -> Map | None:
        """The map holding keyframe ``kf_id`` (None when no map does)."""
        with self._lock:
            for m in self.maps.values():
                if kf_id in m._kfs:
                    return m
            return None

    def keyframe(self, kf_id: int) -> KeyFrame:
        """The keyframe with this id, in whichever map holds it; KeyError when none does."""
        m = self.map_of(kf_id)
        if m is None:
            raise KeyError(f"keyframe {kf_id} is in no map of the atlas")
        return m._kfs[kf_id]

    def largest(self) -> Map:
        """The map with the most good keyframes (the active one on a tie)."""
        with self._lock:
            maps = list(self.maps.values())
            if not maps:
                return self.new_map()
            return max(maps, key=lambda m: (m.n_keyframes(), m is self.active))

    def __len__(self) -> int:
        return len(self.maps)

    def summary(self) -> list[dict[str, Any]]:
        """One record per map: id, whether active, keyframes, points."""
        with self._lock:
            return [
                {"map_id": m.map_id, "active": m is self.active, "keyframes": m.n_keyframes(), "points": m.n_points()}
                for m in self.maps.values()
            ]
