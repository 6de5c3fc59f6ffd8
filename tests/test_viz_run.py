"""Rerun visualisation of a real SLAM run: ``orbslam-hgcn run ... --rerun save FILE.rrd``,
read back with rerun's own reader and checked against the system that made it."""

from __future__ import annotations

import json
import socket
from collections import defaultdict
from types import SimpleNamespace

import numpy as np
import pytest

import rerun as rr
from rerun.chunk import RrdReader

from orbslam_hgcn import cli
from orbslam_hgcn.app import slam as slam_module
from orbslam_hgcn.runtime.system import System
from orbslam_hgcn.trajectory import read_tum
from orbslam_hgcn.viz import records as ent
from orbslam_hgcn.viz.live import LiveViz, gt_in_map, sim3_ate

N_FRAMES = 50


def read_rrd(path) -> dict[str, list[dict]]:
    """Temporal rows per entity path (no leading '/'), sorted by frame."""
    temporal: dict[str, list[dict]] = defaultdict(list)
    for chunk in RrdReader(path).stream().to_chunks():
        if not chunk.is_static:
            temporal[chunk.entity_path.lstrip("/")].extend(chunk.to_record_batch().to_pylist())
    for rows in temporal.values():
        rows.sort(key=lambda r: r.get("frame", -1))
    return temporal


def rows_with(rows: list[dict], column: str) -> list[dict]:
    return [r for r in rows if r.get(column) is not None]


class _Recorder:
    """Observer placed before the visualiser: what the tracker estimated at each frame."""

    def __init__(self) -> None:
        self.poses: dict[int, np.ndarray] = {}  # frame index -> T_wc as tracked
        self.keypoints: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, system, record, result) -> None:
        f = result.frame
        if f is not None:
            self.keypoints[record.index] = (f.keypoints.uv_raw.copy(), f.matched.copy())
        if f is not None and f.T_cw is not None and result.state.name == "OK":
            self.poses[record.index] = f.T_wc
        if result.initialized:
            kf1 = result.new_keyframes[0]
            self.poses[kf1.frame_id] = kf1.T_wc.copy()


@pytest.fixture(scope="module")
def slam_run(synth_replay_100, tmp_path_factory, monkeypatch_module):
    out = tmp_path_factory.mktemp("viz_run")
    rrd = out / "run.rrd"
    made: list[System] = []
    recorder = _Recorder()

    class RecordedSystem(System):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self.observers.append(recorder)
            made.append(self)

    monkeypatch_module.setattr(slam_module, "System", RecordedSystem)  # run builds its System through Slam
    # Sequential: the same run every time (in threaded mode how far the tracked poses are
    # from the refined ones in the trajectory file depends on when local BA lands).
    code = cli.main(["run", str(synth_replay_100), "--out", str(out), "--no-loop", "--vocab", "none",
                     "--max-frames", str(N_FRAMES), "--no-progress", "--rerun", "save", str(rrd), "--sequential"])
    assert code == 0
    (system,) = made
    return SimpleNamespace(out=out, rrd=rrd, system=system, recorder=recorder, temporal=read_rrd(rrd),
                           stats=json.loads((out / "stats.json").read_text()))


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


def test_entities_exist(slam_run):
    t = slam_run.temporal
    for path in (ent.IMAGE, ent.KEYPOINTS_TRACKED, ent.KEYPOINTS_UNTRACKED, ent.CAMERA, ent.MAP_POINTS,
                 ent.KEYFRAMES, ent.COVISIBILITY, ent.TRAJECTORY, ent.GROUND_TRUTH, ent.PLOT_TRACKING,
                 ent.PLOT_FPS, ent.PLOT_KEYFRAMES, ent.PLOT_MAP_POINTS, ent.PLOT_ATE, ent.PLOT_STATE):
        assert t.get(path), f"no data logged at {path}"
    assert len(RrdReader(slam_run.rrd).blueprints()) == 1
    frames = [r["frame"] for r in rows_with(t[ent.PLOT_TRACKING], "Scalars:scalars")]
    assert frames == list(range(N_FRAMES))  # every processed frame is on the frame timeline


