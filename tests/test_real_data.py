"""Real images (../shared/data): initialisation on forward driving (KITTI) and on a
hand-held camera (TUM), short real KITTI runs against the ground truth, and the
distorted EuRoC camera end to end.

KITTI odometry: Geiger, Lenz and Urtasun, CVPR 2012 (CC BY-NC-SA 3.0); TUM RGB-D: Sturm et
al., IROS 2012 (CC BY 4.0); EuRoC MAV: Burri et al., IJRR 2016 (ASL, ETH Zurich).
"""

import json
import time

import numpy as np
import pytest

from orbslam_hgcn.cli import main
from orbslam_hgcn.config import ORBConfig, dataset_settings
from orbslam_hgcn.datasets import open_sequence
from orbslam_hgcn.datasets.base import Sequence
from orbslam_hgcn.features.orb import ORBExtractor
from orbslam_hgcn.geometry.se3 import angle_between_deg, inv_T, rotation_angle_deg
from orbslam_hgcn.map import Frame, Map, check_invariants
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.app.run import run_dataset, trajectory_ate
from orbslam_hgcn.runtime.system import Configs, System
from orbslam_hgcn.tracking.initializer import MonocularInitializer


class _Slice(Sequence):
    """Frames ``lo`` to ``hi - 1`` of ``base``."""

    def __init__(self, base: Sequence, lo: int, hi: int) -> None:
        self.base, self.lo, self.hi = base, lo, hi
        self.name, self.camera, self.ground_truth, self.color = base.name, base.camera, base.ground_truth, False

    def __len__(self) -> int:
        return self.hi - self.lo

    def __getitem__(self, i: int):
        return self.base[self.lo + i]

    @property
    def timestamps(self) -> np.ndarray:
        return self.base.timestamps[self.lo : self.hi]


def _initialise(seq: Sequence, start: int, n_features: int, max_frames: int = 30, gt_tol: float = 0.01):
    """Feed frames from ``start`` to a fresh initialiser until it makes a map; returns the
    initial map and the estimated and ground-truth motions between its two keyframes."""
    ext = ORBExtractor(ORBConfig(n_features=n_features))
    init, m = MonocularInitializer(), Map()
    for i in range(start, min(start + max_frames, len(seq))):
        rec = seq[i]
        f = Frame(i, rec.timestamp, seq.camera, ext.extract(rec.image, seq.camera))
        res = init.add_frame(f, FeatureGrid(f.keypoints, seq.camera), m)
        if res is not None:
            gt = seq.ground_truth
            a, b = gt.nearest(res.kf_first.timestamp, gt_tol), gt.nearest(res.kf_second.timestamp, gt_tol)
            T21 = res.kf_second.T_cw @ res.kf_first.T_wc
            G21 = inv_T(gt.poses[b]) @ gt.poses[a]
            return res, m, T21, G21
    pytest.fail(f"no initialisation within {max_frames} frames from frame {start}")


@pytest.mark.parametrize("start", [40, 80])
def test_initialisation_on_real_forward_driving(kitti_sample, start):
    """KITTI's settings (2000 features, twice that while initialising): a map within 5
    frames, motion within 1 deg of rotation and 3 deg of translation direction.

    ORB-SLAM's own search (reference level-0 keypoints in a 100 px window) never reached
    1 deg of parallax on these frames. Frames 40 and 80 are used because at frames 0-2
    both this initialiser and OpenCV's five-point solver put the direction 2.5-3.3 deg
    from the ground truth's."""
    seq = open_sequence("kitti", kitti_sample)
    res, m, T21, G21 = _initialise(seq, start, 4000)
    assert res.kf_second.frame_id - start <= 5
    assert rotation_angle_deg(T21[:3, :3] @ G21[:3, :3].T) < 1.0
    assert angle_between_deg(T21[:3, 3], G21[:3, 3]) < 3.0
    assert len(res.point_ids) >= 100 and check_invariants(m) == []


