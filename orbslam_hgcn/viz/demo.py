"""A synthetic SLAM run for checking the visualiser without running SLAM.

The camera circles a ball of random map points, looking at its centre, and closes one loop
when it returns to the start. Before the loop the estimate drifts away linearly; the loop
closure removes the drift (the corrected map replaces the drifted one). Frames, map
snapshots, keyframe inserts and the loop are what a pipeline would hand to
:class:`~orbslam_hgcn.viz.rerun_logger.RerunLogger`.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import make_T
from orbslam_hgcn.viz.records import FrameLog, MapSnapshot

if TYPE_CHECKING:
    from orbslam_hgcn.viz.rerun_logger import RerunLogger


@dataclass(frozen=True, eq=False)
class FakeStep:
    """One frame of the synthetic run.

    frame: what the pipeline logs every frame; snapshot: the map after this frame
    (arrays are views of the run's buffers); gt_position: (3,) true camera centre.
    """

    frame: FrameLog
    snapshot: MapSnapshot
    keyframe_inserted: bool
    loop: tuple[int, int] | None
    gt_position: np.ndarray


def demo_camera(width: int = 640, height: int = 480) -> PinholeCamera:
    """An undistorted camera with a 65 degree horizontal field of view."""
    f = 0.5 * width / np.tan(np.radians(32.5))
    return PinholeCamera(fx=f, fy=f, cx=width / 2, cy=height / 2, width=width, height=height, name="demo")


def look_at_T_wc(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) T_wc of a camera at ``centre`` looking at ``target``, image y along world +y."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.stack([x, y, z], axis=1), centre)


def texture(width: int, height: int, seed: int = 0) -> np.ndarray:
    """(H, W) uint8 blurred-noise image with the spectrum of a cluttered indoor scene."""
    rng = np.random.default_rng(seed)
    img = rng.random((height, width)).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 3.0) + 0.3 * cv2.GaussianBlur(img, (0, 0), 0.8)
    img = (img - img.min()) / (np.ptp(img) + 1e-9)
    return (img * 255).astype(np.uint8)


def fake_run(
    n_frames: int = 30,
    *,
    n_points: int = 2000,
    n_keypoints: int = 300,
    keyframe_every: int = 5,
    loop_at: int | None = 20,
    covis_neighbours: int = 4,
    radius: float = 2.0,
    drift: float = 0.3,
    camera: PinholeCamera | None = None,
    images: Sequence[np.ndarray] | None = None,
    seed: int = 0,
) -> Iterator[FakeStep]:
    """Yield ``n_frames`` steps of the synthetic run.

    The map grows linearly to ``n_points`` points and gains a keyframe every
    ``keyframe_every`` frames (and at the loop), each joined to its ``covis_neighbours``
    predecessors. The camera completes a circle of ``radius`` at frame ``loop_at``, where a
    loop joins the newest keyframe to keyframe 0 (None: no loop). ``images`` (cycled) are the
    logged images; default a shifting synthetic texture.
    """
    rng = np.random.default_rng(seed)
    cam = camera or demo_camera()
    period = loop_at if loop_at else max(n_frames, 1)
    pts = rng.normal(scale=0.45, size=(n_points, 3))
    obs = rng.integers(2, 25, size=n_points)
    base = texture(cam.width + n_frames, cam.height, seed) if images is None else None
    drift_dir = np.array([1.0, -0.3, 0.5]) / np.linalg.norm([1.0, -0.3, 0.5])
    n_kf_max = n_frames // keyframe_every + 2
    kf_ids = np.arange(n_kf_max, dtype=np.int64)
    kf_T = np.zeros((n_kf_max, 4, 4))
    kf_true = np.zeros((n_kf_max, 4, 4))
    covis: list[tuple[int, int]] = []
    loops: list[tuple[int, int]] = []
    n_kf = 0
    for i in range(n_frames):
        theta = 2 * np.pi * i / period
        centre = np.array([radius * np.sin(theta), 0.0, -radius * np.cos(theta)])
        T_true = look_at_T_wc(centre, np.zeros(3))
        corrected = loop_at is not None and i >= loop_at
        offset = np.zeros(3) if corrected else drift * (i / period) * drift_dir
        T_est = T_true.copy()
        T_est[:3, 3] += offset
        is_loop = loop_at is not None and i == loop_at
        kf_inserted = i % keyframe_every == 0 or is_loop
        if kf_inserted:
            kf_true[n_kf] = T_true
            kf_T[n_kf] = T_est
            covis += [(n_kf - d, n_kf) for d in range(1, min(covis_neighbours, n_kf) + 1)]
            n_kf += 1
        loop = (n_kf - 1, 0) if is_loop else None
        if loop:
            loops.append(loop)
            kf_T[:n_kf] = kf_true[:n_kf]  # the correction removes the drift of every keyframe
        n_p = max(1, n_points * (i + 1) // n_frames)
        shift = np.zeros(3) if corrected else offset
        # keypoints: projections of the visible map points (tracked) plus clutter (untracked)
        X_c = (pts - T_true[:3, 3]) @ T_true[:3, :3]
        uv, z = cam.project(X_c)
        vis = np.flatnonzero((z > 0) & cam.in_image(uv))[: int(0.7 * n_keypoints)]
        clutter = rng.random((n_keypoints - len(vis), 2)) * [cam.width, cam.height]
        kp = np.vstack([uv[vis], clutter])
        tracked = np.arange(len(kp)) < len(vis)
        image = images[i % len(images)] if images is not None else np.ascontiguousarray(base[:, i : i + cam.width])
        frame = FrameLog(
            index=i, timestamp=i / cam.fps, image=image, keypoints_uv=kp, tracked=tracked,
            T_wc=T_est, state="OK" if i > 0 else "NOT_INITIALIZED", n_tracked=len(vis),
            fps=cam.fps, n_keyframes=n_kf, n_map_points=n_p,
        )
        snapshot = MapSnapshot(
            keyframe_ids=kf_ids[:n_kf], keyframe_T_wc=kf_T[:n_kf], point_ids=np.arange(n_p),
            points_w=pts[:n_p] + shift, point_obs_count=obs[:n_p],
            covis_edges=np.array(covis, dtype=np.int64).reshape(-1, 2),
            loop_edges=np.array(loops, dtype=np.int64).reshape(-1, 2),
        )
        yield FakeStep(frame, snapshot, kf_inserted, loop, centre)


def replay(logger: RerunLogger, steps: Iterator[FakeStep]) -> list[FakeStep]:
    """Log a synthetic run as a pipeline would: every frame, the map when due, the loop,
    the ATE of the positions so far, and the ground truth with each map log."""
    done: list[FakeStep] = []
    sq_sum = 0.0
    for step in steps:
        logger.log_step(step.frame, lambda s=step: s.snapshot,
                        keyframe_inserted=step.keyframe_inserted, loop=step.loop)
        done.append(step)
        sq_sum += float(np.sum((step.frame.T_wc[:3, 3] - step.gt_position) ** 2))
        logger.log_ate(np.sqrt(sq_sum / len(done)), step.frame.index)
        if logger.last_map_frame == step.frame.index:
            logger.log_ground_truth(np.array([s.gt_position for s in done]), step.frame.index)
    return done
