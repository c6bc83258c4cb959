"""Every code cell of the tutorial notebooks runs (no Jupyter needed)."""

import json
import pathlib

import pytest

NOTEBOOKS = sorted((pathlib.Path(__file__).parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs(path):
    nb = json.loads(path.read_text())
    ns: dict = {"__name__": "__notebook__"}
    for i, cell in enumerate(c for c in nb["cells"] if c["cell_type"] == "code"):
        src = "".join(cell["source"])
        exec(compile(src, f"{path.name}[cell {i}]", "exec"), ns)
    # the tour's claims, checked on its own numbers
    import numpy as np

    assert np.median(ns["frac"][ns["strip"]]) < 0.1
    assert np.median(ns["std_map"][ns["strip"]]) < np.median(ns["std_map"][~ns["strip"]])
