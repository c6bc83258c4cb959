"""``gcrsky.inference.chain_diagnostics``: the ESS of every sampled scalar against the floor (issue 38 item 4).

References: AR(1) chains ``x_t = rho x_{t-1} + sqrt(1 - rho^2) e_t`` have the closed-form ESS
``n (1 - rho) / (1 + rho)`` (the integrated autocorrelation time ``(1 + rho) / (1 - rho)``);
independent draws have ESS ``n``.  Tolerances: the estimator's sampling spread for these
lengths (the median over 20 chains of 20000 draws is within ~3 %; 10 % is allowed).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("blackjax")

from gcrsky.inference import chain_diagnostics, diagnostics_warning  # noqa: E402
from gcrsky.inference.diagnostics import ESS_FLOOR, MIN_DRAWS  # noqa: E402


def _ar1(rng, rho: float, n: int, k: int) -> np.ndarray:
    """(n, k) stationary AR(1) chains of unit variance."""
    x = np.empty((n, k))
    x[0] = rng.standard_normal(k)
    e = rng.standard_normal((n, k)) * np.sqrt(1 - rho**2)
    for t in range(1, n):
        x[t] = rho * x[t - 1] + e[t]
    return x


def test_ess_matches_the_closed_form_of_ar1_and_independent_draws():
    rng = np.random.default_rng(0)
    n = 20000
    d = chain_diagnostics({"iid": rng.standard_normal((n, 20)), "ar": _ar1(rng, 0.5, n, 20)})
    assert d["ndraws"] == n and d["n_scalars"] == 40 and d["floor"] == ESS_FLOOR
    assert d["groups"]["iid"]["ess_median"] == pytest.approx(n, rel=0.1)
    assert d["groups"]["ar"]["ess_median"] == pytest.approx(n * 0.5 / 1.5, rel=0.1)
    assert d["ok"] and d["n_below_floor"] == 0 and d["below_floor"] == []
    assert d["worst"].startswith("ar[")  # the correlated chain is the least mixed
    assert d["groups"]["ar"]["split_rhat_max"] == pytest.approx(1.0, abs=0.05)
    assert "ess" not in d["groups"]["ar"]  # more than FULL_LIST scalars: min, median and worst only
    assert diagnostics_warning(d) is None
    json.dumps(d)  # JSON-friendly


def test_slow_and_stuck_scalars_are_named_below_the_floor():
    rng = np.random.default_rng(1)
    n = 2000
    slow = _ar1(rng, 0.995, n, 1)[:, 0]  # ESS ~ n / 400 = 5: far below 100
    stuck = np.full(n, 0.7)  # a scalar that never moved
    d = chain_diagnostics({"q": rng.standard_normal((n, 3)), "s": slow, "theta": stuck[:, None]})
    assert not d["ok"] and d["n_below_floor"] == 2
    assert d["below_floor"] == ["theta[0]", "s"]  # the worst first: never moved, then the slow one
    assert d["groups"]["theta"]["ess"] == [None] and d["ess_min"] is None
    assert d["groups"]["s"]["ess_min"] < 30
    assert set(d["groups"]["q"]["ess"]) and min(d["groups"]["q"]["ess"]) > ESS_FLOOR
    line = diagnostics_warning(d, "the gain chain")
    assert line.startswith("WARNING: the gain chain has not mixed: 2 of 5 sampled scalars")
    assert "theta[0]" in line and "never moved" in line
    json.dumps(d)


def test_a_custom_floor_and_a_chain_too_short_to_tell():
    rng = np.random.default_rng(2)
    x = rng.standard_normal((400, 2))
    assert sorted(chain_diagnostics({"x": x}, floor=1000)["below_floor"]) == ["x[0]", "x[1]"]
    short = chain_diagnostics({"x": x[:MIN_DRAWS - 1]})
    assert short["ok"] is None and short["n_below_floor"] is None and diagnostics_warning(short) is None


def test_bad_chains_are_refused():
    with pytest.raises(ValueError, match="at least one"):
        chain_diagnostics({})
    with pytest.raises(ValueError, match="different numbers of draws"):
        chain_diagnostics({"a": np.zeros(10), "b": np.zeros((11, 2))})
    with pytest.raises(ValueError, match=r"\(ndraws,\) or \(ndraws, k\)"):
        chain_diagnostics({"a": np.zeros((10, 2, 2))})
