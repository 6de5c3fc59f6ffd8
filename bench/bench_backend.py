"""Timings of the optimisation back end on synthetic problems and on real KITTI windows.

    OMP_NUM_THREADS=1 python bench/bench_backend.py [--quick] [--no-kitti]

Prints: pose-only optimisation (300 points, 20% gross outliers; compiled and gtsam), local BA
of a typical window (15 keyframes, ~2000 points, ~10000 observations) with each solver
(``backend.local_ba_solver``: the compiled Schur-complement LM and gtsam) and the longest
pause it causes in another Python thread (gtsam keeps the GIL while iterating; the compiled
solver releases it), the Map <-> array conversion of that window, local BA of real windows
cut from a sequential run over KITTI 00 (Geiger et al., CVPR 2012; ../shared/data) with
both solvers and how far apart their results are, the local mapping profile of that run,
and Sim(3) essential-graph optimisation of 200 keyframes.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.backend.bundle_adjustment import local_bundle_adjustment
from orbslam_hgcn.backend.pose_graph import optimize_essential_graph, relative_sim3
from orbslam_hgcn.backend.pose_only import optimize_pose, optimize_pose_gtsam
from orbslam_hgcn.config import BackendConfig
from orbslam_hgcn.features.keypoints import KeypointSet
from orbslam_hgcn.geometry.camera import PinholeCamera
from orbslam_hgcn.map import Frame, Map
from orbslam_hgcn.map.window import apply_window, local_window

# Known-answer problems shared with the tests (tests/*_fixtures.py).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from backend_fixtures import SCALE_FACTOR, N_LEVELS, drifted_loop, make_scene, perturb_pose  # noqa: E402

log = logging.getLogger(__name__)


def _median_ms(fn, runs: int) -> tuple[float, float]:
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts)), 1e3 * float(np.min(ts))


def bench_pose_only(runs: int) -> None:
    rng = np.random.default_rng(0)
    sc = make_scene(3, 900, 1.0, rng)
    sel = np.flatnonzero(sc.obs_kf == 1)[:300]
    X, uv, info = sc.points[sc.obs_pt[sel]], sc.uv[sel].copy(), sc.inv_sigma2[sel]
    out = rng.random(len(uv)) < 0.2
    uv[out] += rng.uniform(20, 60, (out.sum(), 2)) * rng.choice([-1, 1], (out.sum(), 2))
    T0 = perturb_pose(sc.T_cw[1], 5.0, 0.10, rng)
    res = optimize_pose(T0, X, uv, info, sc.K)
    med, fastest = _median_ms(lambda: optimize_pose(T0, X, uv, info, sc.K), runs)
    print(f"pose-only compiled ({len(X)} points, {out.sum()} outliers): median {med:.2f} ms, min {fastest:.2f} ms "
          f"over {runs} runs (first call, compile or cache load, excluded); inliers {res.inliers.sum()}, "
          f"outliers flagged {(~res.inliers[out]).sum()}/{out.sum()}")
    med, fastest = _median_ms(lambda: optimize_pose_gtsam(T0, X, uv, info, sc.K), max(runs // 20, 5))
    print(f"pose-only gtsam  (same problem, same scheme): median {med:.2f} ms, min {fastest:.2f} ms")


class _Ticker(threading.Thread):
    """Wakes every millisecond and records the longest gap: how long other threads stall."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.stop = threading.Event()
        self.max_gap = 0.0

    def run(self) -> None:
        last = time.perf_counter()
        while not self.stop.is_set():
            time.sleep(0.001)
            now = time.perf_counter()
            self.max_gap = max(self.max_gap, now - last)
            last = now


