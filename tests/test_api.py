"""The Python API (orbslam_hgcn.Slam) on real frames: the poses of `orbslam-hgcn run`, the map
as numpy, saved maps relocalised, typed errors; and live sources (a camera-like source in
process, an MJPEG stream over HTTP for the command)."""

from __future__ import annotations

import http.server
import json
import os
import signal
import socketserver
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from orbslam_hgcn import MapData, OrbslamError, Slam, Tracked
from orbslam_hgcn.app.run import run_dataset, run_live
from orbslam_hgcn.datasets import open_sequence
from orbslam_hgcn.datasets.live import LiveSource, capture_target, is_live
from orbslam_hgcn.errors import ConfigError, DatasetError
from orbslam_hgcn.evaluation.ate import evaluate
from orbslam_hgcn.trajectory import read_tum

ROOT = Path(__file__).resolve().parents[1]
SITTING = ROOT.parent / "shared" / "data" / "tum_fr3_sitting_xyz_148"


@pytest.fixture(scope="module")
def sitting():
    assert SITTING.is_dir(), f"{SITTING}: the shared TUM sitting_xyz frames are missing"
    return open_sequence(None, SITTING)


def test_api_gives_the_poses_of_run_sequential_bit_for_bit(sitting, tmp_path):
    # The example, fed the frames one by one, against the command on the folder.
    with Slam(camera="tum_fr3", vocab="kmeans", sequential=True) as slam:
        results = [slam.track(rec.image, rec.timestamp) for rec in sitting]
        slam.save(tmp_path / "api")
    report = run_dataset(SITTING, tmp_path / "run", sequential=True, progress=False)
    assert report.complete
    for name in ("KeyFrameTrajectory.txt", "CameraTrajectory.txt"):
        assert (tmp_path / "api" / name).read_bytes() == (tmp_path / "run" / name).read_bytes(), name
    assert all(isinstance(r, Tracked) for r in results)
    tracked = [r for r in results if r.ok]
    assert len(tracked) >= 0.9 * len(sitting)
    # Each result's pose is the frame's pose when it was tracked: near the ground truth after
    # the run's Sim(3) alignment (the final trajectory is refined, so not equal to it).
    est = read_tum(tmp_path / "api" / "CameraTrajectory.txt")
    ate = evaluate(sitting.ground_truth, est, align="sim3")
    assert ate.ate.rmse < 0.02
    assert sum(r.keyframe for r in results) + 2 >= json.loads((tmp_path / "api" / "stats.json").read_text())["keyframes"]


def test_api_threaded_map_arrays_save_and_localise(sitting, tmp_path):
    frames = [sitting[i] for i in range(0, 90)]
    with Slam(camera="tum_fr3") as slam:
        assert not slam.sequential and slam.configs.loop_closing.enabled  # the config's defaults
        for rec in frames:
            slam.track(rec.image, rec.timestamp)
        slam.close()
        m = slam.map()
        stats = slam.stats()
        kf_traj = slam.keyframe_trajectory()
        saved = slam.save_map(tmp_path / "room.npz")
    assert isinstance(m, MapData)
    assert m.points.shape == (stats["map_points"], 3) and len(m.point_ids) == stats["map_points"]
    assert m.keyframe_poses.shape == (stats["keyframes"], 4, 4) and stats["keyframes"] >= 5
    assert np.array_equal(m.keyframe_poses, kf_traj.poses)
    assert np.all(m.point_observations >= 1) and np.isfinite(m.points).all()
    assert np.array_equal(np.sort(m.keyframe_frames), m.keyframe_frames)
    # Localisation on the saved map: later frames, never seen, get poses; the map is unchanged.
    later = [sitting[i] for i in range(100, 130)]
    with Slam(camera="tum_fr3", load_map=saved, localization=True, sequential=True) as loc:
        got = [loc.track(rec.image, rec.timestamp, frame=rec.index) for rec in later]
        after = loc.map()
    assert sum(r.ok for r in got) >= 20
    assert after.keyframe_poses.shape == m.keyframe_poses.shape
    assert np.allclose(after.keyframe_poses, m.keyframe_poses)
    # Poses in the map's frame: against ground truth after one Sim(3) fit of the mapped frames.
    gt = sitting.ground_truth
    ok = [r for r in got if r.ok]
    from orbslam_hgcn.trajectory import Trajectory

    traj = Trajectory(np.array([r.timestamp for r in ok]), np.stack([r.pose for r in ok]))
    both = Trajectory(np.concatenate([kf_traj.timestamps, traj.timestamps]),
                      np.concatenate([kf_traj.poses, traj.poses]))
    assert evaluate(gt, both, align="sim3").ate.rmse < 0.03


