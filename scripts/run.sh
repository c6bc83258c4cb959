#!/usr/bin/env bash
# Set up, then run the paper's standard case (200 GCR draws) into runs/standard/.
# Extra arguments go to `gcrsky run` (see `gcrsky run --help`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/gcrsky run --out runs/standard "$@"
