#!/usr/bin/env bash
# Build the documentation site into site/ (mkdocs-material + mkdocstrings + mkdocs-jupyter).
#
#   bash scripts/docs.sh                          # strict build, notebooks executed (~1.5 min on 2 cores)
#   GCRSKY_DOCS_EXECUTE=false bash scripts/docs.sh  # notebooks rendered without running them (~10 s)
#   bash scripts/docs.sh serve                    # live preview on http://127.0.0.1:8000 (same options)
#
# Needs .venv with gcrsky (bash scripts/setup.sh); installs the `docs` extra into it when
# mkdocs or one of the plugins is missing. Extra arguments go to `mkdocs build`.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ ! -x .venv/bin/python ]; then
  echo "scripts/docs.sh: no .venv; run 'bash scripts/setup.sh' first" >&2
  exit 1
fi

if ! .venv/bin/python - <<'EOF' 2>/dev/null
import importlib.util, sys
mods = ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python", "mkdocs_autorefs",
        "mkdocs_jupyter", "mkdocs_include_markdown_plugin", "ipykernel", "pyradiosky", "matplotlib")
sys.exit(any(importlib.util.find_spec(m) is None for m in mods))
EOF
then
  echo "scripts/docs.sh: installing the docs extra into .venv" >&2
  .venv/bin/python -m pip install --quiet -e ".[docs]"
fi

# The notebooks run in a kernel started from this environment: keep XLA's CPU pool single-threaded
# (see gcrsky/parallel/runtime.py) and matplotlib off-screen; never reach for a network.
export XLA_FLAGS="${XLA_FLAGS:---xla_cpu_multi_thread_eigen=false}"
export PJRT_NPROC="${PJRT_NPROC:-8}"   # room for blocked batched LAPACK calls (gcrsky/parallel/runtime.py)
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"  # healpy's OpenMP threads must not spin (gcrsky/parallel/runtime.py)
export MPLBACKEND="${MPLBACKEND:-Agg}"
export NO_MKDOCS_2_WARNING=1

if [ "${1:-}" = "serve" ]; then
  shift
  exec .venv/bin/mkdocs serve --strict "$@"
fi
exec .venv/bin/mkdocs build --strict --site-dir site "$@"
