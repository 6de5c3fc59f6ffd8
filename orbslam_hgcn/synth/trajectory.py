"""Camera paths for synthetic sequences, and loop-closure ground truth.

* :class:`LoopPath`: a hand-held loop around the desk (scene frame), periodic in time so
  the last frame comes back to the first pose; built from integer harmonics of the loop
  phase (slow swings of radius, height, gaze and roll, plus a faint tremor).
* :class:`ReplayPath`: any TUM ground truth, positions interpolated linearly and
  rotations by slerp at arbitrary times.
* :func:`fit_scene_to_trajectory`: builds a scene around a real trajectory: "up" from the
  camera axes, the desk where the optical axes converge, the room around the path.
* :func:`loop_ground_truth`: which frame pairs see the same place from a similar direction.

Camera frames follow TUM / OpenCV: x right, y down, z forward.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from orbslam_hgcn.synth.layout import DeskSpec, build_scene
from orbslam_hgcn.synth.scene import Scene
from orbslam_hgcn.errors import DatasetError
from orbslam_hgcn.trajectory import Trajectory

log = logging.getLogger(__name__)


def look_at(positions: np.ndarray, targets: np.ndarray, up: np.ndarray, roll: np.ndarray | None = None) -> np.ndarray:
    """(N, 4, 4) poses T_wc at positions (N, 3) looking at targets (N, 3), image y along -up,
    then rolled by ``roll`` (N,) radians about the optical axis."""
    z = targets - positions
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(z, np.broadcast_to(up, z.shape))  # right = forward x up
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=2)
    if roll is not None:
        c, s = np.cos(roll), np.sin(roll)
        Rz = np.zeros((len(roll), 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
        R = R @ Rz
    T = np.tile(np.eye(4), (len(positions), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = positions
    return T


class LoopPath:
    """A closed hand-held loop around the desk, in the scene frame (z up).

    The camera walks once round an ellipse whose semi-axes clear the desk by ``clearance``
    metres, at about ``eye_height`` metres, looking at the desk top with slowly wandering
    gaze; every wobble is an integer harmonic of the loop phase, so pose(period) == pose(0).
    With ``laps`` > 1, ``period`` is one lap and the path drifts from lap to lap (it closes
    after the last one).
    """

    def __init__(self, desk: DeskSpec, period: float, seed: int, clearance: float = 1.05,
                 eye_height: float = 1.45, laps: int = 1):
        rng = np.random.default_rng([int(seed), 11])
        self.period = float(period)
        self.a = desk.length / 2 + clearance
        self.b = desk.depth / 2 + clearance
        self.eye_height = eye_height
        self.target_height = desk.height + 0.12
        self.phase0 = float(rng.uniform(0, 2 * np.pi))
        self.speed = rng.normal(0, 1, 2) * [0.12, 0.05]  # time-warp of the phase (k = 1, 2)
        self.speed_ph = rng.uniform(0, 2 * np.pi, 2)

        def harmonics(ks, amp):
            ks = np.asarray(ks, np.float64)
            return ks, rng.normal(0, 1, len(ks)) * amp / np.sqrt(len(ks)), rng.uniform(0, 2 * np.pi, len(ks))

        self.radius = harmonics([2, 3, 4, 5], 0.06)  # relative
        self.height = harmonics([1, 2, 3, 4, 6], 0.08)  # m
        self.gaze_x = harmonics([1, 2, 3, 5], 0.25)  # m, target offsets on the desk
        self.gaze_y = harmonics([1, 2, 3, 5], 0.15)
        self.gaze_z = harmonics([2, 3], 0.06)
        self.roll = harmonics([1, 2, 3, 5], np.radians(4.0))
        self.tremor = harmonics(np.arange(40, 56), 0.002)  # m, hand shake
        self.tremor_rot = harmonics(np.arange(40, 56), np.radians(0.15))
        # Several laps never retrace one path: slow drifts of the radius, height and gaze with
        # a period of all the laps (sub-harmonics of the loop phase), so the path closes after
        # the last lap and each lap passes 0.1-0.2 m and a few degrees beside the others.
        self.laps = int(laps)
        lap_rng = np.random.default_rng([int(seed), 12])
        sub = np.arange(1, self.laps) / self.laps  # empty for one lap
        self.lap_radius = (sub, np.full(len(sub), 0.08), lap_rng.uniform(0, 2 * np.pi, len(sub)))
        self.lap_height = (sub, np.full(len(sub), 0.10), lap_rng.uniform(0, 2 * np.pi, len(sub)))
        self.lap_gaze = (sub, np.full(len(sub), 0.20), lap_rng.uniform(0, 2 * np.pi, len(sub)))

    @staticmethod
    def _sum(h, phi: np.ndarray) -> np.ndarray:
        ks, amp, ph = h
        return np.sin(np.outer(phi, ks) + ph) @ amp

    def phase(self, t: np.ndarray) -> np.ndarray:
        """Loop phase in radians, increasing monotonically by 2 pi per period."""
        tau = 2 * np.pi * np.asarray(t, np.float64) / self.period
        k = np.array([1.0, 2.0])
        return self.phase0 + tau + (np.sin(np.outer(tau, k) + self.speed_ph) @ (self.speed / k))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) scene-frame poses T_sc at times t (N,) seconds."""
        phi = self.phase(np.atleast_1d(t))
        r = 1.0 + self._sum(self.radius, phi) + self._sum(self.lap_radius, phi)
        pos = np.stack([self.a * r * np.cos(phi), self.b * r * np.sin(phi),
                        self.eye_height + self._sum(self.height, phi) + self._sum(self.lap_height, phi)], axis=1)
        pos += np.stack([self._sum(self.tremor, phi + k) for k in range(3)], axis=1)
        target = np.stack([self._sum(self.gaze_x, phi) + self._sum(self.lap_gaze, phi), self._sum(self.gaze_y, phi),
                           self.target_height + self._sum(self.gaze_z, phi)], axis=1)
        target += np.stack([self._sum(self.tremor_rot, phi + k) for k in range(3, 6)], axis=1) * \
            np.linalg.norm(target - pos, axis=1, keepdims=True)
        roll = self._sum(self.roll, phi)
        return look_at(pos, target, np.array([0.0, 0.0, 1.0]), roll)

    def params(self) -> dict:
        return {"kind": "loop", "period_s": self.period, "semi_axes_m": [self.a, self.b],
                "eye_height_m": self.eye_height, "target_height_m": self.target_height}


