"""PLY export of a map (orbslam_hgcn.map.ply, ``orbslam-hgcn map export-ply``): a real map
made by a short run on the real TUM sitting_xyz frames, written and read back with the
independent ``plyfile`` reader, every vertex against the map; colours from the images
against the pixels; the CLI's errors as one line and status 2."""

import subprocess
import sys

import cv2
import numpy as np
import pytest
from plyfile import PlyData

from conftest import REPO, SHARED_DATA
from orbslam_hgcn.cli import main
from orbslam_hgcn.errors import OrbslamError
from orbslam_hgcn.map import Map
from orbslam_hgcn.map.io import read_map
from orbslam_hgcn.map.ply import (
    PlyExportError,
    export_map_ply,
    observation_colours,
    point_colours_from_images,
    write_points_ply,
)

SITTING = SHARED_DATA / "tum_fr3_sitting_xyz_148"
F32 = dict(rtol=1e-6, atol=1e-6)


@pytest.fixture(scope="module")
def saved_map(tmp_path_factory):
    """(map file, its active map) of 40 real frames run in order (about 2 s)."""
    assert (SITTING / "rgb.txt").is_file(), f"real TUM sitting_xyz frames not found at {SITTING}"
    out = tmp_path_factory.mktemp("ply_run")
    res = subprocess.run([sys.executable, "-m", "orbslam_hgcn", "run", str(SITTING), "--out", str(out),
                          "--sequential", "--max-frames", "40", "--no-progress", "--save-map", str(out / "map.npz")],
                         cwd=REPO, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    m = read_map(out / "map.npz").map
    assert m.n_keyframes() >= 4 and m.n_points() >= 200, "the run must build a map worth exporting"
    return out / "map.npz", m


def _vertices(path):
    ply = PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<"
    assert [e.name for e in ply.elements] == ["vertex"]
    return ply, ply["vertex"].data


def test_points_are_the_maps_points(saved_map, tmp_path):
    _, m = saved_map
    paths = export_map_ply(m, tmp_path / "cloud.ply")
    assert paths == {"points": tmp_path / "cloud.ply", "keyframes": tmp_path / "cloud_keyframes.ply"}
    ply, v = _vertices(paths["points"])
    assert [(p.name, p.val_dtype) for p in ply["vertex"].properties] == [
        ("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("observations", "i4")]
    assert ply.comments == [f"orbslam_hgcn map {m.map_id}", "units: map units (monocular: arbitrary scale)"]
    pids = m.point_ids()
    xyz = m.positions(pids)
    n_obs = m.n_observations(pids)
    assert len(v) == m.n_points() == len(pids)
    got = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    np.testing.assert_allclose(got.min(axis=0), xyz.min(axis=0), **F32)
    np.testing.assert_allclose(got.max(axis=0), xyz.max(axis=0), **F32)
    np.testing.assert_allclose(got, xyz, **F32)  # vertex by vertex, in point id order
    assert np.array_equal(v["observations"], n_obs) and n_obs.min() >= 2
    # Without colours: the observation ramp, dark at 2 observations, bright from 15 on.
    rgb = np.stack([v["red"], v["green"], v["blue"]], axis=1)
    assert np.array_equal(rgb, observation_colours(n_obs))
    assert len(np.unique(rgb, axis=0)) > 3
    ramp = observation_colours(np.arange(0, 30))
    assert tuple(ramp[2]) == tuple(ramp[0]) == (68, 1, 84) and tuple(ramp[15]) == tuple(ramp[29]) == (253, 231, 37)
    assert np.all(np.diff(ramp[2:16, 1].astype(int)) > 0)  # green rises all along viridis


def test_keyframes_are_the_maps_camera_centres_and_axes(saved_map, tmp_path):
    _, m = saved_map
    paths = export_map_ply(m, tmp_path / "cloud.ply")
    ply, v = _vertices(paths["keyframes"])
    assert [p.name for p in ply["vertex"].properties] == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue",
                                                         "frame"]
    kfs = m.keyframes()
    assert len(v) == m.n_keyframes() == len(kfs)
    # From T_cw (world to camera): centre -R^T t, optical axis R^T (0, 0, 1) = R's third row.
    T_cw = np.stack([kf.T_cw for kf in kfs])
    centres = -np.einsum("kji,kj->ki", T_cw[:, :3, :3], T_cw[:, :3, 3])
    axes = T_cw[:, 2, :3]
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], axis=1), centres, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.stack([v["nx"], v["ny"], v["nz"]], axis=1), axes, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(axes, axis=1), 1.0, atol=1e-9)
    assert np.array_equal(v["frame"], [kf.frame_id for kf in kfs]) and v["frame"][0] == kfs[0].frame_id
    assert np.all(v["red"] == 255) and np.all(v["green"] == 0) and np.all(v["blue"] == 0)
    # The cameras look at the points: each keyframe sees its own points in front of it.
    for k, kf in enumerate(kfs):
        _, pids = kf.observed_points()
        depth = (m.positions(pids) - centres[k]) @ axes[k]
        assert np.all(depth > 0), kf.id


