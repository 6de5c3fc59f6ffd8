"""bench/bench_peer.py's logic without ORB-SLAM3: when a comparison counts, the median ratio,
the vocabulary gate's verdict, where ORB-SLAM3's vocabulary comes from, and the timing
spans read from ours' stats.json."""

from __future__ import annotations

import gzip
import math
import subprocess
import sys

import pytest

from conftest import REPO, load_bench


@pytest.fixture(scope="module")
def bp():
    return load_bench("bench_peer")


def row(system: str, tracked: int, fps: float) -> dict:
    return {"system": system, "tracked": tracked, "fps": fps}


HEADER = "10 6 0 0\n"


# --- the void-comparison rule ------------------------------------------------------------


def test_compare_run_gives_a_ratio_when_both_track_95_percent(bp):
    v = bp.compare_run(row("orbslam-hgcn", 160, 30.0), row("ORB-SLAM3", 152, 20.0), 160)  # 152 = 95% of 160
    assert v["valid"] and v["ratio"] == pytest.approx(1.5)
    assert "1.50x" in bp.describe_verdict(v, 160)


@pytest.mark.parametrize("ours_tracked, peer_tracked, failing", [
    (160, 28, ["ORB-SLAM3"]),
    (151, 160, ["orbslam-hgcn"]),
    (10, 20, ["orbslam-hgcn", "ORB-SLAM3"]),
])
def test_compare_run_is_void_when_either_side_tracks_under_95_percent(bp, ours_tracked, peer_tracked, failing):
    v = bp.compare_run(row("orbslam-hgcn", ours_tracked, 30.0), row("ORB-SLAM3", peer_tracked, 20.0), 160)
    assert not v["valid"] and "ratio" not in v
    assert [f[0] for f in v["failed"]] == failing
    text = bp.describe_verdict(v, 160)
    assert "void" in text and "x" not in text.replace("ORB-SLAM3", "").split("void")[0]
    for system, tracked in zip(("orbslam-hgcn", "ORB-SLAM3"), (ours_tracked, peer_tracked)):
        if system in failing:
            assert f"{system} tracked {tracked} of 160" in text


def test_compare_run_counts_start_up_in_two_more_ratios(bp):
    ours = {**row("orbslam-hgcn", 160, 40.0), "start_s": 1.0, "loop_s": 4.0}
    peer = {**row("ORB-SLAM3", 159, 32.0), "start_s": 3.0, "loop_s": 5.0}
    v = bp.compare_run(ours, peer, 160)
    assert v["ratio"] == pytest.approx(1.25)
    assert v["ratio_with_start"] == pytest.approx(5.0 / 5.0)  # ours 1 + 4 s against its 5 s span
    assert v["ratio_both_start"] == pytest.approx(8.0 / 5.0)
    text = bp.describe_verdict(v, 160)
    assert "1.00x" in text and "1.60x" in text
    med = bp.median_ratio([v, bp.compare_run({**ours, "start_s": 3.0}, peer, 160)], "ratio_with_start")
    assert med[1] == [pytest.approx(1.0), pytest.approx(5.0 / 7.0)]
    # a run without start-up figures (a failed timing read) gives the plain ratio only
    assert "ratio_with_start" not in bp.compare_run(row("orbslam-hgcn", 160, 40.0), row("ORB-SLAM3", 159, 32.0), 160)


def test_compare_run_gives_the_cpu_per_frame_ratio_where_both_were_sampled(bp):
    ours = {**row("orbslam-hgcn", 160, 40.0), "cpu_ms_per_frame": 40.0}
    peer = {**row("ORB-SLAM3", 159, 32.0), "cpu_ms_per_frame": 60.0}
    v = bp.compare_run(ours, peer, 160)
    assert v["cpu_ratio"] == pytest.approx(1.5) and "CPU per frame 1.50x" in bp.describe_verdict(v, 160)
    assert "cpu_ratio" not in bp.compare_run(ours, {**peer, "cpu_ms_per_frame": math.nan}, 160)
    assert "cpu_ratio" not in bp.compare_run(ours, {**peer, "tracked": 100}, 160)


BURN = """
import subprocess, sys, time
def burn(s):
    end = time.process_time() + s
    while time.process_time() < end:
        pass
if sys.argv[1] == "parent":
    time.sleep(0.3)
    kid = subprocess.Popen([sys.executable, "-c", sys.argv[2], "child", sys.argv[2]])
    burn(0.4)
    kid.wait()
    time.sleep(0.5)
else:
    burn(0.5)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc (Linux)")
def test_tree_cpu_counts_a_process_tree_and_a_child_that_ended(bp):
    """A process that burns 0.4 s of CPU while its child burns 0.5 s and ends, then sleeps:
    the sampled tree used about 0.9 s in all and nothing in its last 0.3 s, as the kernel's
    own accounting of the reaped processes says."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = __import__("time").monotonic()
    proc = subprocess.Popen([sys.executable, "-c", BURN, "parent", BURN])
    cpu = bp.TreeCpu(proc.pid)
    proc.wait()
    cpu.stop()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    kernel = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    t_end = cpu.samples[-1][0] - 2 * bp.CPU_SAMPLE_S  # before the process exited
    whole = cpu.used(t0 if t0 >= cpu.samples[0][0] else cpu.samples[0][0], t_end)
    assert 0.85 <= kernel <= 1.3
    assert whole == pytest.approx(kernel, abs=0.12)
    assert cpu.used(t_end - 0.3, t_end) < 0.05
    assert math.isnan(cpu.used(cpu.samples[0][0] - 1.0, t_end))


