"""The tutorial notebooks on the real HERA files (``NEEDS_REAL`` of tests/test_notebooks.py, whose
``run_notebook`` runs and checks them; skipped where the files are absent): a file of their own so that
pytest-xdist's ``--dist loadfile`` can run them on one worker and the simulated notebooks on the other."""

import pytest
from test_notebooks import NEEDS_REAL, NOTEBOOKS, run_notebook

REAL_NOTEBOOKS = [p for p in NOTEBOOKS if p.name in NEEDS_REAL]


@pytest.mark.slow
@pytest.mark.parametrize("path", REAL_NOTEBOOKS, ids=[p.name for p in REAL_NOTEBOOKS])
def test_notebook_runs(path, monkeypatch):
    run_notebook(path, monkeypatch)
