"""``orbslam-hgcn lcd`` with its defaults on a rendered 30 frames/s loop: the sampling and
the exclusion window chosen from the data make the experiment measure loop closures; the
same run comparing every frame with the frame before it measures nothing.

The sequences are small renders (320x240): the test sequence goes round one office desk
one and a half times at 30 frames/s (the second time on the same path, with other sensor
noise and exposure), the training sequence twice round another office at 10 frames/s. Both
have synth's loop ground truth (camera centres within 0.5 m and optical axes within 30 deg),
which also marks every pair of neighbouring frames.
"""

import json

import numpy as np
import pytest

from orbslam_hgcn.cli import main

SMALL = dict(width=320, height=240, fx=267.7, fy=269.6, cx=160.05, cy=123.8, texel_scale=2.0, loop_gt=True,
             noise=2.0, exposure_drift=0.1)


@pytest.fixture(scope="module")
def office_loops(tmp_path_factory):
    from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence

    root = tmp_path_factory.mktemp("lcd_loops")
    test = render_sequence(root / "test", SynthOptions(frames=450, laps=2, fps=30, scene_seed=4, **SMALL),
                           progress=False)
    train = render_sequence(root / "train", SynthOptions(frames=200, laps=2, fps=10, scene_seed=7, seed=1, **SMALL),
                            progress=False)
    return train, test


def _lcd(train, test, out, *flags):
    code = main(["lcd", "--train", str(train), "--test", str(test), "--out", str(out), *flags])
    assert code == 0
    return json.loads((out / "lcd_results.json").read_text())


def test_default_lcd_measures_loops_and_a_one_frame_window_does_not(office_loops, tmp_path, capsys, caplog):
    train, test = office_loops
    record = _lcd(train, test, tmp_path / "default")
    printed = capsys.readouterr()
    n_frames = len(np.load(test / "loop_gt.npy"))
    # about one image per distinct view, named in images_test.txt
    assert 20 <= record["n_test"] <= n_frames // 5
    listed = [line.split() for line in (tmp_path / "default" / "images_test.txt").read_text().splitlines()
              if not line.startswith("#")]
    assert [int(f[1]) for f in listed] == record["images"]["test"]
    assert all((test / f[3]).is_file() for f in listed)
    # the window is the ground truth's smallest loop separation: well over a second here
    window = record["window"]["test"]
    assert "smallest loop separation" in window["source"] and window["seconds"] > 5.0
    assert "exclusion window" in printed.out and "smallest loop separation" in printed.out
    for method, m in record["methods"].items():
        assert m["n_positive"] >= 10, method
        assert m["recall_at_100p"] >= 0.5, (method, m["recall_at_100p"])
        assert m["auc"] >= 0.8, (method, m["auc"])
        assert m["min_gap"] == window["images"]
        # the threshold fitted on the training sequence keeps its precision there at 100%
        assert m["threshold_from"] == "fitted on training"
        assert m["train_score"]["fp"] == 0 and m["train_score"]["tp"] > 0, (method, m["train_score"])
    # every frame, each compared with the frame before it: its best match is that frame,
    # which is no loop, and the experiment scores (near) nothing
    caplog.clear()
    one = _lcd(train, test, tmp_path / "one", "--stride", "1", "--min-gap", "1")
    assert one["n_test"] == n_frames
    for method, m in one["methods"].items():
        assert m["recall_at_100p"] <= 0.05, (method, m["recall_at_100p"])
        assert m["auc"] <= 0.1, (method, m["auc"])
        assert m["recent_past_share"] > 0.9
    assert "finds the recent past, not loops" in caplog.text
