#!/usr/bin/env bash
# Set up, then run the paper's standard case (200 GCR draws) into runs/standard/.
# Extra arguments go to `gcrsky run` (see `gcrsky run --help`).
# Re-runnable: an earlier run in runs/standard/ is replaced (--overwrite), so the
# results always come from this code and these arguments; pass --resume instead to
# continue a run that was killed (it must have the same arguments).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
mode=(--overwrite)
for a in "$@"; do
  case "$a" in --resume|--overwrite) mode=() ;; esac
done
exec .venv/bin/gcrsky run --out runs/standard ${mode[@]+"${mode[@]}"} "$@"
