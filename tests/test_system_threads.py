"""The threaded system and its optimiser process: reproducible sequential runs, threaded runs
that end cleanly and track as well, stage errors reaching the caller, and the child-process
solver giving the in-process results."""

import contextlib
import dataclasses
import gc
import json
import multiprocessing
import os
import threading
import time
import weakref

import cv2

import numpy as np
import pytest

from orbslam_hgcn.backend.problem import as_problem
from orbslam_hgcn.backend.pose_graph import relative_sim3
from orbslam_hgcn.backend.solver import InProcessSolver, ProcessSolver, SolverError
from orbslam_hgcn.cli import main
from orbslam_hgcn.config import BackendConfig, ORBConfig, ThreadsConfig, load_camera
from orbslam_hgcn.datasets import open_sequence
from orbslam_hgcn.datasets.base import Sequence
from orbslam_hgcn.errors import ConfigError
from orbslam_hgcn.evaluation.ate import evaluate
from orbslam_hgcn.features.orb import ORBExtractor
from orbslam_hgcn.map import check_invariants
from orbslam_hgcn.map.window import apply_window, local_window
from orbslam_hgcn.runtime.extraction import ExtractionError, ExtractionProcess
from orbslam_hgcn.runtime.locks import TrackingFirstLock, first
from orbslam_hgcn.runtime.stages import ThreadedStages
from orbslam_hgcn.runtime.system import Configs, System
from orbslam_hgcn.runtime.worker import WorkerError
from orbslam_hgcn.tracking.tracker import TrackingState

from backend_fixtures import drifted_loop, make_scene, perturb_pose

N_FRAMES = 50  # initialisation takes about 22 frames of this sequence


def _stage_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("orbslam-") and t.is_alive()]


def _assert_nothing_left() -> None:
    assert _stage_threads() == []
    assert multiprocessing.active_children() == []


@pytest.fixture(scope="module")
def seq(synth_replay_100) -> Sequence:
    return open_sequence("tum", synth_replay_100)


@pytest.fixture(scope="module")
def sequential_runs(seq):
    runs = []
    for _ in range(2):
        system = System(seq.camera, sequential=True)
        system.run(seq, N_FRAMES, progress=False)
        runs.append(system)
    return runs


def _threads(**kw) -> Configs:
    c = Configs()
    return dataclasses.replace(c, threads=dataclasses.replace(c.threads, **kw))


@pytest.fixture(scope="module")
def threaded_run(seq):
    # As ORB-SLAM's threads: tracking goes on while local mapping works (no sync).
    system = System(seq.camera, _threads(sync_mapping_s=0.0), sequential=False)
    summary = system.run(seq, N_FRAMES, progress=False)
    return system, summary


def test_threaded_run_with_mapping_sync_equals_the_sequential_run(seq, sequential_runs):
    """With threads.mapping_sync "each" (within sync_mapping_s, default 5 s) a paced
    threaded run gives the sequential run's result, bit for bit: the frames that arrive
    while mapping finishes a keyframe wait, none is dropped."""
    system = System(seq.camera, _threads(mapping_sync="each"), sequential=False)
    system.run(seq, N_FRAMES, progress=False)
    ref = sequential_runs[0]
    for get in (System.keyframe_trajectory, System.camera_trajectory):
        a, b = get(system), get(ref)
        np.testing.assert_array_equal(a.timestamps, b.timestamps)
        np.testing.assert_array_equal(a.poses, b.poses)
    assert system.timings["mapping_sync"] and max(system.timings["mapping_sync"]) > 0
    _assert_nothing_left()


def _slow_mapping_run(seq, until_starved: bool = False, **threads) -> tuple[System, list[int]]:
    """A paced threaded run of the replay whose local mapping takes 0.1 s more per keyframe
    and stalls on its fourth keyframe, 1.5 s or (``until_starved``) until the tracker finds
    a keyframe due and mapping busy (at most 20 s), with keyframes whenever the rules'
    timing allows (the slow replay rarely loses 10% of the reference keyframe's points);
    also the frames on which a keyframe was made after waiting for mapping
    (threads.keyframe_wait_s)."""
    c = _threads(**threads)
    c = dataclasses.replace(c, tracking=dataclasses.replace(c.tracking, ref_ratio=2.0))
    system = System(seq.camera, c, sequential=False)
    process, keyframe_now, starved = system.mapper.process, system.tracker.keyframe_now, system._map_starved_frame
    made_after_wait: list[int] = []
    release = threading.Event()

    def slow(kf):
        if kf.id == 3 and until_starved:
            release.wait(20.0)
        time.sleep(1.5 if kf.id == 3 and not until_starved else 0.1)
        return process(kf)

    def starving(*args):
        release.set()
        return starved(*args)

    def recorded(frame, n_in, *args):
        kf = keyframe_now(frame, n_in, *args)
        if kf is not None:
            made_after_wait.append(kf.frame_id)
        return kf

    system.mapper.process, system.tracker.keyframe_now, system._map_starved_frame = slow, recorded, starving
    system.run(seq, progress=False)
    s = system.stats()
    assert s["frames"]["lost"] == 0 and s["map_resets"] == 0 and s["frames"]["tracked"] >= 75
    return system, made_after_wait


def _camera_pose_errors(seq, system: System) -> tuple[np.ndarray, np.ndarray]:
    """Errors (m) of the camera trajectory after its Sim(3) alignment to the ground truth:
    of every frame, and of the frames that are keyframes (their poses are the keyframes'),
    so that both are measured in one alignment (a keyframe trajectory of a few poses,
    aligned on its own, fits the ground truth closer than its poses are)."""
    cam = system.camera_trajectory()
    ev = evaluate(seq.ground_truth, cam, align="sim3")
    assert ev.num_pairs == len(cam)
    is_kf = np.isin(cam.timestamps, system.keyframe_trajectory().timestamps)
    return ev.ate_errors, ev.ate_errors[is_kf]


