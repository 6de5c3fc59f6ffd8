"""Bundle-adjustment windows: a Map region as plain arrays, and writing results back.

The backend takes and returns arrays; these two functions are the conversion. The local
window follows ORB-SLAM's LocalBundleAdjustment (T-RO 2015, Sec. VI-D): the new keyframe
and its covisible keyframes are free, every other keyframe that sees one of their points is
fixed, and the origin keyframe is always fixed.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.map.map import Map

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BAWindow:
    """A bundle-adjustment problem cut from the map.

    kf_ids:     (K,) int64 keyframe ids; T_cw (K, 4, 4) their poses; fixed (K,) bool
    point_ids:  (P,) int64 map point ids; points (P, 3) their positions
    obs_kf:     (O,) int64 row into kf_ids of each observation
    obs_pt:     (O,) int64 row into point_ids
    obs_feat:   (O,) int64 feature index in the keyframe
    uv:         (O, 2) float64 undistorted keypoint coords
    inv_sigma2: (O,) float64 keypoint information (1 / scale_factor ** (2 octave))
    K:          (3, 3) intrinsics (all keyframes share one camera)
    """

    kf_ids: np.ndarray
    T_cw: np.ndarray
    fixed: np.ndarray
    point_ids: np.ndarray
    points: np.ndarray
    obs_kf: np.ndarray
    obs_pt: np.ndarray
    obs_feat: np.ndarray
    uv: np.ndarray
    inv_sigma2: np.ndarray
    K: np.ndarray

    @property
    def n_observations(self) -> int:
        return len(self.obs_kf)


def _window(m: Map, free: list[int], fixed_extra: bool) -> BAWindow:
    """The points seen by the keyframes ``free`` and all their observations, as arrays;
    with ``fixed_extra`` the other keyframes observing those points join as fixed ones
    (otherwise their observations are left out). Observations come point after point, each
    point's in the order they were made."""
    kfs = {k: m.keyframe(k) for k in free}
    pids_list: list[np.ndarray] = [kfs[k].observed_points()[1] for k in free]
    pids = np.unique(np.concatenate(pids_list)) if pids_list else np.zeros(0, dtype=np.int64)
    pids = pids[~m._pts.bad[pids]].astype(np.int64)
    obs = [m._pts.obs[p] for p in pids.tolist()]
    sizes = np.fromiter(map(len, obs), dtype=np.int64, count=len(obs))
    total = int(sizes.sum())
    o_kf_id = np.fromiter(itertools.chain.from_iterable(o.keys() for o in obs), dtype=np.int64, count=total)
    o_feat = np.fromiter(itertools.chain.from_iterable(o.values() for o in obs), dtype=np.int64, count=total)
    o_pt = np.repeat(np.arange(len(pids), dtype=np.int64), sizes)
    free_a = np.asarray(free, dtype=np.int64)
    fixed_ids = np.zeros(0, dtype=np.int64)
    if fixed_extra and total:
        fixed_ids = np.unique(o_kf_id[~np.isin(o_kf_id, free_a)])
    kf_ids = np.concatenate([free_a, fixed_ids])
    lut = np.full(int(max(kf_ids.max(initial=-1), o_kf_id.max(initial=-1))) + 1, -1, dtype=np.int64)
    lut[kf_ids] = np.arange(len(kf_ids))
    o_kf = lut[o_kf_id]
    keep = o_kf >= 0
    if not keep.all():
        o_kf, o_pt, o_feat = o_kf[keep], o_pt[keep], o_feat[keep]
    uv = np.zeros((len(o_kf), 2))
    inv_s2 = np.zeros(len(o_kf))
    order = np.argsort(o_kf, kind="stable")
    bounds = np.searchsorted(o_kf[order], np.arange(len(kf_ids) + 1))
    for i, k in enumerate(kf_ids.tolist()):
        sel = order[bounds[i] : bounds[i + 1]]
        kp = m.keyframe(int(k)).keypoints
        uv[sel] = kp.uv[o_feat[sel]]
        inv_s2[sel] = kp.inv_level_sigma2[kp.octave[o_feat[sel]]]
    fixed = np.concatenate([free_a == m.origin_id, np.ones(len(fixed_ids), dtype=bool)])
    any_kf = m.keyframe(int(kf_ids[0])) if len(kf_ids) else None
    return BAWindow(
        kf_ids=kf_ids,
        T_cw=np.array([m.keyframe(int(k)).T_cw for k in kf_ids.tolist()]).reshape(-1, 4, 4),
        fixed=fixed,
        point_ids=pids,
        points=m.positions(pids),
        obs_kf=o_kf,
        obs_pt=o_pt,
        obs_feat=o_feat,
        uv=uv,
        inv_sigma2=inv_s2,
        K=any_kf.camera.K if any_kf is not None else np.eye(3),
    )


def local_window(m: Map, kf_id: int, max_free: int | None = None) -> BAWindow:
    """The local BA problem around keyframe ``kf_id`` (it and its covisible keyframes free).

    max_free: at most this many free keyframes (the keyframe and its best covisible ones);
    the other covisible keyframes are then fixed like the rest. None: all are free.
    """
    with m.lock:
        free = [kf_id] + [int(k) for k in m.covisible_keyframes(kf_id) if not m.keyframe(int(k)).bad]
        if max_free is not None and max_free > 0:
            free = free[:max_free]
        return _window(m, free, fixed_extra=True)


def global_window(m: Map) -> BAWindow:
    """Every good keyframe and point; only the origin keyframe is fixed."""
    with m.lock:
        return _window(m, [int(k) for k in m.keyframe_ids()], fixed_extra=False)


def apply_window(m: Map, w: BAWindow, T_cw: np.ndarray, points: np.ndarray, outlier: np.ndarray | None = None) -> int:
    """Write optimised poses of the free keyframes and point positions, erase the observations
    flagged in ``outlier`` (O,) bool, and refresh the points' viewing ranges. Keyframes or
    points that became bad meanwhile are skipped. Returns the number of erased observations."""
    with m.lock:
        erased = 0
        if outlier is not None:
            for o in np.flatnonzero(outlier):
                kf_id, pid = int(w.kf_ids[w.obs_kf[o]]), int(w.point_ids[w.obs_pt[o]])
                if not m.keyframe(kf_id).bad and kf_id in m._pts.obs[pid]:
                    m.erase_observation(kf_id, pid)
                    erased += 1
        for i in np.flatnonzero(~w.fixed):
            if not m.keyframe(int(w.kf_ids[i])).bad:
                m.set_keyframe_pose(int(w.kf_ids[i]), T_cw[i])
        good = ~m._pts.bad[w.point_ids]
        m.set_point_positions(w.point_ids[good], points[good])
        m.update_points(w.point_ids[good], descriptors=False)
        return erased