def test_initialisation_on_real_hand_held_frames(tum_sample):
    """The TUM sample: 16 frames over 2 cm, then one 3.4 s later. The followed keypoints
    reach the far frame and the map is made from it, the motion within 2 deg of rotation
    and 3 deg of direction (the ground truth starts 67 ms after frame 0, when the camera
    has moved about 3 mm of the 71 cm)."""
    seq = open_sequence("tum", tum_sample)
    res, m, T21, G21 = _initialise(seq, 0, 2000, gt_tol=0.1)
    assert res.kf_second.frame_id == 16
    assert rotation_angle_deg(T21[:3, :3] @ G21[:3, :3].T) < 2.0
    assert angle_between_deg(T21[:3, 3], G21[:3, 3]) < 3.0


# Measured (sequential, loop closing on, the default k-means vocabulary, KITTI's settings:
# a keyframe at most every other frame): 32 keyframes, keyframe ATE 21.4 cm, camera ATE
# 18.0 cm; the sequential run is reproducible. The bounds leave 2 keyframes and over 5 cm of
# ATE beyond those, for other BLAS and compiler builds. (With the 0.3 s interval of other
# cameras: 22 keyframes, 23.6 and 18.3 cm.)
KITTI_60_KEYFRAMES = (30, 34)
KITTI_60_ATE_M = 0.27


