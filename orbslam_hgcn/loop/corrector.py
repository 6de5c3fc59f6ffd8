"""Loop correction: propagate the loop similarity, fuse duplicated points, optimise the
essential graph as a Sim(3) pose graph (ORB-SLAM LoopClosing::CorrectLoop and
Optimizer::OptimizeEssentialGraph; Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. VII-B).

In order:

1. the current keyframe gets the corrected similarity pose ``S_cw`` of the loop; each of
   its covisible keyframes i gets ``S_iw = T_ic S_cw`` (T_ic from the poses before the
   correction), and the points they observe move with them (``X' = S_iw^-1 T_iw X``, each
   point by the first neighbour that sees it); the keyframes take the rigid part
   ``[R, t / s]`` of their similarity;
2. the loop's matched points replace the current keyframe's ones; the points of the loop
   keyframe and its neighbours are projected into every corrected keyframe and fused
   (window 4): a keypoint holding a point has it replaced by the loop point, a free one
   gains the observation;
3. the covisibility links each corrected keyframe gained by the fusion, outside the
   corrected set, are the new loop connections;
4. the essential graph (spanning tree, covisibility >= 100, loop edges, the new loop
   connections) is optimised as a Sim(3) pose graph with the loop keyframe fixed
   (:func:`orbslam_hgcn.backend.pose_graph.optimize_essential_graph`, gtsam); the edges of
   the new loop connections are measured from the corrected poses, every other edge from
   the poses before the correction (ORB-SLAM's choice: it keeps the local geometry on
   either side of the loop);
5. every keyframe takes the rigid part of its optimised similarity and every point moves
   with its reference keyframe (the correcting neighbour for the points of step 1); the
   loop edge is added.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.backend.pose_graph import correct_points, optimize_essential_graph, sim3_to_se3
from orbslam_hgcn.config import BackendConfig, LoopClosingConfig
from orbslam_hgcn.geometry.se3 import inv_S
from orbslam_hgcn.loop.projection import match_points_in_keyframe
from orbslam_hgcn.loop.sim3_check import LoopMatch
from orbslam_hgcn.map import Map

log = logging.getLogger(__name__)


@dataclass
class Correction:
    """Counts of one loop correction: neighbourhood size, points moved, points replaced
    and observations added by the fusion, new loop connections, pose-graph edges."""

    n_neighbourhood: int = 0
    n_points_moved: int = 0
    n_replaced: int = 0
    n_added: int = 0
    n_loop_connections: int = 0
    n_edges: int = 0


def resolve_point(m: Map, pid: int) -> int:
    """The good point ``pid`` became through fusions, or -1 (ORB-SLAM GetReplaced)."""
    for _ in range(64):  # fusion chains are short; the bound guards against cycles
        if pid < 0:
            return -1
        p = m.point(pid)
        if not p.bad:
            return pid
        pid = p.replaced_by
    return -1


def resolve_points(m: Map, pids: np.ndarray) -> np.ndarray:
    """(M,) :func:`resolve_point` of each id (only the bad ones are looked up)."""
    out = np.asarray(pids, dtype=np.int64).copy()
    for i in np.flatnonzero(m.point_arrays(out).bad).tolist():
        out[i] = resolve_point(m, int(out[i]))
    return out


def propagate_correction(m: Map, kf_id: int, S_cw: np.ndarray, connected: list[int]):
    """Step 1. Returns ({kf: corrected S_iw}, {kf: T_iw before}, {point: correcting kf})."""
    T_wc = m.keyframe(kf_id).T_wc.copy()
    corrected: dict[int, np.ndarray] = {}
    before: dict[int, np.ndarray] = {}
    for k in connected:
        T_iw = m.keyframe(k).T_cw.copy()
        before[k] = T_iw
        corrected[k] = S_cw.copy() if k == kf_id else (T_iw @ T_wc) @ S_cw
    point_ref: dict[int, int] = {}
    for k in connected:
        _, pids = m.keyframe(k).observed_points()
        pids = pids[~m.point_arrays(pids).bad]
        pids = np.array([p for p in pids.tolist() if p not in point_ref], dtype=np.int64)
        if len(pids) == 0:
            continue
        M = inv_S(corrected[k]) @ before[k]
        m.set_point_positions(pids, m.positions(pids) @ M[:3, :3].T + M[:3, 3])
        point_ref.update((int(p), k) for p in pids)
    for k in connected:
        m.set_keyframe_pose(k, sim3_to_se3(corrected[k]))
    if point_ref:
        m.update_points(np.fromiter(point_ref, dtype=np.int64), descriptors=False)
    return corrected, before, point_ref


def fuse_current_matches(m: Map, kf_id: int, matched: np.ndarray) -> tuple[int, int]:
    """Step 2a: the loop points replace the keyframe's own. Returns (replaced, added)."""
    kf = m.keyframe(kf_id)
    replaced = added = 0
    touched = []
    for slot in np.flatnonzero(matched >= 0).tolist():
        loop = resolve_point(m, int(matched[slot]))
        if loop < 0 or kf.bad:
            continue
        cur = int(kf.point_ids[slot])
        if cur == loop:
            continue
        if cur >= 0:
            m.replace_point(cur, loop)
            replaced += 1
        elif kf_id not in m.point(loop).observations:
            m.add_observation(kf_id, loop, slot)
            added += 1
            touched.append(loop)
    if touched:
        m.update_points(np.array(touched, dtype=np.int64))
    return replaced, added