@pytest.mark.parametrize("mapping_sync", ["due", "each", "points"])
def test_camera_poses_of_a_slow_mapping_run_are_as_good_as_its_keyframes(seq, mapping_sync):
    """Local BA moves keyframes after frames were written relative to them, and mapping
    stalls for 1.5 s: the tracker waits for the stalled keyframe to be mapped (threads.
    sync_mapping_s; "due": when the next keyframe is due, "each": before the next frame),
    so that the frames of the stall are not tracked on against a stale local map, and the
    written poses stay as good as the keyframes': camera ATE within 1.1 times the
    keyframes' (or 0.5 mm more) and no frame off by more than 3 times the keyframes'
    largest error; with "each" (no frame tracked without the newest keyframe's points)
    camera ATE under 4 mm (2.5 mm here, keyframes 3.9 mm; "due" 4.3-5.0 mm, keyframes
    6.2 mm: with mapping 0.1 s slower per keyframe, the frames after each keyframe are
    tracked without its new points; "points" 3.6 mm, keyframes 4.9 mm). Tracking on without the wait (sync_mapping_s 0, as ORB-SLAM's threads), the frames of the stall are tracked against
    a stale local map: camera ATE 5.1 mm, max 10.7 mm, against keyframes' 4.3 and 5.5 mm."""
    system, _ = _slow_mapping_run(seq, mapping_sync=mapping_sync)
    assert system.timings["mapping_sync"] and max(system.timings["mapping_sync"]) > 1000.0  # the stall
    cam, kf = _camera_pose_errors(seq, system)
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    print(f"{mapping_sync}: camera ATE {1000 * rms(cam):.2f} mm (max {1000 * cam.max():.2f}), "
          f"keyframes {1000 * rms(kf):.2f} mm (max {1000 * kf.max():.2f})")
    assert len(kf) >= 4
    assert rms(cam) <= 1.1 * rms(kf) + 0.0005, (rms(cam), rms(kf))
    assert cam.max() <= 3.0 * kf.max(), (cam.max(), kf.max())
    if mapping_sync == "each":
        assert rms(cam) < 0.004, rms(cam)
    _assert_nothing_left()


def test_the_frame_after_a_keyframe_is_tracked_between_its_new_points_and_its_local_ba(seq, monkeypatch):
    """threads.mapping_sync "points": after handing a keyframe to local mapping the
    tracker waits until its new points are triangulated and fused; mapping then solves
    the local BA but holds before writing it back until the next frame is tracked, and
    writes it (and culls) before the frame after that. With the fourth keyframe's fusion
    slowed by 0.3 s: the next frame is tracked after that fusion (the wait is timed),
    against the keyframe's new points, and before its local BA is written, which happens
    before the following frame is tracked. (With "each" the next frame comes after the
    local BA; without any wait, before the new points exist.)"""
    import orbslam_hgcn.mapping.local_mapper as local_mapper

    triangulate, fuse, write = (
        local_mapper.create_new_points, local_mapper.search_in_neighbors, local_mapper.apply_window
    )
    events: list[tuple[str, int]] = []
    new_points: set[int] = set()
    tracked_new: dict[int, int] = {}
    mapping: list = []  # the keyframe being mapped

    def triangulation(m, kf, cfg):
        mapping[:] = [kf]
        new = triangulate(m, kf, cfg)
        if kf.id == 3:
            new_points.update(int(p) for p in new)
            events.append(("triangulated", kf.frame_id))
        return new

    def slow_fusion(m, kf, cfg):
        out = fuse(m, kf, cfg)
        if kf.id == 3:
            time.sleep(0.3)
            events.append(("fused", kf.frame_id))
        return out

    def writing(m, w, *args):
        if mapping[0].id == 3:
            events.append(("BA written", mapping[0].frame_id))
        return write(m, w, *args)

    monkeypatch.setattr(local_mapper, "create_new_points", triangulation)
    monkeypatch.setattr(local_mapper, "search_in_neighbors", slow_fusion)
    monkeypatch.setattr(local_mapper, "apply_window", writing)
    system = System(seq.camera, _threads(mapping_sync="points"), sequential=False)
    track = system.tracker.track

    def tracking(frame):
        events.append(("track", frame.id))
        result = track(frame)
        if new_points:
            ids = frame.point_ids[frame.point_ids >= 0]
            tracked_new[frame.id] = len(new_points & set(int(p) for p in ids))
        events.append(("tracked", frame.id))
        return result

    system.tracker.track = tracking
    system.run(seq, N_FRAMES, progress=False)
    f = next(i for e, i in events if e == "triangulated")
    order = [e for e in events if e[0] in ("triangulated", "fused", "BA written") or e[1] in (f + 1, f + 2)]
    assert order == [("triangulated", f), ("fused", f), ("track", f + 1), ("tracked", f + 1), ("BA written", f),
                     ("track", f + 2), ("tracked", f + 2)], order
    assert len(new_points) >= 20 and tracked_new[f + 1] >= 10, (len(new_points), tracked_new)
    assert max(system.timings["mapping_sync"]) > 250.0  # the slow fusion was waited for
    s = system.stats()
    assert s["frames"]["lost"] == 0 and s["map_resets"] == 0 and s["threads"]["mapping_sync"] == "points"
    _assert_nothing_left()


