"""Operations on a tracked frame shared by the tracking steps: projecting map points into
it, refining its pose against its matches, and keeping its matches clean.

ORB-SLAM (Mur-Artal, Montiel & Tardos, T-RO 2015, Sec. V) refines the frame pose after
every search (motion-only BA, :func:`orbslam_hgcn.backend.pose_only.optimize_pose`) and
drops or flags the matches the optimiser rejects.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from orbslam_hgcn.backend.pose_only import optimize_pose
from orbslam_hgcn.config import BackendConfig
from orbslam_hgcn.map import Frame, Map

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameMatches:
    """A tracked frame's inlier matches, kept so that its pose can be optimised again
    against the final map (:func:`refine_recorded_pose`).

    point_ids: (M,) int64 map points; uv: (M, 2) float32 undistorted pixels; octave: (M,)
    uint8 pyramid levels; scale_factors: (L,) float64 scale of each level and K: (3, 3)
    intrinsics, both the frame's own arrays (shared, not copied). About 17 bytes a match.
    """

    point_ids: np.ndarray
    uv: np.ndarray
    octave: np.ndarray
    scale_factors: np.ndarray
    K: np.ndarray


def project(T_cw: np.ndarray, points_w: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of world points.

    T_cw: (4, 4); points_w: (M, 3); K: (3, 3). Returns ((M, 2) undistorted pixels,
    (M,) depths); points at depth <= 0 get nan pixels.
    """
    X_c = np.asarray(points_w, dtype=np.float64).reshape(-1, 3) @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = X_c[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.where(z > 0, 1.0 / z, np.nan)
    uv = np.stack([K[0, 0] * X_c[:, 0] * inv_z + K[0, 2], K[1, 1] * X_c[:, 1] * inv_z + K[1, 2]], axis=1)
    return uv, z


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """(4, 4) copy of a rigid transform with its rotation projected back onto SO(3) (SVD).

    Products of poses drift off SO(3) by rounding; a drifted rotation makes ``inv_T``
    (which transposes) inexact, and the error grows geometrically along a chain of
    constant-velocity predictions.
    """
    out = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(out[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] = -U[:, -1]
        R = U @ Vt
    out[:3, :3] = R
    return out


def scale_motion(T: np.ndarray, r: float) -> np.ndarray:
    """(4, 4) rigid motion ``T`` scaled by ``r`` in time: rotation angle and translation
    times r (about the same axis; the constant-velocity prediction over r frame periods)."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(Rotation.from_matrix(T[:3, :3]).as_rotvec() * r).as_matrix()
    out[:3, 3] = T[:3, 3] * r
    return out


def pose_from_reference(m: Map, ref_kf_id: int, T_cr: np.ndarray) -> np.ndarray | None:
    """(4, 4) T_cw of a frame stored relative to keyframe ``ref_kf_id`` (T_cw = T_cr T_rw).

    A culled reference is replaced by its spanning-tree parent through the relative pose it
    kept (T_cp), as ORB-SLAM2 does when it writes the trajectory. None when the chain ends
    at a culled keyframe without a parent.
    """
    kf = m.keyframe(ref_kf_id)
    T = np.asarray(T_cr, dtype=np.float64)
    while kf.bad:
        if kf.parent < 0 or kf.T_cp is None:
            return None
        T = T @ kf.T_cp
        kf = m.keyframe(kf.parent)
    return T @ kf.T_cw


def good_keyframe(m: Map, kf_id: int) -> int:
    """``kf_id``, or its nearest good ancestor in the spanning tree when it was culled (-1: none)."""
    while kf_id >= 0 and m.keyframe(kf_id).bad:
        kf_id = m.keyframe(kf_id).parent
    return kf_id


def resolve_points(m: Map, pids: np.ndarray) -> np.ndarray:
    """(M,) ids with each bad point replaced by the point it was fused into, or -1.

    ORB-SLAM2 CheckReplacedInLastFrame: a point fused by local mapping lives on under
    another id; a point culled outright is gone. Only the (few) bad ids are looked up.
    """
    pids = np.asarray(pids, dtype=np.int64).copy()
    valid = np.flatnonzero(pids >= 0)
    if len(valid) == 0:
        return pids
    bad = valid[m.point_arrays(pids[valid]).bad]
    for i in bad:
        pid = int(pids[i])
        for _ in range(64):  # a fuse chain is short; the bound only guards against cycles
            p = m.point(pid)
            if not p.bad:
                break
            pid = p.replaced_by
            if pid < 0:
                break
        pids[i] = pid if pid >= 0 and not m.point(pid).bad else -1
    return pids


def refine_recorded_pose(
    m: Map, matches: FrameMatches, T_cw: np.ndarray, config: BackendConfig, min_points: int
) -> np.ndarray | None:
    """(4, 4) T_cw of a tracked frame optimised again (motion-only) against the map as it is
    now, from its recorded inlier ``matches`` (points fused since are followed to the
    survivor, culled ones left out) and starting at ``T_cw``; None when fewer than
    ``min_points`` points are left or remain inliers."""
    ids = resolve_points(m, matches.point_ids)
    keep = np.flatnonzero(ids >= 0)
    if len(keep) < min_points:
        return None
    inv_sigma2 = 1.0 / matches.scale_factors.astype(np.float64) ** 2
    res = optimize_pose(T_cw, m.positions(ids[keep]), matches.uv[keep].astype(np.float64),
                        inv_sigma2[matches.octave[keep]], matches.K, config)  # fmt: skip
    return res.T_cw if res.ok and int(res.inliers.sum()) >= min_points else None


def refresh_frame_points(frame: Frame, m: Map) -> None:
    """Replace fused points and forget culled ones in ``frame.point_ids``; a point appearing
    at two slots after the replacement keeps only its first slot."""
    frame.point_ids[:] = resolve_points(m, frame.point_ids)
    idx = np.flatnonzero(frame.point_ids >= 0)
    _, first = np.unique(frame.point_ids[idx], return_index=True)
    dup = np.ones(len(idx), dtype=bool)
    dup[first] = False
    frame.point_ids[idx[dup]] = -1
    frame.outlier[frame.point_ids < 0] = False


def optimize_frame_pose(frame: Frame, m: Map, config: BackendConfig) -> int:
    """Motion-only BA of ``frame`` against all its matched points (outlier flags are
    recomputed from scratch, as ORB-SLAM's PoseOptimization does).

    Updates frame.T_cw and frame.outlier; returns the number of inliers.
    """
    idx = np.flatnonzero(frame.point_ids >= 0)
    frame.outlier[:] = False
    if len(idx) < 3:
        return 0
    kp = frame.keypoints
    res = optimize_pose(
        frame.T_cw,
        m.positions(frame.point_ids[idx]),
        kp.uv[idx],
        kp.inv_level_sigma2[kp.octave[idx]],
        frame.camera.K,
        config,
    )
    frame.set_pose(res.T_cw)
    frame.outlier[idx[~res.inliers]] = True
    return int(res.inliers.sum())


def discard_outliers(frame: Frame) -> int:
    """Unlink the matches flagged as outliers; returns how many were dropped."""
    out = frame.outlier & (frame.point_ids >= 0)
    frame.point_ids[out] = -1
    frame.outlier[:] = False
    return int(out.sum())


def n_inliers(frame: Frame) -> int:
    """Matches to map points not flagged as outliers."""
    return int(np.count_nonzero(frame.matched))
