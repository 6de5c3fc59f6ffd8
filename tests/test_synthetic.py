"""Synthetic sequence renderer: exact geometry, occlusion, determinism, trajectories, outputs."""

import dataclasses
import json

import cv2
import numpy as np
import pytest

from orbslam_hgcn.cli import main
from orbslam_hgcn.config import load_camera
from orbslam_hgcn.errors import ConfigError, DatasetError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import rotation_angle_deg
from orbslam_hgcn.synth.layout import DeskSpec
from orbslam_hgcn.synth.render import SceneRenderer, surface_texture
from orbslam_hgcn.synth.scene import Scene, box_quads, face, raycast
from orbslam_hgcn.synth.sequence import CameraEffects, SynthOptions, build_sequence, render_frame, render_sequence
from orbslam_hgcn.synth.trajectory import (
    LoopPath,
    ReplayPath,
    axes_convergence,
    estimate_up,
    fit_scene_to_trajectory,
    look_at,
    loop_ground_truth,
)
from orbslam_hgcn.trajectory import read_tum

CAM = PinholeCamera(535.4, 539.2, 320.1, 247.6, 640, 480)
UP = np.array([0.0, 0.0, 1.0])


def _pose(pos, target, roll=0.0):
    return look_at(np.array([pos], float), np.array([target], float), UP, np.array([roll]))[0]


def _project(T_wc, X):
    return CAM.project((X - T_wc[:3, 3]) @ T_wc[:3, :3])


def _uniform(value, h=64, w=64):
    return np.full((h, w, 3), value, np.uint8)


@pytest.fixture(scope="module")
def loop_setup():
    """The default loop scene and its renderer (real textures), built once."""
    options = SynthOptions(frames=900)
    scene, poses, stamps, _ = build_sequence(options)
    return scene, poses, stamps, SceneRenderer(scene, CAM, options.scene_seed)


