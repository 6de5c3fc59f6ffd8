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
# Compile the numba kernels once now rather than in the first run (40 to 60 s on 2 cores);
# returns at once when numba's cache already holds them.
.venv/bin/python -m orbslam_hgcn.runtime.kernels