def test_threaded_runs_with_mapping_sync_points_are_identical(seq):
    """With threads.mapping_sync "points" local mapping works while the next frames
    arrive, yet every frame is tracked against the same map in every run (mapping holds
    before changing the map after a keyframe's new points until the next frame is
    tracked, and the tracker waits for it at fixed frames): two paced threaded runs give
    the same trajectories, bit for bit."""
    runs = []
    for _ in range(2):
        system = System(seq.camera, _threads(mapping_sync="points"), sequential=False)
        system.run(seq, N_FRAMES, progress=False)
        runs.append(system)
    a, b = runs
    for get, n_min in ((System.camera_trajectory, 20), (System.keyframe_trajectory, 3)):
        ta, tb = get(a), get(b)
        assert len(ta) >= n_min
        np.testing.assert_array_equal(ta.timestamps, tb.timestamps)
        np.testing.assert_array_equal(ta.poses, tb.poses)
    _assert_nothing_left()


def test_a_frame_made_a_keyframe_after_waiting_for_mapping_has_its_keyframes_pose(seq):
    """Without the mapping sync a frame that found mapping busy when its keyframe was due
    waits for mapping to take it (threads.keyframe_wait_s) and becomes a keyframe after
    its pose was written: its written pose is then its keyframe's, moved by local BA like
    it (it was written relative to the old reference keyframe, 25-40 cm off its own
    keyframe's pose on loaded KITTI runs)."""
    system, made_after_wait = _slow_mapping_run(seq, until_starved=True, sync_mapping_s=0.0, keyframe_wait_s=3.0)
    assert made_after_wait  # the path under test was taken
    kfs, cam = system.keyframe_trajectory(), system.camera_trajectory()
    at = {t: i for i, t in enumerate(cam.timestamps)}
    for t, T_wc in zip(kfs.timestamps, kfs.poses):
        np.testing.assert_allclose(cam.poses[at[t]], T_wc, atol=1e-9)
    _assert_nothing_left()


def test_sequential_runs_are_identical(sequential_runs):
    a, b = sequential_runs
    for get, n_min in ((System.camera_trajectory, 20), (System.keyframe_trajectory, 3)):
        ta, tb = get(a), get(b)
        assert len(ta) >= n_min
        np.testing.assert_array_equal(ta.timestamps, tb.timestamps)
        np.testing.assert_array_equal(ta.poses, tb.poses)  # bit for bit
    assert a.map.n_points() == b.map.n_points()
    np.testing.assert_array_equal(a.map.positions(a.map.point_ids()), b.map.positions(b.map.point_ids()))


def test_threaded_run_completes_cleanly_and_tracks_as_well(seq, sequential_runs, threaded_run):
    system, summary = threaded_run
    assert summary.frames == N_FRAMES and not summary.interrupted
    _assert_nothing_left()
    stats, ref = system.stats(), sequential_runs[0].stats()
    assert stats["frames"]["lost"] == 0 and stats["map_resets"] == 0
    assert stats["frames"]["tracked"] == ref["frames"]["tracked"] >= 20
    assert stats["mapping_counts"]["keyframes"] >= 4  # local mapping did run
    assert check_invariants(system.map) == []
    # Accuracy comparable to the sequential run. Keyframes (the monocular result ORB-SLAM
    # reports): within twice its error, or 3 mm. Every frame's pose: without sync the
    # tracker runs ahead of local BA, so frames are tracked against points BA has not
    # refined yet, by how much depends on the timing of the threads. The camera ATE was
    # 2.3-5.2 mm over 21 runs of this run earlier, 2.5-6.6 mm over 13 runs with the faster
    # mapping of today (twice above the 6 mm bound used until then), against 1.9 mm in
    # order; so within five times its error, or 10 mm: a tracker that drifts still fails.
    for get, factor, floor in ((System.keyframe_trajectory, 2.0, 0.003), (System.camera_trajectory, 5.0, 0.010)):
        ate = evaluate(seq.ground_truth, get(system), align="sim3").ate.rmse
        ate_ref = evaluate(seq.ground_truth, get(sequential_runs[0]), align="sim3").ate.rmse
        assert ate < max(factor * ate_ref, floor), (ate, ate_ref)
    # Every frame got a latency figure and a flag saying whether a BA ran meanwhile.
    assert len(system.frame_optimising) == len(system.timings["frame"]) == N_FRAMES
    assert any(system.frame_optimising)


def test_prefetched_features_come_from_the_extractor_the_state_needs(seq, threaded_run):
    # Threaded runs extract frame i + 1 while frame i is tracked: the initial keyframes
    # must still have the initialisation extractor's features, the later ones the normal
    # extractor's, exactly as a direct extraction gives them.
    system, _ = threaded_run
    kfs = sorted(system.map.keyframes(), key=lambda k: k.id)
    n_init, n = system.init_extractor.config.n_features, system.extractor.config.n_features
    assert n_init == 2 * n
    assert len(kfs[0].keypoints) > 1.5 * n
    for kf in (kfs[0], kfs[-1]):
        extractor = system.init_extractor if kf is kfs[0] else system.extractor
        direct = extractor.extract(seq[kf.frame_id].image, seq.camera)
        np.testing.assert_array_equal(kf.keypoints.uv_raw, direct.uv_raw)
        np.testing.assert_array_equal(kf.keypoints.desc, direct.desc)
    assert len(kfs[-1].keypoints) <= n


def test_stage_exception_reaches_the_caller(seq):
    system = System(seq.camera, sequential=False)

    def broken(kf):
        raise RuntimeError(f"mapping broke on keyframe {kf.id}")

    system.mapper.process = broken
    with pytest.raises(WorkerError, match="mapping broke on keyframe") as info:
        system.run(seq, 40, progress=False)
    assert isinstance(info.value.__cause__, RuntimeError)
    _assert_nothing_left()


