"""Sweep benchmark: one manifest of 3 sequences x 2 vocabularies x 3 runs, in sequential
mode, made with ``--jobs 1`` and ``--jobs 2`` on a local Ray instance.

Renders three short office loops (scene seeds 0, 1, 2; ``--frames`` frames each, cached in
``--out``), writes the manifest, runs the sweep twice into fresh folders and prints both
wall times and whether the tables are equal (every figure but frames per second: each
run's trajectory and ATE is the same whichever process made it, since sequential runs are
reproducible). With ``--check-alone`` it also makes each run of the first cell again on
its own (``orbslam-hgcn run`` with the recorded command) and checks its keyframe
trajectory against the sweep's.

    python bench/bench_sweep.py [--frames 150] [--runs 3] [--out /tmp/bench_sweep]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from orbslam_hgcn.app.sweep import run_sweep
from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence


def comparable(path: Path) -> tuple[list, list]:
    data = json.loads((path / "sweep.json").read_text())
    cells = [{k: v for k, v in c.items() if k != "fps"} for c in data["cells"]]
    runs = [{k: (v.replace(str(path.resolve()), "OUT") if k == "command" else v) for k, v in r.items()
             if k not in ("fps", "wall_s", "attempts")} for r in data["runs"]]
    return cells, runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--out", default="/tmp/bench_sweep")
    ap.add_argument("--check-alone", action="store_true", help="also make the first cell's runs on their own")
    args = ap.parse_args()
    root = Path(args.out)
    seqs = []
    for k in range(3):
        folder = root / "data" / f"loop{k}_{args.frames}"
        if not (folder / "scene.json").is_file():
            render_sequence(folder, SynthOptions(frames=args.frames, scene_seed=k), force=True, progress=False)
        seqs.append(folder)
    manifest = root / "sweep.yaml"
    manifest.write_text("sequences:\n" + "".join(f"  - {{name: loop{k}, path: {p}, kind: tum}}\n"
                                                  for k, p in enumerate(seqs))
                        + f"vocabularies: [orb, hgcn]\nruns: {args.runs}\nsequential: true\n")
    walls = {}
    for jobs in (1, 2):
        out = root / f"jobs{jobs}"
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        sw = run_sweep(manifest, out, jobs=jobs, progress=False)
        walls[jobs] = time.perf_counter() - t0
        failed = sum(1 for r in sw.runs if not r.outcome.counts)
        print(f"--jobs {jobs} ({sw.engine}): {len(sw.runs)} runs in {walls[jobs]:.1f} s, {failed} failed")
    print((root / "jobs1" / "sweep.md").read_text())
    same = comparable(root / "jobs1") == comparable(root / "jobs2")
    print(f"wall time: --jobs 1 {walls[1]:.1f} s, --jobs 2 {walls[2]:.1f} s (x{walls[1] / walls[2]:.2f})")
    print(f"tables equal (every figure but fps): {same}")
    if args.check_alone:
        data = json.loads((root / "jobs1" / "sweep.json").read_text())
        cell = data["cells"][0]
        for r in data["runs"]:
            if (r["sequence"], r["vocab"]) != (cell["sequence"], cell["vocabulary"]):
                continue
            argv = r["command"].split()[1:]
            alone = root / "alone" / r["out"]
            argv[argv.index("--out") + 1] = str(alone)
            subprocess.run([sys.executable, "-m", "orbslam_hgcn", *argv], check=False, capture_output=True)
            kf = "KeyFrameTrajectory.txt"
            equal = (alone / kf).read_text() == (root / "jobs1" / r["out"] / kf).read_text()
            print(f"{r['out']} made on its own: same keyframe trajectory as in the sweep: {equal}")


if __name__ == "__main__":
    main()