def test_api_errors_are_typed(sitting, tmp_path):
    with pytest.raises(ConfigError, match="orbb"):
        Slam(camera="tum_fr3", config={"orbb": {"n_features": 1000}})
    with pytest.raises(ConfigError, match="n_featurs"):
        Slam(camera="tum_fr3", config={"orb": {"n_featurs": 1000}})
    with pytest.raises(ConfigError):
        Slam(camera="tum_fr3", config={"orb": {"n_features": "many"}})
    with pytest.raises(OrbslamError):
        Slam(camera="no_such_camera")
    with pytest.raises(ConfigError, match="no camera"):
        Slam()
    with pytest.raises(ConfigError, match="localization"):
        Slam(camera="tum_fr3", localization=True)
    with Slam(camera="tum_fr3", sequential=True, loop_closing=False) as slam:
        assert slam.configs.orb.n_features > 0 and not slam.configs.loop_closing.enabled
        with pytest.raises(ConfigError, match="640x480"):
            slam.track(np.zeros((100, 100), np.uint8), 0.0)
        with pytest.raises(ConfigError, match="uint8"):
            slam.track(np.zeros((480, 640), np.float32), 0.0)
        r = slam.track(cv2.cvtColor(sitting[0].image, cv2.COLOR_GRAY2BGR), 0.0)  # colour is taken
        assert r.state == "not initialised" and r.pose is None
    # A config mapping's values win over the shipped settings; a YAML file holds the camera.
    with Slam(camera="tum_fr3", config={"orb": {"n_features": 777}}, sequential=True) as slam:
        assert slam.configs.orb.n_features == 777
    cam_yaml = tmp_path / "cam.yaml"
    cam_yaml.write_text("fx: 535.4\nfy: 539.2\ncx: 320.1\ncy: 247.6\nwidth: 640\nheight: 480\norb:\n  n_features: 900\n")
    with Slam(config=cam_yaml, sequential=True) as slam:
        assert slam.camera.fx == 535.4 and slam.configs.orb.n_features == 900


class PlayedCamera:
    """A capture object that behaves like a camera: frames of a real sequence delivered in
    real time at ``speed`` times their recorded timing (read() blocks until the next one is
    due), then the end."""

    def __init__(self, images: list[np.ndarray], speed: float, stamps: np.ndarray | None = None) -> None:
        self.images, self.i, self.t0 = images, 0, None
        stamps = np.arange(len(images)) / 5.0 if stamps is None else np.asarray(stamps, dtype=float)
        self.due = (stamps - stamps[0]) / speed if len(images) else stamps

    def isOpened(self) -> bool:  # noqa: N802 - cv2.VideoCapture's name
        return True

    def read(self):
        if self.t0 is None:
            self.t0 = time.perf_counter()
        if self.i >= len(self.images):
            return False, None
        time.sleep(max(0.0, self.t0 + self.due[self.i] - time.perf_counter()))
        img = self.images[self.i]
        self.i += 1
        return True, cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)

    def release(self) -> None:
        pass


def test_live_source_names_and_a_device_that_does_not_open():
    assert is_live("cam:0") and is_live("rtsp://host/stream") and is_live("http://x/y.mjpg")
    assert not is_live("../data/tum") and not is_live("video.mp4")
    assert capture_target("cam:2") == 2 and capture_target("rtsp://h/s") == "rtsp://h/s"
    with pytest.raises(DatasetError, match="cam:N"):
        capture_target("cam:first")

    class Closed(PlayedCamera):
        def isOpened(self):  # noqa: N802
            return False

    from orbslam_hgcn.geometry.camera import PinholeCamera

    cam = PinholeCamera(500, 500, 320, 240, 640, 480)
    with pytest.raises(DatasetError, match="cannot open the camera device 0"):
        LiveSource("cam:0", cam, open_capture=lambda target: Closed([], 1.0))