class _Interrupted(Sequence):
    """The first ``cut`` frames of ``base``, then Ctrl-C."""

    def __init__(self, base: Sequence, cut: int) -> None:
        self.base, self.cut = base, cut
        self.name, self.camera, self.ground_truth, self.color = base.name, base.camera, base.ground_truth, False

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, i: int):
        if i >= self.cut:
            raise KeyboardInterrupt
        return self.base[i]

    @property
    def timestamps(self) -> np.ndarray:
        return self.base.timestamps


def test_ctrl_c_stops_the_threads_and_keeps_the_map(seq):
    system = System(seq.camera, sequential=False)
    summary = system.run(_Interrupted(seq, 30), progress=False)
    assert summary.interrupted and summary.frames == 30
    _assert_nothing_left()
    assert system.stats()["frames"]["tracked"] > 0 and system.map.n_keyframes() >= 2


def test_cli_run_is_threaded_unless_sequential(synth_replay_100, tmp_path):
    for flag, sequential in (([], False), (["--sequential"], True)):
        out = tmp_path / str(sequential)
        args = ["run", str(synth_replay_100), "--dataset", "tum", "--out", str(out), "--no-loop", "--vocab", "none",
                "--max-frames", "26", "--no-progress", *flag]  # fmt: skip
        assert main(args) == 0
        stats = json.loads((out / "stats.json").read_text())
        assert stats["threads"]["sequential"] is sequential
        assert stats["frames"]["tracked"] > 0
        _assert_nothing_left()


class _Retimed(Sequence):
    """``base`` with its timestamps replaced by ``timestamps``."""

    def __init__(self, base: Sequence, timestamps: np.ndarray) -> None:
        self.base, self._t = base, np.asarray(timestamps, dtype=np.float64)
        self.name, self.camera, self.ground_truth, self.color = base.name, base.camera, None, False

    def __len__(self) -> int:
        return len(self._t)

    def __getitem__(self, i: int):
        return dataclasses.replace(self.base[i], timestamp=float(self._t[i]))

    @property
    def timestamps(self) -> np.ndarray:
        return self._t


def _slow_frames(system: System, frames: tuple[int, ...], seconds: float) -> list[int]:
    """Make the tracker of ``system`` take ``seconds`` more on ``frames``; returns the list
    of the frames it tracks, in order, filled as the run goes."""
    processed: list[int] = []
    track = system.tracker.track

    def slow_track(frame):
        processed.append(frame.id)
        if frame.id in frames:
            time.sleep(seconds)
        return track(frame)

    system.tracker.track = slow_track
    return processed


@pytest.mark.parametrize("speed", [1.0, 2.0])
def test_threaded_run_takes_frames_no_faster_than_their_timestamps(seq, speed):
    # A camera at 20 Hz, with the stream stopping for a minute before the last frame: each
    # frame is taken no earlier than its time (divided by the speed) after the first, and
    # the gap is waited for at most a second, the clock starting again from there.
    t = np.arange(12) * 0.05
    t[-1] = t[-2] + 60.0
    c = _threads(speed=speed)
    system = System(seq.camera, c, sequential=False)
    t0 = time.perf_counter()
    summary = system.run(_Retimed(seq, t), progress=False)
    wall = time.perf_counter() - t0
    assert summary.frames == 12
    started = np.asarray(system.frame_started) - system.frame_started[0]
    assert np.all(started[:-1] >= (t[:-1] - t[0]) / speed - 0.002), (started, t)
    assert started[-1] >= started[-2] + 0.9
    assert wall < 30.0  # not the minute of the gap
    assert system.stats()["threads"]["speed"] == speed
    # The run's time without its start-up: from the first frame's extraction to the stages
    # drained, so it spans the frames' pacing and the one-second wait of the gap.
    rt = system.stats()["real_time"]
    assert rt["startup_s"] >= 0.0 and rt["startup_s"] + rt["frames_wall_s"] <= wall
    assert rt["frames_wall_s"] >= (t[-2] - t[0]) / speed + 0.9
    _assert_nothing_left()


def test_a_live_source_behind_its_camera_drops_late_frames_and_counts_them(seq):
    """threads.drop_late (run --drop-late), a camera at 4 Hz, a queue of 0.5 s (the default
    threads.frame_buffer_s) and a tracker that takes 0.9 s more on frames 5 and 12: a frame
    is dropped unprocessed when the frames of the next 0.5 s have arrived by the time the
    system is ready for it, as a camera driver with that queue drops them, and counted;
    every other frame is processed, in order. Without drop_late (the default) every frame
    is processed and the run records how late it fell."""
    t = np.arange(20) * 0.25
    system = System(seq.camera, _threads(drop_late=True), sequential=False)
    assert system.configs.threads.frame_buffer_s == 0.5
    processed = _slow_frames(system, (5, 12), 0.9)
    summary = system.run(_Retimed(seq, t), progress=False)
    stats = system.stats()
    dropped = [r.frame_id for r in system.tracker.records if r.dropped]
    assert summary.frames == 20 and stats["frames"]["frames"] == 20
    assert stats["frames"]["dropped"] == len(dropped) >= 2
    assert sorted(processed + dropped) == list(range(20))  # each frame processed or dropped, once
    assert processed == sorted(processed)
    # Only frames delivered while a slow frame was being tracked are dropped.
    assert 5 in processed and 12 in processed
    assert set(dropped) <= {6, 7, 13, 14}, dropped
    assert stats["real_time"]["drop_late"] and stats["real_time"]["dropped"] == len(dropped)
    no_drop = System(seq.camera, sequential=False)
    processed = _slow_frames(no_drop, (5, 12), 0.9)
    no_drop.run(_Retimed(seq, t), 20, progress=False)
    rt = no_drop.stats()["real_time"]
    assert no_drop.stats()["frames"]["dropped"] == 0 and processed == list(range(20))
    assert not rt["drop_late"] and rt["lag_ms"]["count"] == 20
    assert rt["lag_ms"]["max"] >= 900.0  # frame 5's pose came after its 0.9 s stall
    # Behind the clock by then; caught up by the last frame, which is handed out on time.
    assert 0.5 < rt["real_time_factor"] <= 1.0
    _assert_nothing_left()


