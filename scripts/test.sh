#!/usr/bin/env bash
# Set up, then run the whole test suite: one pytest worker per core, each test file on one
# worker (module fixtures are built once); about 12 minutes on 2 cores.  Extra arguments go
# to pytest, e.g. -m "not slow" for the fast subset, or -n 0 for a single process.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# A larger main-thread stack for the workers: XLA compiles on the calling thread, and two workers died in
# backend_compile_and_load (segfault, the compile of a Gibbs / NUTS program) with the default 8 MB.
ulimit -s unlimited 2>/dev/null || ulimit -s 1048576 2>/dev/null || true
exec .venv/bin/python -m pytest -q -n auto --dist loadfile "$@"
