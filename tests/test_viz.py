"""Rerun visualisation: a synthetic run saved to an .rrd and read back with rerun's own reader."""

from __future__ import annotations

import socket
import subprocess
from collections import defaultdict

import cv2
import numpy as np
import pytest

import rerun as rr
from rerun.chunk import RrdReader

from orbslam_hgcn.config import VizConfig
from orbslam_hgcn.errors import ConfigError, OrbslamError
from orbslam_hgcn.viz import records as ent
from orbslam_hgcn.viz.demo import demo_camera, fake_run, replay
from orbslam_hgcn.viz.records import FrameLog, MapSnapshot, state_code
from orbslam_hgcn.viz.rerun_logger import RerunLogger
from orbslam_hgcn.viz.shapes import colormap, edge_segments, frustum_strips
from orbslam_hgcn.cli import main
from orbslam_hgcn.viz.sinks import DEFAULT_GRPC_URL, grpc_url, parse_rerun_arg, viewer_executable

N_FRAMES, LOOP_AT, KF_EVERY = 30, 20, 5


def read_rrd(path) -> tuple[dict[str, list[dict]], dict[str, list[dict]]]:
    """(temporal, static) rows per entity path (no leading '/'), temporal rows sorted by frame."""
    temporal: dict[str, list[dict]] = defaultdict(list)
    static: dict[str, list[dict]] = defaultdict(list)
    for chunk in RrdReader(path).stream().to_chunks():
        rows = chunk.to_record_batch().to_pylist()
        (static if chunk.is_static else temporal)[chunk.entity_path.lstrip("/")].extend(rows)
    for rows in temporal.values():
        rows.sort(key=lambda r: r.get("frame", -1))
    return temporal, static


def rows_with(rows: list[dict], column: str) -> list[dict]:
    return [r for r in rows if r.get(column) is not None]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    path = tmp_path_factory.mktemp("viz") / "run.rrd"
    cfg = VizConfig(log_every_map=10, map_on_keyframe=True, map_min_interval=KF_EVERY)
    logger = RerunLogger(demo_camera(), "save", path, config=cfg)
    steps = replay(logger, fake_run(N_FRAMES, keyframe_every=KF_EVERY, loop_at=LOOP_AT))
    last_map = logger.last_map_frame
    logger.close()
    temporal, static = read_rrd(path)
    return dict(path=path, steps=steps, temporal=temporal, static=static, last_map=last_map)


def test_expected_entities_exist(run):
    t, s = run["temporal"], run["static"]
    for path in (ent.IMAGE, ent.KEYPOINTS_TRACKED, ent.KEYPOINTS_UNTRACKED, ent.CAMERA, ent.MAP_POINTS,
                 ent.KEYFRAMES, ent.KEYFRAME_PATH, ent.COVISIBILITY, ent.LOOP_EDGES, ent.TRAJECTORY,
                 ent.GROUND_TRUTH, ent.PLOT_TRACKING, ent.PLOT_FPS, ent.PLOT_STATE, ent.PLOT_KEYFRAMES,
                 ent.PLOT_ATE, ent.PLOT_LOOPS, ent.EVENTS):
        assert t.get(path), f"no data logged at {path}"
    assert rows_with(s[ent.IMAGE], "Pinhole:image_from_camera")
    assert len(RrdReader(run["path"]).blueprints()) == 1  # the default layout travels with it


def test_rerun_cli_verifies_recording(run):
    exe = viewer_executable()
    if exe is None:
        pytest.skip("rerun CLI binary not found")
    done = subprocess.run([exe, "rrd", "verify", str(run["path"])], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]


def test_pinhole_matches_camera(run):
    cam = demo_camera()
    (row,) = rows_with(run["static"][ent.IMAGE], "Pinhole:image_from_camera")
    K = np.array(row["Pinhole:image_from_camera"][0]).reshape(3, 3).T  # stored column-major
    np.testing.assert_allclose(K, cam.K, rtol=1e-6)
    assert row["Pinhole:resolution"][0] == [cam.width, cam.height]


