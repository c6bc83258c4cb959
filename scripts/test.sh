#!/usr/bin/env bash
# Set up, then run the whole test suite: one pytest worker per core, each test file on one
# worker (module fixtures are built once); about 40 minutes on 2 cores (the 25 slowest tests are
# listed at the end: where to look when CI nears its time).  Extra arguments go to pytest, e.g.
# -m "not slow" for the fast subset, or -n 0 for a single process.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# --max-worker-restart=0: a crashed worker ends the run with its error at once; pytest-xdist 3.8's loadfile
# scheduler can deadlock when it replaces a crashed worker (pytest-xdist#1323, #1378: the CI run of
# 2026-12-03 idled until its 90-minute limit after a worker crash).
exec .venv/bin/python -m pytest -q -n auto --dist loadfile --max-worker-restart=0 --durations=25 "$@"
