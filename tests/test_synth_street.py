"""Street renders and image degradations: exact ground truth, the KITTI layout read back,
blur along the motion, exposure steps, vignetting, JPEG, fog, determinism, presets."""

import json
import math

import cv2
import numpy as np
import pytest

from orbslam_hgcn.cli import main
from orbslam_hgcn.datasets import open_sequence
from orbslam_hgcn.errors import ConfigError
from orbslam_hgcn.synth.sequence import (
    KITTI_CAMERA,
    SynthOptions,
    build_sequence,
    make_renderer,
    render_frame,
    render_sequence,
    street_options,
    synth_options,
)
from orbslam_hgcn.synth.degrade import Degradations, ExposureSteps, FogSegments, jpeg, vignette_map
from orbslam_hgcn.synth.render import SceneRenderer
from orbslam_hgcn.synth.scene import Scene, face, raycast
from orbslam_hgcn.synth.trajectory import look_at
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import inv_T

# Half-resolution KITTI camera: the street's geometry and motion, a quarter of the pixels.
HALF = dict(width=620, height=188, fx=359.428, fy=359.428, cx=303.5964, cy=92.60785)
UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def street():
    options = street_options(duration=30.0, texel_scale=8.0, **HALF)
    scene, poses, stamps, info = build_sequence(options)
    return options, scene, poses, stamps, make_renderer(scene, options)


def test_street_drive_is_kitti_like():
    options = street_options(duration=30.0)
    _, drive, stamps, info = build_sequence(options)
    T = drive(stamps)
    step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    assert abs(np.median(step) - 0.85) < 0.02 and step.max() < 0.9 and step.min() > 0.4
    heading = np.unwrap(np.arctan2(T[:, 1, 2], T[:, 0, 2]))
    assert np.degrees(np.abs(heading - heading[0]).max()) > 85  # at least one 90-degree corner
    assert np.all(np.abs(T[:, 2, 3] - 1.65) < 0.05)  # camera height, bouncing by centimetres
    tilt = np.degrees(np.arcsin(np.abs(T[:, 2, [0, 2]])))  # roll (image x axis), pitch (optical axis)
    assert tilt.max() < 2.5 and tilt.max() > 0.1  # mild jitter, not none