def test_extraction_runs_ahead_of_a_slow_tracker_by_prefetch_frames(seq):
    """threads.prefetch_frames: while the tracker tracks frame i, the extraction of frames
    i + 1 .. i + prefetch_frames may start in an unpaced run (one frame ahead while it
    initialises, and in paced runs). With a tracker that takes 150 ms more per frame, the
    extraction of frame i + 2 starts before frame i is tracked with 3, never with 1 or in a
    paced run behind its camera; with 6 (more than the reader's queue of 4 frames) frame
    i + 5's does. The poses are the same. The objects alive before the first frame are
    kept from the garbage collector during the run (gc.freeze), and released after it."""
    runs = {}
    for key, speed, depth in (("1", 0.0, 1), ("3", 0.0, 3), ("paced", 1.0, 3), ("6", 0.0, 6)):
        system = System(seq.camera, _threads(speed=speed, prefetch_frames=depth), sequential=False)
        track, ends, frozen = system.tracker.track, {}, []

        def slow_track(frame, track=track, ends=ends, frozen=frozen):
            frozen.append(gc.get_freeze_count() > 0)
            time.sleep(0.15)
            result = track(frame)
            ends[frame.id] = time.perf_counter()
            return result

        system.tracker.track = slow_track
        system.run(seq, 30, progress=False)
        assert all(frozen) and len(frozen) == 30 and gc.get_freeze_count() == 0
        started = np.asarray(system.frame_started)
        tracking = [r.frame_id for r in system.tracker.records if r.state == TrackingState.OK][2:]
        lead = depth - 1 if key == "6" else 2
        ahead = [i for i in tracking if i + lead < 30 and started[i + lead] < ends[i]]
        runs[key] = (ahead, [i for i in tracking if i + lead < 30], system.camera_trajectory())
        _assert_nothing_left()
    assert runs["1"][0] == [] and runs["paced"][0] == []
    for key in ("3", "6"):
        assert len(runs[key][0]) >= 0.8 * len(runs[key][1]), (key, runs[key][0])
    np.testing.assert_allclose(runs["1"][2].poses, runs["3"][2].poses, atol=1e-9)
    np.testing.assert_allclose(runs["1"][2].poses, runs["6"][2].poses, atol=1e-9)
    with pytest.raises(ConfigError, match="threads.prefetch_frames"):
        ThreadsConfig(prefetch_frames=0)


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="no thread niceness here")
def test_unpaced_runs_lower_the_priority_of_the_work_done_ahead(seq):
    """threads.ahead_nice: in an unpaced run the image reader thread and the extraction
    process run at the tracker's niceness plus ahead_nice (they work ahead, off its path);
    in a paced run, where a frame's latency counts its extraction, at the tracker's."""
    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    for speed, nice, expected in ((0.0, 4, min(base + 4, 19)), (1.0, 4, base), (0.0, 0, base)):
        system = System(seq.camera, _threads(speed=speed, ahead_nice=nice), sequential=False)
        seen = []

        def observe(system, rec, result, seen=seen):
            reader = [t for t in threading.enumerate() if t.name == "orbslam-reader"]
            child = [p for p in multiprocessing.active_children() if p.name == "orbslam-extraction"]
            if reader and reader[0].native_id is not None and child:
                seen.append((os.getpriority(os.PRIO_PROCESS, reader[0].native_id),
                             os.getpriority(os.PRIO_PROCESS, child[0].pid)))

        system.observers.append(observe)
        system.run(seq, 8, progress=False)
        assert seen and set(seen) == {(expected, expected)}, (speed, nice, seen)
        assert system.stats()["threads"]["ahead_nice"] == (nice if speed == 0 else 0)
        _assert_nothing_left()
    for name in ("ahead_nice", "solver_nice", "worker_nice"):
        for bad in (-1, 20, 2.5, True):
            with pytest.raises(ConfigError, match=f"threads.{name}"):
                ThreadsConfig(**{name: bad})


def test_unpaced_runs_leave_the_ba_process_at_the_trackers_priority(seq):
    """threads.solver_nice lowers the local BA process's priority in paced runs only: in an
    unpaced one the tracker waits for each local BA (mapping_sync points), so the BA runs at
    its priority."""
    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    for speed, expected in ((0.0, base), (1.0, min(base + 7, 19))):
        system = System(seq.camera, _threads(speed=speed, solver_nice=7, local_ba_process=True), sequential=False)
        seen = set()

        def observe(system, rec, result, seen=seen):
            for p in multiprocessing.active_children():
                if p.name == "orbslam-local-ba":
                    seen.add(os.getpriority(os.PRIO_PROCESS, p.pid))

        system.observers.append(observe)
        system.run(seq, 30, progress=False)
        assert seen == {expected}, (speed, seen)
        assert system.stats()["threads"]["solver_nice"] == expected - base
        _assert_nothing_left()