def search_and_fuse(m: Map, kf_ids: list[int], loop_pids: np.ndarray, config: LoopClosingConfig) -> tuple[int, int]:
    """Step 2b (ORB-SLAM SearchAndFuse): project the loop points into each keyframe with
    its corrected pose and fuse. Returns (replaced, added)."""
    replaced = added = 0
    for k in kf_ids:
        kf = m.keyframe(k)
        if kf.bad:
            continue
        pids = np.unique(resolve_points(m, loop_pids))
        pids = pids[pids >= 0]
        pids = pids[~np.isin(pids, kf.point_ids, kind="table")]
        if len(pids) == 0:
            continue
        grid = kf.grid
        found = match_points_in_keyframe(
            m, kf, grid, kf.T_cw, pids, config.fuse_window, min_view_cos=config.min_view_cos
        )
        touched = []
        for p, idx in zip(pids[found >= 0].tolist(), found[found >= 0].tolist()):
            p = resolve_point(m, p)
            if p < 0 or k in m.point(p).observations:
                continue
            other = int(kf.point_ids[idx])
            if other >= 0:
                if other != p:
                    m.replace_point(other, p)
                    replaced += 1
            else:
                m.add_observation(k, p, idx)
                added += 1
                touched.append(p)
        if touched:
            m.update_points(np.array(touched, dtype=np.int64))
    return replaced, added


def essential_edges(
    m: Map,
    kf_id: int,
    loop_kf_id: int,
    loop_connections: dict[int, set[int]],
    S_init: dict[int, np.ndarray],
    S_before: dict[int, np.ndarray],
) -> tuple[list[int], np.ndarray, np.ndarray]:
    """Step 4's graph: (keyframe ids, (E, 2) rows, (E, 4, 4) measured S_ji) as ORB-SLAM
    builds it (new loop connections first, then tree, loop and strong covisibility edges)."""
    min_w = m.config.essential_min_weight
    kfs = m.keyframes()
    ids = [kf.id for kf in kfs]
    row = {k: i for i, k in enumerate(ids)}
    edges: list[tuple[int, int]] = []
    meas: list[np.ndarray] = []
    inserted: set[tuple[int, int]] = set()

    def add(i: int, j: int, S_iw: np.ndarray, S_jw: np.ndarray) -> None:
        edges.append((row[i], row[j]))
        meas.append(S_jw @ inv_S(S_iw))
        inserted.add((min(i, j), max(i, j)))

    for i, conns in loop_connections.items():
        if m.keyframe(i).bad:
            continue
        for j in sorted(conns):
            if m.keyframe(j).bad:
                continue
            # ORB-SLAM keeps the current-loop keyframe pair and strong links only.
            if (i == kf_id and j == loop_kf_id) or m.covisibility_weight(i, j) >= min_w:
                add(i, j, S_init[i], S_init[j])
    for kf in kfs:
        i = kf.id
        S_iw = S_before[i]
        if kf.parent >= 0 and kf.parent in row:
            add(i, kf.parent, S_iw, S_before[kf.parent])
        for lk in sorted(kf.loop_edges):
            if lk < i and lk in row:
                add(i, lk, S_iw, S_before[lk])
        for n, w in sorted(kf.shared.items()):
            if w < min_w or n == kf.parent or n in kf.children or n in kf.loop_edges or n >= i or n not in row:
                continue
            if (min(i, n), max(i, n)) in inserted:
                continue
            add(i, n, S_iw, S_before[n])
    return ids, np.array(edges, dtype=np.int64).reshape(-1, 2), np.array(meas).reshape(-1, 4, 4)