def test_one_camera_pose_per_frame(run):
    rows = rows_with(run["temporal"][ent.CAMERA], "Transform3D:translation")
    assert [r["frame"] for r in rows] == list(range(N_FRAMES))
    for r, step in zip(rows, run["steps"]):
        T = step.frame.T_wc
        np.testing.assert_allclose(r["Transform3D:translation"][0], T[:3, 3], atol=1e-5)
        np.testing.assert_allclose(np.array(r["Transform3D:mat3x3"][0]).reshape(3, 3).T, T[:3, :3], atol=1e-6)


def test_keypoints_split_by_tracking(run):
    tracked = rows_with(run["temporal"][ent.KEYPOINTS_TRACKED], "Points2D:positions")
    untracked = rows_with(run["temporal"][ent.KEYPOINTS_UNTRACKED], "Points2D:positions")
    assert len(tracked) == len(untracked) == N_FRAMES
    for rt, ru, step in zip(tracked, untracked, run["steps"]):
        f = step.frame
        np.testing.assert_allclose(np.array(rt["Points2D:positions"]), f.keypoints_uv[f.tracked], atol=1e-3)
        assert len(ru["Points2D:positions"]) == int((~f.tracked).sum())


def test_image_round_trip(run):
    rows = rows_with(run["temporal"][ent.IMAGE], "EncodedImage:blob")
    assert [r["frame"] for r in rows] == list(range(N_FRAMES))
    blob = np.array(rows[7]["EncodedImage:blob"][0], dtype=np.uint8)
    decoded = cv2.imdecode(blob, cv2.IMREAD_UNCHANGED)
    original = run["steps"][7].frame.image
    # the logged bytes are exactly OpenCV's JPEG of this frame at the configured quality
    ok, expected = cv2.imencode(".jpg", original, [cv2.IMWRITE_JPEG_QUALITY, VizConfig().jpeg_quality])
    assert ok and blob.tobytes() == expected.tobytes()
    assert decoded.shape == original.shape
    assert np.corrcoef(decoded.ravel(), original.ravel())[0, 1] > 0.95


def test_map_points_at_last_map_log_match_snapshot(run):
    rows = rows_with(run["temporal"][ent.MAP_POINTS], "Points3D:positions")
    assert [r["frame"] for r in rows] == list(range(0, N_FRAMES, KF_EVERY))  # on every keyframe
    last = rows[-1]
    assert last["frame"] == run["last_map"]
    snap = run["steps"][last["frame"]].snapshot
    assert len(last["Points3D:positions"]) == len(snap.points_w)
    np.testing.assert_allclose(np.array(last["Points3D:positions"]), snap.points_w, atol=1e-5)


def test_loop_closure_replaces_map(run):
    rows = {r["frame"]: r for r in rows_with(run["temporal"][ent.MAP_POINTS], "Points3D:positions")}
    assert LOOP_AT in rows, "the map must be logged at the loop closure"
    before = np.array(rows[LOOP_AT - KF_EVERY]["Points3D:positions"])
    after = np.array(rows[LOOP_AT]["Points3D:positions"])
    corrected = run["steps"][LOOP_AT].snapshot.points_w
    np.testing.assert_allclose(after, corrected, atol=1e-5)
    n = len(before)
    assert np.linalg.norm(before - corrected[:n], axis=1).min() > 0.1  # drifted before, corrected after
    events = [r["TextLog:text"][0] for r in run["temporal"][ent.EVENTS] if r.get("TextLog:text")]
    kf_new = run["steps"][LOOP_AT].loop[0]
    assert f"loop closed: keyframe 0 <-> keyframe {kf_new}" in events or \
        f"loop closed: keyframe {kf_new} <-> keyframe 0" in events
    loops = rows_with(run["temporal"][ent.PLOT_LOOPS], "Scalars:scalars")
    assert [(r["frame"], r["Scalars:scalars"][0]) for r in loops] == [(LOOP_AT, 1.0)]


