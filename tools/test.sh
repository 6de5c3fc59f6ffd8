#!/usr/bin/env bash
# Set up the environment (tools/setup.sh) and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/setup.sh
exec .venv/bin/python -m pytest -q -rs -p no:cacheprovider "$@"
