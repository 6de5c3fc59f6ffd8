"""Synthetic monocular sequences in the TUM RGB-D layout, with exact ground truth.

``render_sequence(out_dir, SynthOptions(...))`` writes::

    out_dir/rgb/<timestamp>.png    640x480 colour frames (BGR PNG)
    out_dir/rgb.txt                "timestamp rgb/<timestamp>.png" per frame
    out_dir/groundtruth.txt        TUM poses T_wc of every frame (mid-exposure)
    out_dir/camera.yaml            intrinsics (default: TUM freiburg3, 535.4 539.2 320.1 247.6)
    out_dir/scene.json             seeds, options, scene layout, trajectory parameters
    out_dir/loop_gt.npy            (N, N) bool revisits (with ``loop_gt``)
    out_dir/depth/, depth.txt      16-bit depth, 5000 per metre (with ``depth``)

The scene is an office room (synthetic_layout, from the scene seed) rendered exactly
(synthetic_render) along a generated loop round the desk (also from the scene seed) or a
replayed TUM trajectory (synthetic_trajectory), with textures from the texture seed.
Camera effects, in order: motion blur (the average of sub-frame renders spread over the
shutter time), exposure drift (slow gain and offset changes), Gaussian sensor noise.
The same options give byte-identical files.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from orbslam_hgcn.config import save_camera
from orbslam_hgcn.datasets.synthetic_render import SceneRenderer
from orbslam_hgcn.datasets.synthetic_layout import DeskSpec, build_scene
from orbslam_hgcn.datasets.synthetic_trajectory import LoopPath, ReplayPath, fit_scene_to_trajectory, loop_ground_truth
from orbslam_hgcn.errors import ConfigError, DatasetError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.trajectory import Trajectory, read_tum, write_tum

log = logging.getLogger(__name__)

# zlib level 1 with run-length matching: ~25 % faster than plain level 1 and ~10 % smaller
# on these frames (measured with OpenCV 5.0).
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
MIN_LOOP_S = 10.0  # shortest loop period (s): faster would not be a hand-held walk
_OUTPUTS = ("rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "camera.yaml", "scene.json", "loop_gt.npy")


@dataclass(frozen=True)
class SynthOptions:
    """Options of a synthetic sequence (defaults: a 30 s loop, TUM fr3 camera, no effects)."""

    trajectory: str = "loop"  # "loop" (generated, closes on itself) or "replay" (a TUM file)
    gt: str | None = None  # TUM ground truth to replay (trajectory="replay")
    frames: int | None = None  # number of frames; default: duration, or the whole replayed file
    duration: float | None = None  # seconds; default 30 s for the loop (one lap per sequence,
    #                                sequences under MIN_LOOP_S show the start of a 10 s lap)
    fps: float = 30.0
    fx: float = 535.4  # TUM freiburg3 intrinsics (Sturm et al., IROS 2012)
    fy: float = 539.2
    cx: float = 320.1
    cy: float = 247.6
    width: int = 640
    height: int = 480
    noise: float = 0.0  # Gaussian sensor noise sigma, grey levels
    exposure_drift: float = 0.0  # relative gain swing (0.2: +-20 %), with offsets of 12x this in levels
    motion_blur: bool = False  # average sub-frame renders over the shutter time
    shutter: float = 0.5  # shutter time as a fraction of the frame interval
    seed: int = 0  # sensor noise and exposure drift
    scene_seed: int = 0  # room layout, objects and the loop's wobble
    texture_seed: int | None = None  # surface textures (default: scene_seed)
    repeated_texture: bool = False  # one texture patch repeated on every surface
    texel_scale: float = 1.0  # texel sizes times this (coarser, faster textures when > 1)
    loop_gt: bool = False  # write loop_gt.npy
    loop_gt_dist: float = 0.5  # loop ground truth: camera centres closer than this (m)
    loop_gt_angle: float = 30.0  # ... and optical axes closer than this (degrees)
    depth: bool = False  # also write TUM depth images

    @property
    def camera(self) -> PinholeCamera:
        return PinholeCamera(self.fx, self.fy, self.cx, self.cy, self.width, self.height, fps=self.fps,
                             name="synthetic_tum_fr3")

    def validate(self) -> None:
        if self.trajectory not in ("loop", "replay"):
            raise ConfigError(f"trajectory must be 'loop' or 'replay', not {self.trajectory!r}")
        if self.trajectory == "replay" and not self.gt:
            raise ConfigError("trajectory 'replay' needs a ground-truth file (--gt)")
        if self.frames is not None and self.frames < 1:
            raise ConfigError(f"frames must be at least 1, not {self.frames}")
        if self.duration is not None and self.duration <= 0:
            raise ConfigError(f"duration must be positive, not {self.duration}")
        if self.fps <= 0 or self.noise < 0 or self.exposure_drift < 0 or not 0 < self.shutter <= 1:
            raise ConfigError("fps must be positive, noise and exposure drift non-negative, shutter in (0, 1]")
        if self.texel_scale <= 0:
            raise ConfigError(f"texel_scale must be positive, not {self.texel_scale}")


def build_sequence(options: SynthOptions):
    """The scene and camera motion of a sequence, without rendering.

    Returns (scene, pose function: times (N,) -> T_wc (N, 4, 4), frame timestamps (N,),
    JSON-able trajectory description).
    """
    if options.trajectory == "replay":
        gt = read_tum(options.gt)
        path = ReplayPath(gt)
        n = options.frames
        if n is None and options.duration is not None:
            n = int(round(options.duration * options.fps))
        stamps = path.frame_times(options.fps, n)
        scene, info = fit_scene_to_trajectory(gt.poses, options.scene_seed)
        info.update({"kind": "replay", "source": str(options.gt), "source_poses": len(gt)})
        return scene, path, stamps, info
    n = options.frames if options.frames is not None else int(round((options.duration or 30.0) * options.fps))
    period = max(n / options.fps, MIN_LOOP_S)  # shorter sequences: the start of a walkable loop
    desk_rng = np.random.default_rng([int(options.scene_seed), 5])
    desk = DeskSpec(float(desk_rng.uniform(1.4, 1.8)), float(desk_rng.uniform(0.75, 0.9)), 0.74)
    loop = LoopPath(desk, period, options.scene_seed)
    samples = loop(np.linspace(0.0, period, 400))[:, :3, 3]
    lo, hi = samples[:, :2].min(0) - 1.5, samples[:, :2].max(0) + 1.5
    scene = build_scene(options.scene_seed, desk, (lo[0], hi[0], lo[1], hi[1], 2.7), keep_out=samples)
    T_ws = scene.T_world_scene

    def poses(t):
        return T_ws @ loop(t)

    return scene, poses, np.arange(n) / options.fps, loop.params()


class CameraEffects:
    """Exposure drift and sensor noise, deterministic per (seed, frame)."""

    def __init__(self, options: SynthOptions):
        rng = np.random.default_rng([int(options.seed), 3])
        self.o = options
        self.periods = rng.uniform(4.0, 20.0, (2, 3))
        self.phases = rng.uniform(0, 2 * np.pi, (2, 3))
        self.weights = rng.dirichlet(np.ones(3), 2)

    def gain_offset(self, t: float) -> tuple[float, float]:
        s = (self.weights * np.sin(2 * np.pi * t / self.periods + self.phases)).sum(axis=1)
        A = self.o.exposure_drift
        return 1.0 + A * float(s[0]), 12.0 * A * float(s[1])

    def apply(self, img: np.ndarray, t: float, index: int) -> np.ndarray:
        """img: (H, W, 3) float32 or uint8 -> (H, W, 3) uint8 (gain * img + offset + noise, rounded)."""
        if self.o.exposure_drift == 0 and self.o.noise == 0:
            return img if img.dtype == np.uint8 else np.clip(img + 0.5, 0, 255).astype(np.uint8)
        gain, offset = self.gain_offset(t) if self.o.exposure_drift else (1.0, 0.0)
        if self.o.noise:
            rng = np.random.default_rng([int(self.o.seed), 4, int(index)])
            noise = rng.standard_normal(img.shape, dtype=np.float32)
            return cv2.addWeighted(img, gain, noise, float(self.o.noise), offset, dtype=cv2.CV_8U)
        return cv2.addWeighted(img, gain, img, 0.0, offset, dtype=cv2.CV_8U)


def render_frame(renderer: SceneRenderer, poses, t: float, options: SynthOptions) -> tuple[np.ndarray, np.ndarray]:
    """One exposure at time t: ((H, W, 3) float32 or uint8 image, (H, W) float32 inverse depth).

    With motion blur, sub-frames (an odd number, enough for about 1.5 px of motion
    between neighbours, at most 15) are rendered across the shutter time and averaged; the
    inverse depth is that of the middle sub-frame (the ground-truth pose).
    """
    T = poses(np.array([t]))[0]
    img, inv_depth = renderer.render(T)
    if not options.motion_blur:
        return img, inv_depth
    half = 0.5 * options.shutter / options.fps
    ends = poses(np.array([t - half, t + half]))
    motion = _image_motion(renderer.camera, inv_depth, T, ends)
    n = int(min(15, 2 * np.ceil(motion / 3.0) + 1))
    if n <= 1:
        return img, inv_depth
    acc = img.astype(np.float32)
    offsets = [-half + 2.0 * half * k / (n - 1) for k in range(n) if k != n // 2]  # the middle one is img
    for sub_T in poses(t + np.array(offsets)):
        acc += renderer.render(sub_T)[0]
    return acc * np.float32(1.0 / n), inv_depth


def _image_motion(cam: PinholeCamera, inv_depth: np.ndarray, T_wc: np.ndarray, ends: np.ndarray) -> float:
    """Largest displacement (px) of a 5x5 grid of scene points between the two poses ``ends``."""
    us = np.linspace(0, cam.width - 1, 5)
    vs = np.linspace(0, cam.height - 1, 5)
    uu, vv = np.meshgrid(us, vs)
    w = inv_depth[vv.astype(int), uu.astype(int)].ravel()
    z = np.where(w > 0, 1.0 / np.maximum(w, 1e-6), 10.0)
    Xc = cam.unproject(np.stack([uu.ravel(), vv.ravel()], 1)) * z[:, None]
    Xw = Xc @ T_wc[:3, :3].T + T_wc[:3, 3]
    uv = []
    for T in ends:
        Xe = (Xw - T[:3, 3]) @ T[:3, :3]
        uv.append(cam.project(Xe)[0])
    return float(np.linalg.norm(uv[1] - uv[0], axis=1).max())


def _prepare_out(out: Path, meta_options: dict, force: bool) -> bool:
    """True when ``out`` already holds this very sequence; clears it under ``force``."""
    meta = out / "scene.json"
    if meta.is_file() and not force:
        try:
            old = json.loads(meta.read_text(encoding="utf-8")).get("options")
        except (OSError, json.JSONDecodeError):
            old = None
        if old == meta_options and (out / "rgb.txt").is_file():
            listed = [ln.split()[1] for ln in (out / "rgb.txt").read_text().splitlines() if ln and ln[0] != "#"]
            if listed and all((out / p).is_file() for p in listed):
                return True
    if out.exists() and any(out.iterdir()):
        if not force:
            raise DatasetError(f"{out}: output folder is not empty (use --force to overwrite)")
        for name in _OUTPUTS:
            p = out / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    return False


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"cannot serialise {type(x).__name__}")


def render_sequence(out_dir: str | Path, options: SynthOptions = SynthOptions(), force: bool = False,
                    progress: bool = True) -> Path:
    """Render a synthetic sequence into ``out_dir`` (see the module docstring); returns it.

    An ``out_dir`` that already holds the same sequence (same options, all frames present)
    is kept as it is; any other non-empty folder is refused unless ``force``.
    """
    options.validate()
    out = Path(out_dir)
    meta_options = json.loads(json.dumps(dataclasses.asdict(options), default=_json_default))
    if _prepare_out(out, meta_options, force):
        log.info("%s already holds this sequence; nothing to do", out)
        return out
    cam = options.camera
    scene, poses, stamps, traj_info = build_sequence(options)
    texture_seed = options.scene_seed if options.texture_seed is None else options.texture_seed
    renderer = SceneRenderer(scene, cam, texture_seed, options.repeated_texture, progress=progress,
                             texel_scale=options.texel_scale)
    effects = CameraEffects(options)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    if options.depth:
        (out / "depth").mkdir(exist_ok=True)
    names = [f"{t:.6f}" for t in stamps]
    if len(set(names)) != len(names):
        raise ConfigError(f"fps {options.fps} too high for 6-decimal timestamps")
    gt_poses = poses(stamps)
    for k, (t, name) in enumerate(tqdm(list(zip(stamps, names)), desc="synth", unit="frame", disable=not progress)):
        img, inv_depth = render_frame(renderer, poses, float(t), options)
        img = effects.apply(img, float(t), k)
        if not cv2.imwrite(str(out / "rgb" / f"{name}.png"), img, PNG_PARAMS):
            raise DatasetError(f"{out / 'rgb'}: cannot write {name}.png")
        if options.depth:
            z = np.where(inv_depth > 0, 5000.0 / np.maximum(inv_depth, 1e-9), 0.0)
            cv2.imwrite(str(out / "depth" / f"{name}.png"), np.clip(z + 0.5, 0, 65535).astype(np.uint16),
                        PNG_PARAMS)
    with (out / "rgb.txt").open("w", encoding="utf-8") as fh:
        fh.write("# synthetic colour images\n# timestamp filename\n")
        fh.writelines(f"{n} rgb/{n}.png\n" for n in names)
    if options.depth:
        with (out / "depth.txt").open("w", encoding="utf-8") as fh:
            fh.write("# synthetic depth images, 5000 per metre\n# timestamp filename\n")
            fh.writelines(f"{n} depth/{n}.png\n" for n in names)
    write_tum(out / "groundtruth.txt", Trajectory(stamps, gt_poses))
    save_camera(out / "camera.yaml", cam)
    if options.loop_gt:
        np.save(out / "loop_gt.npy", loop_ground_truth(gt_poses, options.loop_gt_dist, options.loop_gt_angle))
    meta = {"generator": "orbslam_hgcn synth", "options": meta_options, "texture_seed": texture_seed,
            "frames": len(stamps), "trajectory": traj_info, "scene": scene.layout}
    (out / "scene.json").write_text(json.dumps(meta, indent=1, default=_json_default), encoding="utf-8")
    log.info("wrote %d frames to %s", len(stamps), out)
    return out
