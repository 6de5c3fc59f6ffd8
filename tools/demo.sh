#!/usr/bin/env bash
# Set up the environment (tools/setup.sh), render the built-in synthetic loop sequence
# (cached after the first time), run SLAM on it and print the ATE against ground truth.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/setup.sh
CACHE=${ORBSLAM_HGCN_CACHE:-$HOME/.cache/orbslam_hgcn}
SEQ="$CACHE/synth_loop"
OUT=${1:-runs/demo}
.venv/bin/orbslam-hgcn synth --out "$SEQ"
.venv/bin/orbslam-hgcn run "$SEQ" --out "$OUT" "${@:2}"
.venv/bin/orbslam-hgcn eval --gt "$SEQ/groundtruth.txt" --est "$OUT/KeyFrameTrajectory.txt" --out "$OUT"