def test_checkerboard_corners_land_on_their_projections():
    """Absolute registration: known texture corners appear where the pose projects them,
    near (mip level 0) and far (coarser levels), to a fraction of a pixel."""
    n, sq = 512, 64
    ii, jj = np.mgrid[0:n, 0:n]
    board = np.dstack([((ii // sq + jj // sq) % 2 * 200 + 28).astype(np.uint8)] * 3)
    quad = face([0, 0, 0], [0, -1, 0], [0, 0, -1], 2.0, 2.0, "wall", "board", 2.0 / n)
    renderer = SceneRenderer(Scene([quad]), CAM, textures=[board])
    k = np.arange(1, 8) * sq * (2.0 / n)
    a, b = np.meshgrid(k, k)
    X = quad.origin + a.reshape(-1, 1) * quad.u_axis + b.reshape(-1, 1) * quad.v_axis
    rng = np.random.default_rng(0)
    for pos in ([0.3, -1.5, 0.2], [1.0, -2.5, 0.6], [-2.0, -4.0, 0.5], [0.5, -9.0, 0.2]):
        T = _pose(pos, [0.1, 0.0, 0.05], roll=0.2)
        gray = cv2.cvtColor(renderer.render(T)[0], cv2.COLOR_BGR2GRAY)
        uv, _ = _project(T, X)
        ok = CAM.in_image(uv, 8)
        assert ok.sum() >= 30
        start = (uv[ok] + rng.uniform(-1, 1, (ok.sum(), 2))).astype(np.float32).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
        found = cv2.cornerSubPix(gray, start, (3, 3), (-1, -1), crit).reshape(-1, 2)
        err = np.linalg.norm(found - uv[ok], axis=1)
        assert np.median(err) < 0.2 and err.max() < 0.4, (pos, np.median(err), err.max())


def _match(patch, image, centre, radius):
    """Best NCC position (sub-pixel, parabola fit) of ``patch`` around integer ``centre``."""
    h = patch.shape[0] // 2
    cx, cy = int(round(centre[0])), int(round(centre[1]))
    win = image[cy - h - radius:cy + h + radius + 1, cx - h - radius:cx + h + radius + 1]
    score = cv2.matchTemplate(win, patch, cv2.TM_CCOEFF_NORMED)
    y, x = np.unravel_index(np.argmax(score), score.shape)
    if not (0 < x < score.shape[1] - 1 and 0 < y < score.shape[0] - 1):
        return None, score.max()

    def peak(m, c, p):
        d = m - 2 * c + p
        return 0.0 if d == 0 else 0.5 * (m - p) / d

    dx = peak(score[y, x - 1], score[y, x], score[y, x + 1])
    dy = peak(score[y - 1, x], score[y, x], score[y + 1, x])
    return np.array([cx - radius + x + dx, cy - radius + y + dy]), score[y, x]


def test_two_views_agree_with_ground_truth_poses(loop_setup):
    """Patches around textured pixels of frame A are found in frame B where the exact
    ray-cast 3D point projects with B's ground-truth pose."""
    scene, poses, stamps, renderer = loop_setup
    T_a, T_b = poses(stamps[[100, 106]])
    gray_a = cv2.cvtColor(renderer.render(T_a)[0], cv2.COLOR_BGR2GRAY)
    gray_b = cv2.cvtColor(renderer.render(T_b)[0], cv2.COLOR_BGR2GRAY)
    corners = cv2.goodFeaturesToTrack(gray_a, 300, 0.01, 12, blockSize=5).reshape(-1, 2)
    px = np.round(corners)
    px = px[CAM.in_image(px, 30)]
    rays = CAM.unproject(px) @ T_a[:3, :3].T
    s, hit = raycast(scene, np.repeat(T_a[:3, 3][None], len(px), 0), rays)
    assert np.all(hit >= 0)
    X = T_a[:3, 3] + s[:, None] * rays
    uv_b, z_b = _project(T_b, X)
    # Visible in B: inside the image and not occluded (exact ray cast from B).
    d_b = X - T_b[:3, 3]
    s_b, _ = raycast(scene, np.repeat(T_b[:3, 3][None], len(X), 0), d_b)
    vis = CAM.in_image(uv_b, 30) & (np.abs(s_b - 1.0) < 1e-6)
    assert vis.sum() >= 100
    errors = []
    for p, q in zip(px[vis].astype(int), uv_b[vis]):
        patch = gray_a[p[1] - 7:p[1] + 8, p[0] - 7:p[0] + 8]
        found, score = _match(patch, gray_b, q, 8)
        if found is not None and score > 0.8:
            errors.append(np.linalg.norm(found - q))
    errors = np.array(errors)
    assert len(errors) >= 0.8 * vis.sum()
    assert np.median(errors) < 0.25 and np.mean(errors < 1.0) > 0.95, (np.median(errors), np.mean(errors < 1.0))


def test_rendered_depth_matches_ray_cast(loop_setup):
    scene, poses, stamps, renderer = loop_setup
    T = poses(stamps[[400]])[0]
    _, inv_depth = renderer.render(T)
    assert np.all(inv_depth > 0)  # closed room: nothing blank
    rng = np.random.default_rng(1)
    px = np.stack([rng.integers(0, CAM.width, 400), rng.integers(0, CAM.height, 400)], 1)
    s, _ = raycast(scene, np.repeat(T[:3, 3][None], len(px), 0), CAM.unproject(px) @ T[:3, :3].T)
    z = 1.0 / inv_depth[px[:, 1], px[:, 0]]
    rel = np.abs(z - s) / s
    # Away from silhouettes the depth is exact (float32); a few pixels sit on edges.
    assert np.median(rel) < 1e-4 and np.mean(rel < 1e-3) > 0.97


def test_nearer_box_hides_farther_wall_in_any_order():
    wall = face([0, 3.0, 1.0], [0, -1, 0], [0, 0, -1], 4.0, 3.0, "wall", "wall", 0.01)
    box = box_quads([0.0, 1.5, 1.0], [0.4, 0.4, 0.4], label="box", bottom=True)
    T = _pose([0.0, 0.0, 1.0], [0.0, 3.0, 1.0])
    images = []
    for quads in ([wall] + box, box + [wall]):
        tex = [_uniform(230) if q.label == "wall" else _uniform(20, 256, 256) for q in quads]
        img, inv_depth = SceneRenderer(Scene(quads), CAM, textures=tex).render(T)
        images.append(img)
        # The box front face (y = 1.3) spans x, z in [-0.2, 0.2] + (0, 1): project its corners.
        uv, _ = _project(T, np.array([[-0.2, 1.3, 0.8], [0.2, 1.3, 1.2]]))
        (u0, v1), (u1, v0) = uv
        inner = (slice(int(v0) + 3, int(v1) - 2), slice(int(u0) + 3, int(u1) - 2))
        assert np.all(img[inner] == 20)
        np.testing.assert_allclose(1.0 / inv_depth[inner], 1.3, rtol=1e-5)
        outer = np.ones(inv_depth.shape, bool)
        outer[int(v0) - 3:int(v1) + 4, int(u0) - 3:int(u1) + 4] = False
        assert np.all(img[outer] == 230)
        np.testing.assert_allclose(1.0 / inv_depth[outer], 3.0, rtol=1e-5)
    np.testing.assert_array_equal(images[0], images[1])


def test_orb_finds_many_well_spread_keypoints(loop_setup):
    _, poses, stamps, renderer = loop_setup
    for k in (0, 300, 600):
        gray = cv2.cvtColor(renderer.render(poses(stamps[[k]])[0])[0], cv2.COLOR_BGR2GRAY)
        kps = cv2.ORB_create(1000).detect(gray)
        assert len(kps) >= 500
        pts = np.array([kp.pt for kp in kps])
        cells = np.histogram2d(pts[:, 0], pts[:, 1], bins=4, range=[[0, 640], [0, 480]])[0]
        assert np.sum(cells >= 10) >= 14, cells


def test_loop_returns_to_its_start():
    desk = DeskSpec()
    loop = LoopPath(desk, period=30.0, seed=3)
    T0, T1, Tend = loop(np.array([0.0, 30.0, 30.0 - 1 / 30]))
    np.testing.assert_allclose(T0, T1, atol=1e-9)
    assert np.linalg.norm(Tend[:3, 3] - T0[:3, 3]) < 0.05
    poses = loop(np.arange(900) / 30.0)
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert step.max() < 0.03  # smooth, hand-held speeds (< 0.9 m/s)
    gt = loop_ground_truth(poses, 0.5, 30.0)
    assert gt[0, -1] and gt[-1, 0] and not gt[0, 450]
    assert np.array_equal(gt, gt.T) and gt.diagonal().all()


def test_loop_ground_truth_needs_place_and_direction():
    T = np.tile(np.eye(4), (4, 1, 1))
    T[1, :3, 3] = [0.3, 0.0, 0.0]  # near, same direction
    T[2, :3, 3] = [0.1, 0.0, 0.0]
    T[2, :3, :3] = np.diag([-1.0, 1.0, -1.0])  # near, opposite direction
    T[3, :3, 3] = [2.0, 0.0, 0.0]  # far
    gt = loop_ground_truth(T, max_dist=0.5, max_angle_deg=30)
    assert gt[0, 1] and not gt[0, 2] and not gt[0, 3] and gt.diagonal().all()


def test_up_and_convergence_from_a_synthetic_orbit():
    R_tilt = cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))[0]
    up = R_tilt @ UP
    centre = np.array([1.0, -2.0, 0.5])
    ang = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    pos = np.stack([1.5 * np.cos(ang), 1.5 * np.sin(ang), 0.8 + 0.1 * np.sin(3 * ang)], 1)
    T = look_at(pos, np.zeros_like(pos), UP, 0.05 * np.sin(5 * ang))
    T[:, :3, :] = np.einsum("ij,njk->nik", R_tilt, T[:, :3, :])
    T[:, :3, 3] += centre
    assert np.degrees(np.arccos(estimate_up(T[:, :3, :3]) @ up)) < 1.0
    np.testing.assert_allclose(axes_convergence(T[:, :3, 3], T[:, :3, 2]), centre, atol=1e-6)


def test_replay_scene_fits_the_real_trajectory(replay_gt):
    gt = read_tum(replay_gt)
    scene, info = fit_scene_to_trajectory(gt.poses, scene_seed=0)
    P_s = (gt.positions - scene.T_world_scene[:3, 3]) @ scene.T_world_scene[:3, :3]
    room = scene.layout["room"]
    gap = np.stack([P_s[:, 0] - room["x0"], room["x1"] - P_s[:, 0], P_s[:, 1] - room["y0"], room["y1"] - P_s[:, 1]])
    assert gap.min() >= 1.0 and gap.min(axis=1).max() <= 3.0  # walls 1-3 m beyond the path
    assert P_s[:, 2].min() > 0.9 and P_s[:, 2].max() < room["height"] - 0.5
    # No camera inside anything, and every view is filled (closed room): cast the
    # optical axis and the image corners of every 20th frame.
    T = gt.poses[::20]
    uv = np.array([[CAM.cx, CAM.cy], [0, 0], [639, 0], [0, 479], [639, 479]], float)
    rays = np.einsum("nij,kj->nki", T[:, :3, :3], CAM.unproject(uv)).reshape(-1, 3)
    s, hit = raycast(scene, np.repeat(T[:, :3, 3], len(uv), 0), rays)
    assert np.all(hit >= 0) and s.min() > 0.25
    labels = np.array([scene.quads[i].label for i in hit.reshape(len(T), -1)[:, 0]])
    on_desk = ~np.isin(labels, ["floor", "ceiling", "wall_x0", "wall_x1", "wall_y0", "wall_y1", "poster", "door"])
    assert on_desk.mean() > 0.5, on_desk.mean()  # the optical axis mostly meets the desk and furniture


def test_replay_path_reproduces_ground_truth(replay_gt):
    gt = read_tum(replay_gt)
    path = ReplayPath(gt)
    np.testing.assert_allclose(path(gt.timestamps[:500]), gt.poses[:500], atol=1e-9)
    mid = 0.5 * (gt.timestamps[10] + gt.timestamps[11])
    T = path(np.array([mid]))[0]
    np.testing.assert_allclose(T[:3, 3], 0.5 * (gt.positions[10] + gt.positions[11]), atol=1e-12)
    a = rotation_angle_deg(gt.poses[10, :3, :3].T @ T[:3, :3])
    b = rotation_angle_deg(T[:3, :3].T @ gt.poses[11, :3, :3])
    assert abs(a - b) < 1e-6
    stamps = path.frame_times(30.0)
    assert stamps[0] == gt.timestamps[0] and gt.timestamps[-1] - 1 / 30 < stamps[-1] <= gt.timestamps[-1]


def test_replay_sequence_outputs(tmp_path, replay_gt):
    gt = read_tum(replay_gt)
    opts = SynthOptions(trajectory="replay", gt=str(replay_gt), frames=3, texel_scale=8.0,
                        loop_gt=True)
    out = render_sequence(tmp_path / "seq", opts, progress=False)
    written = read_tum(out / "groundtruth.txt")
    np.testing.assert_allclose(written.timestamps, gt.timestamps[0] + np.arange(3) / 30.0, atol=1e-6)
    np.testing.assert_allclose(written.poses, ReplayPath(gt)(written.timestamps), atol=1e-6)
    assert load_camera(out / "camera.yaml") == opts.camera
    lines = [ln.split() for ln in (out / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 3
    for stamp, name in lines:
        img = cv2.imread(str(out / name))
        assert img.shape == (480, 640, 3) and img.std() > 20
        assert abs(float(stamp) - float(name[4:-4])) == 0
    loop = np.load(out / "loop_gt.npy")
    assert loop.shape == (3, 3) and loop.all()
    meta = json.loads((out / "scene.json").read_text())
    assert meta["options"]["trajectory"] == "replay" and meta["frames"] == 3
    # The same trajectory from another place (another checkout) is the same sequence: kept.
    moved = tmp_path / "elsewhere" / "groundtruth.txt"
    moved.parent.mkdir()
    moved.write_bytes(replay_gt.read_bytes())
    stamp = (out / "scene.json").stat().st_mtime_ns
    render_sequence(tmp_path / "seq", dataclasses.replace(opts, gt=str(moved)), progress=False)
    assert (out / "scene.json").stat().st_mtime_ns == stamp
    # Another trajectory is another sequence.
    moved.write_text("".join(replay_gt.read_text().splitlines(keepends=True)[:-1]))
    with pytest.raises(DatasetError, match="not empty"):
        render_sequence(tmp_path / "seq", dataclasses.replace(opts, gt=str(moved)), progress=False)


def test_same_seed_same_bytes_and_seeds_matter(tmp_path):
    small = dict(width=320, height=240, fx=267.7, fy=269.6, cx=160.05, cy=123.8)
    base = dict(frames=2, texel_scale=8.0, noise=2.0, exposure_drift=0.1, motion_blur=True, **small)
    a = render_sequence(tmp_path / "a", SynthOptions(**base), progress=False)
    b = render_sequence(tmp_path / "b", SynthOptions(**base), progress=False)
    c = render_sequence(tmp_path / "c", SynthOptions(**base, seed=1), progress=False)
    names = sorted(p.name for p in (a / "rgb").iterdir())
    assert len(names) == 2
    for name in names:
        assert (a / "rgb" / name).read_bytes() == (b / "rgb" / name).read_bytes()
        assert (a / "rgb" / name).read_bytes() != (c / "rgb" / name).read_bytes()
    assert (a / "groundtruth.txt").read_bytes() == (b / "groundtruth.txt").read_bytes()


def test_texture_seed_and_repeated_mode():
    scene, _, _, _ = build_sequence(SynthOptions(frames=30))
    walls = [i for i, q in enumerate(scene.quads) if q.label.startswith("wall")][:2]
    t0 = [surface_texture(scene, i, 0, texel_scale=4.0)[0] for i in walls]
    t1 = surface_texture(scene, walls[0], 1, texel_scale=4.0)[0]
    assert np.mean(t0[0] != t1) > 0.5 and np.mean(t0[0] != t0[1]) > 0.5
    rep = [surface_texture(scene, i, 0, repeated=True, texel_scale=4.0) for i in walls]
    h = min(r[0].shape[0] for r in rep)
    w = min(r[0].shape[1] for r in rep)
    np.testing.assert_array_equal(rep[0][0][:h, :w], rep[1][0][:h, :w])
    # The patch (500 texels of 1.2 mm) repeats along the wall at its metric size.
    tex, tu, tv = rep[0]
    period = round(500 * 0.0012 / np.sqrt(tu * tv))
    assert tex.shape[1] > 2 * period
    np.testing.assert_array_equal(tex[:, :period], tex[:, period:2 * period])
    assert np.mean(tex[:, :period] != tex[:, period // 2:period // 2 + period]) > 0.5


def test_cli_caches_refuses_and_forces(tmp_path, capsys):
    out = tmp_path / "cli"
    args = ["synth", "--out", str(out), "--frames", "2", "--texel-scale", "8"]
    assert main(args) == 0
    first = (out / "rgb.txt").stat().st_mtime_ns
    assert main(args) == 0  # same options: kept as it is
    assert (out / "rgb.txt").stat().st_mtime_ns == first
    assert main(args + ["--noise", "1"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert main(args + ["--noise", "1", "--force"]) == 0
    assert main(["synth", "--out", str(tmp_path / "x"), "--trajectory", "replay", "--gt", str(tmp_path / "no.txt")]) == 2


def test_an_interrupted_render_leaves_the_output_folder_as_it_was(tmp_path, monkeypatch):
    from orbslam_hgcn.synth import sequence

    opts = SynthOptions(frames=4, texel_scale=8.0)
    out = tmp_path / "seq"
    frame = sequence.camera_frame

    def interrupted(renderer, poses, t, k, *args):
        if k == 2:
            raise KeyboardInterrupt
        return frame(renderer, poses, t, k, *args)

    monkeypatch.setattr(sequence, "camera_frame", interrupted)
    with pytest.raises(KeyboardInterrupt):
        render_sequence(out, opts, progress=False)
    assert not out.exists() and list(tmp_path.iterdir()) == []  # nor a temporary folder
    # A render killed outright leaves its temporary folder: the next render removes it.
    stale = tmp_path / ".seq.partial-999999999"
    (stale / "rgb").mkdir(parents=True)
    monkeypatch.setattr(sequence, "camera_frame", frame)
    assert render_sequence(out, opts, progress=False) == out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]
    assert len(list((out / "rgb").glob("*.png"))) == 4 and (out / "scene.json").is_file()


def test_a_half_written_render_is_made_again_and_user_files_are_kept(tmp_path, capsys):
    """A render cut short by an older version (frames, no scene.json) is replaced without
    --force; --force replaces a complete other sequence and keeps the user's own files."""
    opts = SynthOptions(frames=3, texel_scale=8.0)
    out = tmp_path / "seq"
    (out / "rgb").mkdir(parents=True)
    (out / "rgb" / "0.000000.png").write_bytes(b"half")
    (out / "rgb.txt").write_text("# half\n")
    assert render_sequence(out, opts, progress=False) == out
    assert len(list((out / "rgb").glob("*.png"))) == 3 and (out / "rgb" / "0.000000.png").read_bytes() != b"half"
    (out / "notes.txt").write_text("mine")
    other = SynthOptions(frames=2, texel_scale=8.0)
    with pytest.raises(DatasetError, match="not empty"):
        render_sequence(out, other, progress=False)
    render_sequence(out, other, force=True, progress=False)
    assert len(list((out / "rgb").glob("*.png"))) == 2 and (out / "notes.txt").read_text() == "mine"
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]


def test_demo_cache_recovers_from_an_interrupted_render_and_force_renders_again(tmp_path, monkeypatch):
    from orbslam_hgcn.app.demo import demo_sequence

    cache = tmp_path / "cache"
    folder = cache / "loop_3frames"
    (folder / "rgb").mkdir(parents=True)
    (folder / "rgb" / "1.png").write_bytes(b"")  # an interrupted render of an older version
    (cache / ".loop_3frames.partial-999999999").mkdir()  # and one killed outright
    seq = demo_sequence(cache, frames=3, progress=False)
    assert seq == folder and len(list((folder / "rgb").glob("*.png"))) == 3
    assert [p.name for p in cache.iterdir()] == ["loop_3frames"]
    stamp = (folder / "scene.json").stat().st_mtime_ns
    assert demo_sequence(cache, frames=3, progress=False) == folder
    assert (folder / "scene.json").stat().st_mtime_ns == stamp  # kept
    demo_sequence(cache, frames=3, progress=False, force=True)
    assert (folder / "scene.json").stat().st_mtime_ns != stamp  # rendered again


def test_camera_effects_blur_noise_and_drift():
    small = dict(width=320, height=240, fx=267.7, fy=269.6, cx=160.05, cy=123.8, texel_scale=8.0)
    clean = SynthOptions(duration=10.0, **small)
    scene, poses, stamps, _ = build_sequence(clean)
    renderer = SceneRenderer(scene, clean.camera, texel_scale=8.0)
    t = float(stamps[40])
    sharp = renderer.render(poses(np.array([t]))[0])[0].astype(np.float32)
    blurred = render_frame(renderer, poses, t, SynthOptions(duration=10.0, motion_blur=True, shutter=1.0, **small))[0]
    # Averaging sub-frames keeps the brightness and removes detail.
    assert abs(float(blurred.mean()) - float(sharp.mean())) < 0.5
    lap = [cv2.Laplacian(cv2.cvtColor(np.asarray(im, np.float32), cv2.COLOR_BGR2GRAY), cv2.CV_32F).var()
           for im in (sharp, blurred)]
    assert lap[1] < 0.6 * lap[0]
    noisy = CameraEffects(SynthOptions(noise=3.0, seed=5)).apply(sharp, t, 40).astype(np.float32)
    inner = (sharp > 20) & (sharp < 235)
    assert abs(float((noisy - sharp)[inner].std()) - 3.0) < 0.1
    drift = CameraEffects(SynthOptions(exposure_drift=0.2, seed=5))
    gain, offset = drift.gain_offset(t)
    assert 0.8 <= gain <= 1.2 and abs(offset) <= 2.4
    out = drift.apply(sharp, t, 40).astype(np.float32)
    np.testing.assert_allclose(out[inner], np.clip(sharp * gain + offset, 0, 255)[inner], atol=0.51)


def test_loop_laps_pass_beside_each_other_and_close_after_the_last():
    """--laps 2: the second lap revisits the first from 0.1-0.3 m beside it (still one
    place for the loop ground truth), the camera never jumps, and the path closes."""
    from orbslam_hgcn.synth.trajectory import loop_ground_truth

    opts = SynthOptions(frames=600, laps=2, fps=30, scene_seed=4)
    _, poses, stamps, info = build_sequence(opts)
    assert info["period_s"] == pytest.approx(10.0)
    P = poses(stamps)
    twin = np.linalg.norm(P[300:, :3, 3] - P[:300, :3, 3], axis=1)
    assert 0.05 < twin.min() and twin.max() < 0.4
    assert np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).max() < 0.05  # under 5 cm per frame
    np.testing.assert_allclose(poses(np.array([20.0]))[0], P[0], atol=1e-9)  # closes after two laps
    gt = loop_ground_truth(P)
    assert gt[np.arange(300, 600), np.arange(300)].all()
    with pytest.raises(ConfigError, match="laps"):
        SynthOptions(trajectory="replay", gt="x.txt", laps=2).validate()


def _frames(folder, sub):
    return sorted((folder / sub).iterdir())


def test_jpg_frames_are_the_one_compression_and_read_back(tmp_path):
    """--image-format jpg writes .jpg files at --jpeg-quality (90 by default), the encoding
    of the very frame the PNG render holds (no JPEG round trip before it), which the TUM and
    KITTI readers open with the PNG render's frames and timestamps."""
    from orbslam_hgcn.datasets import open_sequence

    args = ["synth", "--frames", "2", "--texel-scale", "8"]
    assert main(args + ["--out", str(tmp_path / "png")]) == 0
    assert main(args + ["--out", str(tmp_path / "q90"), "--image-format", "jpg"]) == 0
    assert main(args + ["--out", str(tmp_path / "q60"), "--image-format", "jpg", "--jpeg-quality", "60"]) == 0
    png = _frames(tmp_path / "png", "rgb")
    for name, quality in (("q90", 90), ("q60", 60)):
        meta = json.loads((tmp_path / name / "scene.json").read_text())
        assert meta["image_format"] == "jpg" and meta["options"]["jpeg_quality"] == quality
        jpgs = _frames(tmp_path / name, "rgb")
        assert [p.suffix for p in jpgs] == [".jpg", ".jpg"] and [p.stem for p in jpgs] == [p.stem for p in png]
        listed = [ln.split()[1] for ln in (tmp_path / name / "rgb.txt").read_text().splitlines() if ln[0] != "#"]
        assert listed == [f"rgb/{p.name}" for p in jpgs]
        for p, j in zip(png, jpgs):
            ref = cv2.imread(str(p))
            ok, buf = cv2.imencode(".jpg", ref, [cv2.IMWRITE_JPEG_QUALITY, quality])
            assert ok and j.read_bytes() == buf.tobytes()  # this quality, and only this compression
            img = cv2.imread(str(j))
            assert img.shape == (480, 640, 3)
            mad = float(np.abs(img.astype(np.float32) - ref).mean())
            assert (0.3 < mad < 3.0) if quality == 90 else mad > 1.0, (name, mad)
    assert json.loads((tmp_path / "png" / "scene.json").read_text())["image_format"] == "png"
    # Read back: the same frames and timestamps as the PNG render, decoded at its size.
    ref, seq = open_sequence(None, tmp_path / "png"), open_sequence(None, tmp_path / "q90")
    assert type(seq).__name__ == "TumSequence" and len(seq) == len(ref) == 2
    np.testing.assert_array_equal(seq.timestamps, ref.timestamps)
    diff = np.abs(seq[1].image.astype(np.float32) - ref[1].image).mean()
    assert seq[1].image.shape == (480, 640) and 0 < diff < 3
    # The KITTI layout: image_0/NNNNNN.jpg, grey.
    kitti = args + ["--layout", "kitti"]
    assert main(kitti + ["--out", str(tmp_path / "kpng")]) == 0
    assert main(kitti + ["--out", str(tmp_path / "kjpg"), "--image-format", "jpg"]) == 0
    kdir = tmp_path / "kjpg" / "sequences" / "00"
    assert [p.name for p in _frames(kdir, "image_0")] == ["000000.jpg", "000001.jpg"]
    assert cv2.imread(str(kdir / "image_0" / "000000.jpg"), cv2.IMREAD_UNCHANGED).shape == (480, 640)
    ref, seq = open_sequence(None, tmp_path / "kpng" / "sequences" / "00"), open_sequence(None, kdir)
    assert type(seq).__name__ == "KittiSequence" and len(seq) == len(ref) == 2
    np.testing.assert_array_equal(seq.timestamps, ref.timestamps)
    assert seq.camera == ref.camera and seq[0].image.shape == (480, 640)
    assert 0 < np.abs(seq[0].image.astype(np.float32) - ref[0].image).mean() < 3


def test_jpg_renders_are_cached_and_other_formats_refused(tmp_path, capsys):
    """A complete JPEG render is kept as it is (the "already rendered" check finds its .jpg
    frames); the same sequence asked as PNG is another one: refused without --force."""
    from orbslam_hgcn.synth.sequence import synth_options

    for layout, times in (("tum", "rgb.txt"), ("kitti", "sequences/00/times.txt")):
        out = tmp_path / layout
        args = ["synth", "--out", str(out), "--frames", "2", "--texel-scale", "8", "--layout", layout]
        assert main(args + ["--image-format", "jpg"]) == 0
        stamp = (out / times).stat().st_mtime_ns
        assert main(args + ["--image-format", "jpg"]) == 0
        assert (out / times).stat().st_mtime_ns == stamp
        capsys.readouterr()
        assert main(args) == 2 and "not empty" in capsys.readouterr().err
        assert main(args + ["--force"]) == 0
        assert not list(out.rglob("*.jpg")) and len(list(out.rglob("*.png"))) == 2
    # Beside a preset, only the format changes: the preset's quality is the files' quality.
    hard = synth_options("fr3_replay_hard", frames=5)
    jpg = synth_options("fr3_replay_hard", frames=5, image_format="jpg")
    assert jpg == dataclasses.replace(hard, image_format="jpg") and jpg.jpeg_quality == 75
    assert SynthOptions(image_format="jpg").jpeg_quality == 90 and SynthOptions().jpeg_quality == 0
    with pytest.raises(ConfigError, match="image format"):
        SynthOptions(image_format="gif").validate()