def test_frustums_and_edges_at_last_map_log(run):
    frame = run["last_map"]
    snap = run["steps"][frame].snapshot
    kf = rows_with(run["temporal"][ent.KEYFRAMES], "LineStrips3D:strips")[-1]
    assert kf["frame"] == frame
    strips = np.array(kf["LineStrips3D:strips"])
    assert strips.shape == (len(snap.keyframe_ids), 10, 3)
    np.testing.assert_allclose(strips[:, 5], snap.keyframe_centres, atol=1e-5)  # vertex 5: centre
    covis = rows_with(run["temporal"][ent.COVISIBILITY], "LineStrips3D:strips")[-1]
    assert len(covis["LineStrips3D:strips"]) == len(snap.covis_edges)
    loop = np.array(rows_with(run["temporal"][ent.LOOP_EDGES], "LineStrips3D:strips")[-1]["LineStrips3D:strips"])
    assert loop.shape == (1, 2, 3)
    a, b = run["steps"][LOOP_AT].loop
    ends = {tuple(np.round(p, 4)) for p in loop[0]}
    assert ends == {tuple(np.round(snap.keyframe_centres[k], 4)) for k in (a, b)}


def test_scalars_per_frame(run):
    t, steps = run["temporal"], run["steps"]
    tracking = rows_with(t[ent.PLOT_TRACKING], "Scalars:scalars")
    assert [r["Scalars:scalars"] for r in tracking] == [
        [float(s.frame.n_tracked), float(len(s.frame.keypoints_uv))] for s in steps
    ]
    state = rows_with(t[ent.PLOT_STATE], "Scalars:scalars")
    assert [r["Scalars:scalars"][0] for r in state] == [float(state_code(s.frame.state)) for s in steps]
    ate = rows_with(t[ent.PLOT_ATE], "Scalars:scalars")
    assert [r["frame"] for r in ate] == list(range(N_FRAMES)) and ate[0]["Scalars:scalars"][0] == 0.0
    assert len(rows_with(t[ent.PLOT_FPS], "Scalars:scalars")) == N_FRAMES


def test_map_due(tmp_path):
    cfg = VizConfig(log_every_map=3, map_on_keyframe=False)
    with RerunLogger(demo_camera(), "save", tmp_path / "a.rrd", config=cfg) as logger:
        assert logger.map_due(0)  # first map log
        logger.log_map(MapSnapshot.empty(), 0)
        assert [logger.map_due(i) for i in (1, 2, 3)] == [False, False, True]
        assert logger.map_due(1, keyframe_inserted=True) is False
        assert logger.map_due(1, loop_closed=True)
    cfg = VizConfig(log_every_map=10, map_on_keyframe=True, map_min_interval=2)
    with RerunLogger(demo_camera(), "save", tmp_path / "b.rrd", config=cfg) as logger:
        logger.log_map(MapSnapshot.empty(), 0)
        assert [logger.map_due(i, keyframe_inserted=True) for i in (1, 2)] == [False, True]
        assert [logger.map_due(i) for i in (2, 9, 10)] == [False, False, True]


def test_epoch_timestamps_and_trajectory_replacement(tmp_path):
    steps = list(fake_run(3, n_points=50, n_keypoints=20, loop_at=None))
    path = tmp_path / "t.rrd"
    with RerunLogger(demo_camera(), "save", path) as logger:
        for step in steps[:2]:
            f = step.frame
            logger.log_frame(FrameLog(f.index, 1341847980.5 + f.index / 30, f.image, f.keypoints_uv,
                                      f.tracked, f.T_wc, f.state, f.n_tracked, f.fps))
        corrected = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
        logger.log_trajectory(corrected, frame_index=1)
        f = steps[2].frame
        logger.log_frame(FrameLog(2, 1341847980.5 + 2 / 30, None, f.keypoints_uv, f.tracked, f.T_wc,
                                  "LOST", 0, f.fps))
        logger.log_map(steps[2].snapshot)
    temporal, _ = read_rrd(path)
    cams = rows_with(temporal[ent.CAMERA], "Transform3D:translation")
    assert [r["time"].timestamp() for r in cams] == pytest.approx([1341847980.5 + i / 30 for i in range(3)])
    traj = rows_with(temporal[ent.TRAJECTORY], "LineStrips3D:strips")
    assert [r["frame"] for r in traj] == [1, 2]  # the map log falls on the last frame
    np.testing.assert_allclose(traj[-1]["LineStrips3D:strips"][0], np.vstack([corrected, f.T_wc[:3, 3]]), atol=1e-6)
    events = [r["TextLog:text"][0] for r in temporal[ent.EVENTS]]
    assert events == ["tracking state: not_initialized", "tracking state: ok", "tracking state: lost"]