class ReplayPath:
    """Poses of a recorded trajectory at any time: linear positions, slerp rotations."""

    def __init__(self, traj: Trajectory):
        if len(traj) < 2:
            raise DatasetError("replay needs a ground-truth trajectory with at least 2 poses")
        t = traj.timestamps
        if np.any(np.diff(t) <= 0):
            keep = np.concatenate([[True], np.diff(t) > 0])
            t, poses = t[keep], traj.poses[keep]
        else:
            poses = traj.poses
        self.times = t
        self.positions = poses[:, :3, 3]
        self._slerp = Slerp(t, Rotation.from_matrix(poses[:, :3, :3]))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses T_wc at times t (N,), clamped to the recorded span."""
        t = np.clip(np.atleast_1d(np.asarray(t, np.float64)), self.times[0], self.times[-1])
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3] = self._slerp(t).as_matrix()
        for k in range(3):
            T[:, k, 3] = np.interp(t, self.times, self.positions[:, k])
        return T

    def frame_times(self, fps: float, n_frames: int | None = None) -> np.ndarray:
        """Timestamps at ``fps`` from the first recorded time to the last (or n_frames of them)."""
        n = int(np.floor((self.times[-1] - self.times[0]) * fps + 1e-6)) + 1
        if n_frames is not None:
            n = min(n, int(n_frames))
        return self.times[0] + np.arange(n) / fps


def estimate_up(R_wc: np.ndarray) -> np.ndarray:
    """World "up" (3,) from camera orientations (N, 3, 3).

    Hand-held cameras keep their x axis nearly horizontal, so up is the direction most
    perpendicular to all x axes (smallest eigenvector of sum x x^T), signed like the mean
    of the cameras' -y axes; when the x axes do not pin it down (a camera rolling a lot)
    the mean -y axis is used.
    """
    x = R_wc[:, :, 0]
    w, V = np.linalg.eigh(x.T @ x / len(x))
    minus_y = -R_wc[:, :, 1].mean(axis=0)
    up = V[:, 0]
    if w[1] < 4 * w[0] + 0.02:
        up = minus_y
    up = up / np.linalg.norm(up)
    return up if up @ minus_y >= 0 else -up


def axes_convergence(positions: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Least-squares closest point (3,) to the lines positions (N, 3) + s * axes (N, 3)."""
    d = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (N, 3, 3) projectors
    A = P.sum(axis=0)
    b = np.einsum("nij,nj->i", P, positions)
    return np.linalg.lstsq(A, b, rcond=None)[0]


