"""``orbslam-hgcn run`` stopped by SIGTERM as a service manager or ``timeout`` sends it: to
the whole process group, the run's child processes included. The run ends as on Ctrl-C
(its results written, exit status 143), stops its children and starts none again."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np

CLI = Path(sys.executable).with_name("orbslam-hgcn")


def _sequence(root: Path, n: int = 60) -> Path:
    """A TUM-layout folder of ``n`` textured 640x480 frames, 0.1 s apart (fr3 camera)."""
    seq = root / "rgbd_dataset_freiburg3_signals"
    (seq / "rgb").mkdir(parents=True)
    rng = np.random.default_rng(0)
    lines = []
    for i in range(n):
        img = cv2.GaussianBlur((rng.random((480, 640)) * 255).astype(np.uint8), (3, 3), 0)
        cv2.imwrite(str(seq / "rgb" / f"{i}.png"), img)
        lines.append(f"{i / 10:.6f} rgb/{i}.png")
    (seq / "rgb.txt").write_text("\n".join(lines) + "\n")
    return seq


def _default_signals() -> None:
    """In the child: the signal dispositions of a foreground job, whatever the test inherited."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def test_sigterm_to_the_process_group_ends_the_run_with_its_results(tmp_path):
    seq = _sequence(tmp_path)
    out = tmp_path / "out"
    argv = [str(CLI), "run", str(seq), "--out", str(out), "--vocab", "none", "--no-loop", "--speed", "1"]
    proc = subprocess.Popen(argv, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, start_new_session=True,
                            preexec_fn=_default_signals)  # fmt: skip
    chunks = bytearray()

    def read() -> None:
        while True:
            b = proc.stderr.read1(4096)
            if not b:
                return
            chunks.extend(b)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            done = [int(m) for m in re.findall(rb"\|\s*(\d+)/60", bytes(chunks))]  # the progress bar
            if done and max(done) >= 3:
                break
            time.sleep(0.1)
        assert proc.poll() is None, bytes(chunks).decode(errors="replace")
        assert done and max(done) >= 3, "no frame processed in 120 s"
        os.killpg(proc.pid, signal.SIGTERM)  # the run and its children, as `timeout` or systemd do
        rc = proc.wait(60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    reader.join(10)
    stderr = bytes(chunks).decode(errors="replace")
    assert rc == 143, stderr
    assert "process lost" not in stderr and "died" not in stderr and "new process" not in stderr, stderr
    assert "Traceback" not in stderr, stderr
    stats = json.loads((out / "stats.json").read_text())
    assert stats["complete"] is False and stats["end"]["kind"] == "terminated", stats["end"]
    assert stats["end"]["exit_status"] == 143 and stats["interrupted"] is True
    assert 3 <= stats["frames"]["frames"] < 60
    assert stats["child_processes_lost"] == {"extraction": 0, "local_ba": 0}
    assert stats["dataset"]["kind"] == "auto"
    assert (out / "CameraTrajectory.txt").is_file()
    # The children were stopped with the run: nothing is left in its process group.
    for _ in range(50):
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        raise AssertionError("a child process outlived the run")


def test_a_child_outlives_sigterm_by_its_grace_and_is_replaced_unless_stopping():
    """SIGTERM to a child alone: it ends after its grace and the next request replaces it;
    while this process is stopping, a child that died is not started again."""
    import pytest

    from orbslam_hgcn.childprocess import ChildProcess, set_stopping
    from orbslam_hgcn.errors import StageError

    child = ChildProcess("probe", dict, (), term_grace_s=0.5)
    try:
        assert child.call("ping") == "pong"
        pid = child._proc.pid
        os.kill(pid, signal.SIGTERM)
        time.sleep(0.2)
        assert child.call("ping") == "pong" and child._proc.pid == pid  # within the grace: still serving
        child._proc.join(5)
        assert child._proc.exitcode == -signal.SIGTERM
        with pytest.raises(StageError, match="died") as exc:
            child.call("ping")
        assert exc.value.lost and "stopping" not in str(exc.value)
        assert child.call("ping") == "pong" and child._proc.pid != pid  # replaced
        set_stopping(True)
        child.kill()
        with pytest.raises(StageError, match="this process is stopping"):
            child.call("ping")
        with pytest.raises(StageError, match="not started"):
            child.call("ping")
        assert not child.alive
    finally:
        set_stopping(False)
        child.close()