def test_live_run_at_the_camera_rate_drops_late_frames_and_writes_results(sitting, tmp_path):
    images = [sitting[i].image for i in range(0, 120)]
    stamps = np.asarray(sitting.timestamps[:120])
    # At twice the recorded pace (about 10 Hz), one frame queued.
    report = run_live("cam:0", tmp_path / "live", config="tum_fr3", progress=False,
                      open_capture=lambda target: PlayedCamera(images, 2.0, stamps))
    assert report.complete
    s = report.stats
    assert s["dataset"]["kind"] == "live" and s["dataset"]["grabbed"] == 120
    assert s["dataset"]["frames"] + s["dataset"]["dropped"] == 120
    assert s["frames"]["tracked"] >= 0.8 * s["dataset"]["frames"]
    cam = read_tum(tmp_path / "live" / "CameraTrajectory.txt")
    assert len(cam) == s["frames"]["tracked"] and s["keyframes"] >= 5
    # A camera far faster than the system: frames are dropped rather than queued, and what is
    # tracked keeps up with the camera.
    fast = run_live("cam:0", tmp_path / "fast", config="tum_fr3", progress=False, loop_closing=False,
                    open_capture=lambda target: PlayedCamera(images, 40.0, stamps))
    assert fast.stats["dataset"]["dropped"] > 0
    assert fast.stats["dataset"]["frames"] + fast.stats["dataset"]["dropped"] == 120
    # --keep-late: every frame delivered is processed.
    kept = run_live("cam:0", tmp_path / "kept", config="tum_fr3", progress=False, drop_late=False, max_frames=30,
                    open_capture=lambda target: PlayedCamera(images, 40.0, stamps))
    assert kept.stats["dataset"]["frames"] == 30 and kept.stats["frames"]["frames"] == 30


def test_live_source_without_calibration_or_with_another_size(tmp_path, sitting):
    with pytest.raises(OrbslamError, match="no calibration"):
        run_live("cam:0", tmp_path / "a", progress=False, open_capture=lambda t: PlayedCamera([], 1.0))
    small = [cv2.resize(sitting[i].image, (320, 240)) for i in range(3)]
    with pytest.raises(OrbslamError, match="320x240"):
        run_live("cam:0", tmp_path / "b", config="tum_fr3", progress=False,
                 open_capture=lambda t: PlayedCamera(small, 1.0))


