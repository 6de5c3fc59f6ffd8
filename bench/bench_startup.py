"""Start-up of ``orbslam-hgcn run``: from the command to the first frame handed in.

    python bench/bench_startup.py [--sequence ../shared/data/kitti00_first160/sequences/00]
                                  [--dataset kitti] [--runs 5] [--record NAME]

Each run starts ``python -m orbslam_hgcn run SEQUENCE --max-frames 3 --speed 0`` (a
process of its own, as a user's command) and measures, as ``bench_peer.py``'s ``start s``:
from starting the process to its log line "N frames, camera ..." (interpreter, imports,
configuration, vocabulary, dataset; just before ``System.run``), plus ``stats.json``
``real_time.startup_s`` (from there to the first frame's extraction: threads and child
processes started, extractors warmed). Printed per run, with where the compiled kernels came
from (``stats.json`` ``kernels``: built ahead of time, or numba and why) and whether the run
compiled any (numba's cache written); then the median. Run it in a fresh clone after
``bash tools/setup.sh`` to see what a user's first runs cost.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_peer import RUN_READY  # noqa: E402 - a sibling script
from figures import record  # noqa: E402 - a sibling script

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SEQUENCE = REPO.parent / "shared" / "data" / "kitti00_first160" / "sequences" / "00"


def numba_cache_files() -> dict[str, int]:
    """numba's cache files of the package (index and code) and their mtimes."""
    root = Path(os.environ.get("NUMBA_CACHE_DIR") or REPO / "orbslam_hgcn")
    return {str(p): p.stat().st_mtime_ns for p in root.rglob("*") if p.suffix in (".nbi", ".nbc")}


def one_run(sequence: Path, dataset: str, out: Path) -> dict[str, object]:
    cmd = [sys.executable, "-m", "orbslam_hgcn", "run", str(sequence), "--dataset", dataset, "--out", str(out),
           "--max-frames", "3", "--speed", "0", "--no-progress"]  # fmt: skip
    before = numba_cache_files()
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})  # fmt: skip
    assert proc.stdout is not None
    ready_at, lines = None, []
    for line in proc.stdout:
        lines.append(line)
        if ready_at is None and RUN_READY.search(line):
            ready_at = time.monotonic()
    if proc.wait() != 0 or ready_at is None:
        raise SystemExit(f"the run failed:\n{''.join(lines[-20:])}")
    stats = json.loads((out / "stats.json").read_text())
    kernels = stats.get("kernels", {})
    source = ("built ahead of time" if kernels.get("built_ahead") and not kernels.get("numba_imported")
              else f"numba ({kernels.get('not_built_why')})")  # fmt: skip
    changed = {k for k, v in numba_cache_files().items() if before.get(k) != v}
    return {
        "to_ready_s": ready_at - t0,
        "startup_s": float(stats["real_time"]["startup_s"]),
        "start_s": ready_at - t0 + float(stats["real_time"]["startup_s"]),
        "kernels": source,
        "compiled": len(changed),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    parser.add_argument("--dataset", default="kitti")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--record", default=None, help="record the figures as bench/results/NAME.json")
    args = parser.parse_args(argv)
    if not args.sequence.is_dir():
        print(f"no sequence at {args.sequence}", file=sys.stderr)
        return 2
    load_start = os.getloadavg()[0]
    print(f"{args.sequence} ({args.dataset}); {os.cpu_count()} CPUs, load average {load_start:.1f}; "
          f"PYTHONDONTWRITEBYTECODE={os.environ.get('PYTHONDONTWRITEBYTECODE', '')!r}")
    print(f"{'run':>4s} {'to log s':>8s} {'+ run s':>8s} {'start s':>8s} {'compiled':>8s}  kernels")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            row = one_run(args.sequence, args.dataset, Path(tmp) / f"run{i}")
            rows.append(row)
            print(f"{i + 1:>4d} {row['to_ready_s']:8.3f} {row['startup_s']:8.3f} {row['start_s']:8.3f} "
                  f"{row['compiled']:>8d}  {row['kernels']}", flush=True)
    starts = [float(r["start_s"]) for r in rows]
    med = statistics.median(starts)
    kernels = sorted({str(r["kernels"]) for r in rows})
    line = (f"median start-up {med:.3f} s over {len(rows)} runs (run by run "
            f"{', '.join(f'{s:.3f}' for s in starts)} s); kernels: {', '.join(kernels)}; "
            f"numba cache files written: {sum(int(r['compiled']) for r in rows)}")
    print(line)
    if args.record:
        figs = [("sequence", f"{args.sequence.name} ({args.dataset})")]
        figs += [(f"run {i + 1}", f"{r['start_s']:.3f} s ({r['to_ready_s']:.3f} s to the log line, "
                  f"{r['startup_s']:.3f} s in System.run); {r['compiled']} numba cache files written")
                 for i, r in enumerate(rows)]  # fmt: skip
        figs.append(("median", line))
        record(args.record, "Start-up of orbslam-hgcn run: command to the first frame handed in", figs,
               bench_file=__file__, load_start=load_start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