def test_compare_run_is_void_when_a_system_failed(bp):
    v = bp.compare_run(row("orbslam-hgcn", 160, 30.0), {"system": "ORB-SLAM3", "error": "signal 11"}, 160)
    assert not v["valid"] and v["failed"] == [("ORB-SLAM3", 0, "the run failed")]


def test_median_ratio_takes_only_the_valid_runs(bp):
    runs = [
        bp.compare_run(row("orbslam-hgcn", 160, 30.0), row("ORB-SLAM3", 159, 20.0), 160),  # 1.5x
        bp.compare_run(row("orbslam-hgcn", 160, 90.0), row("ORB-SLAM3", 28, 10.0), 160),  # 9x, void
        bp.compare_run(row("orbslam-hgcn", 160, 25.0), row("ORB-SLAM3", 158, 20.0), 160),  # 1.25x
    ]
    med, ratios = bp.median_ratio(runs)
    assert ratios == pytest.approx([1.5, 1.25])
    assert med == pytest.approx(1.375)


def test_median_ratio_is_none_without_a_valid_run(bp):
    runs = [bp.compare_run(row("orbslam-hgcn", 160, 30.0), row("ORB-SLAM3", 28, 20.0), 160)]
    assert bp.median_ratio(runs) is None
    assert bp.median_ratio([]) is None


# --- accuracy beside speed ---------------------------------------------------------------


def test_orbslam3s_euroc_trajectory_becomes_a_tum_file_that_scores_like_ours(bp, tmp_path):
    """ORB-SLAM3 writes a monocular camera trajectory only in EuRoC's layout (nanoseconds);
    rewritten as TUM it must give the same poses at the same times, and score 0 against
    itself."""
    from orbslam_hgcn.trajectory import read_tum

    stamps = [1341845820.819654, 1341845822.495728, 1341845823.5]
    rows = [(0.0, 0.0, 0.0), (0.1, -0.2, 0.3), (0.4, 0.1, 1.2)]
    src = tmp_path / "CameraTrajectory_euroc.txt"
    src.write_text("".join(f"{t * 1e9:.6f} {x} {y} {z} 0 0 0 1\n" for t, (x, y, z) in zip(stamps, rows)))
    dst = tmp_path / "CameraTrajectory.txt"
    assert bp.euroc_to_tum(src, dst) == 3
    traj = read_tum(dst)
    assert traj.timestamps == pytest.approx(stamps, abs=1e-6)
    assert traj.positions.ravel() == pytest.approx([v for r in rows for v in r])
    ate = bp.keyframe_ate(traj, dst)
    assert ate["pairs"] == 3 and ate["rmse_m"] == pytest.approx(0.0, abs=1e-9)
    assert bp.euroc_to_tum(tmp_path / "missing.txt", tmp_path / "none.txt") == 0
    assert not (tmp_path / "none.txt").exists()
    assert "error" in bp.keyframe_ate(traj, tmp_path / "none.txt")


def test_rows_and_medians_carry_keyframe_and_camera_ate(bp):
    def full(ate_cm, cam_cm):
        return {"system": "ORB-SLAM3", "frames": 160, "tracked": 159, "lost": 0, "maps": 1, "keyframes": 88,
                "ate": {"rmse_m": ate_cm / 100, "pairs": 88}, "cam_ate": {"rmse_m": cam_cm / 100, "pairs": 159},
                "fps": 10.0, "frame_ms": 30.0, "loop_s": 16.0, "start_s": 3.0, "shutdown_s": 0.1, "cpu_s": 9.0,
                "cpu_ms_per_frame": 90.0}

    line = bp.format_row("1", full(36.5, 38.25))
    assert "36.50" in line and "38.25" in line
    med = bp.median_row([full(30.0, 40.0), full(36.0, 34.0), full(40.0, 41.0)], "ORB-SLAM3")
    assert med["ate"]["rmse_m"] == pytest.approx(0.36) and med["cam_ate"]["rmse_m"] == pytest.approx(0.40)
    assert med["cam_ate"]["pairs"] == "3/3"
    assert bp.ate_cm(med["cam_ate"]) == "40.00 cm" and bp.ate_cm({"error": "none"}) == "n/a"