# --- sinks ---------------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _log_one_frame(logger: RerunLogger) -> None:
    step = next(fake_run(1, n_points=50, n_keypoints=20))
    logger.log_frame(step.frame)


def test_spawn_without_display_saves_instead(tmp_path, monkeypatch, caplog):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    fallback = tmp_path / "fallback.rrd"
    logger = RerunLogger(demo_camera(), "spawn", fallback_path=fallback, port=_free_port())
    assert (logger.mode, logger.target) == ("save", str(fallback))
    assert "no display" in caplog.text and str(fallback) in caplog.text
    _log_one_frame(logger)
    logger.close()
    temporal, _ = read_rrd(fallback)
    assert len(rows_with(temporal[ent.CAMERA], "Transform3D:translation")) == 1


def test_spawn_without_viewer_binary_saves_instead(tmp_path, monkeypatch):
    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setattr("orbslam_hgcn.viz.sinks.viewer_executable", lambda: None)
    logger = RerunLogger(demo_camera(), "spawn", fallback_path=tmp_path / "f.rrd", port=_free_port())
    assert logger.mode == "save"
    logger.close()
    assert (tmp_path / "f.rrd").is_file()


def test_connect_unreachable_saves_instead(tmp_path):
    logger = RerunLogger(demo_camera(), "connect", f"127.0.0.1:{_free_port()}", fallback_path=tmp_path / "c.rrd")
    assert (logger.mode, logger.target) == ("save", str(tmp_path / "c.rrd"))
    _log_one_frame(logger)
    logger.close()
    assert read_rrd(tmp_path / "c.rrd")[0][ent.CAMERA]


def test_connect_to_running_server(tmp_path):
    port = _free_port()
    server = rr.RecordingStream("viz_test_server")
    server.serve_grpc(grpc_port=port)
    try:
        logger = RerunLogger(demo_camera(), "connect", f"localhost:{port}", fallback_path=tmp_path / "x.rrd")
        assert (logger.mode, logger.target) == ("connect", f"rerun+http://localhost:{port}/proxy")
        _log_one_frame(logger)
        logger.close()
        assert not (tmp_path / "x.rrd").exists()
    finally:
        server.disconnect()


@pytest.mark.parametrize(
    "tokens, expected",
    [
        (["spawn"], ("spawn", None)),
        (["save", "out/run.rrd"], ("save", "out/run.rrd")),
        (["run.rrd"], ("save", "run.rrd")),
        (["connect"], ("connect", DEFAULT_GRPC_URL)),
        (["connect", "10.0.0.5:9000"], ("connect", "rerun+http://10.0.0.5:9000/proxy")),
        (["CONNECT", "rerun+http://host:9876/proxy"], ("connect", "rerun+http://host:9876/proxy")),
    ],
)
def test_parse_rerun_arg(tokens, expected):
    assert parse_rerun_arg(tokens) == expected


@pytest.mark.parametrize(
    "tokens, message",
    [
        ([], "missing mode"),
        (["show"], "unknown mode 'show'"),
        (["spawn", "now"], "takes no argument"),
        (["save"], "exactly one FILE.rrd"),
        (["save", "run.txt"], "must end in .rrd"),
        (["connect", "a:1", "b:2"], "takes one address"),
        (["connect", "host:99999"], "bad port"),
        (["connect", "ftp://host:1"], "unknown scheme"),
        (["connect", "rerun+http://host:1/other"], "path must be /proxy"),
    ],
)
def test_parse_rerun_arg_errors(tokens, message):
    with pytest.raises(OrbslamError, match=message):
        parse_rerun_arg(tokens)


