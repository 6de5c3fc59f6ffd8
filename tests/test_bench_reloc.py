"""bench/bench_reloc.py on the real TUM sitting_xyz frames: every later frame relocalised alone
against a map of the first half, as ORB-SLAM measured relocalisation; and the relocaliser's
two steps beyond ORB-SLAM (matching over all descriptors, covisible keyframes after the
database's candidates) recovering blurred views it misses, without a wrong pose."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SITTING = REPO.parent / "shared" / "data" / "tum_fr3_sitting_xyz_148"


def _bench():
    spec = importlib.util.spec_from_file_location("bench_reloc", REPO / "bench" / "bench_reloc.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def runs():
    from orbslam_hgcn.datasets import open_sequence

    assert SITTING.is_dir(), f"{SITTING}: the shared TUM sitting_xyz frames are missing"
    b = _bench()
    seq = open_sequence(None, SITTING)
    map_frames, queries = b.split(len(seq), "half")
    queries = queries[::2]  # 37 queries: enough to separate the arms, half the time
    return b, {arm: b.run_vocab(seq, "kmeans", map_frames, queries, ["none", "blur"], 0.3, 20.0, arm)
               for arm in ("default", "orbslam")}  # fmt: skip


def test_every_covered_view_relocalises_near_the_truth(runs):
    b, r = runs
    for arm in ("default", "orbslam"):
        v = r[arm]["versions"]["none"]
        assert v["covered"] >= 15 and v["covered_relocalised"] == v["covered"], arm
        assert v["wrong"] == 0
        # No worse than 1.5x the map's own keyframe error, as the target asks.
        assert v["err_median_cm"] <= 1.5 * r[arm]["kf_ate_cm"], (v["err_median_cm"], r[arm]["kf_ate_cm"])
        assert all(row["ms"] > 0 for row in v["rows"])


def test_the_fallbacks_recover_blurred_views_orbslam_rules_miss(runs):
    _, r = runs
    default, orbslam = r["default"]["versions"]["blur"], r["orbslam"]["versions"]["blur"]
    assert default["covered"] == orbslam["covered"]
    # Measured 15 of 37 covered blurred views against 30 with the whole set of queries.
    assert default["covered_relocalised"] >= orbslam["covered_relocalised"] + 4
    assert default["wrong"] == 0 and orbslam["wrong"] == 0
    lost_by_orbslam = {row["frame"] for row in orbslam["rows"] if not row["ok"]}
    found = [row for row in default["rows"] if row["ok"] and row["frame"] in lost_by_orbslam]
    assert found and max(row["err_m"] for row in found) < 0.1
    # ORB-SLAM's rules lose them at BoW matching or the pose; the database is not the cause.
    assert set(orbslam["missed_covered_at"]) <= {"bow", "pose"}


def test_wilson_interval_and_the_degradations():
    b = _bench()
    lo, hi = b.wilson(37, 37)
    assert hi == 1.0 and 0.90 < lo < 0.92
    lo, hi = b.wilson(0, 10)
    assert lo == 0.0 and 0.27 < hi < 0.29
    img = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)
    for kind in b.DEGRADATIONS:
        out = b.degrade(img, kind)
        assert out.shape == img.shape and out.dtype == np.uint8
    assert b.degrade(img, "none") is img
    assert b.degrade(img, "dark").mean() < 0.5 * img.mean() < b.degrade(img, "bright").mean()


def test_vocab_info_says_which_vocabulary_for_what_with_the_recorded_figures(capsys):
    import json

    from orbslam_hgcn import cli

    assert cli.main(["vocab", "info", "kmeans"]) == 0
    out = capsys.readouterr().out
    assert "Which vocabulary for what, measured on real data" in out and "<!--" not in out
    # The figures it prints are the records' (bench/figures.py keeps the page equal to them).
    rec = dict(json.loads((REPO / "bench" / "results" / "reloc_sitting.json").read_text())["figures"])
    for key in ("kmeans default blur", "hgcn default blur"):
        covered = rec[key].split(",")[0].removeprefix("covered ")
        assert covered in " ".join(out.split()), (key, covered)
