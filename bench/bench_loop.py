"""Loop closing and relocalisation on synthetic sequences: loops found, accuracy, timings.

Sequences (rendered once into the cache folder, default ~/.cache/orbslam_hgcn/loop_bench),
with Gaussian sensor noise (sigma 2 grey levels) and a 10% exposure drift by default
(``--noise``, ``--exposure-drift``; 0 and 0 give clean renders, on which the odometry
drifts so little that the tracker can re-find the old map points by itself; the revisit
keyframes are then covisible with the old ones and there is no loop left to detect):

* ``fr3_replay``: the camera path of TUM fr3 long_office_household (Sturm et al., IROS
  2012) replayed in a synthetic office, full length (2613 frames at 30 fps); the camera
  comes back at 75-85 s to the place it saw at 3-7 s;
* ``fr3_repeated``: the same path in a room where one texture patch covers every surface,
  cut at 70 s, before the revisit (no true loop: every loop found is false);
* ``elsewhere``: 60 frames of the same path in another room (scene seed 5), spliced into
  ``fr3_replay`` to force a loss;
* ``circle``: a small loop: 1.3 turns in 20 s (600 frames) on a circle of radius 1.2 m
  round the desk, looking at its centre (written as a TUM file and replayed).

Parts (``--parts``):

* ``hgcn`` / ``orb``: full run with loop closing and that vocabulary: the loops closed
  (both ends' frames and the ground-truth distance and angle between them: a true loop
  joins views less than 0.5 m and 30 deg apart), keyframe and camera ATE RMSE after Sim(3)
  alignment (target: keyframes <= 2 cm with HGCN), frames lost, loop timings, and how the
  revisit keyframes (frames 2250-2549) are tied to the first visit (frames 0-299): how many
  are covisible with first-visit keyframes and what share of their points the first visit
  made. When the odometry drifts little, tracking finds the first visit's points through
  the local map before any loop is detected; the revisit keyframes are then connected to
  the old ones, which loop detection excludes, so no loop closure is needed or made;
* ``noloop``: the same run with loop closing off (the HGCN vocabulary still indexes
  keyframes), for the ATE before/after comparison;
* ``false``: ``fr3_repeated`` with both vocabularies: loops closed (target 0), how many
  keyframes had database candidates, consistent candidates, and how the Sim(3) checks ended;
* ``circle``: the small loop, HGCN vocabulary, loop closing on (the keyframe ATE before
  and after the correction);
* ``reloc``: ``fr3_replay`` with frames 2310-2339 (77-78 s, inside the revisit) replaced
  by 30 frames of ``elsewhere``: frames lost, the frame where tracking resumed, and how
  many frames after the splice that was (target: within 10);
* ``loop``: the ``hgcn`` / ``orb`` part with each vocabulary of ``--vocabs`` (default:
  ``hgcn kmeans orb orb10k``, the shipped ones: HGCN, its k-means ablation at the same
  size, the ORB tree and the ORB tree at about that size); with ``--vocabs``, ``false``
  and ``reloc`` run once per vocabulary of the list as well.

Vocabularies: ``--vocab-hgcn`` / ``--vocab-orb`` files, default the shipped ones.

    python bench/bench_loop.py [--parts hgcn orb noloop false reloc loop] [--cache DIR]
                               [--vocab-hgcn FILE] [--vocab-orb FILE] [--vocabs NAME ...]
                               [--max-frames N] [--json FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.datasets import open_sequence
from orbslam_hgcn.datasets.base import FrameRecord, Sequence
from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence
from orbslam_hgcn.app.run import trajectory_ate
from orbslam_hgcn.runtime.system import Configs, System
from orbslam_hgcn.tracking.tracker import TrackingState
from orbslam_hgcn.trajectory import Trajectory
from orbslam_hgcn.vocabulary import load_vocabulary

# Known-answer problems shared with the tests (tests/*_fixtures.py).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from loop_fixtures import circle_ground_truth  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
FR3_GT = REPO.parent / "shared" / "data" / "tum_fr3_long_office_household_sample" / "groundtruth.txt"
SPLICE = (2310, 2340)  # frames replaced by frames of another room in the relocalisation run
FIRST_VISIT_END = 300  # frames 0-299 (0-10 s): the first visit of the place seen again at the revisit
REVISIT = (2250, 2550)  # frames 2250-2549 (75-85 s): the revisit
CIRCLE_GT = "circle_groundtruth.txt"
SEQUENCES = {
    "fr3_replay": SynthOptions(trajectory="replay", gt=str(FR3_GT)),
    "fr3_repeated": SynthOptions(trajectory="replay", gt=str(FR3_GT), frames=2100, repeated_texture=True),
    "elsewhere": SynthOptions(trajectory="replay", gt=str(FR3_GT), frames=60, scene_seed=5, texture_seed=5),
}


def ensure(name: str, cache: Path, noise: float = 0.0, drift: float = 0.0) -> Path:
    """The rendered sequence ``name`` in ``cache`` (rendered on first use), with Gaussian
    sensor noise ``noise`` (grey levels) and exposure drift ``drift``; the folder name
    carries both when they are not zero."""
    if name == "circle":
        gt = circle_ground_truth(cache / CIRCLE_GT)
        opts = SynthOptions(trajectory="replay", gt=str(gt))
    else:
        opts = SEQUENCES[name]
    folder = name if noise == 0 and drift == 0 else f"{name}_noise{noise:g}_drift{drift:g}"
    opts = dataclasses.replace(opts, noise=noise, exposure_drift=drift)
    return render_sequence(cache / folder, opts, progress=True, cache=True)


class Spliced(Sequence):
    """``base`` with frames [start, stop) showing frames of ``other`` (timestamps kept)."""

    def __init__(self, base: Sequence, other: Sequence, start: int, stop: int) -> None:
        self.base, self.other, self.start, self.stop = base, other, start, stop
        self.name = f"{base.name}+spliced"
        self.camera = base.camera
        self.ground_truth = base.ground_truth
        self.color = base.color

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, index: int) -> FrameRecord:
        rec = self.base[index]
        if self.start <= index < self.stop:
            img = self.other[(index - self.start) % len(self.other)].image
            return FrameRecord(rec.index, rec.timestamp, img, rec.T_wc)
        return rec

    @property
    def timestamps(self) -> np.ndarray:
        return self.base.timestamps


def gt_pose(gt: Trajectory, t: float) -> np.ndarray:
    return gt.poses[int(np.argmin(np.abs(gt.timestamps - t)))]


def describe_loop(gt: Trajectory, ev: dict) -> str:
    """One line per loop. Its two views (ground truth) are ``dist`` m and ``ang`` deg apart;
    the loop is TRUE when the measured similarity agrees with the ground-truth relative
    pose: rotation within 2 deg, translation direction within 15 deg (or both centres
    within 5 cm)."""
    A, B = gt_pose(gt, ev["timestamp"]), gt_pose(gt, ev["loop_timestamp"])
    dist = float(np.linalg.norm(A[:3, 3] - B[:3, 3]))
    ang = float(np.degrees(np.arccos(np.clip(A[:3, 2] @ B[:3, 2], -1, 1))))
    T_cm = np.linalg.inv(A) @ B  # ground truth: loop camera -> current camera
    S = np.asarray(ev["S_cm"])
    s = np.cbrt(np.linalg.det(S[:3, :3]))
    dR = (S[:3, :3] / s) @ T_cm[:3, :3].T
    rot_err = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
    ta, tb = S[:3, 3], T_cm[:3, 3]
    dir_err = float(np.degrees(np.arccos(np.clip(ta @ tb / max(np.linalg.norm(ta) * np.linalg.norm(tb), 1e-12), -1, 1))))
    true = rot_err < 2.0 and (dir_err < 15.0 or dist < 0.05)
    c = ev["correction"]
    t = ev["time_ms"]
    return (
        f"  loop kf {ev['kf_id']} (frame {ev['frame_id']}, {ev['timestamp'] - gt.timestamps[0]:.1f} s) <-> "
        f"kf {ev['loop_kf_id']} (frame {ev['loop_frame_id']}, {ev['loop_timestamp'] - gt.timestamps[0]:.1f} s): "
        f"{'TRUE' if true else 'FALSE'} loop (views {dist:.2f} m, {ang:.0f} deg apart; Sim3 vs ground truth: rotation "
        f"{rot_err:.2f} deg, translation direction {dir_err:.1f} deg), scale {ev['scale']:.3f}, "
        f"{ev['n_sim3_inliers']} Sim3 inliers, {ev['n_matches']} matches, {c['n_replaced']} points fused, "
        f"{c['n_edges']} graph edges; ms: sim3 {t.get('sim3', 0):.0f}, correct {t.get('correct', 0):.0f}, "
        f"global BA {t.get('global_ba', 0):.0f}"
    )


def revisit_link(system: System) -> dict:
    """How the revisit keyframes are tied to the first visit: the share of their map
    points that were made by first-visit keyframes (keyframe ids grow with time, so every
    id up to the last first-visit keyframe's was made then). Above zero, the revisit
    tracks the first visit's points: either a loop closure fused them, or the odometry
    drifted so little that tracking found them through the local map, and the revisit
    keyframes are then covisible with the old ones (no loop is left to detect)."""
    m = system.map
    kfs = m.keyframes()
    first = [kf.id for kf in kfs if kf.frame_id < FIRST_VISIT_END]
    revisit = [kf for kf in kfs if REVISIT[0] <= kf.frame_id < REVISIT[1]]
    if not first or not revisit:
        return {"revisit_keyframes": len(revisit), "points": 0, "from_first_visit": 0}
    last_first = max(first)
    pids = np.concatenate([kf.point_ids[kf.point_ids >= 0] for kf in revisit])
    old = sum(m.point(int(p)).first_kf <= last_first for p in pids)
    covisible = sum(bool(set(m.covisible_keyframes(kf.id).tolist()) & set(first)) for kf in revisit)
    return {"revisit_keyframes": len(revisit), "points": int(len(pids)), "from_first_visit": int(old),
            "covisible_with_first_visit": int(covisible)}


def run(seq: Sequence, vocab_path: str, loop: bool, max_frames: int | None, out: Path | None = None) -> dict:
    vocab = load_vocabulary(vocab_path)
    configs = Configs()
    configs = dataclasses.replace(configs, loop_closing=dataclasses.replace(configs.loop_closing, enabled=loop))
    system = System(seq.camera, configs, vocabulary=vocab, sequential=True)
    # Keyframe ATE just before and just after each loop correction.
    around: list[dict] = []
    closer = system.loop_closer
    if closer is not None:
        process = closer.process

        def process_and_measure(kf):
            before = system.keyframe_trajectory()
            ev = process(kf)
            if ev is not None:
                around.append({"kf": ev.kf_id, "before": trajectory_ate(seq.ground_truth, before),
                               "after": trajectory_ate(seq.ground_truth, system.keyframe_trajectory())})
            return ev

        closer.process = process_and_measure
    t0 = time.perf_counter()
    summary = system.run(seq, max_frames, progress=True)
    wall = time.perf_counter() - t0
    stats = system.stats()
    if out is not None:
        system.save(out)
    records = [r for r in system.tracker.records if r.generation == system.tracker.generation]
    states = {r.frame_id: r.state for r in records}
    return {
        "frames": summary.frames,
        "wall_s": wall,
        "kf_ate": trajectory_ate(seq.ground_truth, system.keyframe_trajectory()),
        "cam_ate": trajectory_ate(seq.ground_truth, system.camera_trajectory()),
        "keyframes": stats["keyframes"],
        "frames_stats": stats["frames"],
        "lost_frames": sorted(f for f, s in states.items() if s == TrackingState.LOST),
        "ok_frames": sorted(f for f, s in states.items() if s == TrackingState.OK),
        "loop": stats.get("loop_closing", {}),
        "reloc": stats.get("relocalization", {}),
        "resets": stats["map_resets"],
        "around_loops": around,
        "revisit": revisit_link(system),
    }


def ate_line(name: str, a: dict) -> str:
    if "error" in a:
        return f"  {name} ATE: n/a ({a['error']})"
    return f"  {name} ATE RMSE (Sim3): {100 * a['rmse_m']:.2f} cm over {a['pairs']} poses (max {100 * a['max_m']:.2f} cm)"


def print_run(title: str, r: dict, gt: Trajectory) -> None:
    f = r["frames_stats"]
    print(f"{title}: {r['frames']} frames in {r['wall_s']:.0f} s, {r['keyframes']} keyframes, tracked {f['tracked']}, "
          f"lost {f['lost']}, resets {r['resets']}")
    print(ate_line("keyframe", r["kf_ate"]))
    print(ate_line("camera", r["cam_ate"]))
    loops = r["loop"].get("loops", [])
    counts = r["loop"].get("counts", {})
    print(f"  loops closed: {len(loops)}; keyframes with consistent candidates: {counts.get('consistent_keyframes', 0)}; "
          f"Sim3 outcomes: {r['loop'].get('candidate_outcomes', {})}")
    for ev in loops:
        print(describe_loop(gt, ev))
    for a in r["around_loops"]:
        if "error" not in a["before"] and "error" not in a["after"]:
            print(f"  keyframe ATE at the loop of kf {a['kf']}: {100 * a['before']['rmse_m']:.2f} cm before the "
                  f"correction, {100 * a['after']['rmse_m']:.2f} cm after ({a['before']['pairs']} keyframes)")
    v = r["revisit"]
    if v["points"]:
        print(f"  revisit (frames {REVISIT[0]}-{REVISIT[1] - 1}): {v['revisit_keyframes']} keyframes, "
              f"{v['covisible_with_first_visit']} of them covisible with first-visit keyframes (frames "
              f"0-{FIRST_VISIT_END - 1}); {v['from_first_visit']} of their {v['points']} map points "
              f"({100 * v['from_first_visit'] / v['points']:.0f}%) were made in the first visit")
    if r["reloc"]:
        print(f"  relocalisation: {r['reloc']['attempts']} attempts, {r['reloc']['successes']} successes "
              f"{r['reloc']['history'][:5]}")


def sub(out: Path | None, name: str) -> Path | None:
    return None if out is None else out / name


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", nargs="+", default=["hgcn", "orb", "noloop", "false", "reloc", "circle"],
                    choices=("hgcn", "orb", "noloop", "false", "reloc", "circle", "loop"))
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "orbslam_hgcn" / "loop_bench")
    ap.add_argument("--vocab-hgcn", default="hgcn")
    ap.add_argument("--vocab-orb", default="orb")
    ap.add_argument("--vocabs", nargs="+", default=None,
                    help="vocabularies (shipped names or files) of the loop part, and of false and reloc when "
                         "given (default for loop: hgcn kmeans orb orb10k)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--noise", type=float, default=2.0,
                    help="sensor noise sigma in grey levels of every sequence (default 2; 0: clean renders)")
    ap.add_argument("--exposure-drift", type=float, default=0.1,
                    help="relative exposure gain swing of every sequence (default 0.1)")
    ap.add_argument("--json", type=Path, default=None, help="also write every figure to this JSON file")
    ap.add_argument("--out", type=Path, default=None, help="write each run's trajectories and stats.json under this folder")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("orbslam_hgcn.loop").setLevel(logging.INFO)
    vocabs = {"hgcn": args.vocab_hgcn, "orb": args.vocab_orb}
    listed = args.vocabs or ["hgcn", "kmeans", "orb", "orb10k"]
    results: dict[str, dict] = {}
    look = (args.noise, args.exposure_drift)
    print(f"sequences rendered with sensor noise {args.noise:g} grey levels and exposure drift {args.exposure_drift:g}")
    main_seq = open_sequence("tum", ensure("fr3_replay", args.cache, *look))
    gt = main_seq.ground_truth
    for part in args.parts:
        if part in ("hgcn", "orb"):
            results[part] = r = run(main_seq, vocabs[part], True, args.max_frames, sub(args.out, part))
            print_run(f"[{part}] fr3_replay, loop closing on, {part} vocabulary", r, gt)
        elif part == "loop":
            for name in listed:
                results[f"loop_{name}"] = r = run(main_seq, vocabs.get(name, name), True, args.max_frames,
                                                  sub(args.out, f"loop_{Path(name).stem}"))
                print_run(f"[loop] fr3_replay, loop closing on, {name} vocabulary", r, gt)
        elif part == "noloop":
            results[part] = r = run(main_seq, vocabs["hgcn"], False, args.max_frames, sub(args.out, part))
            print_run("[noloop] fr3_replay, loop closing off", r, gt)
        elif part == "false":
            seq = open_sequence("tum", ensure("fr3_repeated", args.cache, *look))
            for kind in args.vocabs or ("hgcn", "orb"):
                out = sub(args.out, f"false_{Path(kind).stem}")
                results[f"false_{kind}"] = r = run(seq, vocabs.get(kind, kind), True, args.max_frames, out)
                print_run(f"[false] fr3_repeated (repeated texture, no revisit), {kind} vocabulary", r, seq.ground_truth)
        elif part == "circle":
            seq = open_sequence("tum", ensure("circle", args.cache, *look))
            results[part] = r = run(seq, vocabs["hgcn"], True, args.max_frames, sub(args.out, part))
            print_run("[circle] small loop (1.3 turns round the desk), hgcn vocabulary", r, seq.ground_truth)
        elif part == "reloc":
            other = open_sequence("tum", ensure("elsewhere", args.cache, *look))
            seq = Spliced(main_seq, other, *SPLICE)
            for kind in args.vocabs or ("hgcn",):
                key = part if args.vocabs is None else f"{part}_{kind}"
                results[key] = r = run(seq, vocabs.get(kind, kind), True, args.max_frames,
                                       sub(args.out, f"{part}_{Path(kind).stem}"))
                print_run(f"[reloc] fr3_replay with frames {SPLICE[0]}-{SPLICE[1] - 1} from another room, "
                          f"{kind} vocabulary", r, gt)
                lost = r["lost_frames"]
                resumed = min((f for f in r["ok_frames"] if f >= SPLICE[1]), default=-1)
                print(f"  lost frames: {len(lost)} in all ({len([f for f in lost if SPLICE[0] <= f < SPLICE[1]])} "
                      f"of the 30 spliced); first lost {lost[0] if lost else '-'}; tracking back at frame {resumed}, "
                      f"{resumed - SPLICE[1]} frames after the camera is back in mapped space (target <= 10)")
    if args.json:
        for r in results.values():
            r.pop("ok_frames", None)
        args.json.write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