def _scene_map(sc) -> Map:
    """A Map holding a synthetic scene: one keypoint per observation, random descriptors."""
    rng = np.random.default_rng(1)
    cam = PinholeCamera(fx=sc.K[0, 0], fy=sc.K[1, 1], cx=sc.K[0, 2], cy=sc.K[1, 2], width=640, height=480)
    m = Map()
    slots = []
    for i in range(len(sc.T_cw)):
        sel = np.flatnonzero(sc.obs_kf == i)
        n = len(sel)
        kp = KeypointSet(
            uv_raw=sc.uv[sel].astype(np.float32), uv=sc.uv[sel], octave=sc.octave[sel].astype(np.int32),
            angle=np.zeros(n, np.float32), response=np.ones(n, np.float32),
            desc=rng.integers(0, 256, (n, 32)).astype(np.uint8),
            scale_factors=SCALE_FACTOR ** np.arange(N_LEVELS),
        )  # fmt: skip
        m.add_keyframe(Frame(id=i, timestamp=float(i), camera=cam, keypoints=kp, T_cw=sc.T_cw[i]))
        slots.append(sel)
    first = np.full(len(sc.points), -1)
    for i, sel in enumerate(slots):
        for idx, o in enumerate(sel):
            pid = sc.obs_pt[o]
            if first[pid] < 0:
                first[pid] = m.add_map_point(sc.points[pid], i)
            m.add_observation(i, int(first[pid]), idx)
    for kf in m.keyframes():
        m.update_connections(kf.id)
    m.update_points(m.point_ids())
    return m


def bench_local_ba(runs: int) -> None:
    rng = np.random.default_rng(2)
    sc = make_scene(15, 2100, 0.45, rng)
    fixed = np.zeros(15, dtype=bool)
    fixed[:4] = True
    T0 = sc.T_cw.copy()
    for i in np.flatnonzero(~fixed):
        T0[i] = perturb_pose(sc.T_cw[i], 1.0, 0.05, rng)
    P0 = sc.points + rng.normal(size=sc.points.shape) * 0.05
    args = (sc.obs_kf, sc.obs_pt, sc.uv, sc.inv_sigma2, sc.K)
    print(f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs while measuring)")
    for solver in ("schur", "gtsam"):
        cfg = BackendConfig(local_ba_solver=solver)
        local_bundle_adjustment(T0, fixed, P0, *args, cfg)  # compile or load the kernels
        ticker = _Ticker()
        ticker.start()
        ts = []
        for _ in range(runs):
            t = time.perf_counter()
            local_bundle_adjustment(T0, fixed, P0, *args, cfg)
            ts.append(time.perf_counter() - t)
        ticker.stop.set()
        ticker.join()
        print(f"local BA, {solver} ({len(sc.T_cw)} keyframes, {fixed.sum()} fixed, {len(sc.points)} points, "
              f"{len(sc.obs_kf)} observations, 5 + 10 iterations): median {1e3 * np.median(ts):.0f} ms, "
              f"min {1e3 * np.min(ts):.0f} ms over {runs} runs; "
              f"longest pause of another Python thread {1e3 * ticker.max_gap:.0f} ms")  # fmt: skip

    m = _scene_map(sc)
    newest = int(m.keyframe_ids()[-1])
    t = time.perf_counter()
    w = local_window(m, newest)
    t_cut = time.perf_counter() - t
    res = local_bundle_adjustment(w.T_cw, w.fixed, w.points, w.obs_kf, w.obs_pt, w.uv, w.inv_sigma2, w.K)
    t = time.perf_counter()
    apply_window(m, w, res.T_cw, res.points, res.outlier)
    t_apply = time.perf_counter() - t
    print(f"map window of keyframe {newest} ({len(w.kf_ids)} keyframes, {w.fixed.sum()} fixed, "
          f"{len(w.point_ids)} points, {w.n_observations} observations): cut {1e3 * t_cut:.0f} ms, "
          f"write back {1e3 * t_apply:.0f} ms")  # fmt: skip


