"""bench/bench_long.py: the quarter statistics and their ratios, the map and memory per tenth,
the per-lap evidence, the /proc memory sampler of a process tree, and a run's series.npz
read back against its stats.json."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from conftest import SHARED_DATA, load_bench
from orbslam_hgcn.datasets import open_sequence
from orbslam_hgcn.errors import OrbslamError
from orbslam_hgcn.runtime.results import read_series, write_series

bench = load_bench("bench_long")


def _series(**kw) -> dict[str, np.ndarray]:
    """A made-up series.npz: 100 frames, none tracked, no keyframe (``kw`` overrides)."""
    n = 100
    s = {
        "frame": np.arange(n), "frame_t": np.arange(n) / 10.0, "frame_wall": 1000.0 + np.arange(n) * 0.1,
        "tracking_ms": np.full(n, np.nan), "frame_ms": np.ones(n), "frame_ref_kf": np.full(n, -1),
        "count_frame": np.arange(0, n, 10), "count_keyframes": np.arange(10), "count_points": 100 * np.arange(10),
        "kf_id": np.zeros(0, int), "kf_frame": np.zeros(0, int), "kf_mapping_ms": np.zeros(0),
        "kf_local_ba_ms": np.zeros(0), "kf_wall": np.zeros(0), "loop_kf_id": np.zeros(0, int),
        "loop_detect_ms": np.zeros(0), "loop_query_ms": np.zeros(0), "loop_db_keyframes": np.zeros(0, int),
    }  # fmt: skip
    s.update(kw)
    return s


def test_quarter_statistics_and_ratio():
    idx = np.arange(100, 200)  # frames 100-199: quarters 100-124 and 175-199
    v = np.full(100, 50.0)
    v[:25], v[75:] = 10.0, 13.0
    v[[0, 80]] = np.nan  # frames not tracked are left out, not counted as 0
    v[1] = 40.0  # the first quarter's mean moves, its median not
    q = bench.quarter_stats(idx, v, 100, 199)
    assert q["first"]["n"] == 24 and q["last"]["n"] == 24
    assert q["first"]["median"] == 10.0 and q["last"]["median"] == 13.0
    assert q["ratio_median"] == pytest.approx(1.3)
    assert q["first"]["mean"] == pytest.approx((23 * 10 + 40) / 24)
    assert q["ratio_mean"] == pytest.approx(13.0 / ((23 * 10 + 40) / 24))
    # Keyframes indexed by their frame: none in the last quarter gives no ratio, not 0 or inf.
    q = bench.quarter_stats(np.array([100, 110, 150]), np.array([5.0, 7.0, 9.0]), 100, 199)
    assert q["first"]["median"] == 6.0 and q["last"]["n"] == 0 and math.isnan(q["ratio_median"])


def test_cost_growth_uses_each_keyframes_frame_and_only_queried_loop_checks():
    s = _series(
        tracking_ms=np.where(np.arange(100) < 50, 2.0, 3.0),
        kf_id=np.array([0, 1, 2, 3]), kf_frame=np.array([0, 10, 80, 95]), kf_mapping_ms=np.array([40.0, 60, 55, 45]),
        loop_kf_id=np.array([0, 1, 2, 3]), loop_detect_ms=np.array([0.1, 1.0, 3.0, 5.0]),
        loop_query_ms=np.array([np.nan, 0.5, 2.0, 2.5]),
    )  # fmt: skip
    g = bench.cost_growth(s)
    assert g["tracking ms/frame"]["ratio_median"] == pytest.approx(1.5)
    assert g["local mapping ms/kf"]["first"]["median"] == 50.0 and g["local mapping ms/kf"]["last"]["median"] == 50.0
    # Keyframe 0's detection made no query (skipped after the map's start): left out of both rows.
    assert g["loop detection ms/kf"]["first"]["n"] == 1 and g["loop detection ms/kf"]["ratio_median"] == 4.0
    assert g["db query ms/kf"]["ratio_median"] == pytest.approx(4.5)


def test_tenths_take_the_last_count_and_memory_sample_before_each_frame():
    samples = [(1000.0 + t, int(1024 * (100 + 10 * t)), int(1024 * (50 + 10 * t)), 3) for t in np.arange(0, 11, 0.5)]
    rows = bench.tenths(_series(), samples)
    assert [r["frame"] for r in rows] == [9, 19, 29, 39, 49, 59, 69, 79, 89, 99]
    assert rows[0]["keyframes"] == 0 and rows[0]["points"] == 0  # count of frame 0; frame 10's comes after
    assert rows[-1]["keyframes"] == 9 and rows[-1]["points"] == 900
    # Frame 99's pose came out at 1009.9 s: the sample of 1009.5 s.
    assert rows[-1]["tree_mb"] == pytest.approx(195.0) and rows[-1]["run_mb"] == pytest.approx(145.0)
    assert rows[0]["wall_s"] == pytest.approx(0.9) and rows[-1]["camera_s"] == pytest.approx(9.9)
    g = bench.growth(rows)
    assert g["run_mb"] == pytest.approx(145.0 / rows[0]["run_mb"])
    assert g["run_mb_per_1000_points"] == pytest.approx((145.0 - rows[0]["run_mb"]) / 900 * 1000)
    assert bench.tenths(_series(), [])[-1]["tree_mb"] is None  # no /proc: no memory, the rest printed


def test_lap_evidence_names_the_earliest_way_each_lap_joined():
    n, lap = 400, 100.0
    frames = np.arange(n)
    # Keyframes every 10 frames; frames 230-274 (lap 3's window) track against lap 1's keyframes.
    kf_frame = np.arange(0, n, 10)
    ref = frames // 10
    ref[230:275] = (frames[230:275] - 200) // 10
    tracking = np.ones(n)
    tracking[300:] = np.nan  # lap 4 lost: its frames track against nothing
    s = _series(frame=frames, frame_t=frames / 30.0, frame_wall=frames / 30.0, tracking_ms=tracking, frame_ref_kf=ref,
                kf_id=np.arange(len(kf_frame)), kf_frame=kf_frame)  # fmt: skip
    stats = {"loop_closing": {"loops": [{"frame_id": 160, "loop_frame_id": 20}, {"frame_id": 240, "loop_frame_id": 200}],
                              "merges": []},
             "relocalization": {"history": [[390, 2, 50]]}, "events": [{"frame": 300, "event": "lost"}]}  # fmt: skip
    laps = bench.lap_evidence(s, stats, n, lap)
    assert [x["verdict"] for x in laps] == ["first lap", "loop", "joined", "relocalised"]
    assert laps[1]["window"] == (75, 174) and laps[1]["loops"] == [(160, 20)]
    # The loop of frame 240 matched a frame only 40 frames earlier: no earlier lap.
    assert laps[2]["loops"] == [] and laps[2]["joined_from"] == 230 and laps[2]["joined_frames"] == 45
    assert laps[3]["lost"] == 1 and laps[3]["relocalised"] == [390] and laps[3]["window"] == (275, 399)
    assert "loop closed at frame 160 with frame 20" in bench._lap_text(laps[1])


def _sampled(code: str):
    """Run ``python -c code`` to its end with a MemorySampler on it: (process, sampler)."""
    proc = subprocess.Popen([sys.executable, "-c", code])
    sampler = bench.MemorySampler(proc.pid, interval_s=0.1).start()
    try:
        proc.wait(timeout=60)
    finally:
        sampler.stop()
    return proc, sampler


@pytest.mark.skipif(not bench.proc_supported(), reason="reads Linux /proc")
def test_memory_sampler_sums_a_process_tree():
    # A child holding 200 MiB whose own child holds 100 MiB, both for 2.5 s.
    grandchild = "import time; b = b'x' * (100 << 20); time.sleep(2.5)"
    child = textwrap.dedent(f"""
        import subprocess, sys, time
        p = subprocess.Popen([sys.executable, "-c", {grandchild!r}])
        b = b'y' * (200 << 20)
        time.sleep(2.5)
        p.wait()
    """)
    proc, sampler = _sampled(child)
    assert proc.returncode == 0
    assert sampler.peak_root_kb >= 200 * 1024  # VmRSS is in kB (KiB)
    assert sampler.peak_kb >= 300 * 1024 and sampler.peak_kb > sampler.peak_root_kb + 90 * 1024
    assert sampler.max_processes == 2 and sampler.rss_fallbacks == 0
    assert bench.rss_kb(proc.pid) is None  # gone


@pytest.mark.skipif(not bench.proc_supported(), reason="reads Linux /proc")
def test_memory_sampler_counts_pages_shared_by_a_fork_once():
    # 200 MiB written, then a fork: the two processes share the pages (copy on write), so
    # their VmRSS add up to 400 MiB and more, their PSS to about 200 MiB.
    code = textwrap.dedent("""
        import os, time
        b = bytearray(200 << 20)
        b[::4096] = b'x' * len(b[::4096])
        pid = os.fork()
        time.sleep(2.5)
        if pid:
            os.waitpid(pid, 0)
    """)
    proc, sampler = _sampled(code)
    assert proc.returncode == 0 and sampler.max_processes == 2 and sampler.rss_fallbacks == 0
    assert sampler.peak_root_kb >= 200 * 1024  # the parent's VmRSS alone
    assert 190 * 1024 <= sampler.peak_kb < 300 * 1024  # counted once, not twice


def test_series_file_round_trip_and_damage(tmp_path):
    arrays = _series(kf_id=np.array([3, 4]), kf_frame=np.array([7, 9]))
    path = write_series(tmp_path / "series.npz", arrays)
    back = read_series(path)
    assert set(back) == set(arrays) and all(np.array_equal(back[k], arrays[k], equal_nan=True) for k in arrays)
    path.write_bytes(path.read_bytes()[:50])
    with pytest.raises(OrbslamError, match="series"):
        read_series(path)


def test_tail_sequence_holds_the_last_frames_of_either_layout(synth_replay_100, tmp_path):
    kitti = SHARED_DATA / "kitti00_first160" / "sequences" / "00"
    for kind, seq, start in (("kitti", kitti, 120), ("tum", synth_replay_100, 75)):
        full = open_sequence(kind, seq)
        tail = open_sequence(kind, bench.tail_sequence(seq, kind, start, tmp_path / kind))
        assert len(tail) == len(full) - start
        np.testing.assert_array_equal(tail.timestamps, full.timestamps[start:])
        for i in (0, len(tail) - 1):
            np.testing.assert_array_equal(tail[i].image, full[start + i].image)
        assert tail.ground_truth is not None
        np.testing.assert_allclose(tail.ground_truth.poses[0], full.ground_truth.poses[start]
                                   if kind == "kitti" else full.ground_truth.poses[0])  # fmt: skip
        assert tail.camera.K.tolist() == full.camera.K.tolist()


def test_tail_costs_leave_out_the_maps_start_and_split_map_from_scene():
    tracking = np.r_[np.full(10, 50.0), np.full(90, 4.0)]  # the first tenth: the map's start
    alone = bench.tail_costs(_series(tracking_ms=tracking, kf_frame=np.array([2, 30, 60, 90]),
                                     kf_mapping_ms=np.array([500.0, 60.0, 60.0, 62.0])))  # fmt: skip
    assert alone == {"tracking ms/frame": 4.0, "local mapping ms/kf": 60.0}
    full = {"growth": {"tracking ms/frame": {"first": {"median": 2.0}, "last": {"median": 5.0}},
                       "local mapping ms/kf": {"first": {"median": 40.0}, "last": {"median": 60.0}}}}  # fmt: skip
    cmp = bench.tail_comparison(full, alone)
    assert cmp["tracking ms/frame"]["map"] == pytest.approx(1.25) and cmp["tracking ms/frame"]["scene"] == 2.0
    assert cmp["local mapping ms/kf"]["map"] == 1.0 and cmp["local mapping ms/kf"]["scene"] == 1.5


def test_a_run_that_writes_nothing_is_an_error_not_a_traceback(tmp_path):
    fail = [sys.executable, "-c", "import sys; print('boom', file=sys.stderr); sys.exit(3)"]
    r = bench.run_once(tmp_path, "tum", "unpaced", "none", 0, fail, "fails", keep=tmp_path / "keep")
    assert r["exit"] == 3 and r["error"].startswith("exit 3, no stats.json: boom")


def test_series_of_a_real_run_match_its_stats(synth_replay_100, tmp_path):
    """``orbslam-hgcn run`` over 100 rendered frames, unpaced, as the bench runs it: its
    series.npz summarises to the figures of its stats.json, and the bench reads it."""
    cli = bench._cli()
    r = bench.run_once(synth_replay_100, "tum", "unpaced", "none", 0, cli, "short", keep=tmp_path)
    assert "error" not in r and r["exit"] == 0 and r.get("note") is None
    s, stats = read_series(tmp_path / "short" / "series.npz"), r["stats"]
    t = stats["timing_ms"]
    assert np.array_equal(s["frame"], np.arange(100)) and np.all(np.diff(s["frame_wall"]) >= 0)
    trk = s["tracking_ms"][np.isfinite(s["tracking_ms"])]
    assert len(trk) == t["tracking_per_frame"]["count"] > 50
    assert np.median(trk) == pytest.approx(t["tracking_per_frame"]["median"])
    assert np.median(s["frame_ms"]) == pytest.approx(t["frame_total"]["median"])
    cpu = s["tracking_cpu_ms"]
    assert np.array_equal(np.isfinite(cpu), np.isfinite(s["tracking_ms"]))
    assert np.median(cpu[np.isfinite(cpu)]) == pytest.approx(t["tracking_cpu_per_frame"]["median"])
    assert len(s["kf_id"]) == t["local_mapping_per_keyframe"]["count"] >= 5 and len(set(s["kf_id"])) == len(s["kf_id"])
    assert np.median(s["kf_mapping_ms"]) == pytest.approx(t["local_mapping_per_keyframe"]["median"])
    assert np.median(s["kf_local_ba_ms"]) == pytest.approx(t["local_ba_per_keyframe"]["median"])
    assert np.all((s["kf_frame"] >= 0) & (s["kf_frame"] < 100))
    assert s["kf_wall"].min() >= s["frame_wall"][0] and s["kf_wall"].max() <= s["frame_wall"][-1] + 30
    lc = stats["loop_closing"]
    assert len(s["loop_kf_id"]) == lc["counts"]["keyframes"] and set(s["loop_kf_id"]) <= set(s["kf_id"])
    assert np.mean(s["loop_detect_ms"]) == pytest.approx(lc["timing_ms"]["detect"])
    queried = np.isfinite(s["loop_query_ms"])
    assert np.all(s["loop_query_ms"][queried] <= s["loop_detect_ms"][queried])
    assert np.array_equal(s["count_frame"], s["frame"][::10]) and s["count_points"][-1] > 100
    assert np.all(np.diff(s["loop_db_keyframes"]) <= 1)
    tracked = np.isfinite(s["tracking_ms"])
    assert set(s["frame_ref_kf"][tracked]) <= set(s["kf_id"])
    # Both memories sampled; the tree's sum of PSS may be below the run's VmRSS: the library
    # pages it shares with processes outside the tree (this test's own) count in part.
    assert r["peak_tree_mb"] > 50 and r["peak_run_mb"] > 50 and r["samples"]
    fig = bench.analyse(r, bench.plan("office", 100 / 7200), "unpaced")
    assert set(fig["growth"]) == {"tracking ms/frame", "tracking CPU ms/frame", "local mapping ms/kf",
                                  "loop detection ms/kf", "db query ms/kf"}
    assert len(fig["tenths"]) == 10 and fig["tenths"][-1]["keyframes"] > 0 and fig["tenths"][-1]["run_mb"] > 50
    assert fig["tracked"] == stats["frames"]["tracked"] and fig["peak_tree_mb"] == r["peak_tree_mb"]
