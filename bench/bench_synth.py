"""Speed of the synthetic sequence renderer on one core.

Prints, per option set, the texture build time, the median and mean render time per
frame (render plus camera effects) and the frames/s that gives, and the frames/s with
PNG encoding included (what ``orbslam-hgcn synth`` achieves before disk writes).

    OMP_NUM_THREADS=1 python bench/bench_synth.py [--frames 900] [--stride 3]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from orbslam_hgcn.datasets.synthetic import PNG_PARAMS, SynthOptions, build_sequence, CameraEffects, render_frame  # noqa: E402
from orbslam_hgcn.datasets.synthetic_render import SceneRenderer  # noqa: E402

TUM_GT = Path(__file__).resolve().parents[1].parent / "shared/data/tum_fr3_long_office_household_sample/groundtruth.txt"


def bench(name: str, options: SynthOptions, stride: int) -> None:
    t0 = time.perf_counter()
    scene, poses, stamps, _ = build_sequence(options)
    texture_seed = options.scene_seed if options.texture_seed is None else options.texture_seed
    renderer = SceneRenderer(scene, options.camera, texture_seed, options.repeated_texture,
                             texel_scale=options.texel_scale)
    build = time.perf_counter() - t0
    effects = CameraEffects(options)
    render_s, total_s, draws = [], [], []
    for k in range(0, len(stamps), stride):
        t = float(stamps[k])
        t0 = time.perf_counter()
        img, _ = render_frame(renderer, poses, t, options)
        img = effects.apply(img, t, k)
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
    for name, options in sets:
        if args.only is None or args.only in name:
            bench(name, options, args.stride)


if __name__ == "__main__":
    main()
