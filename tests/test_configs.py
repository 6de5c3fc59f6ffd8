"""Shipped camera configs load and carry the published calibrations; bad configs are named errors."""

import re

import numpy as np
import pytest

from orbslam_hgcn.config import CONFIG_DIR, load_camera
from orbslam_hgcn.errors import ConfigError

# Published values: TUM RGB-D file-formats page (Sturm et al. 2012), EuRoC sensor.yaml
# (Burri et al. 2016), KITTI odometry calib.txt P0 (Geiger et al. 2012).
PUBLISHED = {
    "tum_fr1": (517.3, 516.5, 318.6, 255.3, 640, 480, [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
    "tum_fr2": (520.9, 521.0, 325.1, 249.7, 640, 480, [0.2312, -0.7849, -0.0033, -0.0001, 0.9172]),
    "tum_fr3": (535.4, 539.2, 320.1, 247.6, 640, 480, [0, 0, 0, 0, 0]),
    "euroc_cam0": (458.654, 457.296, 367.215, 248.375, 752, 480, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]),
    "kitti_00-02": (718.856, 718.856, 607.1928, 185.2157, 1241, 376, [0, 0, 0, 0, 0]),
    "kitti_03": (721.5377, 721.5377, 609.5593, 172.854, 1242, 375, [0, 0, 0, 0, 0]),
    "kitti_04-12": (707.0912, 707.0912, 601.8873, 183.1104, 1226, 370, [0, 0, 0, 0, 0]),
}
FPS = {"tum": 30.0, "euroc": 20.0, "kitti": 10.0}

GOOD = "name: t\nwidth: 640\nheight: 480\nfps: 30\nfx: 500\nfy: 500\ncx: 320\ncy: 240\ndistortion: [0, 0, 0, 0]\n"


def test_every_shipped_config_loads_and_names_its_source():
    files = sorted(CONFIG_DIR.glob("*.yaml"))
    assert {f.stem for f in files} >= set(PUBLISHED)
    for f in files:
        cam = load_camera(f)
        assert cam.width > 0 and cam.height > 0
        assert 0 < cam.cx < cam.width and 0 < cam.cy < cam.height
        text = f.read_text()
        assert re.search(r"^# .*(Sturm et al|Burri et al|Geiger et al)", text, re.M), f"{f.name}: no source comment"


@pytest.mark.parametrize("name", sorted(PUBLISHED))
def test_shipped_config_matches_published_calibration(name):
    cam = load_camera(name)  # by bare name
    assert cam == load_camera(CONFIG_DIR / f"{name}.yaml")
    fx, fy, cx, cy, w, h, dist = PUBLISHED[name]
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (fx, fy, cx, cy, w, h)
    np.testing.assert_array_equal(cam.dist_coeffs[: len(dist)], dist)
    assert cam.fps == FPS[name.split("_")[0]]
    assert cam.name == name


def test_euroc_config_agrees_with_the_sample_sensor_yaml(euroc_layout):
    """The shipped euroc_cam0 camera is EuRoC's cam0 calibration as the reader reads it from
    a sensor.yaml (the real sample's, or the stand-in's copy of the published one)."""
    from orbslam_hgcn.datasets.euroc import read_sensor_yaml

    cam, _ = read_sensor_yaml(euroc_layout / "mav0" / "cam0" / "sensor.yaml")
    assert cam == load_camera("euroc_cam0")


def test_good_minimal_config_loads(tmp_path):
    p = tmp_path / "good.yaml"
    p.write_text(GOOD)
    cam = load_camera(p)
    assert (cam.fx, cam.cx, cam.width) == (500.0, 320.0, 640)


@pytest.mark.parametrize(
    "edit, key",
    [
        (lambda s: s.replace("fx: 500\n", ""), r"\[fx\]"),
        (lambda s: s.replace("fx: 500", "fx: 0"), r"\[fx\]"),
        (lambda s: s.replace("fx: 500", "fx: -500"), r"\[fx\]"),
        (lambda s: s.replace("fx: 500", "fx: abc"), r"\[fx\]"),
        (lambda s: s.replace("cx: 320", "cx: 700"), r"\[cx/cy\]"),
        (lambda s: s.replace("cy: 240", "cy: -1"), r"\[cx/cy\]"),
        (lambda s: s.replace("distortion: [0, 0, 0, 0]", "distortion: [0, 0, 0]"), r"\[distortion\]"),
        (lambda s: s.replace("distortion: [0, 0, 0, 0]", "distortion: [0, a, 0, 0]"), r"\[distortion\]"),
        (lambda s: s.replace("distortion: [0, 0, 0, 0]", "distortion: 0.1"), r"\[distortion\]"),
        (lambda s: s.replace("width: 640", "width: 640.5"), r"\[width\]"),
    ],
)
def test_bad_config_is_a_config_error_naming_file_and_key(tmp_path, edit, key):
    p = tmp_path / "cam_bad.yaml"
    p.write_text(edit(GOOD))
    with pytest.raises(ConfigError, match=r"cam_bad\.yaml " + key):
        load_camera(p)


def test_invalid_yaml_names_file_and_line(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text(GOOD + "fy: [1, 2\nname: x\n")
    with pytest.raises(ConfigError, match=r"broken\.yaml:\d+: not valid YAML"):
        load_camera(p)


def test_missing_config_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match=r"nope\.yaml: config file not found"):
        load_camera(tmp_path / "nope.yaml")


@pytest.mark.parametrize(
    "name, features", [("kitti_00-02", 2000), ("kitti_03", 2000), ("kitti_04-12", 2000),
                       ("tum_fr1", 1000), ("tum_fr2", 1000), ("tum_fr3", 1000), ("euroc_cam0", 1000)],
)  # fmt: skip
def test_shipped_configs_carry_orb_slams_settings(name, features):
    """ORB-SLAM's example settings (ORBextractor.*) for each camera, used as stage settings."""
    from orbslam_hgcn.runtime.system import Configs

    c = Configs.from_yaml(CONFIG_DIR / f"{name}.yaml")
    assert (c.orb.n_features, c.orb.scale_factor, c.orb.n_levels) == (features, 1.2, 8)
    assert (c.orb.ini_th_fast, c.orb.min_th_fast) == (20.0, 7.0)


def _kitti_00_layout(tmp_path):
    """A KITTI odometry folder with sequence 00's calib.txt (its P0, P1) and two blank 1241x376
    frames: what a run reads to tell the camera."""
    import cv2
    import numpy as np

    folder = tmp_path / "sequences" / "00"
    (folder / "image_0").mkdir(parents=True)
    for i in range(2):
        cv2.imwrite(str(folder / "image_0" / f"{i:06d}.png"), np.full((376, 1241), 128, np.uint8))
    (folder / "times.txt").write_text("0.000000e+00\n1.036000e-01\n")
    p0 = "7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0"
    p1 = "7.188560e+02 0 6.071928e+02 -3.861448e+02 0 7.188560e+02 1.852157e+02 0 0 0 1 0"
    (folder / "calib.txt").write_text(f"P0: {p0}\nP1: {p1}\n")
    return folder


def test_dataset_settings_follow_the_datasets_camera(tmp_path, tum_layout, euroc_layout):
    """A run picks the settings of the shipped config whose camera the dataset has (KITTI's
    calib.txt included), or of the dataset kind's family; none for an unknown camera."""
    from orbslam_hgcn.config import dataset_settings
    from orbslam_hgcn.datasets import open_sequence
    from orbslam_hgcn.geometry.camera import PinholeCamera

    path, settings = dataset_settings(open_sequence("kitti", _kitti_00_layout(tmp_path)).camera, "kitti")
    assert path.stem == "kitti_00-02" and settings["orb"]["n_features"] == 2000
    path, _ = dataset_settings(open_sequence("tum", tum_layout).camera, "tum")
    assert path.stem == "tum_fr3"
    path, settings = dataset_settings(open_sequence("euroc", euroc_layout).camera, "euroc")
    assert path.stem == "euroc_cam0" and settings["orb"]["n_features"] == 1000
    odd = PinholeCamera(fx=700.0, fy=700.0, cx=600.0, cy=180.0, width=1200, height=360)
    path, settings = dataset_settings(odd, "kitti")  # another KITTI-like camera: the family's settings
    assert path.stem.startswith("kitti_") and settings["orb"]["n_features"] == 2000
    assert dataset_settings(odd, "folder") == (None, {})


def test_config_overrides_dataset_settings_key_by_key(tmp_path):
    """--config replaces only the keys it names: the rest of a section keeps the dataset's."""
    from orbslam_hgcn.runtime.system import Configs

    user = tmp_path / "user.yaml"
    user.write_text("orb: {n_levels: 6}\ntracking: {min_inliers: 40}\n")
    import yaml

    c = Configs.from_layers([(yaml.safe_load((CONFIG_DIR / "kitti_00-02.yaml").read_text()), "kitti"),
                             (yaml.safe_load(user.read_text()), user)])  # fmt: skip
    assert (c.orb.n_features, c.orb.n_levels, c.tracking.min_inliers) == (2000, 6, 40)
    bad = tmp_path / "bad.yaml"
    bad.write_text("orb: {n_featurez: 3}\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml.*orb\.n_featurez"):
        Configs.from_layers([({}, "kitti"), (yaml.safe_load(bad.read_text()), bad)])


@pytest.mark.parametrize("text, section, said", [
    ("orbb: {n_features: 1500}\n", "orbb", "did you mean 'orb'"),
    ("vocabulary: {kind: hgcn}\n", "vocabulary", "--vocab"),
    ("tracking: {min_inliers: 40}\nlocal_maping: {ba_max_keyframes: 5}\n", "local_maping", "did you mean 'local_mapping'"),
])
def test_a_section_no_stage_reads_is_refused(tmp_path, capsys, text, section, said):
    """A misspelt section (or one that is no setting) would otherwise be ignored without a
    word: the API raises a ConfigError naming the file and the section, and `run` says so in
    one line with status 2 before it makes anything."""
    import yaml

    from orbslam_hgcn import cli
    from orbslam_hgcn.runtime.system import Configs

    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match=rf"bad\.yaml \[{section}\]: unknown section"):
        Configs.from_yaml(bad)
    with pytest.raises(ConfigError, match=section):
        Configs.from_layers([({}, "kitti"), (yaml.safe_load(text), bad)])
    seq = tmp_path / "seq"
    seq.mkdir()
    assert cli.main(["run", str(seq), "--out", str(tmp_path / "out"), "--config", str(bad)]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and section in err[0] and said in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "out").exists()


def test_every_section_a_shipped_config_or_the_viewer_uses_is_accepted(tmp_path):
    """The camera and the sections other commands read from the same file still load."""
    from orbslam_hgcn.runtime.system import Configs

    ok = tmp_path / "ok.yaml"
    ok.write_text("camera: {name: c, model: pinhole, width: 640, height: 480, fps: 30, fx: 500, fy: 500, "
                  "cx: 320, cy: 240, distortion: [0, 0, 0, 0, 0]}\nviz: {}\nfabmap: {}\nhgcn: {}\nvocab_tree: {}\n"
                  "orb: {n_features: 1500}\n")
    assert Configs.from_yaml(ok).orb.n_features == 1500
    for path in sorted(CONFIG_DIR.glob("*.yaml")):
        Configs.from_yaml(path)
