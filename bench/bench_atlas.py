"""The atlas: new maps after a loss, merging on the revisit, no false merges, and the demo
loop beside a CPU hog.

Sequences (rendered once into the cache folder, default ~/.cache/orbslam_hgcn):

* ``loop_default``: the demo's 30 s loop round the desk (900 frames at 30 Hz); the camera
  ends where it started;
* ``loop_450frames``: the same loop in 15 s (450 frames), so that 2 s of it cover twice
  the angle;
* ``elsewhere``: 60 frames of the TUM fr3 camera path (Sturm et al., IROS 2012) in another
  room (scene seed 5), the unrelated frames of the ``unrelated`` part;
* ``fr3_repeated``: the fr3 camera path, 70 s, in a room where one texture patch covers
  every surface and the camera does not come back to a place it saw (the loop bench's
  no-revisit sequence).

Parts (``--parts``), each with the HGCN and the ORB vocabulary, threaded at the camera's
rate (as ``orbslam-hgcn run``) and, with ``--sequential``, in order as well:

* ``cut``: frames 150-209 (5-7 s) of the loop black (the camera comes out of the cut
  close enough to what the first map saw to be relocalised in it);
* ``cut_fast``: frames 75-134 (2.5-4.5 s) of the 15 s loop black (the camera comes out
  of the cut in unmapped space: a new map, merged when the loop comes round);
* ``unrelated``: frames 150-209 of the loop showing ``elsewhere``;
* ``false``: ``fr3_repeated`` with frames 600-659 (20-22 s) black: two maps of places that
  never overlap, so every merge is false (target 0);
* ``hog``: the loop as it is, beside a busy process on one core (``--hog`` busy processes;
  default 1): the longest stretch of frames without a pose once the first map exists
  (target: at most 1 s).

Printed per run: the frames where maps were started and initialised, how long after the
disturbance ended tracking resumed (target: within 1 s), merges (the frames of both ends,
and whether the ground truth agrees: the two views within 0.5 m and 30 deg), maps left at
the end, the keyframe and camera ATE of the output map after Sim(3) alignment (target for
the merged map: <= 1 cm), frames without a pose outside the disturbance, the longest
stretch without a pose.

    python bench/bench_atlas.py [--parts cut cut_fast unrelated false hog] [--runs 1] [--sequential]
                                [--hog 1] [--cache DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

import numpy as np

from orbslam_hgcn.datasets import open_sequence
from orbslam_hgcn.datasets.base import FrameRecord, Sequence
from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence
from orbslam_hgcn.app.run import trajectory_ate
from orbslam_hgcn.runtime.system import Configs, System
from orbslam_hgcn.vocabulary import load_vocabulary

REPO = Path(__file__).resolve().parents[1]
FR3_GT = (REPO.parent / "shared" / "data" / "tum_fr3_long_office_household_sample" / "groundtruth.txt").resolve()
CUT = (150, 210)  # 5-7 s of the loop
FALSE_CUT = (600, 660)  # 20-22 s of the no-revisit sequence
FAST_CUT = (75, 135)  # 2.5-4.5 s of the 15 s loop
SEQUENCES = {
    "loop_default": SynthOptions(),
    "loop_450frames": SynthOptions(frames=450),
    "elsewhere": SynthOptions(trajectory="replay", gt=str(FR3_GT), frames=60, scene_seed=5, texture_seed=5),
    "fr3_repeated": SynthOptions(trajectory="replay", gt=str(FR3_GT), frames=2100, repeated_texture=True),
}


class Disturbed(Sequence):
    """``base`` with frames [start, stop) black, or showing frames of ``other``."""

    def __init__(self, base: Sequence, start: int, stop: int, other: Sequence | None = None) -> None:
        self.base, self.start, self.stop, self.other = base, start, stop, other
        self.name, self.camera, self.ground_truth, self.color = base.name, base.camera, base.ground_truth, False

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, i: int) -> FrameRecord:
        rec = self.base[i]
        if self.start <= i < self.stop:
            img = np.zeros_like(rec.image) if self.other is None else self.other[(i - self.start) % len(self.other)].image
            return FrameRecord(rec.index, rec.timestamp, img, rec.T_wc)
        return rec

    @property
    def timestamps(self) -> np.ndarray:
        return self.base.timestamps


def _hog() -> None:
    x = 0
    while True:
        x += 1


def merge_truth(seq: Sequence, ev: dict) -> tuple[float, float]:
    """Ground-truth distance (m) and angle (deg) between the two views a merge joined."""
    a, b = seq[int(ev["frame_id"])].T_wc, seq[int(ev["match_frame_id"])].T_wc
    dist = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    ang = float(np.degrees(np.arccos(np.clip(a[:3, 2] @ b[:3, 2], -1.0, 1.0))))
    return dist, ang


def run_once(seq: Sequence, vocab: str, sequential: bool, disturbed: tuple[int, int] | None, hogs: int) -> dict:
    system = System(seq.camera, Configs(), vocabulary=load_vocabulary(vocab), sequential=sequential)
    procs = [mp.get_context("spawn").Process(target=_hog, daemon=True) for _ in range(hogs)]
    for p in procs:
        p.start()
    try:
        t0 = time.perf_counter()
        system.run(seq, progress=False)
        wall = time.perf_counter() - t0
    finally:
        for p in procs:
            p.terminate()
            p.join()
    st = system.stats()
    fps = seq.camera.fps
    init = [e["frame"] for e in st["events"] if e["event"] == "initialized"]
    no_pose = np.array([r.frame_id for r in system.tracker.records if r.T_cr is None], dtype=np.int64)
    first_pose = init[0] - 1 if init else len(seq)  # the reference frame of the first map gets a pose
    gaps, run_len = [], 0
    has_pose = np.ones(len(seq), bool)
    has_pose[no_pose] = False
    for i in range(max(first_pose, 0), len(seq)):
        run_len = 0 if has_pose[i] else run_len + 1
        gaps.append(run_len)
    out = {
        "vocab": vocab, "mode": "sequential" if sequential else "threaded", "wall_s": wall,
        "events": [e for e in st["events"] if e["event"] != "lost"],
        "maps_at_end": len(system.atlas), "frames": st["frames"],
        "kf_ate": trajectory_ate(seq.ground_truth, system.keyframe_trajectory()),
        "cam_ate": trajectory_ate(seq.ground_truth, system.camera_trajectory()),
        "longest_gap_s": max(gaps, default=0) / fps,
        "merges": [{**m, "truth": merge_truth(seq, m)} for m in st["atlas"]["merges"]],
        "loops": len(st["loop_closing"].get("loops", [])),
    }  # fmt: skip
    if disturbed is not None:
        lo, hi = disturbed
        after = [i for i in range(hi, len(seq)) if has_pose[i]]
        out["resumed_after_s"] = (after[0] - hi) / fps if after else None
        outside = ((no_pose < lo) | (no_pose >= hi)) & (no_pose >= first_pose)
        out["no_pose_outside"] = int(np.count_nonzero(outside))
    return out


def describe(r: dict) -> str:
    ev = ", ".join(f"{e['event']} {e['frame']} (map {e.get('map')})" for e in r["events"])
    lines = [f"  {r['vocab']}/{r['mode']}: {ev}; {r['maps_at_end']} map(s) at the end, {r['loops']} loop(s) closed, "
             f"{r['wall_s']:.0f} s"]
    for m in r["merges"]:
        d, a = m["truth"]
        lines.append(f"    merge at frame {m['frame_id']} with frame {m['match_frame_id']}: "
                     f"{'TRUE' if d < 0.5 and a < 30 else 'FALSE'} (views {d:.2f} m, {a:.0f} deg apart), "
                     f"scale {m['scale']:.3f}, {m['n_matches']} matches")  # fmt: skip
    f, k, c = r["frames"], r["kf_ate"], r["cam_ate"]
    ate = lambda a: f"{100 * a['rmse_m']:.2f} cm ({a['pairs']} poses)" if "rmse_m" in a else a.get("error", "n/a")  # noqa: E731
    lines.append(f"    frames: tracked {f['tracked']}, in other maps {f['other_maps']}, lost {f['lost']}, not initialised "
                 f"{f['not_initialized']}, reset {f['reset']}, dropped {f['dropped']}; keyframe ATE {ate(k)}, camera "
                 f"ATE {ate(c)}; longest stretch without a pose {r['longest_gap_s']:.2f} s")  # fmt: skip
    if "resumed_after_s" in r:
        res = r["resumed_after_s"]
        lines.append((f"    tracking resumed {res:.2f} s after the disturbance" if res is not None
                      else "    tracking never resumed")
                     + f"; frames without a pose outside it, once the first map exists: {r['no_pose_outside']}")  # fmt: skip
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", nargs="+", default=["cut", "cut_fast", "unrelated", "false", "hog"],
                    choices=["cut", "cut_fast", "unrelated", "false", "hog"])  # fmt: skip
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--sequential", action="store_true", help="also run each part in order (reproducible)")
    ap.add_argument("--hog", type=int, default=1, help="busy processes in the hog part (default 1)")
    ap.add_argument("--vocabs", nargs="+", default=["hgcn", "orb"])
    ap.add_argument("--cache", default=os.path.expanduser("~/.cache/orbslam_hgcn"))
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    cache = Path(a.cache)

    def seq(name: str) -> Sequence:
        return open_sequence("tum", render_sequence(cache / name, SEQUENCES[name], progress=False, cache=True))

    print(f"bench_atlas: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at start")
    results: dict = {}
    modes = [False, True] if a.sequential else [False]
    for part in a.parts:
        if part == "false":
            base, cut = seq("fr3_repeated"), FALSE_CUT
            s = Disturbed(base, *cut)
        elif part == "cut_fast":
            base, cut = seq("loop_450frames"), FAST_CUT
            s = Disturbed(base, *cut)
        else:
            base, cut = seq("loop_default"), CUT
            s = Disturbed(base, *cut, seq("elsewhere") if part == "unrelated" else None)
            if part == "hog":
                s, cut = base, None
        print(f"\n== {part}")
        for vocab in a.vocabs:
            for sequential in modes if part != "hog" else [False]:
                for _ in range(a.runs):
                    r = run_once(s, vocab, sequential, cut, a.hog if part == "hog" else 0)
                    print(describe(r), flush=True)
                    results.setdefault(part, []).append(r)
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
