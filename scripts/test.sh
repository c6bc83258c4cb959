#!/usr/bin/env bash
# Set up, then run the whole test suite: one pytest worker per core, each test file on one
# worker (module fixtures are built once); about 12 minutes on 2 cores.  Extra arguments go
# to pytest, e.g. -m "not slow" for the fast subset, or -n 0 for a single process.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python -m pytest -q -n auto --dist loadfile "$@"