def test_short_real_kitti_run_as_a_user_runs_it(kitti_sample, tmp_path, capsys):
    """The first 60 KITTI frames (52 m) through ``orbslam-hgcn run SEQ --out OUT``, first with
    the command's defaults (stages in worker threads, frames taken at the camera's 10 Hz,
    loop closing on with the default (k-means) vocabulary), then with ``--sequential``; KITTI's
    settings are picked from calib.txt both times, and the ATE printed is stats.json's.

    A paced threaded run drops the frames it falls behind on, so how many it tracks depends
    on the machine's load (on a 2-core machine at load average 20 it dropped
    57 of 60): the threaded run is held to its accounting and wiring, the sequential one to
    the figures. Sequential: the map is made on frame 1 or 2, every frame is tracked and
    keyframes come at most every 0.15 s of camera time once the map has 5 (KITTI's settings:
    every other frame); most of the ATE
    comes from the first 10 frames (frames 40-99 alone: 5 cm, next test)."""
    out = tmp_path / "threaded"
    assert main(["run", str(kitti_sample), "--out", str(out), "--max-frames", "60", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    s = json.loads((out / "stats.json").read_text())
    assert s["threads"]["sequential"] is False and s["threads"]["speed"] == 1.0 and s["complete"] is True
    assert s["settings"]["dataset"] == "kitti_00-02" and s["settings"]["orb_features"] == 2000
    assert "KMeansVocabulary" in s["vocabulary"] and "loops" in s["loop_closing"]
    f = s["frames"]
    assert f["frames"] == 60 == sum(f[k] for k in ("tracked", "lost", "not_initialized", "reset", "dropped",
                                                    "unreadable", "other_maps"))
    for name, a in s["ate_sim3"].items():
        assert ("rmse_m" in a) == (f"ATE Sim(3) ({name}," in printed)
        if "rmse_m" in a:
            assert f"rmse {100 * a['rmse_m']:.2f} cm" in printed

    out = tmp_path / "sequential"
    assert main(["run", str(kitti_sample), "--out", str(out), "--max-frames", "60", "--no-progress",
                 "--sequential"]) == 0
    printed = capsys.readouterr().out
    s = json.loads((out / "stats.json").read_text())
    assert s["settings"]["dataset"] == "kitti_00-02" and "KMeansVocabulary" in s["vocabulary"]
    init = [e["frame"] for e in s["events"] if e["event"] == "initialized"]
    assert init and init[0] <= 2
    assert s["frames"]["tracked"] == 60 and s["map_resets"] == 0
    assert KITTI_60_KEYFRAMES[0] <= s["keyframes"] <= KITTI_60_KEYFRAMES[1]
    ate = s["ate_sim3"]
    assert f"rmse {100 * ate['keyframes']['rmse_m']:.2f} cm" in printed
    assert ate["keyframes"]["rmse_m"] < KITTI_60_ATE_M and ate["camera"]["rmse_m"] < KITTI_60_ATE_M


def test_real_kitti_frames_40_to_99_against_ground_truth(kitti_sample):
    """60 frames of straight driving from frame 40, sequential, KITTI's settings: keyframe
    ATE 6.06 cm here (29 keyframes); with local BA in ORB-SLAM's order
    (local_mapping.ba_beside_mapping false) 5.01 cm, which the full 160 frames reverse
    (37.16 against 38.79 cm)."""
    seq = open_sequence("kitti", kitti_sample)
    path, settings = dataset_settings(seq.camera, "kitti")
    system = System(seq.camera, Configs.from_layers([(settings, path)]), sequential=True)
    system.run(_Slice(seq, 40, 100), progress=False)
    stats = system.stats()
    assert stats["frames"]["tracked"] >= 58 and stats["map_resets"] == 0
    ate = trajectory_ate(seq.ground_truth, system.keyframe_trajectory())
    assert ate["pairs"] >= 12 and ate["rmse_m"] < 0.07, ate  # 6.06 cm measured; 1 cm margin
    assert check_invariants(system.map) == []


def test_euroc_sample_runs_end_to_end_with_its_distortion(euroc_sample, tmp_path):
    """95 real frames with radial-tangential distortion, threaded as a user runs them: the
    settings of the EuRoC camera, no error, every frame accounted for. The vehicle hardly
    moves (1.5 cm), so no map is expected."""
    r = run_dataset(euroc_sample, tmp_path / "run", progress=False)
    f = r.stats["frames"]
    assert r.stats["settings"]["dataset"] == "euroc_cam0"
    assert f["frames"] == 95 == f["tracked"] + f["lost"] + f["not_initialized"] + f["reset"] + f["dropped"]


def _stalled_mapping_run(kitti_sample, **threads) -> System:
    """Threaded, paced run over KITTI frames 40-89 (the CLI's defaults: KITTI's settings,
    the HGCN vocabulary, with ``threads`` settings) whose local mapping stalls 0.8 s on its
    seventh keyframe, as when another job takes the CPU: at 10 Hz forward driving the
    points of a keyframe leave the view within about half a second."""
    from orbslam_hgcn.vocabulary import load_vocabulary

    seq = open_sequence("kitti", kitti_sample)
    path, settings = dataset_settings(seq.camera, "kitti")
    c = Configs.from_layers([(settings, path), ({"threads": threads}, "test")])
    system = System(seq.camera, c, vocabulary=load_vocabulary("hgcn"), sequential=False)
    process = system.mapper.process

    def stalling(kf):
        if kf.id == 6:
            time.sleep(0.8)
        return process(kf)

    system.mapper.process = stalling
    system.run(_Slice(seq, 40, 90), progress=False)
    return system


def test_a_recorded_sequence_beside_a_stalled_mapping_tracks_every_frame_late(kitti_sample):
    """The defaults: the tracker waits for local mapping to finish each keyframe
    (threads.sync_mapping_s), the stall included, and the frames that arrive meanwhile
    wait: every frame is tracked, none dropped, and the run records how late it fell."""
    s = _stalled_mapping_run(kitti_sample).stats()
    assert s["map_resets"] == 0 and s["frames"]["lost"] == 0, s["frames"]
    assert s["frames"]["tracked"] == 50 and s["frames"]["dropped"] == 0, s["frames"]
    assert s["timing_ms"]["mapping_sync"]["max"] > 700.0  # the stall was waited for
    assert s["real_time"]["lag_ms"]["count"] == 50 and s["real_time"]["lag_ms"]["max"] > 700.0


def test_a_due_keyframe_is_mapped_before_tracking_loses_the_map(kitti_sample):
    """Without the mapping sync (sync_mapping_s 0, as ORB-SLAM's threads): when a frame
    tracks fewer than keyframe_urgent_inliers points and mapping is busy, the tracker
    waits (at most threads.keyframe_wait_s) for mapping to take a keyframe, makes it from
    that frame and waits for its points, and the frames that arrive meanwhile wait: the
    run keeps its map through the stall. (Without that wait the same run was lost in some
    runs and not in others, depending on where the stall falls among the frames, so this
    test does not assert the run without it.)"""
    s = _stalled_mapping_run(kitti_sample, sync_mapping_s=0.0, keyframe_wait_s=0.5).stats()
    assert s["map_resets"] == 0 and s["frames"]["lost"] == 0, s["frames"]
    assert s["timing_ms"]["keyframe_wait"]["count"] > 0
    assert s["frames"]["tracked"] == 50 and s["frames"]["dropped"] == 0, s["frames"]


def _mapping_stalled_until_released(kitti_sample, without_the_wait: bool) -> tuple[System, dict]:
    """Threaded, paced run over KITTI frames 40-89 (the CLI's defaults) whose local mapping
    stops before its seventh keyframe until released, never by the clock: by the tracker
    entering its wait for a due keyframe (threads.mapping_sync "due"), by the track being
    lost, or after the last frame. ``without_the_wait``: from the stall on the tracker does not
    wait for a due keyframe, as ORB-SLAM's threads (a keyframe due while mapping is busy is
    skipped).
    Also how the stall ended."""
    import threading

    from orbslam_hgcn.vocabulary import load_vocabulary

    seq = open_sequence("kitti", kitti_sample)
    path, settings = dataset_settings(seq.camera, "kitti")
    c = Configs.from_layers([(settings, path), ({"threads": {"keyframe_wait_s": 0.0, "mapping_sync": "due"}}, "test")])
    assert c.threads.sync_mapping_s > 0  # the default bound
    system = System(seq.camera, c, vocabulary=load_vocabulary("hgcn"), sequential=False)
    process, track, due = system.mapper.process, system.tracker.track, system._map_due_keyframe
    release, ended = threading.Event(), {"by": None, "frames_stalled": 0}
    stalled = threading.Event()

    def stalling(kf):
        if kf.id == 6:
            stalled.set()
            release.wait(60.0)
        return process(kf)

    def end(by):
        if stalled.is_set() and not release.is_set():
            ended["by"] = by
            release.set()

    def tracking(frame):
        result = track(frame)
        ended["frames_stalled"] += int(stalled.is_set() and not release.is_set())
        if result.lost:
            end("lost")
        if frame.id == 89:
            end("last frame")
            release.set()
        return result

    def waiting(result, stages):
        if stalled.is_set():
            if without_the_wait:
                return
            end("wait")
        due(result, stages)

    system.mapper.process, system.tracker.track, system._map_due_keyframe = stalling, tracking, waiting
    system.run(_Slice(seq, 40, 90), progress=False)
    assert stalled.is_set()
    return system, ended


@pytest.mark.parametrize("without_the_wait", [False, True])
def test_a_keyframe_due_while_mapping_stalls_waits_and_keeps_the_track(kitti_sample, without_the_wait):
    """Local mapping stalls (never by the clock) on a keyframe of forward driving. With
    threads.mapping_sync "due" the next keyframe due finds it busy, the tracker waits for it there, makes that
    keyframe and tracks every frame. Without that wait the tracker drives on over a map
    that no longer grows, and the track is lost within the 50 frames."""
    system, ended = _mapping_stalled_until_released(kitti_sample, without_the_wait)
    s = system.stats()
    if without_the_wait:
        assert ended["by"] == "lost" and ended["frames_stalled"] > 0, ended  # lost during the stall
        assert s["frames"]["lost"] > 0 or s["map_resets"] > 0, s["frames"]
    else:
        assert ended["by"] == "wait" and ended["frames_stalled"] <= 5, ended  # released by the next due keyframe
        assert s["map_resets"] == 0 and s["frames"]["lost"] == 0, s["frames"]
        assert s["frames"]["tracked"] == 50 and s["frames"]["dropped"] == 0, s["frames"]