def test_one_camera_pose_per_tracked_frame(slam_run):
    system, rec = slam_run.system, slam_run.recorder
    rows = rows_with(slam_run.temporal[ent.CAMERA], "Transform3D:translation")
    frames = [r["frame"] for r in rows]
    tracked = sorted(r.frame_id for r in system.tracker.records
                     if r.T_cr is not None and r.generation == system.tracker.generation)
    assert len(tracked) >= 10, "the run should track a good part of the frames"
    assert frames == tracked  # exactly one pose per tracked frame, none for the others
    assert sorted(rec.poses) == tracked
    for r in rows:
        T = rec.poses[r["frame"]]
        np.testing.assert_allclose(r["Transform3D:translation"][0], T[:3, 3], atol=1e-5)
        np.testing.assert_allclose(np.array(r["Transform3D:mat3x3"][0]).reshape(3, 3).T, T[:3, :3], atol=1e-5)


def test_poses_agree_with_camera_trajectory_file(slam_run):
    """The file holds the same frames; its poses come from the keyframes after local BA and
    one more optimisation against the final map, so they differ from the tracked ones by
    small adjustments only; the recording's final trajectory is the file's."""
    traj = read_tum(slam_run.out / "CameraTrajectory.txt")
    rows = rows_with(slam_run.temporal[ent.CAMERA], "Transform3D:translation")
    assert len(traj) == len(rows)
    logged = np.array([r["Transform3D:translation"][0] for r in rows])
    extent = np.linalg.norm(np.ptp(traj.poses[:, :3, 3], axis=0))
    assert extent > 0
    assert np.max(np.linalg.norm(logged - traj.poses[:, :3, 3], axis=1)) < 0.05 * extent
    final = rows_with(slam_run.temporal[ent.TRAJECTORY], "LineStrips3D:strips")[-1]
    np.testing.assert_allclose(np.array(final["LineStrips3D:strips"][0]), traj.poses[:, :3, 3], atol=1e-5)


def test_keypoints_split_by_tracking(slam_run):
    t, kps = slam_run.temporal, slam_run.recorder.keypoints
    tracked = {r["frame"]: r for r in rows_with(t[ent.KEYPOINTS_TRACKED], "Points2D:positions")}
    untracked = {r["frame"]: r for r in rows_with(t[ent.KEYPOINTS_UNTRACKED], "Points2D:positions")}
    n_tracked_frames = 0
    for i, (uv, matched) in kps.items():
        np.testing.assert_allclose(np.array(tracked[i]["Points2D:positions"]).reshape(-1, 2), uv[matched], atol=1e-3)
        assert len(untracked[i]["Points2D:positions"]) == int((~matched).sum())
        n_tracked_frames += bool(matched.any())
    assert n_tracked_frames >= 10


def test_final_map_matches_system(slam_run):
    system = slam_run.system
    rows = rows_with(slam_run.temporal[ent.MAP_POINTS], "Points3D:positions")
    final = rows[-1]
    assert final["frame"] == N_FRAMES - 1
    n = system.map.n_points()
    assert n > 100 and len(final["Points3D:positions"]) == n == slam_run.stats["map_points"]
    np.testing.assert_allclose(np.array(final["Points3D:positions"]),
                               system.map.positions(system.map.point_ids()), atol=1e-5)
    assert len(final["Points3D:colors"]) == n
    frusta = rows_with(slam_run.temporal[ent.KEYFRAMES], "LineStrips3D:strips")[-1]
    assert len(frusta["LineStrips3D:strips"]) == system.map.n_keyframes() == slam_run.stats["keyframes"]
    assert len(rows) < N_FRAMES / 3  # the map is logged at a reduced rate


def test_final_ate_matches_evaluation(slam_run):
    """The last ATE point is the run's camera ATE (evo's Sim(3) alignment) to 1e-6 relative."""
    ate = rows_with(slam_run.temporal[ent.PLOT_ATE], "Scalars:scalars")
    expected = slam_run.stats["ate_sim3"]["camera"]["rmse_m"]
    assert ate[-1]["frame"] == N_FRAMES - 1
    assert ate[-1]["Scalars:scalars"][0] == pytest.approx(expected, rel=1e-6)
    gt = rows_with(slam_run.temporal[ent.GROUND_TRUTH], "LineStrips3D:strips")[-1]
    assert len(gt["LineStrips3D:strips"][0]) == N_FRAMES  # every frame of the replay has ground truth


def test_sim3_ate_recovers_a_similarity():
    rng = np.random.default_rng(3)
    gt = rng.normal(size=(40, 3))
    angle = 0.7
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    est = (gt @ R) / 2.5 + [1.0, -2.0, 0.5]  # est = R^T gt / 2.5 + t: gt = 2.5 R (est - t)
    rmse, S = sim3_ate(est, gt)
    assert rmse < 1e-9
    np.testing.assert_allclose(np.cbrt(np.linalg.det(S[:3, :3])), 2.5, rtol=1e-9)
    np.testing.assert_allclose(gt_in_map(gt, S), est, atol=1e-9)
    assert sim3_ate(est[:2], gt[:2]) is None