def correct_loop(
    m: Map,
    match: LoopMatch,
    config: LoopClosingConfig | None = None,
    backend: BackendConfig | None = None,
) -> Correction:
    """Close the loop of ``match`` in ``m`` (steps 1-5); the caller holds the map still
    (local mapping paused). Global BA is separate (:mod:`orbslam_hgcn.loop.global_ba`)."""
    cfg = config or LoopClosingConfig()
    out = Correction()
    with m.lock:
        kf_id, loop_kf_id = match.kf_id, match.loop_kf_id
        m.update_connections(kf_id)
        connected = [int(k) for k in m.covisible_keyframes(kf_id) if not m.keyframe(int(k)).bad] + [kf_id]
        previous = {k: {int(x) for x in m.covisible_keyframes(k)} for k in connected}
        corrected, before, point_ref = propagate_correction(m, kf_id, match.S_cw, connected)
        out.n_neighbourhood, out.n_points_moved = len(connected), len(point_ref)
        r1, a1 = fuse_current_matches(m, kf_id, match.matched)
        r2, a2 = search_and_fuse(m, connected, match.loop_pids, cfg)
        out.n_replaced, out.n_added = r1 + r2, a1 + a2
        connected_set = set(connected)
        loop_connections: dict[int, set[int]] = {}
        for k in connected:
            if m.keyframe(k).bad:
                continue
            m.update_connections(k)
            now = {int(x) for x in m.covisible_keyframes(k)}
            loop_connections[k] = now - previous[k] - connected_set
        out.n_loop_connections = sum(len(v) for v in loop_connections.values())
        # Poses before the pose graph (corrected ones for the neighbourhood) and before
        # the whole correction (the edges' measurements).
        S_init = {kf.id: corrected.get(kf.id, kf.T_cw) for kf in m.keyframes()}
        S_before = {kf.id: before.get(kf.id, kf.T_cw) for kf in m.keyframes()}
        ids, edges, S_ji = essential_edges(m, kf_id, loop_kf_id, loop_connections, S_init, S_before)
        out.n_edges = len(edges)
        S0 = np.stack([S_init[k] for k in ids])
        row = {k: i for i, k in enumerate(ids)}
        fixed = np.ones(len(ids), dtype=bool)  # keyframes without any edge stay where they are
        fixed[edges.reshape(-1)] = False
        fixed[row[loop_kf_id]] = True
        S_opt = optimize_essential_graph(S0, edges, S_ji, fixed, config=backend)
        m.set_keyframe_poses(np.array(ids), sim3_to_se3(S_opt))
        pids = m.point_ids()
        refs = np.array([point_ref.get(int(p), m.point(int(p)).ref_kf) for p in pids], dtype=np.int64)
        known = np.isin(refs, ids)
        ref_rows = np.array([row[int(r)] for r in refs[known]], dtype=np.int64)
        m.set_point_positions(pids[known], correct_points(m.positions(pids[known]), ref_rows, S0, S_opt))
        m.update_points(pids[known], descriptors=False)
        m.add_loop_edge(loop_kf_id, kf_id)
    log.info(
        "loop %d-%d corrected: %d keyframes moved with the loop, %d points replaced, %d observations added, "
        "%d new loop connections, %d pose-graph edges",
        kf_id, loop_kf_id, out.n_neighbourhood, out.n_replaced, out.n_added, out.n_loop_connections, out.n_edges,
    )  # fmt: skip
    return out
