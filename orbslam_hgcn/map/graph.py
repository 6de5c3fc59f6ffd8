"""Graph views of a Map as plain arrays: the essential graph, snapshots, invariant checks.

The essential graph (ORB-SLAM, T-RO 2015, Sec. III-D) keeps the spanning tree, the
covisibility edges with at least 100 shared points and the loop edges; the loop closer
optimises it as a Sim(3) pose graph.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from orbslam_hgcn.map.map import Map

log = logging.getLogger(__name__)

TREE, COVISIBILITY, LOOP = 0, 1, 2  # edge kinds


@dataclass(frozen=True)
class GraphEdges:
    """Undirected keyframe edges, each listed once with i < j.

    kf_ids: (K,) int64 good keyframe ids (rows of any pose array built from them)
    edges:  (E, 2) int64 indices into kf_ids
    kind:   (E,) int8 TREE, COVISIBILITY or LOOP
    weight: (E,) int64 shared map points of the pair
    """

    kf_ids: np.ndarray
    edges: np.ndarray
    kind: np.ndarray
    weight: np.ndarray


def essential_graph(m: Map, min_weight: int | None = None) -> GraphEdges:
    """Spanning-tree, strong covisibility (>= ``min_weight``, default
    MapConfig.essential_min_weight) and loop edges of the good keyframes."""
    if min_weight is None:
        min_weight = m.config.essential_min_weight
    with m.lock:
        kfs = m.keyframes()
        index = {kf.id: i for i, kf in enumerate(kfs)}
        found: dict[tuple[int, int], int] = {}

        def put(a: int, b: int, kind: int) -> None:
            if a in index and b in index and a != b:
                key = (min(index[a], index[b]), max(index[a], index[b]))
                found.setdefault(key, kind)

        for kf in kfs:
            if kf.parent >= 0:
                put(kf.id, kf.parent, TREE)
        for kf in kfs:
            for other in kf.loop_edges:
                put(kf.id, other, LOOP)
        for kf in kfs:
            for other, w in kf.shared.items():
                if w >= min_weight:
                    put(kf.id, other, COVISIBILITY)
        keys = sorted(found)
        edges = np.array(keys, dtype=np.int64).reshape(-1, 2)
        kind = np.array([found[k] for k in keys], dtype=np.int8)
        weight = np.array([kfs[i].shared.get(kfs[j].id, 0) for i, j in keys], dtype=np.int64)
        return GraphEdges(np.array([kf.id for kf in kfs], dtype=np.int64), edges, kind, weight)


@dataclass(frozen=True)
class MapSnapshot:
    """Plain arrays of a map at one moment, for visualisation and saving.

    kf_ids (K,) int64, kf_timestamps (K,) float64, kf_T_wc (K, 4, 4) float64;
    point_ids (P,) int64, points (P, 3) float64, point_ref_kf (P,) int64;
    covis_edges (E, 2) int64 keyframe ids (a < b), covis_weights (E,) int64 (pairs meeting
    the covisibility threshold); tree_edges (T, 2) int64 (child, parent) keyframe ids;
    loop_edges (L, 2) int64 keyframe ids (a < b).
    """

    kf_ids: np.ndarray
    kf_timestamps: np.ndarray
    kf_T_wc: np.ndarray
    point_ids: np.ndarray
    points: np.ndarray
    point_ref_kf: np.ndarray
    covis_edges: np.ndarray
    covis_weights: np.ndarray
    tree_edges: np.ndarray
    loop_edges: np.ndarray

    def save(self, path: str | Path) -> None:
        """Write all arrays to one ``.npz`` file."""
        np.savez_compressed(path, **{k: getattr(self, k) for k in self.__dataclass_fields__})

    @classmethod
    def load(cls, path: str | Path) -> MapSnapshot:
        with np.load(path) as data:
            return cls(**{k: data[k] for k in cls.__dataclass_fields__})


def snapshot(m: Map) -> MapSnapshot:
    """Copy the map's estimates and graph into a :class:`MapSnapshot` under the lock."""
    with m.lock:
        kfs = m.keyframes()
        pids = m.point_ids()
        th = m.config.covisibility_min_weight
        covis = sorted(
            (kf.id, o, w) for kf in kfs for o, w in kf.shared.items() if kf.id < o and w >= th
        )
        tree = [(kf.id, kf.parent) for kf in kfs if kf.parent >= 0]
        loops = sorted({(min(kf.id, o), max(kf.id, o)) for kf in kfs for o in kf.loop_edges})
        return MapSnapshot(
            kf_ids=np.array([kf.id for kf in kfs], dtype=np.int64),
            kf_timestamps=np.array([kf.timestamp for kf in kfs], dtype=np.float64),
            kf_T_wc=np.array([kf.T_wc for kf in kfs], dtype=np.float64).reshape(-1, 4, 4),
            point_ids=pids,
            points=m.positions(pids),
            point_ref_kf=m._pts.ref_kf[pids].copy(),
            covis_edges=np.array([c[:2] for c in covis], dtype=np.int64).reshape(-1, 2),
            covis_weights=np.array([c[2] for c in covis], dtype=np.int64),
            tree_edges=np.array(tree, dtype=np.int64).reshape(-1, 2),
            loop_edges=np.array(loops, dtype=np.int64).reshape(-1, 2),
        )


