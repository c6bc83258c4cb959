"""``gcrsky run --data`` on a small :mod:`gcrsky.checks.hera_sim` file: automatic lmax, compression, the truth.

A 19-antenna hexagon of 4 m dishes 4 m apart at 100 MHz (reach 42, the sky drawn to 49), 8
LSTs over 8 h: the run must merge the 171 baselines into their 30 groups before any response
is built (positions read through ECEF differ by ~1e-9 m), choose the reach as lmax, fit the
data (chi^2/dof ~ 1: the data-dominated directions), and its posterior must cover the truth
(whitened error z^2 ~ 1 over the coefficients; no single one is data-dominated in an 8-LST strip).
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from gcrsky import cli
from gcrsky.checks.hera_sim import hex_rows, reach_lmax, simulate_hera_file
from gcrsky.instrument import hex_array
from gcrsky.sphere.modes import mode_table

NDRAWS = 60


@pytest.fixture(scope="module")
def hera_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("hera")
    sim = simulate_hera_file(d / "hex19.uvh5", n_side=3, spacing_m=4.0, dish_m=4.0, n_times=8, seed=3)
    rc = cli.main(["run", "--data", str(sim.path), "--dish-diameter", "4", "--nside", str(sim.nside),
                   "--nsamples", str(NDRAWS), "--out", str(d / "run"), "--no-progress", "--no-plots",
                   "--flux-scale", "accept"])  # a 4 m dish's autos of this draw are ~2x the GSM's: not the point
    return sim, d / "run", rc


def test_hex_rows_and_reach():
    assert hex_rows(7) == (7, 8, 9, 10, 11, 12, 13, 12, 11, 10, 9, 8, 7) and sum(hex_rows(7)) == 127
    assert reach_lmax(hex_array(hex_rows(7)), 100e6, 14.0) == 409  # 2 pi (175.2 m + 14.4 m) / 2.998 m


@pytest.mark.slow
def test_run_on_a_hera_sim_file_chooses_the_reach_and_covers_the_truth(hera_run):
    sim, out, rc = hera_run
    assert rc == 0
    assert (sim.n_antennas, sim.n_baselines, sim.n_groups) == (19, 171, 30)
    assert sim.lmax_sky > sim.reach and 0.15 < sim.noise_fraction < 0.3
    s = json.loads((out / "summary.json").read_text())
    band = s["data_checks"]["band_limit"]
    assert band["chosen"] == "reach" and band["lmax"] == sim.reach and band["rows_cut"] == 0
    assert s["config"]["compressed"] and band["rows_for_memory"] == 30
    assert s["run"]["method"] in ("dataspace", "cholesky")
    assert 0.8 < s["goodness_of_fit"]["chi2_per_dof"][0] < 1.2 and not s["goodness_of_fit"]["rejected"]
    lmax = band["lmax"]
    with h5py.File(out / "results.h5", "r") as h:
        assert h["antpairs"].shape == (30, 2)
        wf, draws = h["wiener_filter"][0], h["draws"][0]
        ell, m, im = h["modes/ell"][()], h["modes/m"][()], h["modes/is_imag"][()]
        prior_sd = 1.0 / np.sqrt(h["prior_inv_var"][0])
    full = mode_table(sim.lmax_sky)
    index = {(int(a), int(b), bool(c)): k for k, (a, b, c) in enumerate(zip(full.ell, full.m, full.is_imag))}
    truth = sim.a_true[0, [index[(int(a), int(b), bool(c))] for a, b, c in zip(ell, m, im)]]
    sd = draws.std(axis=0, ddof=1)
    assert ell.max() == lmax and np.median(sd / prior_sd) < 1.0  # the data narrow the prior
    # no single coefficient is decided by a drift-scan strip; the truth is a draw from the prior, so over
    # every coefficient the whitened error is ~1 (x 59/57 for the 60 draws' variance); measured 1.10
    z2 = float(np.mean(((wf - truth) / sd) ** 2))
    assert 0.85 < z2 < 1.3, z2
