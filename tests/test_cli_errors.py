"""One error contract for every command: the same bad inputs (a missing path, an output
path under a file, an unknown vocabulary, bad numbers) give exit status 2 and one line on
stderr, before any work and without a traceback; Ctrl-C and SIGTERM give 130 and 143,
and the commands with results (compare, demo, sweep) keep those made so far.

The commands are called in-process (``cli.main``); the signals are real ones, sent to this
process at a point where the command is working. Each test sets the SIGINT disposition it
tests (Python's own handler, as in a foreground job) rather than inheriting it: a shell
starts a background job (``nohup``, ``&`` in a script) with SIGINT ignored, and the command
rightly leaves an ignored SIGINT ignored."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from orbslam_hgcn import cli

GT = Path(__file__).resolve().parent / "data" / "tum_fr3_long_office_household_groundtruth.txt"


@pytest.fixture(autouse=True)
def ctrl_c_raises():
    """SIGINT raises KeyboardInterrupt during the test, whatever this process inherited."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A file, a TUM-like folder (rgb.txt, three small textured images), a ground-truth loop
    matrix for them, and a sweep manifest over the folder."""
    root = tmp_path_factory.mktemp("inputs")
    afile = root / "afile"
    afile.write_text("not a folder\n")
    seq = root / "rgbd_dataset_freiburg3_seq"  # the name gives the camera: TUM fr3, 640x480
    (seq / "rgb").mkdir(parents=True)
    rng = np.random.default_rng(0)
    lines = []
    for i in range(3):
        img = cv2.GaussianBlur((rng.random((480, 640)) * 255).astype(np.uint8), (3, 3), 0)
        cv2.imwrite(str(seq / "rgb" / f"{i}.png"), img)
        lines.append(f"{i / 30:.6f} rgb/{i}.png")
    (seq / "rgb.txt").write_text("\n".join(lines) + "\n")
    gt = root / "loop_gt.npy"
    np.save(gt, np.zeros((3, 3), dtype=bool))
    manifest = root / "sweep.yaml"
    manifest.write_text(f"sequences:\n  - {{name: s, path: {seq}, kind: tum}}\nvocabularies: [orb]\n")
    return SimpleNamespace(root=root, afile=afile, under=str(afile / "sub"), seq=str(seq), gt=str(gt),
                           manifest=str(manifest))


def _cases(x) -> dict[str, tuple[list[str], str]]:
    """Each bad input: (argv, a piece of the one line expected)."""
    out = str(x.root / "out")
    seq, under, gt = x.seq, x.under, str(GT)
    lcd = ["lcd", "--train", seq, "--test", seq, "--gt", x.gt]
    return {
        # a missing path
        "run/missing": (["run", "/nonexistent", "--out", out], "/nonexistent"),
        "compare/missing": (["compare", "/nonexistent", "--out", out], "/nonexistent"),
        "sweep/missing": (["sweep", "/nonexistent.yaml", "--out", out], "/nonexistent.yaml"),
        "eval/missing": (["eval", "--gt", "/nonexistent", "--est", gt, "--out", out], "/nonexistent"),
        "synth/missing": (["synth", "--out", out, "--trajectory", "replay", "--gt", "/nonexistent"], "/nonexistent"),
        "vocab-train/missing": (["vocab", "train", "--kind", "orb", "--images", "/nonexistent", "--out",
                                 out + "/v.npz"], "/nonexistent"),
        "vocab-info/missing": (["vocab", "info", "/nonexistent.npz"], "/nonexistent.npz"),
        "vocab-export/missing": (["vocab", "export", "/nonexistent.npz", "--out", out + "/v.txt"], "/nonexistent"),
        "lcd/missing": (["lcd", "--train", "/nonexistent", "--test", seq, "--gt", x.gt, "--out", out], "/nonexistent"),
        "demo/bad-rerun": (["demo", "--out", out, "--rerun", "connect", "a:b:c", "--frames", "5"], "--rerun"),
        # an output path under a file
        "run/under": (["run", seq, "--out", under], "is a file"),
        "compare/under": (["compare", seq, "--out", under], "is a file"),
        "sweep/under": (["sweep", x.manifest, "--out", under, "--no-ray"], "is a file"),
        "eval/under": (["eval", "--gt", gt, "--est", gt, "--out", under], "is a file"),
        "synth/under": (["synth", "--out", under, "--frames", "2"], "is a file"),
        "vocab-train/under": (["vocab", "train", "--kind", "orb", "--images", seq, "--out", under + "/v.npz"],
                              "is a file"),
        "vocab-export/under": (["vocab", "export", "orb", "--out", under + "/v.txt"], "is a file"),
        "lcd/under": ([*lcd, "--out", under], "is a file"),
        "demo/under": (["demo", "--out", under, "--frames", "5"], "is a file"),
        "demo/cache-under": (["demo", "--out", out, "--cache", under, "--frames", "5"], "is a file"),
        "viz-demo/under": (["viz-demo", "--rerun", "save", under + "/x.rrd", "--frames", "3"], "is a file"),
        # an unknown vocabulary
        "run/vocab": (["run", seq, "--out", out, "--vocab", "nosuch"], "nosuch"),
        "compare/vocab": (["compare", seq, "--out", out, "--vocabs", "orb", "nosuch"], "nosuch"),
        "vocab-info/vocab": (["vocab", "info", "nosuch"], "nosuch"),
        "vocab-export/vocab": (["vocab", "export", "nosuch", "--out", out + "/v.txt"], "nosuch"),
        "lcd/vocab": ([*lcd, "--out", out, "--vocab", "nosuch"], "nosuch"),
        # bad numbers
        "run/frames": (["run", seq, "--out", out, "--max-frames", "0"], "--max-frames"),
        "compare/runs": (["compare", seq, "--out", out, "--runs", "0"], "--runs"),
        "compare/frames": (["compare", seq, "--out", out, "--max-frames", "0"], "--max-frames"),
        "compare/jobs": (["compare", seq, "--out", out, "--jobs", "0"], "--jobs"),
        "sweep/jobs": (["sweep", x.manifest, "--out", out, "--jobs", "0"], "--jobs"),
        "eval/delta": (["eval", "--gt", gt, "--est", gt, "--out", out, "--delta", "0"], "delta"),
        "synth/frames": (["synth", "--out", out, "--frames", "0"], "frames"),
        "vocab-train/words-0": (["vocab", "train", "--kind", "hgcn", "--images", seq, "--words", "0", "--out",
                                 out + "/v.npz"], "--words"),
        "vocab-train/kmeans-words": (["vocab", "train", "--kind", "kmeans", "--images", seq, "--words", "-5",
                                      "--out", out + "/v.npz"], "--words must be at least 2, found -5"),
        "vocab-train/orb-words": (["vocab", "train", "--kind", "orb", "--images", seq, "--words", "0", "--out",
                                   out + "/v.npz"], "--words"),
        "vocab-train/features": (["vocab", "train", "--kind", "orb", "--images", seq, "--n-features", "0", "--out",
                                  out + "/v.npz"], "--n-features"),
        "vocab-train/levels": (["vocab", "train", "--kind", "orb", "--images", seq, "--levels", "0", "--out",
                                out + "/v.npz"], "levels"),
        "vocab-train/epochs": (["vocab", "train", "--kind", "hgcn", "--images", seq, "--epochs", "0", "--out",
                                out + "/v.npz"], "epochs"),
        "lcd/stride": ([*lcd, "--out", out, "--stride", "0"], "stride"),
        "lcd/features": ([*lcd, "--out", out, "--n-features", "0"], "--n-features"),
        "demo/runs": (["demo", "--out", out, "--runs", "0", "--frames", "5"], "--runs"),
        "demo/frames": (["demo", "--out", out, "--frames", "0"], "--frames"),
        "viz-demo/frames": (["viz-demo", "--frames", "0"], "--frames"),
    }


CASES = list(_cases(SimpleNamespace(root=Path("/r"), under="/u", seq="/s", gt="/g", manifest="/m")))


def _one_error_line(err: str, command: str) -> str:
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("orbslam-hgcn")]
    assert len(lines) == 1 and lines[0].startswith(f"orbslam-hgcn {command}: "), err
    return lines[0]


@pytest.mark.parametrize("case", CASES)
def test_bad_input_is_one_line_and_status_2_before_any_work(case, inputs, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("ORBSLAM_HGCN_CACHE", str(tmp_path / "cache"))
    argv, expected = _cases(inputs)[case]
    out = inputs.root / "out"
    rc = cli.main(argv)
    err = capsys.readouterr().err
    line = _one_error_line(err, argv[0])
    assert rc == 2 and expected in line, (rc, line)
    assert not out.exists() and not (tmp_path / "cache").exists()  # nothing made before the check


# --- interruptions ------------------------------------------------------------------------


def _kill_on_call(sig: int, calls: int = 1):
    """A function that sends ``sig`` to this process on its ``calls``-th call."""
    count = [0]

    def kill(*_a, **_k):
        count[0] += 1
        if count[0] == calls:
            os.kill(os.getpid(), sig)
        return count[0]

    return kill


def _fake_run(sig: int, at_run: int):
    """Stands in for run_dataset: writes a complete stats.json; run ``at_run`` is stopped by ``sig``."""
    kill = _kill_on_call(sig, at_run)

    def run(path, out, vocab=None, **kw):
        kill()
        stats = {"frames": {"frames": 10, "tracked": 10, "lost": 0, "dropped": 0}, "map_resets": 0, "wall_s": 1.0,
                 "ate_sim3": {"keyframes": {"rmse_m": 0.002}}, "loop_closing": {"loops": []},
                 "dataset": {"name": "fake"}}  # fmt: skip
        out.mkdir(parents=True)
        (out / "stats.json").write_text(json.dumps(stats))
        return SimpleNamespace(paths={"stats": out / "stats.json"})

    return run


SIGNALS = [(signal.SIGINT, 130), (signal.SIGTERM, 143)]


@pytest.mark.parametrize("sig,status", SIGNALS)
def test_compare_interrupted_keeps_the_runs_made(sig, status, inputs, tmp_path, capsys, monkeypatch):
    import orbslam_hgcn.app.run as run_mod

    monkeypatch.setattr(run_mod, "run_dataset", _fake_run(sig, at_run=2))
    before = signal.getsignal(signal.SIGTERM)
    rc = cli.main(["compare", inputs.seq, "--out", str(tmp_path / "c"), "--runs", "3", "--vocabs", "orb"])
    assert signal.getsignal(signal.SIGTERM) == before
    assert rc == status and "Traceback" not in capsys.readouterr().err
    data = json.loads((tmp_path / "c" / "compare.json").read_text())
    assert [(r["run"], r["ok"]) for r in data["runs"]] == [(1, True), (2, False)]
    assert data["summary"]["orb"]["ate_rmse_m"]["values"] == [0.002]


@pytest.mark.parametrize("sig,status", SIGNALS)
def test_demo_interrupted(sig, status, inputs, tmp_path, capsys, monkeypatch):
    import orbslam_hgcn.app.demo as demo_mod
    import orbslam_hgcn.app.run as run_mod

    monkeypatch.setattr(demo_mod, "demo_sequence", lambda *a, **k: Path(inputs.seq))
    monkeypatch.setattr(run_mod, "run_dataset", _fake_run(sig, at_run=2))
    rc = cli.main(["demo", "--out", str(tmp_path / "d"), "--no-rerun", "--no-progress"])
    assert rc == status and "Traceback" not in capsys.readouterr().err
    data = json.loads((tmp_path / "d" / "compare.json").read_text())
    assert [(r["vocab"], r["ok"]) for r in data["runs"]] == [("hgcn", True), ("orb", False)]


def test_compare_and_demo_exit_1_when_runs_fail(inputs, tmp_path, capsys, monkeypatch):
    """As sweep does: 1 when a run failed (here every run), with the tables written."""
    import orbslam_hgcn.app.demo as demo_mod
    import orbslam_hgcn.app.run as run_mod
    from orbslam_hgcn.errors import DatasetError

    def failing(path, out, **kw):
        raise DatasetError(f"{path}: unreadable")

    monkeypatch.setattr(run_mod, "run_dataset", failing)
    monkeypatch.setattr(demo_mod, "demo_sequence", lambda *a, **k: Path(inputs.seq))
    assert cli.main(["compare", inputs.seq, "--out", str(tmp_path / "c"), "--runs", "2", "--vocabs", "orb"]) == 1
    assert cli.main(["demo", "--out", str(tmp_path / "d"), "--no-rerun", "--no-progress"]) == 1
    for folder in ("c", "d"):
        data = json.loads((tmp_path / folder / "compare.json").read_text())
        assert data["runs"] and not any(r["ok"] for r in data["runs"])
    capsys.readouterr()


@pytest.mark.parametrize("sig,status", SIGNALS)
def test_sweep_interrupted_keeps_the_tables(sig, status, inputs, tmp_path, capsys, monkeypatch):
    import orbslam_hgcn.app.sweep as sweep_mod

    def processes(argvs, engine):
        out = Path(argvs[0][1])
        out.mkdir(parents=True, exist_ok=True)
        stats = {"frames": {"frames": 10, "tracked": 10, "lost": 0, "dropped": 0}, "map_resets": 0, "wall_s": 1.0,
                 "ate_sim3": {"keyframes": {"rmse_m": 0.002}}, "loop_closing": {"loops": []}, "complete": True}
        yield 0, {"stats": stats, "error": None, "attempts": 1}
        os.kill(os.getpid(), sig)

    manifest = tmp_path / "m.yaml"
    manifest.write_text(f"sequences: [{{name: s, path: {inputs.seq}, kind: tum}}]\nvocabularies: [orb]\nruns: 2\n")
    monkeypatch.setattr(sweep_mod, "run_processes", processes)
    rc = cli.main(["sweep", str(manifest), "--out", str(tmp_path / "s"), "--no-ray", "--no-progress"])
    assert rc == status and "Traceback" not in capsys.readouterr().err
    data = json.loads((tmp_path / "s" / "sweep.json").read_text())
    assert data["interrupted"] is True and len(data["runs"]) == 1


@pytest.mark.parametrize("sig,status", SIGNALS)
def test_synth_and_lcd_interrupted(sig, status, inputs, tmp_path, capsys, monkeypatch):
    import orbslam_hgcn.placerec.lcd as lcd_mod
    import orbslam_hgcn.synth.sequence as synth_mod

    build = synth_mod.build_sequence
    kill = _kill_on_call(sig)
    monkeypatch.setattr(synth_mod, "build_sequence", lambda *a, **k: (kill(), build(*a, **k))[1])
    assert cli.main(["synth", "--out", str(tmp_path / "sy"), "--frames", "2"]) == status
    _one_line_without_traceback(capsys.readouterr().err, "synth")
    monkeypatch.setattr(lcd_mod, "lcd_command", _kill_on_call(sig))
    assert cli.main(["lcd", "--train", inputs.seq, "--test", inputs.seq, "--gt", inputs.gt,
                     "--out", str(tmp_path / "l")]) == status
    _one_line_without_traceback(capsys.readouterr().err, "lcd")


def _one_line_without_traceback(err: str, command: str) -> None:
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("orbslam-hgcn")]
    assert len(lines) == 1 and lines[0].startswith(f"orbslam-hgcn {command}: "), err


def test_output_piped_into_a_reader_that_stops_ends_without_a_traceback():
    """`orbslam-hgcn vocab info hgcn | true`: the reader has closed the pipe before the command
    writes (the interpreter's start alone takes longer than `true`); the command stops quietly
    with status 141, as a shell reports SIGPIPE, and no traceback."""
    import subprocess
    import sys

    proc = subprocess.run(["bash", "-c", f"'{sys.executable}' -m orbslam_hgcn vocab info hgcn | true; "
                           "echo status ${PIPESTATUS[0]} >&2"], capture_output=True, text=True, timeout=300)
    assert "Traceback" not in proc.stderr and "BrokenPipeError" not in proc.stderr, proc.stderr
    assert "status 141" in proc.stderr, proc.stderr