def test_local_ba_in_the_mapping_thread_gives_the_process_results(seq):
    """By default the compiled local BA runs in the mapping thread, with no child process
    for it: the poses are those of a run that solves it in its process."""
    trajectories, children = {}, {}
    for in_process in (False, True):
        system = System(seq.camera, _threads(speed=0.0, local_ba_process=in_process), sequential=False)
        names = set()

        def observe(system, rec, result, names=names):
            names.update(p.name for p in multiprocessing.active_children())

        system.observers.append(observe)
        system.run(seq, N_FRAMES, progress=False)
        trajectories[in_process], children[in_process] = system.camera_trajectory(), names
        assert system.stats()["timing_ms"]["local_ba_per_keyframe"]["count"] >= 3
        _assert_nothing_left()
    assert "orbslam-local-ba" in children[True] and "orbslam-local-ba" not in children[False]
    assert len(trajectories[False]) > 10
    np.testing.assert_array_equal(trajectories[False].poses, trajectories[True].poses)


def test_a_run_extracts_here_until_its_extraction_process_is_ready(seq, monkeypatch):
    """The run does not wait for the extraction process to start: it extracts the first
    frames itself meanwhile, and every frame gets the same keypoints either way, so the
    poses are those of a run that waited for the process before its first frame."""
    import orbslam_hgcn.runtime.system as system_module

    from fault_fixtures import extraction_process

    trajectories, requests = {}, {}
    for wait in (True, False):
        made: list = []
        monkeypatch.setattr(system_module, "ExtractionProcess", extraction_process(0.5, wait, made))
        system = System(seq.camera, _threads(speed=0.0), sequential=False)
        system.run(seq, 80, progress=False)
        trajectories[wait] = system.camera_trajectory()
        requests[wait] = made[0]._child.requests
        _assert_nothing_left()
    assert requests[True] >= 80  # every frame (and a ping) went to the process
    assert 0 < requests[False] < 75  # the first frames, a second's worth at least, were extracted here
    waited, not_waited = trajectories[True], trajectories[False]
    assert len(waited) > 10
    np.testing.assert_array_equal(not_waited.timestamps, waited.timestamps)
    np.testing.assert_array_equal(not_waited.poses, waited.poses)


def test_a_run_leaves_objects_frozen_by_the_caller_frozen(seq):
    """A caller that froze its own objects (gc.freeze) finds them frozen after a run: an
    unreachable cycle frozen before the run outlives a collection after it."""

    class Node:
        pass

    node = Node()
    node.self = node
    alive = weakref.ref(node)
    del node
    gc.freeze()
    try:
        System(seq.camera, _threads(), sequential=False).run(seq, 5, progress=False)
        gc.collect()
        assert alive() is not None and gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
    gc.collect()
    assert alive() is None
    _assert_nothing_left()


def test_speed_and_keyframe_wait_must_be_finite_non_negative_numbers(synth_replay_100, tmp_path):
    with pytest.raises(ConfigError, match="threads.speed"):
        ThreadsConfig(speed=-1.0)
    with pytest.raises(ConfigError, match="threads.speed"):
        ThreadsConfig(speed=float("nan"))
    with pytest.raises(ConfigError, match="threads.keyframe_wait_s"):
        ThreadsConfig(keyframe_wait_s=-0.1)
    args = ["run", str(synth_replay_100), "--out", str(tmp_path / "x"), "--vocab", "none", "--no-loop",
            "--no-progress", "--speed", "-2"]  # fmt: skip
    assert main(args) == 2
    assert not (tmp_path / "x" / "stats.json").exists()


# --- the optimiser process -----------------------------------------------------------------
def _ba_problem(seed: int = 3):
    rng = np.random.default_rng(seed)
    sc = make_scene(6, 300, 0.7, rng)
    fixed = np.zeros(6, dtype=bool)
    fixed[:2] = True
    T0 = sc.T_cw.copy()
    for i in range(2, 6):
        T0[i] = perturb_pose(sc.T_cw[i], 2.0, 0.10, rng)
    P0 = sc.points + rng.normal(size=sc.points.shape) * 0.10
    return sc, as_problem(T0, fixed, P0, sc.obs_kf, sc.obs_pt, sc.uv, sc.inv_sigma2, sc.K)


