"""Dataset readers on the real TUM and EuRoC samples and on small sequences written here."""

import os
import shutil

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from orbslam_hgcn.config import load_camera, save_camera
from orbslam_hgcn.datasets import detect_kind, open_sequence
from orbslam_hgcn.datasets.euroc import EurocSequence
from orbslam_hgcn.datasets.kitti import KittiSequence
from orbslam_hgcn.datasets.tum import TumSequence
from orbslam_hgcn.errors import DatasetError, OrbslamError
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.geometry.se3 import inv_T, make_T

SMALL = PinholeCamera(100.0, 100.0, 40.0, 30.0, 80, 60, name="small")


def _rand_T(rng):
    return make_T(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))


def _images(rng, n, shape=(60, 80)):
    return [rng.integers(0, 256, size=shape, dtype=np.uint8) for _ in range(n)]


# --- TUM RGB-D (real sample) -----------------------------------------------------------


def _tum_listing(folder):
    rows = [ln.split() for ln in (folder / "rgb.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    return np.array([float(r[0]) for r in rows]), [r[1] for r in rows]


def test_tum_sample_frames_timestamps_and_images(tum_sample):
    seq = open_sequence("tum", tum_sample)
    stamps, names = _tum_listing(tum_sample)
    assert len(seq) == 19 == len(stamps)
    assert seq.timestamps[0] == pytest.approx(1341847980.722988, abs=1e-6)
    np.testing.assert_array_equal(seq.timestamps, stamps)
    assert seq.camera == load_camera("tum_fr3")  # inferred from the folder name
    frames = list(seq)
    assert [f.index for f in frames] == list(range(19))
    for f, name in zip(frames[:3], names):
        assert f.image.shape == (480, 640) and f.image.dtype == np.uint8
        raw = cv2.imread(str(tum_sample / name), cv2.IMREAD_COLOR)
        diff = np.abs(f.image.astype(int) - cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY).astype(int))
        assert diff.max() <= 1  # decoder's grey conversion vs cvtColor: rounding only
    color = open_sequence("tum", tum_sample, color=True)[5].image
    assert color.shape == (480, 640, 3)
    np.testing.assert_array_equal(color, cv2.imread(str(tum_sample / names[5]), cv2.IMREAD_COLOR))
    # Frames 0 and 1 precede the ground truth; the three late frames were chosen with a
    # pose within 5 ms.
    gt = np.loadtxt(tum_sample / "groundtruth.txt", comments="#")
    assert [i for i in range(19) if seq.pose(i) is not None] == list(range(2, 19))
    for i in (16, 17, 18):
        assert np.min(np.abs(gt[:, 0] - seq.timestamps[i])) < 0.005


def test_tum_ground_truth_is_nearest_line_within_20ms(tum_layout):
    seq = TumSequence(tum_layout)
    gt = np.loadtxt(tum_layout / "groundtruth.txt", comments="#")
    assert len(seq.ground_truth) == len(gt)
    with_pose = []
    for f in seq:
        dt = np.abs(gt[:, 0] - f.timestamp)
        j = int(np.argmin(dt))
        if dt[j] > 0.02:
            assert f.T_wc is None
            continue
        with_pose.append(f.index)
        R = Rotation.from_quat(gt[j, 4:8] / np.linalg.norm(gt[j, 4:8])).as_matrix()
        np.testing.assert_allclose(f.T_wc, make_T(R, gt[j, 1:4]), atol=1e-12)
    assert len(with_pose) >= len(seq) - 2


def _tum_copy(tmp_path, src, name="seq"):
    dst = tmp_path / name
    dst.mkdir()
    (dst / "rgb").symlink_to(src / "rgb")
    shutil.copy(src / "rgb.txt", dst / "rgb.txt")
    return dst


def test_tum_camera_precedence(tmp_path, tum_layout):
    folder = _tum_copy(tmp_path, tum_layout)
    with pytest.raises(OrbslamError, match=r"seq: .*--config"):
        TumSequence(folder)
    own = PinholeCamera(600.0, 600.0, 320.0, 240.0, 640, 480, name="own")
    save_camera(folder / "camera.yaml", own)
    assert TumSequence(folder).camera == own
    assert TumSequence(folder, "tum_fr1").camera == load_camera("tum_fr1")
    fr2 = _tum_copy(tmp_path, tum_layout, "rgbd_dataset_freiburg2_xyz")
    assert TumSequence(fr2).camera == load_camera("tum_fr2")
    assert TumSequence(fr2).ground_truth is None and TumSequence(fr2)[3].T_wc is None


def test_tum_commas_and_comments_tolerated(tmp_path, tum_layout):
    folder = _tum_copy(tmp_path, tum_layout)
    stamps, names = _tum_listing(tum_layout)
    (folder / "rgb.txt").write_text("# c\n\n" + "".join(f"{t:.6f}, {n}\n" for t, n in zip(stamps[:4], names)))
    seq = TumSequence(folder, "tum_fr3")
    np.testing.assert_allclose(seq.timestamps, stamps[:4], atol=1e-9)


@pytest.mark.parametrize(
    "listing, match",
    [
        ("# only a comment\n", r"rgb\.txt: no images listed"),
        ("1.0 rgb/a.png\n2.0 rgb/b.png extra\n", r"rgb\.txt:2: expected 'timestamp filename'"),
        ("# h\n1.0 rgb/a.png\nx1 rgb/b.png\n", r"rgb\.txt:3: not a number"),
        ("1.0 rgb/a.png\n1.0 rgb/b.png\n", r"rgb\.txt:2: timestamp .* does not increase"),
    ],
)
def test_tum_malformed_listing_names_file_and_line(tmp_path, listing, match):
    (tmp_path / "rgb.txt").write_text(listing)
    with pytest.raises(DatasetError, match=match):
        TumSequence(tmp_path, SMALL)


def test_tum_missing_folder_and_bad_images(tmp_path):
    with pytest.raises(DatasetError, match=r"nowhere: TUM sequence folder not found"):
        TumSequence(tmp_path / "nowhere")
    with pytest.raises(DatasetError, match=r"rgb\.txt: image listing not found"):
        TumSequence(tmp_path, SMALL)
    (tmp_path / "rgb").mkdir()
    (tmp_path / "rgb" / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage, not an image")
    (tmp_path / "rgb.txt").write_text("#\n1.0 rgb/a.png\n2.0 rgb/b.png\n")
    seq = TumSequence(tmp_path, SMALL)  # listings are checked up front, images lazily
    with pytest.raises(DatasetError, match=r"a\.png: image file not found \(listed at .*rgb\.txt:2\)"):
        seq[0]
    with pytest.raises(DatasetError, match=r"b\.png: cannot read image .*rgb\.txt:3"):
        seq[1]


def test_tum_bad_ground_truth_line(tmp_path, tum_layout):
    folder = _tum_copy(tmp_path, tum_layout)
    (folder / "groundtruth.txt").write_text("# t x y z qx qy qz qw\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"groundtruth\.txt:3"):
        TumSequence(folder, "tum_fr3")


def test_image_size_must_match_camera(tum_layout):
    with pytest.raises(DatasetError, match=r"\.png: image is 640x480 but camera 'small' expects 80x60"):
        TumSequence(tum_layout, SMALL)[0]


# --- EuRoC (real sample) ---------------------------------------------------------------


def _euroc_gt(path):
    rows = [ln.split(",") for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    ns = np.array([int(r[0].split(".")[0]) for r in rows], dtype=np.int64)
    vals = np.array([[float(x) for x in r[1:8]] for r in rows])
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(vals[:, [4, 5, 6, 3]]).as_matrix()  # file order w x y z
    T[:, :3, 3] = vals[:, :3]
    return ns, T


def test_euroc_sample_frames_camera_and_ground_truth(euroc_sample):
    cam_dir = euroc_sample / "mav0" / "cam0"
    seq = open_sequence("euroc", euroc_sample)
    ns = np.array([int(ln.split(",")[0]) for ln in (cam_dir / "data.csv").read_text().splitlines()[1:]])
    assert len(seq) == 95 == len(ns)
    np.testing.assert_array_equal(seq.timestamps_ns, ns)
    np.testing.assert_allclose(seq.timestamps, ns * 1e-9, rtol=0, atol=1e-6)
    cam = seq.camera
    assert (cam.width, cam.height, cam.fps) == (752, 480, 20.0)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (458.654, 457.296, 367.215, 248.375)
    np.testing.assert_array_equal(cam.dist_coeffs, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0])
    assert seq.T_BS[0, 1] == pytest.approx(-0.999880929698) and seq.T_BS[2, 3] == pytest.approx(0.00981073058949)

    gt_ns, gt_T = _euroc_gt(euroc_sample / "groundtruth_left_cam.csv")
    exact = {int(t): k for k, t in enumerate(gt_ns)}
    n_pose = 0
    for f in seq:
        assert f.image.shape == (480, 752) and f.image.dtype == np.uint8
        k = exact.get(int(ns[f.index]))
        if k is None:
            assert f.T_wc is None
            assert np.min(np.abs(gt_ns - ns[f.index])) > 20_000_000
        else:
            n_pose += 1
            np.testing.assert_allclose(f.T_wc, gt_T[k], atol=1e-9)
    assert n_pose == 74
    raw = cv2.imread(str(cam_dir / "data" / f"{ns[40]}.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(seq[40].image, raw)


def test_euroc_accepts_root_mav0_or_camera_folder(euroc_layout):
    a = EurocSequence(euroc_layout)
    for p in (euroc_layout / "mav0", euroc_layout / "mav0" / "cam0"):
        b = open_sequence(None, p)
        assert isinstance(b, EurocSequence) and b.camera == a.camera
        np.testing.assert_array_equal(b.has_pose, a.has_pose)


def _euroc_copy(tmp_path, src):
    cam = tmp_path / "seq" / "mav0" / "cam0"
    cam.mkdir(parents=True)
    (cam / "data").symlink_to(src / "mav0" / "cam0" / "data")
    for f in ("data.csv", "sensor.yaml"):
        shutil.copy(src / "mav0" / "cam0" / f, cam / f)
    return tmp_path / "seq", cam


def test_euroc_body_frame_ground_truth_uses_T_BS(tmp_path, euroc_layout):
    root, cam = _euroc_copy(tmp_path, euroc_layout)
    ref = EurocSequence(euroc_layout)
    gt_ns, T_wc = _euroc_gt(euroc_layout / "groundtruth_left_cam.csv")
    T_wb = T_wc @ inv_T(ref.T_BS)
    q = Rotation.from_matrix(T_wb[:, :3, :3]).as_quat()  # x y z w
    state = cam.parent / "state_groundtruth_estimate0"
    state.mkdir()
    with (state / "data.csv").open("w") as fh:
        fh.write("#timestamp, p_RS_R_x [m], ..., b_a_RS_S_z [m s^-2]\n")
        for t, T, qi in zip(gt_ns, T_wb, q):
            vals = [*T[:3, 3], qi[3], *qi[:3]] + [0.0] * 9  # velocities and biases: ignored
            fh.write(f"{t}," + ",".join(f"{v:.15g}" for v in vals) + "\n")
    seq = EurocSequence(root)
    np.testing.assert_array_equal(seq.has_pose, ref.has_pose)
    for i in np.flatnonzero(ref.has_pose)[::10]:
        np.testing.assert_allclose(seq.pose(i), ref.pose(i), atol=1e-9)


def test_euroc_opencv_matrix_tags_and_bad_sensor_yaml(tmp_path, euroc_layout):
    root, cam = _euroc_copy(tmp_path, euroc_layout)
    text = (cam / "sensor.yaml").read_text()
    (cam / "sensor.yaml").write_text(text.replace("T_BS:\n", "T_BS: !!opencv-matrix\n"))
    seq = EurocSequence(root)
    assert seq.T_BS[1, 0] == pytest.approx(0.999557249008)
    (cam / "sensor.yaml").write_text(text.replace("radial-tangential", "equidistant"))
    with pytest.raises(DatasetError, match=r"sensor\.yaml \[distortion_model\]: unsupported"):
        EurocSequence(root)
    (cam / "sensor.yaml").write_text(text.replace("intrinsics: [458.654,", "intrinsics: [-458.654,"))
    with pytest.raises(DatasetError, match=r"sensor\.yaml \[intrinsics\]: value must be positive"):
        EurocSequence(root)
    (cam / "sensor.yaml").write_text(text.replace("resolution: [752, 480]", "resolution: [752]"))
    with pytest.raises(DatasetError, match=r"sensor\.yaml \[resolution\]"):
        EurocSequence(root)


def test_euroc_malformed_csv_lines(tmp_path, euroc_layout):
    root, cam = _euroc_copy(tmp_path, euroc_layout)
    lines = (cam / "data.csv").read_text().splitlines()
    (cam / "data.csv").write_text("\n".join(lines[:5] + ["14037152732x,a.png"] + lines[5:]) + "\n")
    with pytest.raises(DatasetError, match=r"data\.csv:6: not a nanosecond timestamp"):
        EurocSequence(root)
    (cam / "data.csv").write_text("#timestamp [ns],filename\n")
    with pytest.raises(DatasetError, match=r"data\.csv: no images listed"):
        EurocSequence(root)
    shutil.copy(euroc_layout / "mav0" / "cam0" / "data.csv", cam / "data.csv")
    gt_lines = "#h\n1403715274312143104,1,2,3,1,0,0,0\n1403715274362142976,1,2,x,1,0,0,0\n"
    (root / "groundtruth_left_cam.csv").write_text(gt_lines)
    with pytest.raises(DatasetError, match=r"groundtruth_left_cam\.csv:3: not a number"):
        EurocSequence(root)
    with pytest.raises(DatasetError, match=r"not an EuRoC sequence"):
        EurocSequence(tmp_path)


# --- KITTI, image folder and video (written here) --------------------------------------


def _write_kitti(tmp_path, rng, n=4, seq="05"):
    folder = tmp_path / "dataset" / "sequences" / seq
    (folder / "image_0").mkdir(parents=True)
    imgs = _images(rng, n, (60, 80))
    for i, im in enumerate(imgs):
        cv2.imwrite(str(folder / "image_0" / f"{i:06d}.png"), im)
    stamps = np.arange(n) * 0.1036 + 0.0001
    (folder / "times.txt").write_text("".join(f"{t:.6e}\n" for t in stamps))
    P0 = [101.5, 0, 40.5, 0, 0, 102.5, 29.5, 0, 0, 0, 1, 0]
    P1 = [101.5, 0, 40.5, -38.0, 0, 102.5, 29.5, 0, 0, 0, 1, 0]
    (folder / "calib.txt").write_text(
        "".join(f"{k}: " + " ".join(f"{v:.12e}" for v in P) + "\n" for k, P in (("P0", P0), ("P1", P1)))
    )
    poses = np.stack([_rand_T(rng) for _ in range(n)])
    (tmp_path / "dataset" / "poses").mkdir()
    (tmp_path / "dataset" / "poses" / f"{seq}.txt").write_text(
        "".join(" ".join(f"{v:.12e}" for v in T[:3].ravel()) + "\n" for T in poses)
    )
    return folder, imgs, stamps, poses


def test_kitti_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    folder, imgs, stamps, poses = _write_kitti(tmp_path, rng)
    seq = open_sequence(None, folder)
    assert isinstance(seq, KittiSequence) and len(seq) == 4
    cam = seq.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (101.5, 102.5, 40.5, 29.5, 80, 60)
    assert cam.fps == pytest.approx(1 / 0.1036)
    np.testing.assert_allclose(seq.timestamps, stamps, atol=1e-9)
    for f, im, T in zip(seq, imgs, poses):
        np.testing.assert_array_equal(f.image, im)
        np.testing.assert_allclose(f.T_wc, T, atol=1e-11)
    np.testing.assert_allclose(seq.ground_truth.poses, poses, atol=1e-11)
    assert KittiSequence(folder, poses=tmp_path / "dataset" / "poses" / "05.txt").pose(2) is not None


@pytest.mark.parametrize(
    "target, edit, match",
    [
        ("calib.txt", lambda s: s.split("\n", 1)[1], r"calib\.txt \[P0\]: missing"),
        ("calib.txt", lambda s: s.replace("P1:", "P1"), r"calib\.txt:2: expected 'KEY: 12 numbers'"),
        ("times.txt", lambda s: s.replace("2.073", "2.0x3", 1), r"times\.txt:3: not a number"),
        ("times.txt", lambda s: "", r"times\.txt: no timestamps listed"),
        ("times.txt", lambda s: s + "9.9\n", r"image_0: holds 4 PNG images but .*times\.txt lists 5"),
        ("poses", lambda s: s.replace("\n", " 1.0\n", 2).replace(" 1.0\n", "\n", 1), r"05\.txt:2: expected 12 values"),
        ("poses", lambda s: s.split("\n", 1)[1], r"05\.txt: holds 3 poses but .* lists 4"),
    ],
)
def test_kitti_malformed_files(tmp_path, target, edit, match):
    folder, *_ = _write_kitti(tmp_path, np.random.default_rng(4))
    path = tmp_path / "dataset" / "poses" / "05.txt" if target == "poses" else folder / target
    path.write_text(edit(path.read_text()))
    with pytest.raises(DatasetError, match=match):
        KittiSequence(folder)


def test_kitti_corrupt_image(tmp_path):
    folder, *_ = _write_kitti(tmp_path, np.random.default_rng(5))
    (folder / "image_0" / "000002.png").write_bytes(b"not a png")
    seq = KittiSequence(folder)
    seq[1]
    with pytest.raises(DatasetError, match=r"000002\.png: cannot read image"):
        seq[2]


def test_folder_round_trip_natural_order(tmp_path):
    rng = np.random.default_rng(6)
    imgs = _images(rng, 4)
    for name, im in zip(["img1.png", "img2.bmp", "img10.png", "IMG11.tif"], imgs):
        cv2.imwrite(str(tmp_path / name), im)
    (tmp_path / "notes.txt").write_text("not an image")
    with pytest.raises(OrbslamError, match="--config"):
        open_sequence("folder", tmp_path)
    seq = open_sequence(None, tmp_path, SMALL, fps=5.0)
    assert [p.name for p in seq.paths] == ["img1.png", "img2.bmp", "img10.png", "IMG11.tif"]
    np.testing.assert_allclose(seq.timestamps, [0.0, 0.2, 0.4, 0.6])
    for f, im in zip(seq, imgs):
        np.testing.assert_array_equal(f.image, im)
        assert f.T_wc is None
    c = open_sequence("folder", tmp_path, SMALL, color=True)[0].image
    assert c.shape == (60, 80, 3) and np.array_equal(c[..., 1], imgs[0])


def test_folder_errors(tmp_path):
    with pytest.raises(DatasetError, match=r"gone: image folder not found"):
        open_sequence("folder", tmp_path / "gone", SMALL)
    (tmp_path / "e").mkdir()
    with pytest.raises(DatasetError, match=r"e: no images found"):
        open_sequence("folder", tmp_path / "e", SMALL)
    (tmp_path / "e" / "a.jpg").write_bytes(b"\xff\xd8\xff truncated")
    with pytest.raises(DatasetError, match=r"a\.jpg: cannot read image"):
        open_sequence("folder", tmp_path / "e", SMALL)[0]


def test_video_round_trip(tmp_path):
    yy, xx = np.mgrid[0:60, 0:80]
    frames = [((xx * (2 + i) + yy * (7 - i)) % 256).astype(np.uint8) for i in range(6)]
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 12.0, (80, 60), True)
    assert w.isOpened()
    for fr in frames:
        w.write(cv2.cvtColor(fr, cv2.COLOR_GRAY2BGR))
    w.release()
    with pytest.raises(OrbslamError, match="--config"):
        open_sequence("video", path)
    seq = open_sequence(None, path, SMALL)
    assert len(seq) == 6 and seq.fps == 12.0
    got = list(seq)
    np.testing.assert_allclose([f.timestamp for f in got], np.arange(6) / 12.0)
    for i, f in enumerate(got):
        assert f.image.shape == (60, 80) and f.image.dtype == np.uint8
        err = [np.abs(f.image.astype(float) - fr).mean() for fr in frames]
        assert int(np.argmin(err)) == i and err[i] < 4.0  # MJPG is lossy: nearest is its own frame
    np.testing.assert_array_equal(seq[3].image, got[3].image)
    assert open_sequence("video", path, SMALL, fps=30.0)[2].timestamp == pytest.approx(2 / 30)


def _panning_video(path, fourcc: str, n: int = 90) -> list[np.ndarray]:
    """Write ``n`` frames (80x60 grey) of a window panning over a noise texture, with a
    little jitter, as an inter-coded clip (mp4v, XVID) or an intra-only one (MJPG); returns
    the frames written."""
    rng = np.random.default_rng(0)
    big = cv2.GaussianBlur(rng.integers(0, 256, (200, 400), dtype=np.uint8), (0, 0), 1.5)
    frames = [big[50 + i % 7:110 + i % 7, 3 * i:3 * i + 80].copy() for i in range(n)]
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30.0, (80, 60), True)
    assert w.isOpened()
    for fr in frames:
        w.write(cv2.cvtColor(fr, cv2.COLOR_GRAY2BGR))
    w.release()
    return frames


def _decoded(path) -> list[np.ndarray]:
    """Every frame of a video decoded in order by a fresh decoder, grey."""
    cap, out = cv2.VideoCapture(str(path)), []
    while True:
        ok, fr = cap.read()
        if not ok:
            return out
        out.append(cv2.cvtColor(fr, cv2.COLOR_BGR2GRAY))


@pytest.mark.parametrize("fourcc, suffix", [("mp4v", ".mp4"), ("XVID", ".avi")])
def test_video_is_read_in_order_and_seeks_only_out_of_order(tmp_path, fourcc, suffix):
    path = tmp_path / f"clip{suffix}"
    written = _panning_video(path, fourcc)
    ref = _decoded(path)
    seq = open_sequence("video", path, SMALL)
    assert len(seq) == len(ref) == len(written)
    # Frame by frame, as a run takes them: no seek, the frames a decoder gives in order.
    for i in range(len(seq)):
        np.testing.assert_array_equal(seq[i].image, ref[i])
    assert seq.seeks == 0
    for i, fr in enumerate(ref):  # lossy, but each is nearest its own written frame
        err = [np.abs(fr.astype(float) - w).mean() for w in written[max(0, i - 2):i + 3]]
        assert int(np.argmin(err)) == min(i, 2) and err[min(i, 2)] < 6.0
    # A few frames ahead: decoded through, still no seek; out of order: one seek each.
    seq.close()
    np.testing.assert_array_equal(seq[5].image, ref[5])
    np.testing.assert_array_equal(seq[20].image, ref[20])
    assert seq.seeks == 0
    for i in (70, 12, 13, 40, 3):
        np.testing.assert_array_equal(seq[i].image, ref[i])
    assert seq.seeks == 3  # 70, 12 and 3; 13 follows 12, and 40 is decoded on to from 14
    np.testing.assert_array_equal(np.stack([f.image for f in seq]), np.stack(ref))


def test_video_frame_count_comes_from_the_stream_end(tmp_path):
    path = tmp_path / "clip.avi"
    _panning_video(path, "XVID")
    data = path.read_bytes()
    path.write_bytes(data[: int(0.8 * len(data))])  # the header still announces 90 frames
    ref = _decoded(path)
    assert 0 < len(ref) < 90
    seq = open_sequence("video", path, SMALL)
    assert len(seq) == 90
    got = [f.image for f in seq]
    assert len(got) == len(seq) == len(ref) and len(seq.timestamps) == len(ref)
    np.testing.assert_array_equal(np.stack(got), np.stack(ref))
    with pytest.raises(IndexError):
        seq[len(ref)]


def test_video_errors(tmp_path):
    with pytest.raises(DatasetError, match=r"none\.avi: video file not found"):
        open_sequence("video", tmp_path / "none.avi", SMALL)
    (tmp_path / "bad.avi").write_bytes(os.urandom(256))
    with pytest.raises(DatasetError, match=r"bad\.avi: cannot open video"):
        open_sequence("video", tmp_path / "bad.avi", SMALL)


def test_factory_detection_and_errors(tmp_path, tum_layout, euroc_layout):
    assert detect_kind(tum_layout) == "tum"
    assert detect_kind(euroc_layout) == "euroc"
    with pytest.raises(DatasetError, match=r"nothing: no such file or folder"):
        detect_kind(tmp_path / "nothing")
    with pytest.raises(DatasetError, match=r"cannot tell the dataset kind"):
        detect_kind(tmp_path)
    # The root of a KITTI odometry download names its sequences and the folder to run.
    for name in ("04", "00"):
        (tmp_path / "sequences" / name).mkdir(parents=True)
        (tmp_path / "sequences" / name / "times.txt").write_text("0.0\n")
    with pytest.raises(DatasetError, match=r"a KITTI odometry folder holding sequences 00, 04; run one of them, "
                       r"e\.g\. .*sequences/00$"):
        detect_kind(tmp_path)
    with pytest.raises(DatasetError, match=r"unknown dataset kind 'bag'"):
        open_sequence("bag", tmp_path)


def test_kitti_reads_jpeg_images_and_refuses_mixed_or_missing_ones(tmp_path):
    folder, imgs, stamps, _ = _write_kitti(tmp_path, np.random.default_rng(6))
    img_dir = folder / "image_0"
    for i, im in enumerate(imgs):
        (img_dir / f"{i:06d}.png").unlink()
        cv2.imwrite(str(img_dir / f"{i:06d}.jpg"), im, [cv2.IMWRITE_JPEG_QUALITY, 95])
    seq = open_sequence(None, folder)
    assert isinstance(seq, KittiSequence) and len(seq) == 4
    assert (seq.camera.width, seq.camera.height) == (80, 60)
    np.testing.assert_allclose(seq.timestamps, stamps, atol=1e-9)
    for f, p in zip(seq, sorted(img_dir.iterdir())):
        np.testing.assert_array_equal(f.image, cv2.imread(str(p), cv2.IMREAD_GRAYSCALE))
    cv2.imwrite(str(img_dir / "000004.png"), imgs[0])
    with pytest.raises(DatasetError, match=r"image_0: mixes image formats \(4 \.jpg, 1 \.png\)"):
        KittiSequence(folder)
    (img_dir / "000004.png").unlink()
    (img_dir / "000003.jpg").unlink()
    with pytest.raises(DatasetError, match=r"image_0: holds 3 JPEG images but .*times\.txt lists 4"):
        KittiSequence(folder)
    for p in img_dir.iterdir():
        p.unlink()
    with pytest.raises(DatasetError, match=r"image_0: holds no PNG or JPEG images .* lists 4"):
        KittiSequence(folder)
