#!/usr/bin/env bash
# Create (or reuse) the project's virtual environment in .venv and install gcrsky
# with its test dependencies.  Idempotent; needs only the package index.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e ".[all,test]"