def test_process_solver_gives_the_in_process_results():
    sc, p = _ba_problem()
    cfg = BackendConfig()
    local = InProcessSolver()
    S_true, S_drift, edges, S_ji = drifted_loop(20, np.random.default_rng(6))
    edges = np.vstack([edges, [[19, 0]]])
    S_ji = np.concatenate([S_ji, relative_sim3(S_true[19], S_true[0])[None]])
    fixed = np.zeros(20, dtype=bool)
    fixed[0] = True
    with ProcessSolver("test-solver") as remote:
        (a, hit_a), (b, hit_b) = local.local_ba(p, cfg, 0.0), remote.local_ba(p, cfg, 0.0)
        ga, gb = local.global_ba(p, 5, cfg), remote.global_ba(p, 5, cfg)
        ea = local.essential_graph(S_drift, edges, S_ji, fixed, None, cfg)
        eb = remote.essential_graph(S_drift, edges, S_ji, fixed, None, cfg)
        assert remote.alive
    assert not remote.alive
    assert not hit_a and not hit_b
    assert not np.allclose(a.T_cw, p.T_cw)  # the BA moved the free poses
    for x, y in ((a.T_cw, b.T_cw), (a.points, b.points), (ga.T_cw, gb.T_cw), (ga.points, gb.points), (ea, eb)):
        np.testing.assert_allclose(y, x, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(a.outlier, b.outlier)
    # A stop request is forwarded to the child: nothing is optimised when it may end the
    # robust iterations, and only those run by default.
    with ProcessSolver("test-solver") as remote:
        stopped, _ = remote.local_ba(p, BackendConfig(local_ba_abort_robust=True), 0.0, should_stop=lambda: True)
        robust_only, _ = remote.local_ba(p, cfg, 0.0, should_stop=lambda: True)
    np.testing.assert_array_equal(stopped.T_cw, p.T_cw)
    late, _ = local.local_ba(p, cfg, 0.0, should_stop=lambda: True)
    assert not np.allclose(robust_only.T_cw, p.T_cw)
    np.testing.assert_allclose(robust_only.T_cw, late.T_cw, rtol=0, atol=1e-9)


def test_process_solver_errors_surface():
    sc, p = _ba_problem()
    solver = ProcessSolver("test-solver").start()
    try:
        bad = p._replace(fixed=p.fixed[:3])  # one flag per pose is required
        with pytest.raises(SolverError, match="fixed must have one flag per pose") as info:
            solver.local_ba(bad, BackendConfig())
        assert "in the child process" in str(info.value) and "Traceback" in str(info.value)
        # The process survives a failed request, and one that dies is reported.
        solver.ping()
        solver.kill()
        with pytest.raises(SolverError, match="died|lost"):
            solver.local_ba(p, BackendConfig())
        # The next request starts a fresh process.
        res, _ = solver.local_ba(p, BackendConfig())
        assert res.T_cw.shape == p.T_cw.shape
    finally:
        solver.close()
    assert not solver.alive


@pytest.mark.skipif(not hasattr(os, "nice"), reason="no process niceness here")
def test_process_solver_runs_at_lower_priority():
    with ProcessSolver("test-solver", nice=4) as remote:
        remote.ping()
        child = [p for p in multiprocessing.active_children() if p.name == "orbslam-test-solver"]
        assert len(child) == 1
        assert os.getpriority(os.PRIO_PROCESS, child[0].pid) == min(os.getpriority(os.PRIO_PROCESS, 0) + 4, 19)


def test_extraction_process_gives_the_direct_keypoints(tum_layout):
    img = cv2.imread(str(sorted((tum_layout / "rgb").glob("*.png"))[0]), cv2.IMREAD_GRAYSCALE)
    cam = load_camera("tum_fr3")
    configs = {"normal": ORBConfig(), "init": ORBConfig(n_features=2000)}
    proc = ExtractionProcess(configs, cam)
    try:
        assert not proc.alive
        proc.start()  # returns once the child has built its extractors
        assert proc.alive
        for name, cfg in configs.items():
            kps, ms = proc.extract(name, img)
            direct = ORBExtractor(cfg).extract(img, cam)
            assert ms > 0 and len(kps) > 0.9 * cfg.n_features
            for field in ("uv_raw", "uv", "octave", "angle", "desc"):
                np.testing.assert_array_equal(getattr(kps, field), getattr(direct, field))
        # A bad request comes back as an error with the child's traceback; the process
        # goes on serving.
        with pytest.raises(ExtractionError, match="expected an \\(H, W\\) uint8 image") as info:
            proc.extract("normal", img.astype(np.float32))
        assert "Traceback" in str(info.value)
        assert len(proc.extract("normal", img)[0]) > 900
        assert proc.alive
    finally:
        proc.close()
    assert not proc.alive


def test_tracking_first_lock_lets_the_priority_waiter_in_first():
    lock = TrackingFirstLock()
    order: list[str] = []
    lock.acquire()
    assert lock.acquire(blocking=False)  # re-entrant for the owner
    lock.release()

    def take(name: str, prio: bool) -> None:
        with first(lock) if prio else lock:
            order.append(name)

    normal = threading.Thread(target=take, args=("mapper", False))
    normal.start()
    prio = threading.Thread(target=take, args=("tracker", True))
    prio.start()
    while lock._first_waiting == 0:
        threading.Event().wait(0.001)
    lock.release()
    for t in (normal, prio):
        t.join(5)
    assert order == ["tracker", "mapper"]
    with pytest.raises(RuntimeError):
        lock.release()


def test_ctrl_c_while_waiting_for_the_lock_is_a_keyboard_interrupt():
    """SIGINT reaches the main thread (the tracker) while it waits with priority: the wait
    ends with KeyboardInterrupt (not an error of the lock), and the lock is left usable.
    SIGINT raises here even where this process inherited it ignored (a background job)."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _ctrl_c_while_waiting_for_the_lock()
    finally:
        signal.signal(signal.SIGINT, previous)


def _ctrl_c_while_waiting_for_the_lock() -> None:
    import signal

    lock = TrackingFirstLock()
    holder_has_it, done = threading.Event(), threading.Event()

    def hold() -> None:
        with lock:
            holder_has_it.set()
            done.wait(5)

    holder = threading.Thread(target=hold)
    holder.start()
    holder_has_it.wait(5)
    threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT)).start()
    with pytest.raises(KeyboardInterrupt):
        lock.acquire_first()
    assert lock._first_waiting == 0 and lock._owner != threading.get_ident()
    done.set()
    holder.join(5)
    assert lock.acquire(timeout=1)  # free again, and takeable
    lock.release()


def test_ba_result_written_back_after_the_map_changed(sequential_runs):
    """A local BA solved without the map lock comes back to a map where keyframes were culled
    and points fused or discarded meanwhile: those are skipped, the rest is written."""
    m = sequential_runs[1].map  # the last user of this run
    kf_id = int(m.keyframe_ids()[-1])
    w = local_window(m, kf_id)
    free = [int(k) for k in w.kf_ids[~w.fixed] if int(k) not in (kf_id, m.origin_id)]
    assert free and len(w.point_ids) > 10
    culled = free[-1]
    assert m.set_bad_keyframe(culled)
    p_bad, p_old, p_new = (int(p) for p in w.point_ids[:3])
    m.set_bad_point(p_bad)
    m.replace_point(p_old, p_new)
    T_new = w.T_cw.copy()
    T_new[:, :3, 3] += 0.01
    X_new = w.points + 0.01
    outlier = np.isin(w.point_ids[w.obs_pt], [p_bad, p_old])
    # Points left with too few observations by the culled keyframe went bad with it.
    good = np.flatnonzero(~m.point_arrays(w.point_ids).bad)
    assert not np.isin([p_bad, p_old], w.point_ids[good]).any() and len(good) > 10
    before_bad = m.positions(w.point_ids[:2])
    erased = apply_window(m, w, T_new, X_new, outlier)
    assert erased == 0  # those observations went with the points
    row = {int(k): i for i, k in enumerate(w.kf_ids)}
    np.testing.assert_array_equal(m.keyframe(kf_id).T_cw, T_new[row[kf_id]])
    assert not np.allclose(m.keyframe(culled).T_cw, T_new[row[culled]])
    np.testing.assert_array_equal(m.positions(w.point_ids[good]), X_new[good])
    np.testing.assert_array_equal(m.positions(w.point_ids[:2]), before_bad)  # bad points untouched
    assert check_invariants(m) == []


# --- pausing local mapping for a loop correction -----------------------------------------
class _StubMap:
    def __init__(self) -> None:
        self.lock = TrackingFirstLock()

    def set_not_erase(self, kf_id: int) -> None:
        pass

    def set_erase(self, kf_id: int) -> None:
        pass


class _StubKeyFrame:
    def __init__(self, kf_id: int) -> None:
        self.id, self.bad = kf_id, False


class _SlowMapper:
    """Maps a keyframe in 30 ms and records the order."""

    def __init__(self) -> None:
        self.map, self.solver, self.should_abort, self.in_ba = _StubMap(), None, None, False
        self.done: list[int] = []

    def process(self, kf):
        time.sleep(0.03)
        self.done.append(kf.id)
        return None


@pytest.fixture
def slow_stages():
    """Threaded stages over a :class:`_SlowMapper`, closed (and checked) afterwards."""
    mapper = _SlowMapper()
    stages = ThreadedStages(mapper, None, process_solver=False)
    try:
        yield mapper, stages
    finally:
        stages.close()
    _assert_nothing_left()


def test_pausing_mapping_first_maps_every_keyframe_handed_over(slow_stages):
    # A loop correction moves the keyframes of the map; one still waiting in local
    # mapping's queue has no spanning-tree parent and no connections yet, so it would keep
    # its uncorrected pose. As in ORB-SLAM, a pause first maps the queued keyframes, and a
    # keyframe handed over by a frame being tracked when the pause is asked is waited for.
    mapper, stages = slow_stages
    for i in range(3):
        stages.submit(_StubKeyFrame(i))
    stages.pause_mapping(True)
    try:
        assert mapper.done == [0, 1, 2]
        assert not stages.mapping_idle()  # the tracker makes no keyframe meanwhile
    finally:
        stages.pause_mapping(False)

    handed = threading.Event()

    def frame_in_flight():
        with stages.handover():
            handed.set()
            time.sleep(0.05)  # tracking the frame
            stages.submit(_StubKeyFrame(3))

    t = threading.Thread(target=frame_in_flight)
    t.start()
    handed.wait()
    stages.pause_mapping(True)
    try:
        assert mapper.done == [0, 1, 2, 3]
    finally:
        stages.pause_mapping(False)
    t.join()
    assert stages.mapping_idle()


def test_tracker_waits_for_busy_mapping_only_as_long_as_asked(slow_stages):
    mapper, stages = slow_stages
    for i in range(4):
        stages.submit(_StubKeyFrame(i))
    assert not stages.mapping_idle()
    assert not stages.wait_for_mapping(0.01)  # 4 keyframes of 30 ms still to map
    assert stages.wait_for_mapping(5.0)
    assert mapper.done == [0, 1, 2, 3] and stages.mapping_idle()


class _DroppingMapper(_SlowMapper):
    """Halfway through a keyframe, the tracker discards the map (Atlas.drop) and the next
    step finds its keyframe bad, as a map lost with few keyframes is discarded."""

    def __init__(self, atlas, drop: bool) -> None:
        super().__init__()
        self.atlas, self.drop = atlas, drop
        self.map = atlas.new_map()

    def process(self, kf):
        if kf.id == 1:
            if self.drop:
                self.atlas.drop(self.map)
            self.map._good_kf(kf.id)  # the keyframe is not in the map: ValueError
        self.done.append(kf.id)
        return None


@pytest.mark.parametrize("drop", [True, False])
def test_a_map_discarded_while_its_keyframe_is_mapped_does_not_stop_mapping(drop):
    from orbslam_hgcn.map.atlas import Atlas

    mapper = _DroppingMapper(Atlas(), drop)
    stages = ThreadedStages(mapper, None, process_solver=False)
    mapper.map.set_erase = mapper.map.set_not_erase = lambda kf_id: None  # keyframes not in the map
    try:
        for i in range(3):
            stages.submit(_StubKeyFrame(i))
        stages.wait_for_mapping(5.0, done=True)
        if drop:  # the discarded map's keyframe is left, the worker goes on
            stages.check()
            assert mapper.map.dropped and mapper.done == [0, 2]
        else:  # any other error is a bug of the stage: the run stops with it
            with pytest.raises(WorkerError, match="does not exist or is bad"):
                stages.check()
    finally:
        with contextlib.suppress(WorkerError):
            stages.close()
    _assert_nothing_left()
