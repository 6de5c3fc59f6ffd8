"""Faults injected into ``orbslam-hgcn run``: unreadable frames (truncated PNG, zero-byte
file, wrong size), a bundle-adjustment process killed, an extraction process that raises or
dies, a stage that raises, a bug, SIGTERM, and a bad ``--out``. Each run either goes on or
stops cleanly: the results of the frames processed are on disk, the exit status says how
it ended, one line names the cause, and no thread or child process is left behind."""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import signal
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from fault_fixtures import failing_extraction

from orbslam_hgcn.backend.solver import ProcessSolver
from orbslam_hgcn.cli import main
from orbslam_hgcn.config import save_camera
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.mapping import local_mapper
from orbslam_hgcn.mapping.local_mapper import LocalMapper
from orbslam_hgcn.runtime import system as system_module
from orbslam_hgcn.tracking.tracker import Tracker
from orbslam_hgcn.trajectory import read_tum

N_FRAMES = 60  # initialisation takes about 22 frames of the replay
BAD = {30: "truncated", 31: "empty", 32: "wrong size"}


def _nothing_left() -> None:
    assert [t.name for t in threading.enumerate() if t.name.startswith("orbslam-") and t.is_alive()] == []
    assert multiprocessing.active_children() == []


@pytest.fixture(scope="module")
def no_drops(tmp_path_factory) -> Path:
    """A config whose paced runs process every frame, however late (the default drops frames
    when the system falls behind its camera, as a loaded test machine may)."""
    path = tmp_path_factory.mktemp("config") / "no_drops.yaml"
    path.write_text("threads:\n  frame_buffer_s: 0\n")
    return path


@pytest.fixture(scope="module")
def ba_process(tmp_path_factory) -> Path:
    """no_drops, with local BA solved in its child process (threads.local_ba_process; by
    default the mapping thread solves it)."""
    path = tmp_path_factory.mktemp("config") / "ba_process.yaml"
    path.write_text("threads:\n  frame_buffer_s: 0\n  local_ba_process: true\n")
    return path


@pytest.fixture(scope="module")
def broken_seq(synth_replay_100, tmp_path_factory) -> Path:
    """The replay with frame 30 truncated, 31 an empty file and 32 of half the size."""
    seq = tmp_path_factory.mktemp("broken") / "seq"
    shutil.copytree(synth_replay_100, seq)
    files = sorted((seq / "rgb").glob("*.png"))
    data = files[30].read_bytes()
    files[30].write_bytes(data[: len(data) // 2])
    files[31].write_bytes(b"")
    img = cv2.imread(str(files[32]))
    cv2.imwrite(str(files[32]), cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2)))
    return seq


def _run(
    seq: Path, out: Path, capsys, config: Path, *extra: str, frames: int = N_FRAMES
) -> tuple[int, dict, list[str]]:
    """``orbslam-hgcn run`` in this process: (exit status, stats.json or {}, the lines on
    stderr that the command printed)."""
    code = main(["run", str(seq), "--dataset", "tum", "--out", str(out), "--vocab", "none", "--no-loop",
                 "--no-progress", "--max-frames", str(frames), "--config", str(config), *extra])  # fmt: skip
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("orbslam-hgcn")]
    stats_file = out / "stats.json"
    stats = json.loads(stats_file.read_text()) if stats_file.is_file() else {}
    _nothing_left()
    return code, stats, err


def _camera_stamps(out: Path) -> np.ndarray:
    return read_tum(out / "CameraTrajectory.txt").timestamps


@pytest.mark.parametrize("mode", [[], ["--sequential"]], ids=["threaded", "sequential"])
def test_unreadable_frames_are_skipped_and_counted(broken_seq, tmp_path, capsys, no_drops, mode):
    code, stats, err = _run(broken_seq, tmp_path / "out", capsys, no_drops, *mode)
    assert code == 0 and err == []
    assert stats["complete"] is True and stats["end"]["kind"] == "complete"
    f = stats["frames"]
    assert f["frames"] == N_FRAMES and f["unreadable"] == len(BAD)
    assert [b["frame"] for b in stats["bad_frames"]] == sorted(BAD)
    assert "empty image file" in stats["bad_frames"][1]["error"]
    assert "expects 640x480" in stats["bad_frames"][2]["error"]
    # Tracking went on past the skipped frames.
    assert f["tracked"] >= N_FRAMES - 22 - len(BAD) - 3
    stamps = _camera_stamps(tmp_path / "out")
    assert stamps.max() > float(stats["bad_frames"][-1]["t"])


