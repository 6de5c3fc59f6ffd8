"""Relocalisation measured as ORB-SLAM measured it (Mur-Artal, Montiel and Tardos, T-RO 2015,
Sec. VIII-B): a map built from part of a real sequence, then every later frame given to
relocalisation on its own, as a kidnapped camera.

For each vocabulary (``--vocabs``: kmeans, hgcn, orb, hgcn_graph, ...) the map is built by
the system in order (``Slam(sequential=True)``, the shipped settings of the camera) from the
map frames, then each query frame is relocalised alone against it: its ORB features
extracted as tracking extracts them, its BoW vector from the vocabulary, then the
relocaliser of the tracker (:func:`orbslam_hgcn.tracking.relocalization.relocalize`:
keyframe-database candidates, BoW matching, EPnP RANSAC, pose optimisation, search by
projection), with no motion prior and nothing kept from one query to the next.

Splits (``--split``): ``half``, the map from the first half of the frames and the queries
from the second (TUM sitting_xyz: the camera comes back over the same desk);
``interleave``, the map from the even frames and the queries the odd ones (KITTI 00 drives
forward and never comes back: each query lies between two mapped frames).

A query's view is covered when a mapped frame's ground-truth pose is within 0.3 m and 20
degrees of its own (``--cover-m``, ``--cover-deg``; at KITTI's scale, metres of driving,
``--cover-m 2``). Printed per vocabulary and query version: recall over every query, recall
over the covered ones with its 95% Wilson interval, the median and p95 position error of
the relocalised poses after the Sim(3) that aligns the map's keyframes to the ground truth
(the map's own keyframe ATE beside it), candidates returned by the database and tried in
PnP, the relocaliser's inliers, and milliseconds per query (relocalisation and the local
map; extraction apart). Misses of covered views are told by the step that lost them: no
candidate from the database, no candidate with 15 BoW matches (``bow``), no pose with 50
inliers (``pose``), or too few inliers once the local map is searched (``local map``).

Query versions (``--degrade``): ``none``; ``blur`` (a 15-pixel horizontal box kernel, a pan
during the exposure); ``dark`` (gain 0.4) and ``bright`` (gain 1.8, clipped), exposure
changes; ``lowres`` (half resolution and back, the detail of a camera with half the pixels);
``jpeg`` (quality 25).

Relocaliser settings (``--arms``): ``default``, the system's; ``orbslam``, ORB-SLAM's rules
alone (``relocalization.exhaustive_fallback: false``, ``covisible_fallback: 0``). A
relocalisation more than ``--cover-m`` from the truth counts as wrong.

ORB-SLAM3 (pyorbslam3) is not run beside it: pyorbslam3 can neither load a saved atlas nor
put its tracker back into the lost state between frames, so it cannot relocalise each later
frame alone from a fixed map; its localisation mode tracks the queries as a sequence.

Usage::

    python bench/bench_reloc.py [--sequence ../shared/data/tum_fr3_sitting_xyz_148] [--split half]
                                [--vocabs kmeans hgcn orb hgcn_graph] [--degrade none blur dark bright lowres jpeg]
                                [--record NAME]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
DEGRADATIONS = ("none", "blur", "dark", "bright", "lowres", "jpeg")


def degrade(image: np.ndarray, kind: str) -> np.ndarray:
    """A query image as the camera might have given it (see the module text)."""
    if kind == "none":
        return image
    if kind == "blur":
        return cv2.blur(image, (15, 1))
    if kind in ("dark", "bright"):
        gain = 0.4 if kind == "dark" else 1.8
        return np.clip(image.astype(np.float32) * gain + 0.5, 0, 255).astype(np.uint8)
    if kind == "lowres":
        h, w = image.shape[:2]
        small = cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    if kind == "jpeg":
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 25])
        return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    raise ValueError(kind)


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a proportion k / n."""
    if n == 0:
        return (math.nan, math.nan)
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (max(0.0, c - h), min(1.0, c + h))


def rot_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def covered(T_q: np.ndarray, mapped: list[np.ndarray], max_m: float, max_deg: float) -> bool:
    """Whether a mapped frame's ground-truth pose is near the query's (position and angle)."""
    return any(np.linalg.norm(T[:3, 3] - T_q[:3, 3]) <= max_m and rot_deg(T[:3, :3], T_q[:3, :3]) <= max_deg
               for T in mapped)  # fmt: skip