def test_loop_event_marks_timeline_and_replaces_map(slam_run, tmp_path):
    """A loop reported by the loop closer: event, loop count, corrected map and trajectory."""
    system = slam_run.system
    kf_ids = system.map.keyframe_ids()
    closer = SimpleNamespace(loops=[])
    stub = SimpleNamespace(map=system.map, tracker=system.tracker, loop_closer=closer, camera=system.camera,
                           camera_trajectory=system.camera_trajectory)
    path = tmp_path / "loop.rrd"
    viz = LiveViz(system.camera, "save", path)
    image = np.zeros((system.camera.height, system.camera.width), np.uint8)
    result = SimpleNamespace(frame=None, state=system.tracker.state, new_keyframes=[], time_ms=5.0,
                             initialized=False)
    for i in range(3):
        if i == 2:
            closer.loops.append(SimpleNamespace(kf_id=int(kf_ids[-1]), loop_kf_id=int(kf_ids[0])))
        viz(stub, SimpleNamespace(index=i, timestamp=float(i), image=image, T_wc=None), result)
    viz.finish(stub)
    t = read_rrd(path)
    events = [r["TextLog:text"][0] for r in t[ent.EVENTS] if r.get("TextLog:text")]
    assert f"loop closed: keyframe {kf_ids[-1]} <-> keyframe {kf_ids[0]}" in events
    assert [(r["frame"], r["Scalars:scalars"][0]) for r in rows_with(t[ent.PLOT_LOOPS], "Scalars:scalars")] == [(2, 1.0)]
    assert 2 in [r["frame"] for r in rows_with(t[ent.MAP_POINTS], "Points3D:positions")]
    loop_edges = rows_with(t[ent.LOOP_EDGES], "LineStrips3D:strips")
    assert loop_edges and len(loop_edges[-1]["LineStrips3D:strips"]) == 1
    traj = rows_with(t[ent.TRAJECTORY], "LineStrips3D:strips")
    assert 2 in [r["frame"] for r in traj]
    assert len(traj[-1]["LineStrips3D:strips"][0]) == len(system.camera_trajectory())


# --- sinks through the run command ------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(dataset, out, *rerun: str) -> int:
    return cli.main(["run", str(dataset), "--out", str(out), "--no-loop", "--vocab", "none", "--max-frames", "3",
                     "--sequential", "--no-progress", "--rerun", *rerun])


def test_spawn_without_display_saves_into_output_folder(synth_replay_100, tmp_path, monkeypatch, caplog):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    assert _run(synth_replay_100, tmp_path, "spawn") == 0
    assert "no display" in caplog.text
    t = read_rrd(tmp_path / "rerun.rrd")
    assert [r["frame"] for r in rows_with(t[ent.PLOT_TRACKING], "Scalars:scalars")] == [0, 1, 2]


def test_connect_unreachable_saves_into_output_folder(synth_replay_100, tmp_path):
    assert _run(synth_replay_100, tmp_path, "connect", f"127.0.0.1:{_free_port()}") == 0
    assert (tmp_path / "rerun.rrd").is_file()


def test_connect_streams_to_running_server(synth_replay_100, tmp_path):
    port = _free_port()
    server = rr.RecordingStream("viz_run_test_server")
    server.serve_grpc(grpc_port=port)
    try:
        assert _run(synth_replay_100, tmp_path, "connect", f"localhost:{port}") == 0
        assert not (tmp_path / "rerun.rrd").exists()
    finally:
        server.disconnect()


def test_bad_rerun_argument_is_one_line_error(synth_replay_100, tmp_path, capsys):
    assert _run(synth_replay_100, tmp_path, "save", str(tmp_path / "x.txt")) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "must end in .rrd" in err
    assert not (tmp_path / "stats.json").exists()  # refused before the run started


def test_viz_section_of_run_config(tmp_path):
    from orbslam_hgcn.errors import ConfigError
    from orbslam_hgcn.viz.live import viz_config_from

    good = tmp_path / "good.yaml"
    good.write_text("viz:\n  log_every_map: 5\n  point_colour: height\n")
    cfg = viz_config_from(good)
    assert (cfg.log_every_map, cfg.point_colour) == (5, "height")
    bad = tmp_path / "bad.yaml"
    bad.write_text("viz:\n  point_colour: rainbow\n")
    with pytest.raises(ConfigError, match="point_colour"):
        viz_config_from(bad)
