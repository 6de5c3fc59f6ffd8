"""Speed of the synthetic sequence renderer on one core.

Prints, per option set, the texture build time, the median and mean render time per
frame (render plus camera effects and degradations) and the frames/s that gives, and the
frames/s with PNG encoding included (what ``orbslam-hgcn synth`` achieves before disk
writes). The street makes its textures when they first come into view, so its texture
time is counted in its frames (the mean and p95 more than the median).

    OMP_NUM_THREADS=1 python bench/bench_synth.py [--frames 900] [--stride 3] [--only street]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from orbslam_hgcn.synth.sequence import (  # noqa: E402
    PRESETS,
    REF_DEPTH,
    CameraEffects,
    SynthOptions,
    build_sequence,
    camera_frame,
    make_renderer,
    street_options,
    synth_options,
)
from orbslam_hgcn.synth.degrade import Degradations  # noqa: E402
from orbslam_hgcn.synth.output import PNG_PARAMS  # noqa: E402

TUM_GT = Path(__file__).resolve().parents[1].parent / "shared/data/tum_fr3_long_office_household_sample/groundtruth.txt"


def bench(name: str, options: SynthOptions, stride: int) -> None:
    t0 = time.perf_counter()
    scene, poses, stamps, _ = build_sequence(options)
    renderer = make_renderer(scene, options)
    build = time.perf_counter() - t0
    effects = CameraEffects(options)
    degrade = Degradations(options, options.camera, float(stamps[0]), float(stamps[-1]), REF_DEPTH[options.scene])
    grey = options.layout == "kitti"
    render_s, total_s, draws = [], [], []
    for k in range(0, len(stamps), stride):
        t = float(stamps[k])
        t0 = time.perf_counter()
        img, _ = camera_frame(renderer, poses, t, k, options, effects, degrade, grey)
        t1 = time.perf_counter()
        cv2.imencode(".png", img, PNG_PARAMS)
        t2 = time.perf_counter()
        render_s.append(t1 - t0)
        total_s.append(t2 - t0)
        draws.append(renderer.last_draw_count)
    r = np.array(render_s)
    tot = np.array(total_s)
    print(f"{name:<28} textures {build:5.1f} s | {len(r):4d} frames | render median {1e3 * np.median(r):6.1f} ms "
          f"mean {1e3 * r.mean():6.1f} ms p95 {1e3 * np.percentile(r, 95):6.1f} ms -> median {1 / np.median(r):5.1f} fps, "
          f"overall {len(r) / r.sum():5.1f} fps | with PNG {len(tot) / tot.sum():5.1f} fps | "
          f"tiles drawn {np.median(draws):.0f}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=900, help="sequence length per option set (default 900 = 30 s)")
    ap.add_argument("--stride", type=int, default=3, help="render every n-th frame of the sequence (default 3)")
    ap.add_argument("--gt", type=Path, default=TUM_GT, help="TUM ground truth for the replay set")
    ap.add_argument("--only", help="run only the option sets whose name contains this")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')} cv2 threads={cv2.getNumThreads()} "
          f"cv2 {cv2.__version__}")
    n = args.frames
    sets = [
        ("loop, clean", SynthOptions(frames=n)),
        ("loop, noise 2 + drift 0.2", SynthOptions(frames=n, noise=2.0, exposure_drift=0.2)),
        ("loop, motion blur", SynthOptions(frames=n, motion_blur=True)),
        ("loop, repeated texture", SynthOptions(frames=n, repeated_texture=True)),
    ]
    if args.gt.is_file():
        sets.append(("replay fr3 long office", SynthOptions(trajectory="replay", gt=str(args.gt), frames=n)))
        sets.append(("preset fr3_replay_hard", synth_options("fr3_replay_hard", gt=str(args.gt), frames=n)))
    street_n = max(1, n // 3)  # 10 Hz: the same duration as the 30 Hz sets
    sets += [
        ("street, clean", street_options(frames=street_n)),
        ("street, motion blur (flow)", street_options(frames=street_n, motion_blur=True, motion_blur_mode="flow",
                                                      shutter=PRESETS["street"]["shutter"])),
        ("preset street", synth_options("street", frames=street_n)),
    ]
    for name, options in sets:
        if args.only is None or args.only in name:
            bench(name, options, args.stride)


if __name__ == "__main__":
    main()