def check_invariants(m: Map) -> list[str]:
    """Every violation of the map's link invariants, as readable lines (empty: consistent).

    Checks: each observation is linked at both ends and only between good objects of the
    map (in an atlas, its own points: the point store is shared); bad
    points and keyframes hold no links; shared-point counts (covisibility weights) equal a
    recount from the observations and are symmetric; the spanning tree links good keyframes
    both ways, has no cycle and reaches every good keyframe from the origin; loop edges are
    symmetric.
    """
    out: list[str] = []
    with m.lock:
        s, kfs = m._pts, m._kfs
        # In an atlas the point store is shared: check this map's points only.
        own = range(s.n) if m.atlas is None else np.flatnonzero(s.owner[: s.n] == m.map_id).tolist()
        for pid in own:
            obs = s.obs[pid]
            if s.bad[pid] and obs:
                out.append(f"bad point {pid} still has observations {obs}")
            for k, idx in obs.items():
                kf = kfs.get(k)
                if kf is None or kf.bad:
                    out.append(f"point {pid} observed by missing or bad keyframe {k}")
                elif kf._point_ids[idx] != pid:
                    out.append(f"point {pid} says keyframe {k} slot {idx}, slot holds {kf._point_ids[idx]}")
        for k, kf in kfs.items():
            slots = np.flatnonzero(kf._point_ids >= 0)
            if kf.bad and (len(slots) or kf.shared):
                out.append(f"bad keyframe {k} still has links")
            count: Counter[int] = Counter()
            for idx in slots:
                pid = int(kf._point_ids[idx])
                if pid >= s.n or s.bad[pid]:
                    out.append(f"keyframe {k} slot {idx} holds missing or bad point {pid}")
                    continue
                if s.obs[pid].get(k) != idx:
                    out.append(f"keyframe {k} slot {idx} holds point {pid} which does not list it")
                if m.atlas is not None and s.owner[pid] != m.map_id:
                    out.append(f"keyframe {k} slot {idx} holds point {pid} of map {s.owner[pid]}")
                count.update(o for o in s.obs[pid] if o != k)
            if count != Counter(kf.shared):
                diff = {o: (kf.shared.get(o, 0), count.get(o, 0)) for o in set(count) | set(kf.shared)}
                diff = {o: v for o, v in diff.items() if v[0] != v[1]}
                out.append(f"keyframe {k} covisibility weights (stored, actual) differ: {diff}")
            for o, w in kf.shared.items():
                if o not in kfs or kfs[o].shared.get(k) != w:
                    out.append(f"covisibility weight {k}-{o} is not symmetric")
            for o in kf.loop_edges:
                if o not in kfs or k not in kfs[o].loop_edges:
                    out.append(f"loop edge {k}-{o} is not symmetric")
        out.extend(_check_tree(m))
    return out


def _check_tree(m: Map) -> list[str]:
    out: list[str] = []
    good = {k: kf for k, kf in m._kfs.items() if not kf.bad}
    for k, kf in good.items():
        if kf.parent >= 0:
            p = good.get(kf.parent)
            if p is None:
                out.append(f"keyframe {k} has missing or bad parent {kf.parent}")
            elif k not in p.children:
                out.append(f"keyframe {k} is not among the children of its parent {kf.parent}")
        for c in kf.children:
            if c not in good or good[c].parent != k:
                out.append(f"keyframe {k} lists child {c} whose parent is not {k}")
    if not good:
        return out
    seen, stack = set(), [m.origin_id]
    while stack:
        k = stack.pop()
        if k in seen:
            out.append(f"spanning tree has a cycle through keyframe {k}")
            continue
        seen.add(k)
        stack.extend(c for c in good[k].children if c in good)
    # Keyframes not yet connected (no shared points at all) are legitimately outside the tree.
    lost = [k for k, kf in good.items() if k not in seen and not kf.first_connection]
    if lost:
        out.append(f"keyframes not reachable from the origin in the spanning tree: {sorted(lost)}")
    return out
