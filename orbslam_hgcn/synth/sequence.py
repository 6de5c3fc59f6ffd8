"""Synthetic monocular sequences with exact ground truth, in the TUM or KITTI layout.

``render_sequence(out_dir, SynthOptions(...))`` writes, in the TUM layout (default)::

    out_dir/rgb/<timestamp>.png    640x480 colour frames (BGR PNG; .jpg with image_format="jpg")
    out_dir/rgb.txt                "timestamp rgb/<timestamp>.png" per frame
    out_dir/groundtruth.txt        TUM poses T_wc of every frame (mid-exposure)
    out_dir/camera.yaml            intrinsics (default: TUM freiburg3, 535.4 539.2 320.1 247.6)
    out_dir/scene.json             seeds, options, scene layout, trajectory parameters
    out_dir/loop_gt.npy            (N, N) bool revisits (with ``loop_gt``)
    out_dir/depth/, depth.txt      16-bit depth, 5000 per metre (with ``depth``)

and in the KITTI odometry layout (``layout="kitti"``, grey frames; what ``KittiSequence``
reads)::

    out_dir/sequences/NN/image_0/000000.png ...   grey frames (.jpg with image_format="jpg")
    out_dir/sequences/NN/times.txt                seconds from the first frame
    out_dir/sequences/NN/calib.txt                P0..P3 (P1, P3: a 0.54 m stereo baseline)
    out_dir/sequences/NN/depth/                   16-bit depth, 256 per metre (with ``depth``)
    out_dir/poses/NN.txt                          3x4 T_wc rows, the first camera as world
    out_dir/camera.yaml, scene.json, loop_gt.npy  as above

Scenes: an office room (:mod:`.layout`, from the scene seed) seen along a generated loop
round the desk (also from the scene seed) or a replayed TUM trajectory
(:mod:`.trajectory`); or a street (:mod:`.street`) driven forward through corners,
with a sky. Both are rendered exactly (:mod:`.render`), with textures from the texture
seed. Camera effects, in order: fog (:mod:`.degrade`), motion blur (the average of
sub-frame renders spread over the shutter time, or each pixel blurred along its own
motion), vignetting, auto-exposure steps, exposure drift (slow gain and offset changes),
Gaussian sensor noise, rounding, JPEG compression. The same options give byte-identical
files.

Frames are PNG files (lossless; ``jpeg_quality`` then round-trips each frame through JPEG
in memory) or, with ``image_format="jpg"``, JPEG files at ``jpeg_quality`` (90 when not
given): the file is then the one compression, as a camera that delivers JPEG frames.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from orbslam_hgcn.config import save_camera
from orbslam_hgcn.errors import ConfigError, DatasetError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.synth.degrade import Degradations, flow_blur
from orbslam_hgcn.synth.layout import DeskSpec, build_scene
from orbslam_hgcn.synth.output import (
    IMAGE_FORMATS,
    existing_render,
    install,
    make_writer,
    partial_folder,
    remove_stale_partials,
    writer_class,
)
from orbslam_hgcn.synth.render import SceneRenderer
from orbslam_hgcn.synth.trajectory import LoopPath, ReplayPath, fit_scene_to_trajectory, loop_ground_truth
from orbslam_hgcn.trajectory import read_tum

log = logging.getLogger(__name__)

MIN_LOOP_S = 10.0  # shortest loop period (s): faster would not be a hand-held walk
# KITTI odometry sequence 00's camera P0 (Geiger et al., CVPR 2012; configs/kitti_00-02.yaml).
KITTI_CAMERA = {"fx": 718.856, "fy": 718.856, "cx": 607.1928, "cy": 185.2157, "width": 1241, "height": 376,
                "fps": 10.0}
STREET_DURATION = 45.0  # default length of a street drive (s)
JPEG_FILE_QUALITY = 90  # quality of JPEG frame files (image_format="jpg") when none is given
STREET_TILE_M = 4.0  # tile edge of street surfaces (m): fewer draws over kilometres of surfaces
REF_DEPTH = {"office": 1.5, "street": 15.0}  # typical depths (m), the fog's reference


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
    # Fields below this line are left out of scene.json while at their defaults, so that
    # sequences rendered before they existed still match their cached options.
    scene: str = "office"  # "office" or "street" (use the KITTI camera: street_options())
    layout: str = "tum"  # "tum" (colour, rgb.txt) or "kitti" (grey, sequences/NN/image_0)
    kitti_sequence: int = 0  # NN of the KITTI layout
    motion_blur_mode: str = "subframes"  # "subframes" (average of renders) or "flow" (along each pixel's motion)
    vignetting: float = 0.0  # darkening of the image corners (0.3: corners at 70 %)
    exposure_steps: float = 0.0  # auto-exposure jumps of +-(0.75..1.25) x this (0.4: 30-50 %)
    exposure_step_interval: float = 4.0  # mean seconds between auto-exposure steps
    exposure_settle: int = 4  # frames the auto-exposure takes to undo a step (to 5 %)
    jpeg_quality: int = 0  # JPEG encode/decode at this quality (1-100; 0: none); the files' quality with "jpg"
    fog: float = 0.0  # fog stretches: contrast lost at the scene's reference depth (0..1)
    laps: int = 1  # the generated loop: times round the desk, each lap beside the others
    image_format: str = "png"  # frame files: "png", or "jpg" (at jpeg_quality, 90 when 0; no in-memory round trip)
    draw_distance: float = 0.0  # tiles whose nearest corner is farther (m, along the optical axis) are not drawn (0: all)

    def __post_init__(self):
        if self.image_format == "jpg" and not self.jpeg_quality:
            object.__setattr__(self, "jpeg_quality", JPEG_FILE_QUALITY)

    @property
    def camera(self) -> PinholeCamera:
        return PinholeCamera(self.fx, self.fy, self.cx, self.cy, self.width, self.height, fps=self.fps,
                             name="synthetic_tum_fr3" if self.scene == "office" else f"synthetic_{self.scene}")

    def validate(self) -> None:
        if self.trajectory not in ("loop", "replay"):
            raise ConfigError(f"trajectory must be 'loop' or 'replay', not {self.trajectory!r}")
        if self.scene not in ("office", "street"):
            raise ConfigError(f"scene must be 'office' or 'street', not {self.scene!r}")
        if self.scene == "street" and (self.trajectory != "loop" or self.loop_gt or self.repeated_texture):
            raise ConfigError("the street scene has its own drive: no --trajectory replay, --loop-gt or "
                              "--repeated-texture")
        if self.layout not in ("tum", "kitti") or not 0 <= self.kitti_sequence <= 99:
            raise ConfigError(f"layout must be 'tum' or 'kitti' (sequence 0-99), not {self.layout!r}")
        if self.motion_blur_mode not in ("subframes", "flow"):
            raise ConfigError(f"motion blur mode must be 'subframes' or 'flow', not {self.motion_blur_mode!r}")
        if not (0 <= self.vignetting < 1 and 0 <= self.fog < 1 and self.exposure_steps >= 0
                and self.exposure_step_interval > 0 and self.exposure_settle >= 1 and 0 <= self.jpeg_quality <= 100):
            raise ConfigError("vignetting and fog must be in [0, 1), exposure steps non-negative with a positive "
                              "interval and settle, JPEG quality in 0-100")
        if self.trajectory == "replay" and not self.gt:
            raise ConfigError("trajectory 'replay' needs a ground-truth file (--gt)")
        if self.frames is not None and self.frames < 1:
            raise ConfigError(f"frames must be at least 1, not {self.frames}")
        if self.duration is not None and self.duration <= 0:
            raise ConfigError(f"duration must be positive, not {self.duration}")
        if self.fps <= 0 or self.noise < 0 or self.exposure_drift < 0 or not 0 < self.shutter <= 1:
            raise ConfigError("fps must be positive, noise and exposure drift non-negative, shutter in (0, 1]")
        if self.laps < 1 or (self.laps > 1 and (self.trajectory != "loop" or self.scene != "office")):
            raise ConfigError(f"laps must be at least 1, and more than one only for the office loop, not {self.laps}")
        if self.texel_scale <= 0:
            raise ConfigError(f"texel_scale must be positive, not {self.texel_scale}")
        if not (math.isfinite(self.draw_distance) and self.draw_distance >= 0):
            raise ConfigError(f"draw distance must be a finite number of metres >= 0 (0: no limit), "
                              f"not {self.draw_distance}")
        if self.image_format not in IMAGE_FORMATS:
            raise ConfigError(f"image format must be one of {', '.join(IMAGE_FORMATS)}, not {self.image_format!r}")


def street_options(**kw) -> SynthOptions:
    """Options of a street drive with the KITTI 00 camera (1241x376 at 10 Hz); ``kw`` overrides."""
    return SynthOptions(**{"scene": "street", **KITTI_CAMERA, **kw})


FR3_GT = Path(__file__).resolve().parents[3] / "shared/data/tum_fr3_long_office_household_sample/groundtruth.txt"
# Degradations of the hard presets: blur along the image motion, auto-exposure steps of
# 30-50 % every 2-6 s, vignetting (corners at 70 %), sensor noise, slow exposure drift, JPEG.
_HARD = {"motion_blur": True, "motion_blur_mode": "flow", "vignetting": 0.3, "exposure_steps": 0.4,
         "exposure_step_interval": 4.0, "exposure_drift": 0.1}
PRESETS: dict[str, dict] = {
    # The demo's office loop: 30 s round the desk, clean, with loop ground truth.
    "office_loop": {"loop_gt": True},
    # The real fr3 long-office camera path replayed in a synthetic room (2,613 frames at
    # 30 Hz), 16 ms exposures, AE settling over 6 frames, JPEG quality 75.
    "fr3_replay_hard": {"trajectory": "replay", "gt": str(FR3_GT), **_HARD, "shutter": 0.5, "noise": 2.0,
                        "exposure_settle": 6, "jpeg_quality": 75},
    # A 60 s street drive with KITTI 00's camera, written in the KITTI layout, 5 ms
    # exposures, AE settling over 3 frames, JPEG quality 80.
    "street": {"scene": "street", "layout": "kitti", "duration": 60.0, **_HARD, "shutter": 0.05, "noise": 1.5,
               "exposure_settle": 3, "jpeg_quality": 80},
}


def synth_options(preset: str | None = None, **kw) -> SynthOptions:
    """Options from a preset of PRESETS (or none), ``kw`` overriding its values; a street
    scene gets the KITTI camera unless ``kw`` sets it."""
    if preset is not None and preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; use one of {', '.join(PRESETS)}")
    base = dict(PRESETS[preset]) if preset else {}
    if kw.get("frames") is not None:
        base.pop("duration", None)
    base.update(kw)
    if base.get("scene") == "street":
        base = {**KITTI_CAMERA, **base}
    return SynthOptions(**base)


def _frame_count(options: SynthOptions, default_s: float) -> int:
    if options.frames is not None:
        return options.frames
    return int(round((options.duration or default_s) * options.fps))


def build_sequence(options: SynthOptions):
    """The scene and camera motion of a sequence, without rendering.

    Returns (scene, pose function: times (N,) -> T_wc (N, 4, 4), frame timestamps (N,),
    JSON-able trajectory description).
    """
    if options.scene == "street":
        from orbslam_hgcn.synth.street import StreetSpec, build_street

        n = _frame_count(options, STREET_DURATION)
        spec = StreetSpec()
        scene, drive = build_street(options.scene_seed, n / options.fps * spec.speed + 1.0, spec)
        return scene, drive, np.arange(n) / options.fps, drive.params()
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
    n = _frame_count(options, 30.0)
    period = max(n / options.fps / options.laps, MIN_LOOP_S)  # shorter laps: the start of a walkable loop
    desk_rng = np.random.default_rng([int(options.scene_seed), 5])
    desk = DeskSpec(float(desk_rng.uniform(1.4, 1.8)), float(desk_rng.uniform(0.75, 0.9)), 0.74)
    loop = LoopPath(desk, period, options.scene_seed, laps=options.laps)
    samples = loop(np.linspace(0.0, period, 400))[:, :3, 3]
    lo, hi = samples[:, :2].min(0) - 1.5, samples[:, :2].max(0) + 1.5
    scene = build_scene(options.scene_seed, desk, (lo[0], hi[0], lo[1], hi[1], 2.7), keep_out=samples)
    T_ws = scene.T_world_scene

    def poses(t):
        return T_ws @ loop(t)

    return scene, poses, np.arange(n) / options.fps, loop.params()


_FIRST_NEW_FIELD = [f.name for f in dataclasses.fields(SynthOptions)].index("scene")


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


class SkyView:
    """A renderer with a sky behind the scene: the same ``render(T_wc)`` and ``camera``."""

    def __init__(self, renderer: SceneRenderer, sky):
        self.renderer = renderer
        self.sky = sky
        self.camera = renderer.camera

    @property
    def last_draw_count(self) -> int:
        return self.renderer.last_draw_count

    def render(self, T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.renderer.render(T_wc, background=self.sky(T_wc))


def make_renderer(scene, options: SynthOptions, progress: bool = False):
    """The renderer of a sequence's scene (textures built here): ``render(T_wc)``, ``camera``."""
    texture_seed = options.scene_seed if options.texture_seed is None else options.texture_seed
    if options.scene == "street":
        from orbslam_hgcn.synth.street_textures import SkyBackground, StreetTextures

        from orbslam_hgcn.synth.render_lod import LodSceneRenderer

        textures = StreetTextures(scene, texture_seed, options.texel_scale)
        renderer = LodSceneRenderer(scene, options.camera, textures, tile_m=STREET_TILE_M)
        renderer.draw_distance = options.draw_distance or math.inf
        return SkyView(renderer, SkyBackground(options.camera, scene.sun, texture_seed, scene.T_world_scene))
    renderer = SceneRenderer(scene, options.camera, texture_seed, options.repeated_texture, progress=progress,
                             texel_scale=options.texel_scale)
    renderer.draw_distance = options.draw_distance or math.inf
    return renderer