def test_parse_rerun_arg_rejects_directory(tmp_path):
    d = tmp_path / "x.rrd"
    d.mkdir()
    with pytest.raises(ConfigError, match="is a directory"):
        parse_rerun_arg(["save", str(d)])


def test_grpc_url_forms():
    assert grpc_url("9000") == "rerun+http://127.0.0.1:9000/proxy"
    assert grpc_url("http://h:1") == "rerun+http://h:1/proxy"
    assert grpc_url("[::1]:9876") == "rerun+http://[::1]:9876/proxy"
    assert grpc_url("rerun+https://viewer.example.org/proxy") == "rerun+https://viewer.example.org:443/proxy"


def test_viz_demo_command(tmp_path, capsys):
    out = tmp_path / "demo.rrd"
    assert main(["viz-demo", "--rerun", "save", str(out), "--frames", "8"]) == 0
    assert f"rerun save: {out}" in capsys.readouterr().out
    assert len(rows_with(read_rrd(out)[0][ent.CAMERA], "Transform3D:translation")) == 8
    assert main(["viz-demo", "--rerun", "save", str(tmp_path / "demo.txt")]) == 2
    assert "must end in .rrd" in capsys.readouterr().err


# --- records, shapes, config ------------------------------------------------------------------
def test_frustum_geometry():
    cam = demo_camera()
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    strip = frustum_strips(T[None], cam, depth=0.5)[0]
    np.testing.assert_allclose(strip[5], [1, 2, 3])
    corners_c = strip[[0, 1, 2, 3]] - [1.0, 2.0, 3.0]
    np.testing.assert_allclose(corners_c[:, 2], 0.5, atol=1e-6)
    uv, _ = cam.project(corners_c)
    np.testing.assert_allclose(uv, [[0, 0], [cam.width, 0], [cam.width, cam.height], [0, cam.height]], atol=1e-3)
    # every one of the 8 frustum edges is drawn
    drawn = {frozenset(e) for e in zip([0, 1, 2, 3, 0, 4, 1, 2, 4], [1, 2, 3, 0, 4, 1, 2, 4, 3])}
    assert drawn == {frozenset(e) for e in [(0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (1, 4), (2, 4), (3, 4)]}


def test_edge_segments_drop_unknown_ids():
    ids = np.array([7, 3, 5])
    pos = np.array([[7.0, 0, 0], [3.0, 0, 0], [5.0, 0, 0]])
    seg = edge_segments(ids, pos, np.array([[3, 7], [5, 9], [7, 5]]))
    np.testing.assert_allclose(seg[:, :, 0], [[3, 7], [7, 5]])


def test_colormap_range():
    c = colormap(np.array([0.0, 2.0, 15.0, 99.0, np.nan]), 2.0, 15.0)
    assert (c[0] == c[1]).all() and (c[2] == c[3]).all() and not (c[1] == c[2]).all()
    assert c.dtype == np.uint8 and c.shape == (5, 3)


def test_records_validate_shapes():
    with pytest.raises(ValueError, match="tracked"):
        FrameLog(0, 0.0, None, np.zeros((3, 2)), np.zeros(2, bool), None, "OK", 0, 30.0)
    with pytest.raises(ValueError, match="T_wc"):
        FrameLog(0, 0.0, None, np.zeros((0, 2)), np.zeros(0, bool), np.eye(3), "OK", 0, 30.0)
    with pytest.raises(ValueError, match="keyframe_T_wc"):
        MapSnapshot(np.arange(2), np.zeros((3, 4, 4)), np.arange(1), np.zeros((1, 3)), np.ones(1))
    with pytest.raises(ValueError, match="points"):
        MapSnapshot(np.arange(1), np.zeros((1, 4, 4)), np.arange(2), np.zeros((1, 3)), np.ones(2))
    assert state_code("Recently Lost") == 3 and state_code("weird") == -1


def test_viz_config_rejects_bad_values():
    with pytest.raises(ConfigError, match="viz.point_colour"):
        VizConfig(point_colour="rainbow")
    with pytest.raises(ConfigError, match="viz.log_every_map"):
        VizConfig(log_every_map=0)
