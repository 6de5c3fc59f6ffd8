#!/usr/bin/env bash
# Set up the environment (tools/setup.sh), then run `orbslam-hgcn demo`: render the built-in
# synthetic loop sequence (cached after the first time), run SLAM with the shipped HGCN
# vocabulary and then the ORB baseline, print the ATE of both, and leave a rerun recording
# in demo_out/demo.rrd. Extra arguments go to the demo command (see --help).
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/setup.sh
exec .venv/bin/orbslam-hgcn demo "$@"