class _MjpegServer:
    """An MJPEG stream over HTTP (as IP cameras serve) of real frames, at ``speed`` times
    their recorded pace (``stamps``), looped ``loops`` times."""

    def __init__(self, images: list[np.ndarray], stamps, speed: float = 2.0, loops: int = 1) -> None:
        jpgs = [cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes() for img in images]
        gaps = np.diff(np.asarray(stamps, dtype=float), append=stamps[-1] + 0.2) / speed

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                try:
                    for _ in range(loops):
                        for j, gap in zip(jpgs, gaps):
                            self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                                             % len(j) + j + b"\r\n")
                            time.sleep(gap)
                except (BrokenPipeError, ConnectionResetError):
                    pass

            def log_message(self, *a):
                pass

        self.server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        threading.Thread(target=self.server.serve_forever, daemon=True).start()
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/stream.mjpg"

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def _cli(args, **kw):
    return subprocess.Popen([sys.executable, "-m", "orbslam_hgcn", *args], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def test_run_on_a_stream_until_it_ends_and_until_ctrl_c(sitting, tmp_path):
    images = [sitting[i].image for i in range(0, 60)]
    stamps = sitting.timestamps[:60]
    server = _MjpegServer(images, stamps)
    try:
        p = _cli(["run", server.url, "--config", "tum_fr3", "--out", str(tmp_path / "ended"), "--no-progress"])
        out, err = p.communicate(timeout=240)
        assert p.returncode == 0, err[-2000:]
        stats = json.loads((tmp_path / "ended" / "stats.json").read_text())
        assert stats["complete"] and stats["dataset"]["kind"] == "live" and stats["dataset"]["grabbed"] == 60
        assert stats["frames"]["tracked"] >= 30
    finally:
        server.close()
    # A stream that goes on: Ctrl-C ends the run, whose results are written.
    server = _MjpegServer(images, stamps, loops=100)
    try:
        p = _cli(["run", server.url, "--config", "tum_fr3", "--out", str(tmp_path / "stopped"), "--no-progress"])
        deadline = time.time() + 120
        series = tmp_path / "stopped"
        time.sleep(12.0)  # start-up and about 80 frames
        assert p.poll() is None and time.time() < deadline
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
        assert p.returncode == 130, err[-2000:]
        stats = json.loads((series / "stats.json").read_text())
        assert not stats["complete"] and stats["end"]["kind"] == "interrupted"
        assert stats["frames"]["tracked"] >= 20
        assert len(read_tum(series / "CameraTrajectory.txt")) == stats["frames"]["tracked"]
        assert "Traceback" not in err
    finally:
        server.close()


def test_run_says_when_a_device_cannot_be_opened(tmp_path):
    p = _cli(["run", "cam:57", "--config", "tum_fr3", "--out", str(tmp_path / "x")],
             env={**os.environ, "OPENCV_LOG_LEVEL": "ERROR", "OPENCV_VIDEOIO_DEBUG": "0"})
    out, err = p.communicate(timeout=120)
    assert p.returncode == 2
    lines = [ln for ln in err.splitlines() if ln.startswith("orbslam-hgcn run: error:")]
    assert len(lines) == 1 and "cannot open the camera device 57" in lines[0], err
    assert "Traceback" not in err


def test_run_export_ply_coloured_from_the_images(tmp_path):
    from plyfile import PlyData

    out = tmp_path / "run"
    report = run_dataset(SITTING, out, sequential=True, progress=False, max_frames=40, export_ply=out / "map.ply",
                         loop_closing=False)
    pts = PlyData.read(str(report.paths["ply_points"]))["vertex"]
    kfs = PlyData.read(str(report.paths["ply_keyframes"]))["vertex"]
    assert pts.count == report.stats["map_points"] and kfs.count == report.stats["keyframes"]
    # Colours come from the frames (these are stored grey): every point grey, of many shades;
    # the observation ramp, used without images, has no grey colour.
    rgb = np.stack([pts["red"], pts["green"], pts["blue"]], axis=1).astype(int)
    assert (np.ptp(rgb, axis=1) == 0).all() and rgb[:, 0].std() > 20
    kf = read_tum(out / "KeyFrameTrajectory.txt")
    centres = np.stack([kfs["x"], kfs["y"], kfs["z"]], axis=1)
    assert np.allclose(np.sort(centres, axis=0), np.sort(kf.poses[:, :3, 3], axis=0), atol=1e-5)
    # The output is checked before the first frame.
    with pytest.raises(OrbslamError, match=".ply"):
        run_dataset(SITTING, tmp_path / "x", export_ply=tmp_path / "map.txt", progress=False)


def _example(name, *args, timeout=300):
    return subprocess.run([sys.executable, str(ROOT / "examples" / name), *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def test_the_examples_run_on_real_frames(sitting, tmp_path):
    # TUM's images are named by their timestamps, which the example keeps: the run of `run`.
    r = _example("folder_of_images.py", SITTING / "rgb", "--camera", "tum_fr3", "--out", tmp_path / "f")
    assert r.returncode == 0, r.stderr[-2000:]
    from plyfile import PlyData

    stats = json.loads((tmp_path / "f" / "stats.json").read_text())
    assert stats["frames"]["tracked"] >= 140
    assert PlyData.read(str(tmp_path / "f" / "map.ply"))["vertex"].count == stats["map_points"]
    r = _example("relocalise_saved_map.py", SITTING, "--out", tmp_path / "r")
    assert r.returncode == 0, r.stderr[-2000:]
    line = [ln for ln in r.stdout.splitlines() if ln.startswith("localised")][0]
    located, total = (int(w) for w in line.split()[1:4:2])
    assert total == len(sitting) - len(sitting) // 2 and located >= 0.9 * total
    server = _MjpegServer([sitting[i].image for i in range(40)], sitting.timestamps[:40])
    try:
        r = _example("webcam.py", server.url, "--camera", "tum_fr3", "--out", tmp_path / "w", "--max-frames", "30")
    finally:
        server.close()
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((tmp_path / "w" / "stats.json").read_text())["frames"]["frames"] == 30
    r = _example("folder_of_images.py", tmp_path, "--camera", "tum_fr3", "--out", tmp_path / "e")
    assert r.returncode == 2 and "no images" in r.stderr