def render_frame(renderer: SceneRenderer, poses, t: float, options: SynthOptions,
                 post=None) -> tuple[np.ndarray, np.ndarray]:
    """One exposure at time t: ((H, W, 3) float32 or uint8 image, (H, W) float32 inverse depth).

    With motion blur, sub-frames (an odd number, enough for about 1.5 px of motion
    between neighbours, at most 15) are rendered across the shutter time and averaged; the
    inverse depth is that of the middle sub-frame (the ground-truth pose). In the "flow"
    mode, the middle render is blurred along each pixel's own motion instead
    (``degrade.flow_blur``). ``post(img, inv_depth)``, when given, is applied to
    every render before averaging (fog).
    """
    T = poses(np.array([t]))[0]
    img, inv_depth = renderer.render(T)
    if post is not None:
        img = post(img, inv_depth)
    if not options.motion_blur:
        return img, inv_depth
    half = 0.5 * options.shutter / options.fps
    ends = poses(np.array([t - half, t + half]))
    if options.motion_blur_mode == "flow":
        return flow_blur(img, inv_depth, renderer.camera, T, ends[0], ends[1]), inv_depth
    motion = _image_motion(renderer.camera, inv_depth, T, ends)
    n = int(min(15, 2 * np.ceil(motion / 3.0) + 1))
    if n <= 1:
        return img, inv_depth
    acc = img.astype(np.float32)
    offsets = [-half + 2.0 * half * k / (n - 1) for k in range(n) if k != n // 2]  # the middle one is img
    for sub_T in poses(t + np.array(offsets)):
        sub, sub_inv = renderer.render(sub_T)
        acc += sub if post is None else post(sub, sub_inv)
    return acc * np.float32(1.0 / n), inv_depth


def camera_frame(renderer, poses, t: float, k: int, options: SynthOptions, effects: CameraEffects,
                 degrade: Degradations, grey: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Frame k at time t as the camera delivers it: ((H, W[, 3]) uint8 image, (H, W) float32
    inverse depth). Render (with fog) and blur, grey (KITTI layout), vignetting and
    exposure steps, exposure drift and noise, rounding, JPEG (in memory, for PNG files only:
    JPEG files are the compression themselves)."""
    img, inv_depth = render_frame(renderer, poses, t, options, degrade.scene_post(t))
    if grey:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    img = degrade.photometric(img, t)
    return degrade.compress(effects.apply(img, t, k)), inv_depth


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


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"cannot serialise {type(x).__name__}")


def _meta_options(options: SynthOptions) -> dict:
    """JSON-able options for scene.json; the newer fields only when they differ from their
    defaults (older sequences keep matching their cache); the ground truth of a replay by
    the SHA-256 of its file."""
    d = dataclasses.asdict(options)
    for f in dataclasses.fields(SynthOptions)[_FIRST_NEW_FIELD:]:
        if d[f.name] == f.default:
            del d[f.name]
    if d.get("gt") and Path(d["gt"]).is_file():
        # The replayed trajectory by its content, so that a render stays the same sequence
        # wherever the file lies (another checkout, a moved folder); scene.json's
        # trajectory info keeps the path.
        d["gt"] = "sha256:" + hashlib.sha256(Path(d["gt"]).read_bytes()).hexdigest()
    return json.loads(json.dumps(d, default=_json_default))


def render_sequence(out_dir: str | Path, options: SynthOptions = SynthOptions(), force: bool = False,
                    progress: bool = True, cache: bool = False) -> Path:
    """Render a synthetic sequence into ``out_dir`` (see the module docstring).

    Returns the folder to read it from: ``out_dir`` (TUM layout) or
    ``out_dir/sequences/NN`` (KITTI layout). An ``out_dir`` that already holds the same
    sequence (same options, all frames present) is kept as it is, unless ``force``; one
    that holds only an interrupted render's files is replaced; any other non-empty folder
    is refused unless ``force`` (which replaces the render's files and keeps any other) or
    ``cache`` (a folder this caller owns: whatever it holds is replaced by this sequence).

    The frames are written into a temporary folder beside ``out_dir`` and moved into it
    once complete (:func:`~orbslam_hgcn.synth.output.install`): an interrupted render
    leaves ``out_dir`` as it was.
    """
    options.validate()
    out = Path(out_dir)
    meta_options = _meta_options(options)
    writer_cls = writer_class(options.layout)
    found = existing_render(out, meta_options, writer_cls, options.kitti_sequence)
    seq_dir = Path("sequences") / f"{options.kitti_sequence:02d}" if options.layout == "kitti" else Path()
    if found == "same" and not force:
        log.info("%s already holds this sequence; nothing to do", out)
        return out / seq_dir
    if found == "other" and not (force or cache):
        raise DatasetError(f"{out}: output folder is not empty (use --force to overwrite)")
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out}: output path is a file, not a folder")
    if found == "incomplete":
        log.warning("%s holds an incomplete render (interrupted); rendering it again", out)
    remove_stale_partials(out)
    partial = partial_folder(out)
    partial.mkdir(parents=True)
    try:
        n = _render_into(partial, options, meta_options, progress)
        if cache and found == "other":
            shutil.rmtree(out)
        install(partial, out)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    log.info("wrote %d frames to %s", n, out)
    return out / seq_dir


def _render_into(out: Path, options: SynthOptions, meta_options: dict, progress: bool) -> int:
    """Render every frame and file of a sequence into the folder ``out``, scene.json last;
    returns the number of frames."""
    cam = options.camera
    scene, poses, stamps, traj_info = build_sequence(options)
    renderer = make_renderer(scene, options, progress)
    effects = CameraEffects(options)
    degrade = Degradations(options, cam, float(stamps[0]), float(stamps[-1]), REF_DEPTH[options.scene])
    writer = make_writer(options.layout, out, stamps, options.depth, options.kitti_sequence, options.image_format,
                         options.jpeg_quality)
    gt_poses = poses(stamps)
    for k, t in enumerate(tqdm(stamps.tolist(), desc="synth", unit="frame", disable=not progress)):
        writer.frame(k, *camera_frame(renderer, poses, t, k, options, effects, degrade, writer.grey))
    writer.finish(stamps, gt_poses, cam)
    save_camera(out / "camera.yaml", cam)
    if options.loop_gt:
        np.save(out / "loop_gt.npy", loop_ground_truth(gt_poses, options.loop_gt_dist, options.loop_gt_angle))
    texture_seed = options.scene_seed if options.texture_seed is None else options.texture_seed
    meta = {"generator": "orbslam_hgcn synth", "options": meta_options, "texture_seed": texture_seed,
            "frames": len(stamps), "image_format": options.image_format, "trajectory": traj_info,
            "scene": scene.layout}
    if options.layout == "kitti":
        meta["T_world_first_camera"] = gt_poses[0]  # KITTI poses are relative to the first camera
    (out / "scene.json").write_text(json.dumps(meta, indent=1, default=_json_default), encoding="utf-8")
    return len(stamps)