def test_street_depth_matches_ray_cast_and_spans_near_to_far(street):
    options, scene, poses, stamps, renderer = street
    cam = options.camera
    T = poses(stamps[[5]])[0]
    img, inv_depth = renderer.render(T)
    sky = inv_depth == 0
    assert 0.05 < sky.mean() < 0.6 and sky[: cam.height // 4].mean() > sky[-cam.height // 4:].mean()
    z = 1.0 / inv_depth[~sky]
    assert z.min() < 7.0 and np.percentile(z, 99.5) > 80.0  # the road under the image to far facades
    rng = np.random.default_rng(1)
    px = np.stack([rng.integers(0, cam.width, 300), rng.integers(0, cam.height, 300)], 1)
    px = px[inv_depth[px[:, 1], px[:, 0]] > 0]
    s, hit = raycast(scene, np.repeat(T[:3, 3][None], len(px), 0), cam.unproject(px) @ T[:3, :3].T)
    assert np.all(hit >= 0)
    rel = np.abs(1.0 / inv_depth[px[:, 1], px[:, 0]] - s) / s
    assert np.median(rel) < 1e-4 and np.mean(rel < 1e-3) > 0.95


def test_draw_distance_leaves_far_surfaces_to_the_sky(street):
    options, scene, poses, stamps, view = street
    T = poses(stamps[[5]])[0]
    full_img, full_inv = view.render(T)
    n_full = view.last_draw_count
    view.renderer.draw_distance = 40.0
    try:
        img, inv = view.render(T)
        n_near = view.last_draw_count
    finally:
        view.renderer.draw_distance = math.inf
    assert n_near < 0.5 * n_full
    z_full = np.where(full_inv > 0, 1.0 / np.maximum(full_inv, 1e-9), np.inf)
    far = np.isfinite(z_full) & (z_full > 80.0)
    assert far.mean() > 0.01 and np.all(inv[far] == 0)  # the far facades give way to the sky
    near = z_full < 10.0
    assert near.mean() > 0.2 and np.mean(np.all(img == full_img, axis=2)[near]) > 0.99  # the near scene is kept
    with pytest.raises(ConfigError):
        street_options(draw_distance=-1.0).validate()
    assert synth_options("street", frames=2, draw_distance=150.0).draw_distance == 150.0


def _ncc_find(patch, image, centre, radius):
    h = patch.shape[0] // 2
    cx, cy = int(round(centre[0])), int(round(centre[1]))
    win = image[cy - h - radius:cy + h + radius + 1, cx - h - radius:cx + h + radius + 1]
    if win.shape != (2 * (h + radius) + 1,) * 2:
        return None, 0.0
    score = cv2.matchTemplate(win, patch, cv2.TM_CCOEFF_NORMED)
    y, x = np.unravel_index(np.argmax(score), score.shape)
    if not (0 < x < score.shape[1] - 1 and 0 < y < score.shape[0] - 1):
        return None, 0.0

    def peak(m, c, p):
        d = m - 2 * c + p
        return 0.0 if d == 0 else 0.5 * (m - p) / d

    dx = peak(score[y, x - 1], score[y, x], score[y, x + 1])
    dy = peak(score[y - 1, x], score[y, x], score[y + 1, x])
    return np.array([cx - radius + x + dx, cy - radius + y + dy]), float(score[y, x])


@pytest.fixture(scope="module")
def written_street(tmp_path_factory):
    """A short street sequence written in the KITTI layout (half resolution), read back."""
    options = street_options(frames=8, texel_scale=2.0, layout="kitti", **HALF)
    seq_dir = render_sequence(tmp_path_factory.mktemp("street") / "k", options, progress=False)
    return options, seq_dir, open_sequence("kitti", seq_dir, None)


def test_street_ground_truth_is_exact(written_street):
    """Scene points seen in one written frame appear in another where the written poses
    and calibration project them (frames read back through the KITTI reader)."""
    options, seq_dir, seq = written_street
    scene, _, _, _ = build_sequence(options)
    T_w0 = np.array(json.loads((seq_dir.parents[1] / "scene.json").read_text())["T_world_first_camera"])
    cam = seq.camera
    a, b = seq[3], seq[5]  # 1.7 m apart
    T_a, T_b = T_w0 @ a.T_wc, T_w0 @ b.T_wc
    corners = cv2.goodFeaturesToTrack(a.image, 300, 0.02, 8, blockSize=5).reshape(-1, 2)
    px = np.round(corners)
    px = px[cam.in_image(px, 20)]
    rays = cam.unproject(px) @ T_a[:3, :3].T
    s, hit = raycast(scene, np.repeat(T_a[:3, 3][None], len(px), 0), rays)
    keep = hit >= 0
    X = T_a[:3, 3] + s[keep, None] * rays[keep]
    px = px[keep]
    uv_b, z_b = cam.project((X - T_b[:3, 3]) @ T_b[:3, :3])
    s_b, _ = raycast(scene, np.repeat(T_b[:3, 3][None], len(X), 0), X - T_b[:3, 3])
    vis = cam.in_image(uv_b, 20) & (np.abs(s_b - 1.0) < 1e-6) & (z_b > 3.0)  # not occluded, not too close
    assert vis.sum() >= 60
    errors = []
    for p, q in zip(px[vis].astype(int), uv_b[vis]):
        found, score = _ncc_find(a.image[p[1] - 5:p[1] + 6, p[0] - 5:p[0] + 6], b.image, q, 6)
        if found is not None and score > 0.85:
            errors.append(np.linalg.norm(found - q))
    errors = np.array(errors)
    assert len(errors) >= 0.5 * vis.sum(), (len(errors), vis.sum())
    assert np.median(errors) < 0.35 and np.mean(errors < 1.0) > 0.8, (np.median(errors), np.mean(errors < 1.0))


def test_kitti_layout_is_read_with_the_right_camera_and_poses(tmp_path):
    options = street_options(frames=3, texel_scale=8.0, layout="kitti", kitti_sequence=7)
    seq_dir = render_sequence(tmp_path / "k", options, progress=False)
    assert seq_dir == tmp_path / "k" / "sequences" / "07"
    seq = open_sequence("kitti", seq_dir, None)
    cam = seq.camera
    for key in ("fx", "fy", "cx", "cy", "width", "height"):
        assert getattr(cam, key) == KITTI_CAMERA[key], key
    assert abs(cam.fps - 10.0) < 1e-6 and len(seq) == 3
    np.testing.assert_allclose(seq.timestamps, [0.0, 0.1, 0.2], atol=1e-9)
    frame = seq[2]
    assert frame.image.shape == (376, 1241) and frame.image.dtype == np.uint8 and frame.image.std() > 15
    # Poses: KITTI's convention (the first camera is the world), equal to the drive's.
    _, drive, stamps, _ = build_sequence(options)
    T = drive(stamps)
    expected = inv_T(T[0]) @ T
    np.testing.assert_allclose(seq[0].T_wc, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(frame.T_wc, expected[2], atol=1e-8)
    meta = json.loads((tmp_path / "k" / "scene.json").read_text())
    np.testing.assert_allclose(meta["T_world_first_camera"], T[0], atol=1e-12)
    calib = (seq_dir / "calib.txt").read_text().split("\n")
    assert [ln.split(":")[0] for ln in calib if ln] == ["P0", "P1", "P2", "P3"]


def _stripes_renderer(cam):
    """A wall 3 m ahead of the origin (y = 3), vertical black and white bars 8 cm wide."""
    n = 512
    tex = np.zeros((n, n, 3), np.uint8)
    tex[:, (np.arange(n) // 32) % 2 == 0] = 220
    tex[:, (np.arange(n) // 32) % 2 == 1] = 30
    quad = face([0, 3.0, 0], [0, -1, 0], [0, 0, -1], 2.56, 2.56, "wall", "stripes", 2.56 / n)
    return SceneRenderer(Scene([quad]), cam, textures=[tex])


@pytest.mark.parametrize("mode", ["flow", "subframes"])
def test_blur_is_along_the_image_motion(mode):
    """Vertical bars blur under sideways motion and stay sharp under vertical motion."""
    cam = PinholeCamera(300.0, 300.0, 159.5, 119.5, 320, 240)
    renderer = _stripes_renderer(cam)
    options = SynthOptions(motion_blur=True, motion_blur_mode=mode, shutter=1.0, fps=30.0, width=320, height=240)

    def path(direction):
        def poses(t):
            t = np.atleast_1d(t)
            pos = np.outer(t, direction) * 0.6  # 0.6 m/s: 6 px over the 1/30 s shutter at 3 m
            return look_at(pos, pos + [0.0, 3.0, 0.0], UP)
        return poses

    sharp = cv2.cvtColor(renderer.render(path([1.0, 0, 0])(0.0)[0])[0], cv2.COLOR_BGR2GRAY).astype(np.float32)
    energy = {}
    for name, d in (("sideways", [1.0, 0, 0]), ("vertical", [0, 0, 1.0])):
        img = np.asarray(render_frame(renderer, path(d), 0.0, options)[0], np.float32)
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        energy[name] = np.abs(np.diff(grey[40:-40, 40:-40], axis=1)).max(axis=1).mean()
        assert abs(float(grey.mean()) - float(sharp.mean())) < 1.0  # blur keeps the brightness
    e0 = np.abs(np.diff(sharp[40:-40, 40:-40], axis=1)).max(axis=1).mean()
    assert energy["sideways"] < 0.35 * e0, (energy, e0)  # steepest step spread over ~6 px
    assert energy["vertical"] > 0.9 * e0, (energy, e0)


def test_flow_blur_matches_sub_frame_average_in_the_office():
    small = dict(width=320, height=240, fx=267.7, fy=269.6, cx=160.05, cy=123.8, texel_scale=8.0)
    opts = SynthOptions(duration=10.0, motion_blur=True, shutter=1.0, **small)
    scene, poses, stamps, _ = build_sequence(opts)
    renderer = make_renderer(scene, opts)
    t = float(stamps[40])
    sharp = renderer.render(poses(np.array([t]))[0])[0].astype(np.float32)
    sub = render_frame(renderer, poses, t, opts)[0]
    flow = render_frame(renderer, poses, t, SynthOptions(**{**opts.__dict__, "motion_blur_mode": "flow"}))[0]
    assert np.abs(flow - sub).mean() < 0.45 * np.abs(sub - sharp).mean()


def test_exposure_steps_change_brightness_as_specified():
    fps, settle = 10.0, 4
    steps = ExposureSteps(0.4, 1.5, settle, fps, 0.0, 30.0, seed=3)
    factors = np.exp(steps.log_factors)
    assert len(factors) >= 10 and np.all((np.abs(factors - 1) >= 0.3 - 1e-9) & (np.abs(factors - 1) <= 0.5 + 1e-9))
    assert np.any(factors > 1) and np.any(factors < 1)
    np.testing.assert_allclose(steps.times * fps, np.round(steps.times * fps), atol=1e-6)  # on frames
    opts = SynthOptions(exposure_steps=0.4, exposure_step_interval=1.5, exposure_settle=settle, fps=fps, seed=3)
    cam = PinholeCamera(100, 100, 31.5, 23.5, 64, 48)
    degrade = Degradations(opts, cam, 0.0, 30.0, 1.5)
    flat = np.full((48, 64), 100.0, np.float32)
    mean = {round(k): float(degrade.photometric(flat, k / fps).mean()) for k in range(300)}
    for t, f in zip(steps.times, factors):
        k = int(round(t * fps))
        if k + settle + 1 >= 300:
            break
        assert abs(mean[k] / mean[k - 1] - f) < 0.03 * f  # the jump, whole, on the step's frame
        assert abs(np.log(mean[k + settle] / mean[k - 1])) < 0.06 * abs(np.log(f)) + 0.01  # settled


def test_vignetting_jpeg_and_fog():
    cam = PinholeCamera(200, 200, 79.5, 59.5, 160, 120)
    v = vignette_map(cam, 0.3)
    assert abs(v[60, 80] - 1.0) < 1e-3 and abs(min(v[0, 0], v[-1, -1], v[0, -1], v[-1, 0]) - 0.7) < 1e-6
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (120, 160), dtype=np.uint8), (0, 0), 2.0)
    err = [np.abs(jpeg(img, q).astype(float) - img).mean() for q in (20, 60, 95)]
    assert err[0] > err[1] > err[2] > 0 and np.array_equal(jpeg(img, 60), jpeg(img, 60))
    fog = FogSegments(0.7, 15.0, 0.0, 60.0, seed=2)
    assert fog.strength(0.0) == 0.0 and len(fog.segments) == 2
    a, b = fog.segments[0]
    assert fog.strength(0.5 * (a + b)) == 1.0
    inv = np.full(img.shape, 1 / 15.0, np.float32)
    foggy = fog.apply(img, inv, 0.5 * (a + b))
    assert foggy.std() < 0.2 * img.std()  # 30 % of the contrast kept at 15 m, halved in flat light


def test_street_and_degradations_same_seed_same_bytes(tmp_path):
    base = dict(frames=2, texel_scale=8.0, layout="kitti", motion_blur=True, motion_blur_mode="flow",
                shutter=0.2, vignetting=0.3, exposure_steps=0.4, exposure_step_interval=0.1, jpeg_quality=80,
                fog=0.5, noise=1.0, **HALF)
    out = [render_sequence(tmp_path / name, street_options(**base, seed=seed), progress=False)
           for name, seed in (("a", 0), ("b", 0), ("c", 1))]
    for k in range(2):
        a, b, c = ((o / "image_0" / f"{k:06d}.png").read_bytes() for o in out)
        assert a == b and a != c
    assert (out[0].parents[1] / "poses" / "00.txt").read_bytes() == (out[1].parents[1] / "poses" / "00.txt").read_bytes()


def test_presets_and_cli(tmp_path, capsys):
    street = synth_options("street", frames=5)
    assert street.scene == "street" and street.layout == "kitti" and street.fx == KITTI_CAMERA["fx"]
    assert street.frames == 5 and street.duration is None and street.motion_blur_mode == "flow"
    hard = synth_options("fr3_replay_hard", gt="x.txt")
    assert hard.trajectory == "replay" and hard.gt == "x.txt" and hard.jpeg_quality and hard.vignetting
    assert synth_options("office_loop") == SynthOptions(loop_gt=True)
    args = ["synth", "--out", str(tmp_path / "s"), "--preset", "street", "--frames", "2", "--texel-scale", "8",
            "--jpeg-quality", "50"]
    assert main(args) == 0
    seq = tmp_path / "s" / "sequences" / "00"
    assert capsys.readouterr().out.strip() == str(seq)
    assert sorted(p.name for p in (seq / "image_0").iterdir()) == ["000000.png", "000001.png"]
    meta = json.loads((tmp_path / "s" / "scene.json").read_text())["options"]
    assert meta["jpeg_quality"] == 50 and meta["scene"] == "street"
    assert main(args) == 0  # same options: kept as it is
    assert main(["synth", "--out", str(tmp_path / "x"), "--scene", "street", "--trajectory", "replay",
                 "--gt", "g.txt"]) == 2