def fit_scene_to_trajectory(poses_wc: np.ndarray, scene_seed: int, clearance: float = 0.3) -> tuple[Scene, dict]:
    """Build a scene around a recorded trajectory (N, 4, 4) T_wc; returns (scene, fit info).

    * up: :func:`estimate_up`; the scene frame has z = up and x = the main horizontal
      direction of the path.
    * desk top height: 0.65 m below the median camera height, but between the least-squares
      convergence point of the optical axes and 0.6 m above it; floor 0.74 m lower (or
      0.3 m below the lowest camera).
    * desk centre: where the optical axes meet the desk-top plane (median of their hits,
      axes pointing down only). When the camera circles a wide desk, the least-squares
      convergence point lies below the desk top and off the centre of what is looked at;
      it is the fallback when fewer than 10 axes point down.
    * desk size: the largest (from 1.8 x 1.2 m down) that keeps ``clearance`` metres in
      plan from every camera position; furniture keeps 0.45 m; walls 1.5 m beyond the path.
    """
    P = poses_wc[:, :3, 3]
    axes = poses_wc[:, :3, 2]
    up = estimate_up(poses_wc[:, :3, :3])
    c = axes_convergence(P, axes)
    h = (P - c) @ up
    desk_top = float(np.clip(np.median(h) - 0.65, 0.0, 0.6))  # above c, along up
    down = axes @ up < -0.1
    centre = c + desk_top * up
    hits = np.zeros((0, 3))
    if down.sum() >= 10:
        s = (desk_top - h[down]) / (axes[down] @ up)
        hits = P[down] + s[:, None] * axes[down]
        near = s < 4.0
        hits = hits[near]
        if near.sum() >= 10:
            centre = np.median(hits, axis=0)
            centre -= ((centre - c) @ up - desk_top) * up
    horiz = (P - c) - np.outer(h, up)
    _, _, Vt = np.linalg.svd(horiz - horiz.mean(0), full_matrices=False)
    x = Vt[0] - (Vt[0] @ up) * up
    x /= np.linalg.norm(x)
    y = np.cross(up, x)
    floor = min(-0.74, float(h.min()) - desk_top - 0.3)  # relative to the desk top
    T_ws = np.eye(4)
    T_ws[:3, :3] = np.column_stack([x, y, up])
    T_ws[:3, 3] = centre + floor * up
    P_s = (P - T_ws[:3, 3]) @ T_ws[:3, :3]  # camera centres in the scene frame
    L, D = 1.8, 1.2
    while L > 0.6 and not _desk_clear(P_s, L, D, clearance):
        L, D = L * 0.95, D * 0.95
    lo = np.minimum(P_s[:, :2].min(0), [-L / 2, -D / 2]) - 1.5
    hi = np.maximum(P_s[:, :2].max(0), [L / 2, D / 2]) + 1.5
    height = max(2.6, float(P_s[:, 2].max()) + 1.0)
    focus = ((hits - T_ws[:3, 3]) @ T_ws[:3, :3])[::max(1, len(hits) // 500), :2]
    scene = build_scene(scene_seed, DeskSpec(L, D, -floor), (lo[0], hi[0], lo[1], hi[1], height),
                        keep_out=P_s, T_world_scene=T_ws, focus=focus)
    info = {"up": up.tolist(), "axes_convergence": c.tolist(), "desk_centre": centre.tolist(),
            "desk_size_m": [L, D], "desk_height_m": -floor,
            "camera_height_m": [float(P_s[:, 2].min()), float(P_s[:, 2].max())]}
    log.info("replay scene: desk %.2f x %.2f m, room %.1f x %.1f x %.1f m", L, D, hi[0] - lo[0], hi[1] - lo[1], height)
    return scene, info


def _desk_clear(P_s: np.ndarray, L: float, D: float, clearance: float) -> bool:
    gap = np.maximum(np.abs(P_s[:, :2]) - [L / 2, D / 2], 0.0)
    return bool(np.linalg.norm(gap, axis=1).min() >= clearance)


def loop_ground_truth(poses_wc: np.ndarray, max_dist: float = 0.5, max_angle_deg: float = 30.0) -> np.ndarray:
    """(N, N) bool: frames i and j show the same place from a similar direction.

    True when the camera centres are within ``max_dist`` metres and the optical axes
    within ``max_angle_deg`` degrees; the diagonal is True. poses_wc: (N, 4, 4) T_wc.
    """
    P = poses_wc[:, :3, 3]
    z = poses_wc[:, :3, 2]
    sq = np.einsum("ij,ij->i", P, P)
    d2 = sq[:, None] + sq[None, :] - 2.0 * (P @ P.T)
    cos = np.clip(z @ z.T, -1.0, 1.0)
    return (d2 <= max_dist ** 2) & (cos >= np.cos(np.radians(max_angle_deg)))