# --- the gate ------------------------------------------------------------------------------


def test_gate_passes_at_98_percent_of_the_median_run(bp):
    assert bp.gate_verdict([159, 159, 126], 160) == (True, 159.0)
    assert bp.gate_verdict([157], 160)[0]  # 157 / 160 = 98.1%
    assert not bp.gate_verdict([156], 160)[0]  # 97.5%
    assert not bp.gate_verdict([28, 31, 160], 160)[0]
    assert not bp.gate_verdict([], 160)[0]


def test_gate_counts_a_failed_run_as_nothing_tracked(bp):
    assert bp.tracked_of({"system": "ORB-SLAM3", "error": "exit status 1"}) == 0
    assert bp.tracked_of(row("ORB-SLAM3", 159, 1.0)) == 159


# --- timing --------------------------------------------------------------------------------


def test_ours_spans_split_the_frames_wall_time_at_the_last_pose(bp):
    # 15.9 camera seconds at 2x real time: 7.95 s to the last pose, the rest of 9 s shutdown
    loop, shut = bp.ours_spans(9.0, 2.0, 15.9)
    assert loop == pytest.approx(7.95) and shut == pytest.approx(1.05)
    loop, shut = bp.ours_spans(3.0, None, 0.0)
    assert loop == 3.0 and math.isnan(shut)
    assert bp.fps(160, 8.0) == 20.0 and bp.fps(160, float("nan")) == 0.0


# --- the vocabulary ------------------------------------------------------------------------


def test_default_vocabulary_is_beside_the_repository(bp):
    assert bp.DEFAULT_PEER_VOCAB == REPO.parent / "shared" / "peer" / "ORBvoc_real_k10L6.txt.gz"


def test_a_gz_vocabulary_is_gunzipped_into_the_cache(bp, tmp_path):
    src = tmp_path / "voc.txt.gz"
    src.write_bytes(gzip.compress((HEADER + "0 1 " + "0 " * 32 + "1\n").encode()))
    path, exported = bp.resolve_peer_vocab(str(src), cache=tmp_path / "cache")
    assert not exported and path == tmp_path / "cache" / "voc.txt"
    assert path.read_text().startswith(HEADER)
    # the default, given as such, the same way
    path2, _ = bp.resolve_peer_vocab(None, cache=tmp_path / "cache2", default=src)
    assert path2.read_text() == path.read_text()


def test_a_text_vocabulary_is_used_as_it_is(bp, tmp_path):
    src = tmp_path / "ORBvoc.txt"
    src.write_text(HEADER)
    assert bp.resolve_peer_vocab(str(src), cache=tmp_path / "cache") == (src.resolve(), False)
    other = tmp_path / "vocabulary.dat"  # no .txt name, but DBoW2's header
    other.write_text(HEADER)
    assert bp.resolve_peer_vocab(str(other), cache=tmp_path / "cache")[0] == other.resolve()


def test_an_orbslam_hgcn_vocabulary_goes_through_the_export(bp, tmp_path):
    seen = []

    def export(source, cache):
        seen.append(source)
        return cache / "exported.txt"

    npz = tmp_path / "tree.npz"
    npz.write_bytes(b"PK")
    assert bp.resolve_peer_vocab(str(npz), cache=tmp_path, export=export) == (tmp_path / "exported.txt", True)
    assert bp.resolve_peer_vocab("orb", cache=tmp_path, export=export)[1]
    assert seen == [str(npz), "orb"]


def test_a_missing_vocabulary_is_a_clear_error(bp, tmp_path):
    with pytest.raises(bp.VocabularyNotFound, match="--peer-vocab FILE"):
        bp.resolve_peer_vocab(None, cache=tmp_path, default=tmp_path / "absent.txt.gz")
    with pytest.raises(bp.VocabularyNotFound, match="file not found"):
        bp.resolve_peer_vocab(str(tmp_path / "absent.txt"), cache=tmp_path)
    with pytest.raises(bp.VocabularyNotFound, match="nor a shipped vocabulary"):
        bp.resolve_peer_vocab("no_such_vocabulary", cache=tmp_path)
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"\x00\x01")
    with pytest.raises(bp.VocabularyNotFound, match="neither a DBoW2"):
        bp.resolve_peer_vocab(str(junk), cache=tmp_path)


def test_the_bench_says_so_when_the_vocabulary_is_missing(tmp_path):
    """Exit status 2, a line naming the option, no traceback (before any ORB-SLAM3 check)."""
    proc = subprocess.run([sys.executable, str(REPO / "bench" / "bench_peer.py"), "--sequence", str(tmp_path),
                           "--peer-vocab", str(tmp_path / "absent.txt.gz")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "file not found" in proc.stdout and "Traceback" not in proc.stdout + proc.stderr