def test_on_bad_frame_stop_keeps_the_frames_before(broken_seq, tmp_path, capsys, no_drops):
    out = tmp_path / "out"
    code, stats, err = _run(broken_seq, out, capsys, no_drops, "--on-bad-frame", "stop")
    assert code == 3
    assert len(err) == 1 and "frame 30" in err[0] and "cannot read image" in err[0]
    assert stats["complete"] is False
    assert stats["end"]["kind"] == "bad_frame" and stats["end"]["frame"] == 30 and stats["end"]["exit_status"] == 3
    assert stats["frames"]["frames"] == 31 and stats["frames"]["tracked"] > 0
    stamps = _camera_stamps(out)
    assert len(stamps) == stats["frames"]["tracked"] and stamps.max() < float(stats["bad_frames"][0]["t"])
    assert (out / "KeyFrameTrajectory.txt").stat().st_size > 0


def test_a_killed_local_ba_process_is_replaced_and_the_run_goes_on(
    synth_replay_100, tmp_path, capsys, ba_process, monkeypatch
):
    killed: list[int] = []
    local_ba = ProcessSolver.local_ba

    def kill_first(self, *args, **kw):
        if not killed:
            killed.append(self._child._proc.pid)
            self.kill()  # the child dies with the problem on its way: the request finds it dead
        return local_ba(self, *args, **kw)

    monkeypatch.setattr(ProcessSolver, "local_ba", kill_first)
    code, stats, err = _run(synth_replay_100, tmp_path / "out", capsys, ba_process, frames=100)
    assert killed and code == 0 and err == []
    assert stats["complete"] is True
    assert stats["child_processes_lost"]["local_ba"] == 1 == stats["mapping_counts"]["ba_process_lost"]
    assert stats["mapping_counts"]["ba_keyframes_free"] > 0  # later keyframes had their BA
    assert stats["frames"]["tracked"] > 60 and stats["frames"]["lost"] == 0


def test_a_local_ba_process_lost_too_often_stops_the_run_with_its_results(
    synth_replay_100, tmp_path, capsys, ba_process, monkeypatch
):
    local_ba = ProcessSolver.local_ba

    def kill(self, *args, **kw):
        self.kill()
        return local_ba(self, *args, **kw)

    monkeypatch.setattr(ProcessSolver, "local_ba", kill)
    monkeypatch.setattr(local_mapper, "MAX_LOST_SOLVERS", 0)
    out = tmp_path / "out"
    code, stats, err = _run(synth_replay_100, out, capsys, ba_process, frames=100)
    assert code == 4
    assert len(err) == 1 and "mapping worker failed" in err[0] and "local-ba process died" in err[0]
    assert stats["complete"] is False and stats["end"]["kind"] == "stage_failed"
    assert stats["end"]["stage"] == "mapping"
    assert 0 < stats["frames"]["frames"] < 100 and stats["frames"]["tracked"] > 0
    assert len(_camera_stamps(out)) == stats["frames"]["tracked"]


def test_an_extraction_process_that_raises_stops_the_run_with_its_results(
    synth_replay_100, tmp_path, capsys, no_drops, monkeypatch
):
    monkeypatch.setattr(system_module, "ExtractionProcess", failing_extraction(35, False, tmp_path / "once"))
    out = tmp_path / "out"
    code, stats, err = _run(synth_replay_100, out, capsys, no_drops)
    assert code == 4
    assert len(err) == 1 and "extraction process" in err[0] and "injected extraction failure" in err[0]
    assert "Traceback" not in err[0]
    assert stats["end"]["kind"] == "stage_failed" and stats["end"]["stage"] == "extraction process"
    assert 25 < stats["frames"]["frames"] < 40 and stats["frames"]["tracked"] > 0
    assert len(_camera_stamps(out)) == stats["frames"]["tracked"]


def test_a_dead_extraction_process_is_replaced_and_the_run_goes_on(
    synth_replay_100, tmp_path, capsys, no_drops, monkeypatch
):
    monkeypatch.setattr(system_module, "ExtractionProcess", failing_extraction(35, True, tmp_path / "once"))
    code, stats, err = _run(synth_replay_100, tmp_path / "out", capsys, no_drops)
    assert (tmp_path / "once").is_file()  # the process did die
    assert code == 0 and err == []
    assert stats["complete"] is True and stats["child_processes_lost"]["extraction"] == 1
    assert stats["frames"]["frames"] == N_FRAMES and stats["frames"]["lost"] == 0


