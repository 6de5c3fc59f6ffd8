"""Map merging: the active map and another map of the atlas, joined where the camera
recognises a place of the other map (ORB-SLAM3's map merging; Campos et al., "ORB-SLAM3",
T-RO 2021, Sec. VI).

The match comes from loop detection (:mod:`.detector`), which searches the keyframes of
every map, and the same geometric verification as a loop (:func:`.sim3_check.compute_sim3`):
a similarity ``S_cm`` between the current keyframe (active map) and a keyframe of the
other map, with at least 40 matched points. Then:

1. the other map is moved into the active map's frame and scale: its keyframes and points
   by ``S_ao = T_aw(current)^-1 S_cm T_ow(match)``, which puts the matched keyframe where the
   match says it is seen from the current keyframe;
2. its keyframes and points join the active map (their ids are kept: the maps of an atlas
   share their id spaces); its spanning tree is re-rooted at the matched keyframe and hung
   under the current one;
3. from there on the match is a loop inside one map, closed as one
   (:func:`.corrector.correct_loop`): duplicated points around the seam are fused, the
   covisibility links the fusion creates become loop connections, and the essential graph
   is optimised as a Sim(3) pose graph, which spreads the error left at the seam over both
   sides;
4. a welding bundle adjustment: local BA around the current keyframe, whose window now
   spans keyframes of both former maps.

ORB-SLAM3 moves the active map into the other map's frame; here the other map moves, so
that the tracker, local mapping and everything holding the active map keep their map and
frame (a merge must not disturb the real-time path). The result differs by one
similarity of the whole map, which no evaluation after Sim(3) alignment sees.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from orbslam_hgcn.backend.problem import as_problem
from orbslam_hgcn.backend.pose_graph import sim3_to_se3
from orbslam_hgcn.backend.solver import InProcessSolver
from orbslam_hgcn.config import BackendConfig, LoopClosingConfig
from orbslam_hgcn.geometry.se3 import inv_S, inv_T
from orbslam_hgcn.loop.corrector import Correction, correct_loop
from orbslam_hgcn.loop.sim3_check import LoopMatch
from orbslam_hgcn.map import Map
from orbslam_hgcn.map.window import apply_window, local_window

log = logging.getLogger(__name__)


@dataclass
class MergeEvent:
    """One merge: the current keyframe (active map) and the matched one (other map), their
    frames, the maps, the similarity that moved the other map (``S_ao``, (4, 4)) and its
    scale, counts of what moved and of the correction, step times (ms)."""

    kf_id: int
    match_kf_id: int
    frame_id: int
    match_frame_id: int
    active_map: int
    merged_map: int
    S_ao: np.ndarray
    scale: float
    n_keyframes_moved: int
    n_points_moved: int
    n_matches: int
    correction: Correction
    welding_ba_keyframes: int = 0
    time_ms: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = {k: v for k, v in asdict(self).items() if k not in ("S_ao", "correction")}
        d["S_ao"] = self.S_ao.tolist()
        d["correction"] = vars(self.correction)
        return d


def _reroot(m: Map, new_root: int) -> None:
    """Make ``new_root`` the root of its spanning tree by reversing the parent links on
    its path to the old root."""
    path = [new_root]
    while m.keyframe(path[-1]).parent >= 0:
        path.append(m.keyframe(path[-1]).parent)
        if len(path) > len(m._kfs) + 1:  # a cycle would be a corrupted tree
            raise RuntimeError(f"spanning tree of keyframe {new_root} has a cycle")
    for i in range(len(path) - 1, 0, -1):
        m.change_parent(path[i], path[i - 1])
    kf = m.keyframe(new_root)
    if kf.parent >= 0:
        m.keyframe(kf.parent).children.discard(new_root)
    kf.parent = -1


def move_into(active: Map, other: Map, S_ao: np.ndarray, kf_id: int, match_kf_id: int) -> tuple[int, int]:
    """Steps 1 and 2: move every keyframe and point of ``other`` into ``active`` through
    the similarity ``S_ao`` (other-map coordinates to active-map coordinates), hang its
    tree under keyframe ``kf_id`` through ``match_kf_id``, and take ``other`` out of the
    atlas. Returns (keyframes moved, points moved). The caller holds the atlas lock."""
    atlas = active.atlas
    s = float(np.cbrt(np.linalg.det(S_ao[:3, :3])))
    S_oa = inv_S(S_ao)
    moved_kfs = 0
    for kf in other._kfs.values():
        if not kf.bad:
            kf._set_pose(sim3_to_se3(kf.T_cw @ S_oa))
            moved_kfs += 1
        if kf.T_cp is not None:  # a culled keyframe's pose relative to its parent
            T_cp = kf.T_cp.copy()
            T_cp[:3, 3] *= s
            kf.T_cp = T_cp
    for hook in atlas.merge_hooks:
        hook(set(other._kfs), s)
    store = other._pts
    pids = other.point_ids()
    if len(pids):
        store.position[pids] = store.position[pids] @ S_ao[:3, :3].T + S_ao[:3, 3]
    everything = np.flatnonzero(store.owner[: store.n] == other.map_id)
    store.owner[everything] = active.map_id
    active._kfs.update(other._kfs)
    other._kfs = {}
    _reroot(active, match_kf_id)
    active.change_parent(match_kf_id, kf_id)
    active.keyframe(match_kf_id).first_connection = False
    if len(pids):
        active.update_points(pids, descriptors=False)
    atlas.remove(other)
    return moved_kfs, len(pids)


def welding_ba(m: Map, kf_id: int, backend: BackendConfig, solver: Any = None) -> int:
    """Step 4: local BA around ``kf_id`` (it and its covisible keyframes free, the rest of
    the window fixed). Returns the number of free keyframes."""
    solver = solver if solver is not None else InProcessSolver()
    with m.lock:
        w = local_window(m, kf_id)
    if w.n_observations == 0 or not (~w.fixed).any():
        return 0
    problem = as_problem(w.T_cw, w.fixed, w.points, w.obs_kf, w.obs_pt, w.uv, w.inv_sigma2, w.K)
    res, _ = solver.local_ba(problem, backend, 0.0, None)
    apply_window(m, w, res.T_cw, res.points, res.outlier)
    return int((~w.fixed).sum())


def merge_maps(
    active: Map,
    match: LoopMatch,
    config: LoopClosingConfig | None = None,
    backend: BackendConfig | None = None,
    solver: Any = None,
) -> MergeEvent:
    """Merge the map holding ``match.loop_kf_id`` into ``active`` (steps 1-4); ``match``
    is a verified match of the current keyframe ``match.kf_id`` of the active map. The
    caller holds the map still (local mapping paused), as for a loop correction."""
    cfg = config or LoopClosingConfig()
    backend = backend or BackendConfig()
    atlas = active.atlas
    t0 = time.perf_counter()
    with active.lock:
        other = atlas.map_of(match.loop_kf_id)
        if other is None or other is active:
            raise ValueError(f"keyframe {match.loop_kf_id} is not in another map of the atlas")
        kf, cand = active.keyframe(match.kf_id), other.keyframe(match.loop_kf_id)
        S_ao = inv_T(kf.T_cw) @ match.S_cm @ cand.T_cw
        scale = float(np.cbrt(np.linalg.det(S_ao[:3, :3])))
        n_kfs, n_pts = move_into(active, other, S_ao, kf.id, cand.id)
        t1 = time.perf_counter()
        # The match is now a loop inside the active map; the current keyframe already has
        # the pose the match gives it.
        loop = LoopMatch(
            kf.id, cand.id, match.S_cm, kf.T_cw.copy(), match.matched, match.loop_kf_ids, match.loop_pids,
            match.n_sim3_inliers, match.n_matches,
        )  # fmt: skip
        corr = correct_loop(active, loop, cfg, backend)
        t2 = time.perf_counter()
    n_free = welding_ba(active, kf.id, backend, solver)
    t3 = time.perf_counter()
    event = MergeEvent(
        kf.id, cand.id, kf.frame_id, cand.frame_id, active.map_id, other.map_id, S_ao, scale, n_kfs, n_pts,
        match.n_matches, corr, n_free,
        {"move": 1000.0 * (t1 - t0), "correct": 1000.0 * (t2 - t1), "welding_ba": 1000.0 * (t3 - t2)},
    )  # fmt: skip
    atlas.merges.append(event.to_dict())
    log.info("maps merged: map %d (%d keyframes, %d points) into map %d at keyframes %d-%d, scale %.3f",
             other.map_id, n_kfs, n_pts, active.map_id, kf.id, cand.id, scale)  # fmt: skip
    return event