def bench_kitti_windows(runs: int, frames: int = 120) -> None:
    """Local BA with both solvers on windows cut from a sequential run over real KITTI frames
    (KITTI's settings, 2000 ORB features), and that run's local mapping profile."""
    from pathlib import Path

    from orbslam_hgcn.config import dataset_settings
    from orbslam_hgcn.datasets import open_sequence
    from orbslam_hgcn.runtime.system import Configs, System

    path = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti00_first160" / "sequences" / "00"
    if not path.is_dir():
        print(f"KITTI windows: skipped, {path} not found")
        return
    seq = open_sequence("kitti", path)
    sp, settings = dataset_settings(seq.camera, "kitti")
    system = System(seq.camera, Configs.from_layers([(settings, sp)]), sequential=True)
    system.run(seq, frames, progress=False)
    t = system.mapper.timings
    steps = ", ".join(f"{k} {np.median(v):.1f}" for k, v in t.items() if k not in ("total_cpu", "local_ba_cpu"))
    print(f"KITTI 00 frames 0-{frames - 1}, sequential: {system.map.n_keyframes()} keyframes; local mapping per "
          f"keyframe, median ms: {steps}")  # fmt: skip
    m = system.map
    for kf in [int(k) for k in m.keyframe_ids()][-12::4]:
        w = local_window(m, kf)
        prob = (w.T_cw, w.fixed, w.points, w.obs_kf, w.obs_pt, w.uv, w.inv_sigma2, w.K)
        out, times = {}, {}
        for solver in ("schur", "gtsam"):
            cfg = BackendConfig(local_ba_solver=solver)
            out[solver] = local_bundle_adjustment(*prob, cfg)
            times[solver] = _median_ms(lambda cfg=cfg: local_bundle_adjustment(*prob, cfg), runs)[0]
        centres = [(-np.einsum("kji,kj->ki", r.T_cw[:, :3, :3], r.T_cw[:, :3, 3])) for r in out.values()]
        depth = float(np.median(np.linalg.norm(w.points - centres[0][:1], axis=1)))
        print(f"  KITTI window of keyframe {kf} ({len(w.kf_ids)} keyframes, {(~w.fixed).sum()} free, "
              f"{len(w.point_ids)} points, {w.n_observations} observations): schur {times['schur']:.0f} ms, "
              f"gtsam {times['gtsam']:.0f} ms (median of {runs}); keyframe centres apart by at most "
              f"{np.abs(centres[0] - centres[1]).max() / depth:.1e} of the median point distance, outliers "
              f"{int(out['schur'].outlier.sum())} / {int(out['gtsam'].outlier.sum())}")  # fmt: skip


def bench_pose_graph(runs: int) -> None:
    rng = np.random.default_rng(3)
    n = 200
    S_true, S_drift, edges, S_ji = drifted_loop(n, rng, trans_drift=0.0)
    # Essential-graph-like extra edges: each keyframe to the 2nd and 3rd next (strong covisibility).
    extra = np.array([(i, i + d) for d in (2, 3) for i in range(n - d)])
    S_extra = np.stack([relative_sim3(S_drift[i], S_drift[j]) for i, j in extra])
    E = np.vstack([edges, extra, [[n - 1, 0]]])
    M = np.concatenate([S_ji, S_extra, relative_sim3(S_true[n - 1], S_true[0])[None]])
    med, fastest = _median_ms(lambda: optimize_essential_graph(S_drift, E, M, fixed=0), runs)
    print(f"pose graph ({n} keyframes, {len(E)} Sim3 edges, 20 LM iterations): median {med:.1f} ms, min {fastest:.1f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions")
    ap.add_argument("--no-kitti", action="store_true", help="skip the real KITTI windows")
    args = ap.parse_args()
    q = args.quick
    bench_pose_only(100 if q else 500)
    bench_local_ba(2 if q else 5)
    if not args.no_kitti:
        bench_kitti_windows(2 if q else 5)
    bench_pose_graph(3 if q else 10)


if __name__ == "__main__":
    main()