def test_a_stage_error_stops_the_run_with_its_results(synth_replay_100, tmp_path, capsys, no_drops, monkeypatch):
    process = LocalMapper.process

    def broken(self, kf):
        if self.counts["keyframes"] >= 3:
            raise RuntimeError(f"mapping broke on keyframe {kf.id}")
        return process(self, kf)

    monkeypatch.setattr(LocalMapper, "process", broken)
    out = tmp_path / "out"
    code, stats, err = _run(synth_replay_100, out, capsys, no_drops)
    assert code == 4 and len(err) == 1 and "mapping broke on keyframe" in err[0]
    assert stats["end"]["stage"] == "mapping" and stats["frames"]["tracked"] > 0
    assert read_tum(out / "KeyFrameTrajectory.txt").timestamps.size >= 3


def test_a_bug_stops_the_run_with_its_results_and_traceback(synth_replay_100, tmp_path, capsys, no_drops, monkeypatch):
    track = Tracker.track

    def buggy(self, frame):
        if frame.id == 40:
            raise ValueError("a bug in tracking")
        return track(self, frame)

    monkeypatch.setattr(Tracker, "track", buggy)
    out = tmp_path / "out"
    code, stats, err = _run(synth_replay_100, out, capsys, no_drops, "--sequential")
    assert code == 1 and len(err) == 1 and "ValueError: a bug in tracking" in err[0]
    assert stats["end"]["kind"] == "internal_error" and stats["frames"]["frames"] == 40
    assert "a bug in tracking" in (out / "traceback.txt").read_text()
    assert len(_camera_stamps(out)) == stats["frames"]["tracked"] > 0


def test_sigterm_ends_the_run_with_its_results(synth_replay_100, tmp_path, capsys, no_drops, monkeypatch):
    process = LocalMapper.process

    def terminate(self, kf):
        if self.counts["keyframes"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return process(self, kf)

    monkeypatch.setattr(LocalMapper, "process", terminate)
    before = signal.getsignal(signal.SIGTERM)
    code, stats, err = _run(synth_replay_100, tmp_path / "out", capsys, no_drops, frames=100)
    assert signal.getsignal(signal.SIGTERM) == before
    assert code == 143 and len(err) == 1 and "SIGTERM" in err[0]
    assert stats["complete"] is False and stats["end"]["kind"] == "terminated" and stats["interrupted"] is True
    assert 0 < stats["frames"]["frames"] < 100 and stats["frames"]["tracked"] > 0


def test_a_video_shorter_than_its_container_says_ends_the_run_cleanly(tmp_path):
    """A truncated inter-coded video: the container announces 90 frames, the stream holds
    fewer; the run ends at the stream's end, complete."""
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (400, 800), dtype=np.uint8), (0, 0), 2.0)
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"XVID"), 30.0, (320, 240), True)
    for i in range(90):
        w.write(cv2.cvtColor(texture[80:320, 2 * i:2 * i + 320], cv2.COLOR_GRAY2BGR))
    w.release()
    data = path.read_bytes()
    path.write_bytes(data[: int(0.8 * len(data))])
    camera = tmp_path / "camera.yaml"
    save_camera(camera, PinholeCamera(300.0, 300.0, 160.0, 120.0, 320, 240, fps=30.0, name="clip"))
    out = tmp_path / "out"
    code = main(["run", str(path), "--config", str(camera), "--out", str(out), "--vocab", "none", "--no-loop",
                 "--no-progress"])  # fmt: skip
    stats = json.loads((out / "stats.json").read_text())
    _nothing_left()
    assert code == 0 and stats["complete"] is True
    assert 50 < stats["frames"]["frames"] == stats["dataset"]["frames"] < 90
    assert stats["frames"]["unreadable"] == 0


def test_out_is_checked_before_the_first_frame(synth_replay_100, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for out, message in ((a_file, "names an existing file"), (a_file / "sub", "is a file")):
        code = main(["run", str(synth_replay_100), "--out", str(out), "--vocab", "none", "--no-progress"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and message in err[0]
    code = main(["run", str(synth_replay_100), "--out", str(tmp_path / "o"), "--vocab", "none", "--no-progress",
                 "--save-map", str(tmp_path)])  # fmt: skip
    assert code == 2 and "--save-map names a folder" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    _nothing_left()
