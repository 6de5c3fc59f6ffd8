"""Timing of ORB extraction, the matchers and the geometric solvers.

Prints median and 95th-percentile wall time per call, and the CPU time of the calling
thread (less sensitive to other processes sharing the cores). Run from the repository:

    python bench/bench_features.py [--repeats 30] [--threads 1]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import cv2
import numpy as np

from orbslam_hgcn.config import ORBConfig, load_camera
from orbslam_hgcn.features.orb import ORBExtractor
from orbslam_hgcn.geometry.epipolar import epipole, fundamental_12_from_poses
from orbslam_hgcn.geometry.pnp import solve_pnp_ransac
from orbslam_hgcn.geometry.se3 import inv_T
from orbslam_hgcn.geometry.sim3 import sim3_ransac
from orbslam_hgcn.geometry.two_view import TwoViewInitializer
from orbslam_hgcn.match.grid import FeatureGrid
from orbslam_hgcn.match.matching import (
    bow_candidate_pairs,
    brute_force_match,
    fuse_candidates,
    search_by_bow,
    search_by_projection,
    search_for_initialization,
    search_for_triangulation,
)
from orbslam_hgcn.vocabulary.bow import FeatureVector

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TUM = DATA / "tum_fr3_long_office_household_sample"
EUROC = DATA / "euroc_V1_01_easy_first95" / "mav0" / "cam0" / "data"


def set_data_root(root: Path) -> None:
    """Read the sample data from another folder (same layout as shared/data)."""
    global DATA, TUM, EUROC
    DATA = root
    TUM = DATA / "tum_fr3_long_office_household_sample"
    EUROC = DATA / "euroc_V1_01_easy_first95" / "mav0" / "cam0" / "data"


def timed(fn, repeats: int) -> tuple[np.ndarray, np.ndarray, object]:
    """Wall and thread-CPU seconds of ``repeats`` calls (after one warm-up call)."""
    out = fn()
    wall, cpu = [], []
    for _ in range(repeats):
        c0, t0 = time.thread_time(), time.perf_counter()
        out = fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    return np.array(wall), np.array(cpu), out


def report(name: str, wall: np.ndarray, cpu: np.ndarray, extra: str = "") -> None:
    print(
        f"{name:44s} wall median {np.median(wall) * 1e3:7.2f} ms  p95 {np.percentile(wall, 95) * 1e3:7.2f} ms"
        f"  | cpu median {np.median(cpu) * 1e3:7.2f} ms  {extra}"
    )


def synthetic_images(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """640x480 images of random textured shapes over a smooth background, lightly blurred."""
    images = []
    yy, xx = np.mgrid[0:480, 0:640]
    for _ in range(n):
        img = (80 + 60 * np.sin(xx / rng.uniform(40, 120)) * np.cos(yy / rng.uniform(40, 120))).astype(np.float32)
        for _ in range(150):
            c = (int(rng.integers(0, 640)), int(rng.integers(0, 480)))
            col = float(rng.uniform(0, 255))
            if rng.random() < 0.5:
                cv2.circle(img, c, int(rng.integers(3, 40)), col, -1)
            else:
                d = rng.integers(5, 60, 2)
                cv2.rectangle(img, c, (c[0] + int(d[0]), c[1] + int(d[1])), col, -1)
        img += rng.normal(0, 4, img.shape).astype(np.float32)
        images.append(np.clip(cv2.GaussianBlur(img, (3, 3), 0.8), 0, 255).astype(np.uint8))
    return images


def bench_extraction(repeats: int) -> None:
    cam = load_camera("tum_fr3")
    tum = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted((TUM / "rgb").glob("*.png"))]
    synth = synthetic_images(3, np.random.default_rng(0))
    ex = ORBExtractor(ORBConfig())
    ex2 = ORBExtractor(ORBConfig(n_features=2000))
    orb = cv2.ORB_create(1000)
    print(f"-- extraction, 640x480 ({len(tum)} TUM frames, {len(synth)} synthetic), {repeats} runs per image")
    for label, images in (("TUM", tum), ("synthetic", synth)):
        for name, fn in (
            ("ORBExtractor 1000", lambda im: ex.extract(im, cam)),
            ("ORBExtractor 2000 (initialisation)", lambda im: ex2.extract(im, cam)),
            ("cv2.ORB_create(1000) (reference)", lambda im: orb.detectAndCompute(im, None)),
        ):
            walls, cpus, counts = [], [], []
            for im in images:
                w, c, out = timed(lambda: fn(im), max(1, repeats // max(1, len(images) // 4)))
                walls.append(w)
                cpus.append(c)
                counts.append(len(out[0]) if isinstance(out, tuple) else len(out))
            report(f"{label}: {name}", np.concatenate(walls), np.concatenate(cpus), f"keypoints {np.mean(counts):.0f}")
    if EUROC.is_dir():
        ecam = load_camera("euroc_cam0")
        eimgs = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted(EUROC.glob("*.png"))[:5]]
        w, c = [], []
        for im in eimgs:
            ww, cc, _ = timed(lambda: ex.extract(im, ecam), max(1, repeats // 2))
            w.append(ww)
            c.append(cc)
        report("EuRoC 752x480 (undistorted): ORBExtractor 1000", np.concatenate(w), np.concatenate(c))


def bench_matchers(repeats: int) -> None:
    rng = np.random.default_rng(1)
    cam = load_camera("tum_fr3")
    ex = ORBExtractor()
    t1, t2 = 1341847980.722988, 1341847980.754743
    k1 = ex.extract(cv2.imread(str(TUM / f"rgb/{t1:.6f}.png"), cv2.IMREAD_GRAYSCALE), cam)
    k2 = ex.extract(cv2.imread(str(TUM / f"rgb/{t2:.6f}.png"), cv2.IMREAD_GRAYSCALE), cam)
    print("-- matchers (two consecutive TUM frames, 1000 keypoints each)")
    w, c, grid2 = timed(lambda: FeatureGrid(k2, cam), repeats)
    report("FeatureGrid build", w, c)
    w, c, (m, _) = timed(lambda: search_for_initialization(k1, k2, grid2, k1.uv, 100.0), repeats)
    report("search_for_initialization (window 100)", w, c, f"matches {(m >= 0).sum()}")
    w, c, pairs = timed(lambda: brute_force_match(k1.desc, k2.desc, 0.8), repeats)
    report("brute_force_match 1000x1000", w, c, f"matches {len(pairs)}")
    # Projection searches: the 1000 keypoints of frame 1 stand for projected map points.
    w, c, (m, _) = timed(
        lambda: search_by_projection(
            k2, grid2, k1.uv, k1.octave, k1.desc, 15.0, level_range=(-1, 1), ref_angle=k1.angle
        ),
        repeats,
    )
    report("search_by_projection motion model (th 15)", w, c, f"matches {(m >= 0).sum()}")
    w, c, (m, _) = timed(
        lambda: search_by_projection(k2, grid2, k1.uv, k1.octave, k1.desc, 4.0, level_range=(-1, 0), ratio=0.8),
        repeats,
    )
    report("search_by_projection local map (r 4)", w, c, f"matches {(m >= 0).sum()}")
    nodes1 = rng.integers(0, 300, len(k1))
    nodes2 = rng.integers(0, 300, len(k2))
    fv1 = FeatureVector.from_nodes(nodes1)
    fv2 = FeatureVector.from_nodes(nodes2)
    w, c, m = timed(lambda: search_by_bow(fv1, fv2, k1.desc, k2.desc, k1.angle, k2.angle), repeats)
    report("search_by_bow (300 random nodes)", w, c, f"matches {(m >= 0).sum()}")
    T_1w = np.eye(4)
    T_2w = np.eye(4)
    T_2w[:3, 3] = [-0.1, 0.0, 0.0]
    F12 = fundamental_12_from_poses(T_1w, T_2w, cam.K, cam.K)
    e2 = epipole(T_1w, T_2w, cam.K)
    w, c, p = timed(lambda: search_for_triangulation(k1, k2, F12, e2, bow_candidate_pairs(fv1, fv2)), repeats)
    report("search_for_triangulation (BoW pairs)", w, c, f"pairs {len(p)}")
    X = np.concatenate([(k1.uv - cam.K[:2, 2]) / [cam.fx, cam.fy], np.ones((len(k1), 1))], axis=1) * 2.0
    normals = X / np.linalg.norm(X, axis=1, keepdims=True)
    d = np.linalg.norm(X, axis=1)
    grid1 = FeatureGrid(k1, cam)
    w, c, (m, _) = timed(lambda: fuse_candidates(k1, grid1, cam, T_1w, X, k1.desc, normals, d / 2, d * 2), repeats)
    report("fuse_candidates (1000 points)", w, c, f"matches {(m >= 0).sum()}")


def bench_solvers(repeats: int) -> None:
    from orbslam_hgcn.trajectory import read_tum

    cam = load_camera("tum_fr3")
    print("-- geometry")
    ex = ORBExtractor()
    t1, t2 = 1341847980.722988, 1341847984.106759
    k1 = ex.extract(cv2.imread(str(TUM / f"rgb/{t1:.6f}.png"), cv2.IMREAD_GRAYSCALE), cam)
    k2 = ex.extract(cv2.imread(str(TUM / f"rgb/{t2:.6f}.png"), cv2.IMREAD_GRAYSCALE), cam)
    pairs = brute_force_match(k1.desc, k2.desc, 0.9)
    init = TwoViewInitializer()
    w, c, res = timed(lambda: init.initialize(k1.uv[pairs[:, 0]], k2.uv[pairs[:, 1]], cam.K), repeats)
    extra = "failed"
    if res is not None:
        from orbslam_hgcn.geometry.se3 import angle_between_deg, rotation_angle_deg

        gt = read_tum(TUM / "groundtruth.txt")
        T_21 = inv_T(gt.poses[gt.nearest(t2, 0.1)]) @ gt.poses[gt.nearest(t1, 0.1)]
        extra = (
            f"{res.model}, {len(pairs)} matches, rot err {rotation_angle_deg(res.R21 @ T_21[:3, :3].T):.2f} deg, "
            f"t dir err {angle_between_deg(res.t21, T_21[:3, 3]):.2f} deg, {res.triangulated.sum()} points"
        )
    report("two-view init, real TUM pair (3.4 s apart)", w, c, extra)
    rng = np.random.default_rng(2)
    n = 1000
    uv = rng.uniform([0, 0], [640, 480], (n, 2))
    Xc = np.concatenate([(uv - cam.K[:2, 2]) / [cam.fx, cam.fy], np.ones((n, 1))], axis=1) * rng.uniform(2, 8, (n, 1))
    T = np.eye(4)
    T[:3, 3] = [0.3, 0.0, 0.05]
    uv2 = (Xc + T[:3, 3]) @ cam.K.T
    uv2 = uv2[:, :2] / uv2[:, 2:] + rng.normal(0, 0.5, (n, 2))
    uv1 = uv + rng.normal(0, 0.5, (n, 2))
    uv2[:200] = rng.uniform([0, 0], [640, 480], (200, 2))
    w, c, res = timed(lambda: init.initialize(uv1, uv2, cam.K), repeats)
    report("two-view init, synthetic 1000 matches", w, c, "ok" if res is not None else "failed")
    n = 300
    obs = uv[:n] + rng.normal(0, 0.5, (n, 2))
    obs[:90] = rng.uniform([0, 0], [640, 480], (90, 2))
    w, c, res = timed(lambda: solve_pnp_ransac(Xc[:n], obs, cam.K), repeats)
    report("EPnP RANSAC, 300 matches, 30% outliers", w, c, f"inliers {res.inliers.sum() if res else 0}")
    X2 = Xc[:n] * (1 + rng.normal(0, 0.01, (n, 1)))
    X1 = 1.5 * Xc[:n] + [0.1, 0.0, 0.2]
    X2[:90] = X2[rng.permutation(90)]
    p1 = X1 @ cam.K.T
    p2 = X2 @ cam.K.T
    w, c, res = timed(
        lambda: sim3_ransac(X1, X2, p1[:, :2] / p1[:, 2:], p2[:, :2] / p2[:, 2:], cam.K, cam.K), repeats
    )
    report("Sim3 RANSAC, 300 matches, 30% outliers", w, c, f"scale {res.scale:.4f}" if res else "failed")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--threads", type=int, default=0, help="cv2.setNumThreads (0: OpenCV default)")
    ap.add_argument("--data", type=Path, default=None, help="folder holding the sample data (default: ../shared/data)")
    args = ap.parse_args()
    if args.data is not None:
        set_data_root(args.data)
    if args.threads > 0:
        cv2.setNumThreads(args.threads)
    print(f"cv2 threads {cv2.getNumThreads()}, load average {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} cores")
    bench_extraction(args.repeats)
    bench_matchers(args.repeats)
    bench_solvers(max(3, args.repeats // 3))


if __name__ == "__main__":
    main()
