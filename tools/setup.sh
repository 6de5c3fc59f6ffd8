#!/usr/bin/env bash
# Create (or refresh) the project's virtual environment in .venv with everything installed.
# torch is pinned first to the CPU build so that no CUDA stack is pulled in.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if ! "$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)'; then
    echo "orbslam_hgcn needs Python 3.11 or newer; $("$PY" --version 2>&1) found (set PYTHON=...)" >&2
    exit 1
fi
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
stamp=.venv/.installed-$(cat pyproject.toml | cksum | cut -d' ' -f1)
if [ ! -f "$stamp" ]; then
    .venv/bin/python -m pip install -q --upgrade pip
    .venv/bin/python -m pip install -q "torch==2.13.0"
    .venv/bin/python -m pip install -q -e ".[test]"
    rm -f .venv/.installed-*
    touch "$stamp"
fi
# Byte-compile the package (an editable install does not), so that no run compiles source.
.venv/bin/python -m compileall -q orbslam_hgcn >/dev/null
# Build the compiled kernels for this machine now rather than in the first run (about a
# minute on 2 cores; a run then loads them without numba); returns at once when the build
# is up to date, and falls back to numba's cache when it cannot build.
.venv/bin/python -m orbslam_hgcn.runtime.kernels