def _oldest_view(m, pid):
    kf_id, idx = min(m.point(pid).observations.items())
    kf = m.keyframe(kf_id)
    return kf, kf.keypoints.uv_raw[idx]


def test_colours_from_the_dataset_are_the_keypoints_pixels(saved_map, tmp_path, capsys):
    path, m = saved_map
    out = tmp_path / "coloured.ply"
    assert main(["map", "export-ply", str(path), str(out), "--colour-from", str(SITTING)]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out} ({m.n_points()} points)" in printed
    assert f"wrote {tmp_path / 'coloured_keyframes.ply'} ({m.n_keyframes()} keyframes)" in printed
    assert f"coloured {m.n_points()} of {m.n_points()} points" in printed
    _, v = _vertices(out)
    pids = m.point_ids()
    rgb = np.stack([v["red"], v["green"], v["blue"]], axis=1)
    assert not np.array_equal(rgb, observation_colours(m.n_observations(pids)))
    listing = [line.split() for line in (SITTING / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
    rng = np.random.default_rng(0)
    for row in rng.choice(len(pids), 8, replace=False).tolist():
        kf, (u, vv) = _oldest_view(m, int(pids[row]))
        stamp, name = listing[kf.frame_id]
        assert abs(float(stamp) - kf.timestamp) < 1e-6  # frame_id: the image's line in rgb.txt
        image = cv2.imread(str(SITTING / name), cv2.IMREAD_COLOR)
        b, g, r = image[int(np.floor(vv + 0.5)), int(np.floor(u + 0.5))]
        assert tuple(rgb[row]) == (r, g, b), (pids[row], kf.frame_id)


def test_colours_sampled_in_rgb_order_once_per_image(saved_map, tmp_path):
    _, m = saved_map
    cam = m.keyframes()[0].camera
    rows, cols = np.mgrid[0:cam.height, 0:cam.width]
    bgr = np.stack([cols % 256, rows % 256, np.full_like(rows, 200)], axis=2).astype(np.uint8)
    kfs = m.keyframes()
    missing = kfs[0].frame_id  # the origin keyframe has no image: its points take the next keyframe's
    calls = []

    def image_of(frame_id):
        calls.append(frame_id)
        return None if frame_id == missing else bgr

    colours = point_colours_from_images(m, image_of)
    assert len(calls) == len(set(calls)) and set(calls) <= {kf.frame_id for kf in kfs}
    only_origin = [int(p) for p in m.point_ids() if set(m.point(p).observations) == {kfs[0].id}]
    assert not set(only_origin) & set(colours)
    checked = 0
    for pid in m.point_ids().tolist():
        obs = {k: i for k, i in m.point(pid).observations.items() if k != kfs[0].id}
        if not obs:
            continue
        kf_id = min(obs)
        u, vv = m.keyframe(kf_id).keypoints.uv_raw[obs[kf_id]]
        col, row = int(np.floor(u + 0.5)), int(np.floor(vv + 0.5))
        assert colours[pid] == (200, row % 256, col % 256), pid
        checked += 1
    assert checked == len(colours) > 100
    # Written: those colours, the ramp for the points without one.
    write_points_ply(tmp_path / "c.ply", m, colours)
    _, v = _vertices(tmp_path / "c.ply")
    pids = m.point_ids()
    want = observation_colours(m.n_observations(pids))
    for k, p in enumerate(pids.tolist()):
        if p in colours:
            want[k] = colours[p]
    assert np.array_equal(np.stack([v["red"], v["green"], v["blue"]], axis=1), want)
    # An array of colours, one row per point.
    table = np.tile(np.array([[1, 2, 3]]), (len(pids), 1))
    write_points_ply(tmp_path / "a.ply", m, table)
    _, v = _vertices(tmp_path / "a.ply")
    assert np.all(v["red"] == 1) and np.all(v["green"] == 2) and np.all(v["blue"] == 3)
    with pytest.raises(ValueError, match="one row per point"):
        write_points_ply(tmp_path / "b.ply", m, table[1:])
    # A grey image gives grey colours; an image of the wrong size is refused.
    grey = point_colours_from_images(m, lambda f: bgr[:, :, 0])
    assert all(c[0] == c[1] == c[2] for c in grey.values()) and len(grey) == len(m.point_ids())
    with pytest.raises(OrbslamError, match="not the images the map was made from"):
        point_colours_from_images(m, lambda f: bgr[:100])


def test_export_refuses_bad_paths_and_empty_maps(saved_map, tmp_path):
    _, m = saved_map
    with pytest.raises(PlyExportError, match=r"cloud\.txt: the output must be a \.ply file"):
        export_map_ply(m, tmp_path / "cloud.txt")
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(OrbslamError, match="cannot be created"):
        export_map_ply(m, tmp_path / "a_file" / "cloud.ply")
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(OrbslamError, match="names a folder"):
        export_map_ply(m, tmp_path / "dir.ply")
    with pytest.raises(PlyExportError, match="no points"):
        export_map_ply(Map(), tmp_path / "empty.ply")
    assert not (tmp_path / "empty.ply").exists() and not (tmp_path / "cloud.txt").exists()
    assert issubclass(PlyExportError, OrbslamError)
    # A folder that does not exist yet is made.
    paths = export_map_ply(m, tmp_path / "new" / "deeper" / "cloud.ply")
    assert paths["points"].is_file() and paths["keyframes"].is_file()


def test_cli_errors_are_one_line_and_status_2(saved_map, tmp_path):
    path, _ = saved_map
    (tmp_path / "garbage.npz").write_bytes(b"not a zip file" * 10)
    cases = {
        "map file not found": [str(tmp_path / "missing.npz"), str(tmp_path / "out.ply")],
        "must be a .ply file": [str(path), str(tmp_path / "out.txt")],
        "garbage.npz": [str(tmp_path / "garbage.npz"), str(tmp_path / "out.ply")],
        "not the dataset the map was made from": [str(path), str(tmp_path / "out.ply"), "--colour-from",
                                                  str(SHARED_DATA / "tum_fr3_long_office_household_sample")],
    }
    for expected, args in cases.items():
        res = subprocess.run([sys.executable, "-m", "orbslam_hgcn", "map", "export-ply", *args], cwd=REPO,
                             capture_output=True, text=True, timeout=120)
        err = [line for line in res.stderr.splitlines() if not line.startswith("INFO ")]
        assert res.returncode == 2, (expected, res.stderr)
        assert len(err) == 1 and err[0].startswith("orbslam-hgcn map: error: ") and expected in err[0], res.stderr
        assert "Traceback" not in res.stderr and res.stdout == ""
    assert not (tmp_path / "out.ply").exists() and not (tmp_path / "out.txt").exists()