def split(n: int, how: str) -> tuple[list[int], list[int]]:
    if how == "half":
        return list(range(n // 2)), list(range(n // 2, n))
    if how == "interleave":
        return list(range(0, n, 2)), list(range(1, n, 2))
    raise ValueError(how)


# Relocaliser settings compared: the default, and ORB-SLAM's rules alone (no matching over
# all descriptors after BoW matching, no covisible keyframes after the database's).
ARMS = {"default": {}, "orbslam": {"relocalization": {"exhaustive_fallback": False, "covisible_fallback": 0}}}


def build_map(seq, frames: list[int], vocab: str, arm: str = "default"):
    """The system after tracking ``frames`` in order (stages in order, loop closing as the
    config says), its stages finished; ``arm``: the relocaliser's settings (:data:`ARMS`)."""
    from orbslam_hgcn import Slam

    slam = Slam(seq.camera, vocab=vocab, sequential=True, config=ARMS[arm])
    for i in frames:
        rec = seq[i]
        slam.track(rec.image, rec.timestamp, frame=i)
    slam.close()
    return slam


def map_alignment(slam, gt) -> tuple[np.ndarray | None, float | None]:
    """(S_gt_map, keyframe ATE in m) of the map's keyframes against the ground truth."""
    from orbslam_hgcn.errors import OrbslamError
    from orbslam_hgcn.evaluation.ate import evaluate

    try:
        r = evaluate(gt, slam.keyframe_trajectory(), align="sim3")
    except OrbslamError:
        return None, None
    return r.S_gt_est, float(r.ate.rmse)


def query(slam, image: np.ndarray, index: int, timestamp: float):
    """Relocalise one image alone against the system's map, as ORB-SLAM's tracker does for a
    lost frame (relocalisation, then the local map searched and the pose optimised again),
    in localisation mode and with nothing kept from the previous query: (the frame's
    T_cw or None, the relocaliser's result, ms of the whole step)."""
    from orbslam_hgcn.map import Frame
    from orbslam_hgcn.tracking.tracker import TrackingState

    system = slam.system
    tracker = system.tracker
    tracker.localization = True
    tracker.state = TrackingState.LOST
    tracker.velocity, tracker.last_frame = None, None
    kps = system.extractor.extract(image, system.camera)
    frame = Frame(index, timestamp, system.camera, kps)
    t0 = time.perf_counter()
    with system.map.lock:
        result = tracker.track(frame)
    ms = 1000.0 * (time.perf_counter() - t0)
    ok = result.state == TrackingState.OK
    return (frame.T_cw if ok else None), system.relocalizer.last, ms


def why_missed(res) -> str:
    """The step that lost a query: no database candidate, no candidate with enough BoW
    matches for PnP, no pose with enough inliers, or (relocalised, then) the local map."""
    if res.ok:
        return "local map"
    if res.n_candidates == 0:
        return "database"
    if res.n_tried == 0:
        return "bow"
    return "pose"


def run_vocab(seq, vocab: str, map_frames: list[int], queries: list[int], degradations: list[str],
              cover_m: float, cover_deg: float, arm: str = "default") -> dict:  # fmt: skip
    gt = seq.ground_truth
    t0 = time.perf_counter()
    slam = build_map(seq, map_frames, vocab, arm)
    build_s = time.perf_counter() - t0
    S, kf_ate = map_alignment(slam, gt)
    stats = slam.stats()
    mapped_T = [seq[i].T_wc for i in map_frames if seq[i].T_wc is not None]
    out = {"vocab": vocab, "arm": arm, "map_frames": len(map_frames), "map_tracked": stats["frames"]["tracked"],
           "keyframes": stats["keyframes"], "map_points": stats["map_points"], "kf_ate_cm": None if kf_ate is None
           else 100 * kf_ate, "build_s": build_s, "versions": {}}  # fmt: skip
    recs = {i: seq[i] for i in queries}
    cover = {i: recs[i].T_wc is not None and covered(recs[i].T_wc, mapped_T, cover_m, cover_deg) for i in queries}
    for kind in degradations:
        rows = []
        for i in queries:
            rec = recs[i]
            T_cw, res, ms = query(slam, degrade(rec.image, kind), i, rec.timestamp)
            ok = T_cw is not None
            err = None
            if ok and S is not None and rec.T_wc is not None:
                c_map = -T_cw[:3, :3].T @ T_cw[:3, 3]
                c_gt = S[:3, :3] @ c_map + S[:3, 3]
                err = float(np.linalg.norm(c_gt - rec.T_wc[:3, 3]))
            rows.append({"frame": i, "ok": ok, "covered": cover[i], "err_m": err, "ms": ms,
                         "candidates": res.n_candidates, "tried": res.n_tried, "inliers": res.n_inliers,
                         "missed_at": None if ok else why_missed(res)})  # fmt: skip
        out["versions"][kind] = summarise(rows, cover_m)
    slam.close()
    return out


def summarise(rows: list[dict], wrong_m: float) -> dict:
    cov = [r for r in rows if r["covered"]]
    k_cov = sum(r["ok"] for r in cov)
    errs = sorted(r["err_m"] for r in rows if r["ok"] and r["err_m"] is not None)
    missed = [r["missed_at"] for r in cov if not r["ok"]]
    return {
        "queries": len(rows), "relocalised": sum(r["ok"] for r in rows), "covered": len(cov),
        "wrong": sum(1 for r in rows if r["ok"] and r["err_m"] is not None and r["err_m"] > wrong_m),
        "covered_relocalised": k_cov, "covered_ci": wilson(k_cov, len(cov)),
        "err_median_cm": 100 * statistics.median(errs) if errs else None,
        "err_p95_cm": 100 * float(np.percentile(errs, 95)) if errs else None,
        "candidates_median": statistics.median(r["candidates"] for r in rows),
        "tried_median": statistics.median(r["tried"] for r in rows),
        "inliers_median_ok": statistics.median([r["inliers"] for r in rows if r["ok"]] or [0]),
        "ms_median": statistics.median(r["ms"] for r in rows),
        "ms_p95": float(np.percentile([r["ms"] for r in rows], 95)),
        "missed_covered_at": {k: missed.count(k) for k in ("database", "bow", "pose", "local map")
                              if missed.count(k)},
        "rows": rows,
    }


def fmt_version(v: dict) -> str:
    lo, hi = v["covered_ci"]
    err = "n/a" if v["err_median_cm"] is None else f"{v['err_median_cm']:.1f} / {v['err_p95_cm']:.1f} cm"
    miss = ", ".join(f"{k} {n}" for k, n in v["missed_covered_at"].items()) or "none"
    return (f"covered {v['covered_relocalised']}/{v['covered']} [{100 * lo:.0f}-{100 * hi:.0f}%], all "
            f"{v['relocalised']}/{v['queries']} ({v['wrong']} wrong), error median/p95 {err}, candidates {v['candidates_median']:g}, "
            f"tried {v['tried_median']:g}, inliers {v['inliers_median_ok']:g}, {v['ms_median']:.0f} ms "
            f"(p95 {v['ms_p95']:.0f}); covered misses: {miss}")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", type=Path, default=SHARED / "tum_fr3_sitting_xyz_148")
    ap.add_argument("--split", choices=("half", "interleave"), default="half")
    ap.add_argument("--vocabs", nargs="+", default=["kmeans", "hgcn", "orb", "hgcn_graph"])
    ap.add_argument("--degrade", nargs="+", choices=DEGRADATIONS, default=list(DEGRADATIONS))
    ap.add_argument("--arms", nargs="+", choices=tuple(ARMS), default=["default"],
                    help="relocaliser settings: the default, and ORB-SLAM's rules alone")
    ap.add_argument("--cover-m", type=float, default=0.3)
    ap.add_argument("--cover-deg", type=float, default=20.0)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--record", default=None, metavar="NAME", help="write bench/results/NAME.json (figures.py)")
    args = ap.parse_args()
    import logging

    logging.basicConfig(level=logging.WARNING)
    from orbslam_hgcn.datasets import open_sequence

    load_start = __import__("os").getloadavg()[0]
    seq = open_sequence(None, args.sequence)
    if seq.ground_truth is None:
        print(f"{args.sequence}: no ground truth; the bench needs it", file=sys.stderr)
        return 2
    n = len(seq) if args.max_frames is None else min(len(seq), args.max_frames)
    map_frames, queries = split(n, args.split)
    print(f"{seq.name}: map from {len(map_frames)} frames, {len(queries)} queries ({args.split}); a view is "
          f"covered within {args.cover_m:g} m and {args.cover_deg:g} degrees of a mapped frame")  # fmt: skip
    results = []
    for vocab, arm in [(v, a) for v in args.vocabs for a in args.arms]:
        r = run_vocab(seq, vocab, map_frames, queries, args.degrade, args.cover_m, args.cover_deg, arm)
        results.append(r)
        ate = "n/a" if r["kf_ate_cm"] is None else f"{r['kf_ate_cm']:.2f} cm"
        print(f"\n{vocab} ({arm} relocaliser): map tracked {r['map_tracked']}/{r['map_frames']}, {r['keyframes']} keyframes, "
              f"{r['map_points']} points, keyframe ATE {ate} (built in {r['build_s']:.1f} s)")  # fmt: skip
        for kind, v in r["versions"].items():
            print(f"  {kind:7s} {fmt_version(v)}")
    if args.record:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        import figures

        figs = []
        for r in results:
            ate = "n/a" if r["kf_ate_cm"] is None else f"{r['kf_ate_cm']:.2f} cm"
            for kind, v in r["versions"].items():
                figs.append((f"{r['vocab']} {r['arm']} {kind}", fmt_version(v) + (f"; map keyframe ATE {ate}"
                                                                      if kind == "none" else "")))
        title = f"relocalisation of every later frame alone, {seq.name} ({args.split} split)"
        figures.record(args.record, title, figs, bench_file=__file__, load_start=load_start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
