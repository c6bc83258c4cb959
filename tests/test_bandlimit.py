"""Band limit (gcrsky.model.bandlimit) and goodness of fit (gcrsky.run.fit).

The matvis test reads matvis's visibilities of such a sky (real times, radiometer noise from
the autos) through ``from_uvdata`` with each ``band_limit``.

The simulation is ``benchmarks/band_limit.py``'s (loaded from its file, one owner of
the case): 4 antennas of 6 m Gaussian dishes at 40 and 45 MHz, 12 times, a sky drawn
from ``C_l = 100 / (1 + l)^2`` to l = 36 = 3 x lmax, noise 0.02 K sr, modelled at
lmax 12.  The independent reference is the higher-degree model: the data are made
with every coefficient to l = 36, the fits see l <= 12, and the exact posterior of the
band-limited part is the dense posterior at l = 36 restricted to l <= 12.

Acceptance of the whitened error ``z2 = e^T Cov^-1 e / n`` (n = 169 per channel): under a
right model ``n z2`` is chi-square with n dof, so per channel z2 lies in
[0.680, 1.397] (99.9 %) and the two channels' mean in [0.750, 1.284] (99.9 % of chi-square
with 338 dof / 338).
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import isotropic_problem
from scipy import stats

from gcrsky.model.bandlimit import (
    baseline_reach,
    beam_dish_m,
    choose_lmax,
    cut_rows,
    equivalent_dish_m,
    extend_cl,
    memory_lmax,
    required_lmax,
)
from gcrsky.run.fit import fit_warning, goodness_of_fit

C = 299792458.0


def _bench():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "band_limit.py"
    spec = importlib.util.spec_from_file_location("band_limit_bench", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def bench():
    return _bench()


@pytest.fixture(scope="module")
def cases(bench):
    return bench.cases(seed=1, sigma=0.02)


# ---------------------------------------------------------------- reach


def test_reach_hand_values():
    lam = C / 100e6
    # lengths: 2 pi (|b| + D) / lambda; 14 m on a 14 m dish at 100 MHz: 2 pi 28 / 2.998 = 58.68
    r = baseline_reach(np.array([0.0, 14.0]), [100e6], 14.0)
    np.testing.assert_allclose(r[0], [2 * np.pi * 14 / lam, 2 * np.pi * 28 / lam], rtol=1e-12)
    assert abs(r[0, 1] - 58.68) < 0.01
    # ENU (driftscan): an east baseline of 14 m: 2 pi sqrt(28^2 + 14^2) / lambda = 65.6
    r = baseline_reach(np.array([[14.0, 0.0, 0.0], [0.0, -14.0, 0.0], [3.0, 4.0, 0.0]]), [100e6, 200e6], 14.0)
    np.testing.assert_allclose(r[0, 0], 2 * np.pi * np.hypot(28, 14) / lam, rtol=1e-12)
    np.testing.assert_allclose(r[0, 1], r[0, 0], rtol=1e-12)  # sign and axis symmetric
    np.testing.assert_allclose(r[1], 2 * r[0], rtol=1e-12)  # proportional to frequency
    np.testing.assert_allclose(r[0, 2], 2 * np.pi * np.hypot(17, 18) / lam, rtol=1e-12)
    assert required_lmax(r) == int(np.ceil(2 * r[0, 0]))
    with pytest.raises(ValueError, match="dish_diameter_m"):
        baseline_reach(np.ones(2), [1e8], 0.0)


def test_equivalent_dish_of_a_gaussian_beam():
    from gcrsky.instrument.beams import gaussian_beam

    # Airy: FWHM = 1.029 lambda / D; pyuvdata's GaussianBeam(D) has FWHM ~ lambda / D, so D_eq ~ 1.03 D
    assert equivalent_dish_m(1.02899 * 3.0 / 14.0, C / 3.0) == pytest.approx(14.0, rel=1e-9)
    d = beam_dish_m(gaussian_beam(14.0), [100e6, 150e6])
    np.testing.assert_allclose(d, 1.03 * 14.0, rtol=0.02)
    np.testing.assert_array_equal(beam_dish_m(None, [1e8, 2e8], 10.0), [10.0, 10.0])


def test_choose_lmax_reach_memory_and_given():
    reach = np.array([[10.2, 30.7]])
    assert choose_lmax(reach, None, n_rows=2, budget_bytes=1e12)[0] == 31
    lmax, note = choose_lmax(reach, None, n_rows=2, budget_bytes=1e6)
    assert lmax == memory_lmax(1, 2, 1e6) < 31 and note["chosen"] == "memory"
    assert choose_lmax(reach, 7, n_rows=2)[1] == {"lmax": 7, "reach": 31, "chosen": "given"}
    # few data values (28 rows x 10 times, like H1C): the data-space arrays are far smaller than a dense P, so the
    # cap is set by the response; by hand at lmax 150 (n 22801, response (28, 156^2) complex: 10.9 MB; N_d 560:
    # 3 x 2.5 MB + 2 x 102 MB) 0.22 GB fits 0.5 GB where the dense P (4.2 GB) does not
    dense_cap, ds_cap = memory_lmax(1, 28, 5e8), memory_lmax(1, 28, 5e8, n_times=10)
    assert dense_cap < 100 < 150 < ds_cap


def test_extend_cl_power_law():
    ell = np.arange(11.0)
    cl = 3.0 / (1 + ell) ** 2
    cl[1:] = 3.0 * ell[1:] ** -2.4
    ext = extend_cl(cl, 30)
    np.testing.assert_allclose(ext[0, 11:], 3.0 * np.arange(11, 31.0) ** -2.4, rtol=1e-9)


# ---------------------------------------------------------------- the 3 x lmax sky


def test_cut_rows_report(cases, bench):
    rep = cases["_report"]
    prob = cases["cut"][0]
    reach = baseline_reach(bench.ANTPOS_M[prob.antpairs[:, 1]] - bench.ANTPOS_M[prob.antpairs[:, 0]],
                           bench.FREQS_HZ, beam_dish_m(None, bench.FREQS_HZ, 1.03 * bench.DISH_M))
    assert rep["rows_cut"] == 3 and rep["samples_cut"] == 1 and rep["max_kept_length_m"] == 5.66
    # every sample kept is within reach; the partly cut row has weight 0 where it is not
    w = np.asarray(prob.weights).max(axis=1)  # (Nf, Nrow)
    assert np.all(w[reach > bench.LMAX + 0.2] == 0) and np.all(w[reach < bench.LMAX - 0.2] > 0)
    with pytest.raises(ValueError, match="reaches no baseline"):
        cut_rows(prob, 3, 6.0)


def test_whitened_error_cut_and_marginalised_pass_truncation_fails(cases, bench):
    truth = np.asarray(cases["cut"][0].a_true)
    z2 = {k: bench.whitened_z2(cases[k][1], cases[k][2], truth) for k in ("exact", "cut", "marginalise", "truncate")}
    n = truth.shape[1]
    lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], n) / n
    mlo, mhi = stats.chi2.ppf([5e-4, 1 - 5e-4], 2 * n) / (2 * n)
    for k in ("exact", "cut", "marginalise"):
        assert np.all((z2[k] > lo) & (z2[k] < hi)), (k, z2[k])
        assert mlo < z2[k].mean() < mhi, (k, z2[k])
    assert np.all(z2["truncate"] > 3 * hi), z2["truncate"]  # negative control: measured 10.2 and 14.6


def test_marginalised_close_to_exact(cases):
    """The diagonal marginalisation against the exact one (module docstring of gcrsky.model.bandlimit)."""
    a_ex, cov_ex = cases["exact"][1], cases["exact"][2]
    a_m, cov_m = cases["marginalise"][1], cases["marginalise"][2]
    sd_ex = np.sqrt(np.diagonal(cov_ex, axis1=1, axis2=2))
    ratio = np.sqrt(np.diagonal(cov_m, axis1=1, axis2=2)) / sd_ex
    err = np.sqrt(np.mean(((a_m - a_ex) / sd_ex) ** 2))
    assert err < 0.5 and 0.6 < ratio.min() and ratio.max() < 2.5, (err, ratio.min(), ratio.max())
    a_t = cases["truncate"][1]
    assert np.sqrt(np.mean(((a_t - a_ex) / sd_ex) ** 2)) > err  # truncation is further from the exact answer


# ---------------------------------------------------------------- goodness of fit


def test_fit_accepts_right_models_and_rejects_truncation(cases):
    full, a_full = cases["_full"]
    for name, (prob, a_wf) in {"full": (full, a_full), "cut": cases["cut"][:2],
                               "marginalise": cases["marginalise"][:2]}.items():
        gof = goodness_of_fit(prob, a_wf)
        dof = np.asarray(gof["dof"])
        lo, hi = stats.chi2.ppf(5e-4, dof) / dof, stats.chi2.isf(5e-4, dof) / dof
        assert np.all((gof["chi2_per_dof"] > lo) & (gof["chi2_per_dof"] < hi)), (name, gof["chi2_per_dof"])
        assert not gof["rejected"] and fit_warning(gof, prob.freqs_hz) is None
    prob, a_wf = cases["truncate"][:2]
    gof = goodness_of_fit(prob, a_wf)
    assert gof["rejected"] and gof["rejected_channels"] == [0, 1]  # measured p 4.7e-11 and 2e-8
    assert "does not fit" in fit_warning(gof, prob.freqs_hz)
    json.dumps(gof)  # JSON-friendly


def test_fit_chi2_equals_the_evidence_chi2(cases):
    from gcrsky.inference import log_evidence

    prob, a_wf = cases["marginalise"][:2]
    _, info = log_evidence(prob, method="cholesky", return_info=True)
    gof = goodness_of_fit(prob, a_wf)
    np.testing.assert_allclose(gof["chi2"], np.asarray(info.chi2), rtol=1e-8)
    np.testing.assert_array_equal(gof["dof"], np.asarray(info.n_data))


def test_fit_outliers_locate_a_corrupted_row_and_time(small_array, small_response, bench):
    """On the tests' small well-determined posterior (10 antennas, lmax 6): clean, then 20 sigma on one sample."""
    import dataclasses

    prob = isotropic_problem(small_array, small_response, np.linspace(0, 0.5, 6), seed=3)
    gof = goodness_of_fit(prob, bench.dense_posterior(prob)[0])
    assert not gof["rejected"] and gof["rows"]["n_outliers"] == 0 and gof["times"]["n_outliers"] == 0
    assert gof["n_values_beyond_z_max"] == 0
    assert all(0.7 < x < 1.0 for x in gof["residual_chi2_per_dof"])  # below 1: the posterior explains a part
    data = np.asarray(prob.data).copy()
    data[1, 4, 17] += 20 * 0.05  # 20 sigma on row 17 at time 4 in channel 1
    bad = dataclasses.replace(prob, data=data)
    gof = goodness_of_fit(bad, bench.dense_posterior(bad)[0])
    assert gof["rejected"] and gof["rejected_channels"] == [1]
    assert gof["rows"]["outliers"][0]["index"] == 17 and gof["times"]["outliers"][0]["label"] == "t4"
    assert gof["n_values_beyond_z_max"] >= 1


def test_run_summary_has_the_fit_and_warns_when_rejected(cases, tmp_path):
    from gcrsky.cli.terminal import fit_line
    from gcrsky.run import Draws, Output, RunSpec, Solver, execute

    out = {}
    for name in ("cut", "truncate"):
        summary, _ = execute(cases[name][0], RunSpec(Draws(4, 0, 4), Output(tmp_path / name), Solver("cholesky")))
        doc = json.loads((tmp_path / name / "summary.json").read_text())
        gof = doc["goodness_of_fit"]
        assert len(gof["chi2_per_dof"]) == 2 and len(gof["p_value"]) == 2
        np.testing.assert_allclose(gof["chi2"], goodness_of_fit(cases[name][0], cases[name][1])["chi2"], rtol=1e-6)
        out[name] = (summary, gof)
    assert not out["cut"][1]["rejected"] and not any("does not fit" in w for w in out["cut"][0].warnings)
    assert out["truncate"][1]["rejected"] and any("does not fit" in w for w in out["truncate"][0].warnings)
    assert "REJECTED in 2 channels" in fit_line(out["truncate"][1])


# ---------------------------------------------------------------- matvis: a file of a sky to 3 x lmax


@pytest.fixture(scope="module")
def matvis_file(bench):
    """matvis visibilities (real times at HERA, 23 h, 12 integrations, noise from the autos with
    dt dnu = 5e6) of a positive sky drawn from ``100 / (1 + l)^2`` to l = 36, on ``bench``'s array."""
    pytest.importorskip("matvis")
    from gcrsky.checks.matvis import HERA_SITE, observing_times, site
    from gcrsky.checks.uvsim import simulate_uvdata
    from gcrsky.instrument.beams import gaussian_beam
    from gcrsky.model import isotropic_prior
    from gcrsky.sphere.maps import alm_to_map

    cl = 100.0 / (1 + np.arange(bench.LMAX_SKY + 1)) ** 2
    var = 1 / np.asarray(isotropic_prior(cl[None], (bench.LMAX_SKY + 1) ** 2).inv_var)[0]
    a = np.sqrt(var) * np.random.default_rng(2).standard_normal(var.size)
    a[0] = 0.0
    a[0] = -alm_to_map(a, bench.LMAX_SKY, 32).min() / (0.9 / np.sqrt(4 * np.pi))  # positive: min = 10 % of mean
    sim = simulate_uvdata(bench.ANTPOS_M, site(*HERA_SITE), observing_times("2025-03-21T00:00:00", 23.0, 12),
                          bench.FREQS_HZ, gaussian_beam(bench.DISH_M), a, bench.LMAX_SKY, nside_matvis=64,
                          dt_s=10.0, dnu_hz=5e5)
    prior_cl = cl[: bench.LMAX + 1].copy()
    prior_cl[0] = (2 * a[0]) ** 2  # a broad monopole prior around the positive sky's mean
    return sim.uvdata, a[bench.low_index(bench.LMAX, bench.LMAX_SKY)], prior_cl


@pytest.mark.parametrize("mode", ["cut", "marginalise", "truncate"])
def test_matvis_file_cut_and_marginalised_pass_truncation_fails(matvis_file, bench, mode):
    """from_uvdata at lmax 12 on matvis's data of a sky to l = 36 (the independent simulator).

    Measured z2 per channel: cut 0.96, 0.99; marginalise 0.69, 0.75 (the diagonal is
    conservative here: its posterior is wider than the exact one); truncate 4.8, 32.
    """
    from gcrsky.ingest import from_uvdata

    uvd, truth, prior_cl = matvis_file
    prob = from_uvdata(uvd, lmax=bench.LMAX, nside=32, dish_diameter_m=bench.DISH_M, prior=prior_cl,
                       band_limit=mode, compress=False)
    a_wf, cov = bench.dense_posterior(prob)
    z2 = bench.whitened_z2(a_wf, cov, np.broadcast_to(truth, a_wf.shape))
    gof = goodness_of_fit(prob, a_wf)
    check = prob.config.checks["band_limit"]
    n = truth.size
    lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], n) / n
    assert check["mode"] == mode and check["lmax"] == bench.LMAX and check["rows_beyond_lmax"] == 4
    if mode == "truncate":
        assert z2.max() > 3 * hi and gof["rejected"], (z2, gof["p_value"])
        return
    assert not gof["rejected"], gof["p_value"]
    assert np.all(z2 < hi) and np.all(z2 > (lo if mode == "cut" else 0.6)), z2
    if mode == "cut":
        assert check["rows_cut"] == 3 and check["cut_lengths_m"] == [5.66, 9.43, 12.04, 13.0]
    else:
        assert check["lmax_hi"] == 20 and 0 < check["added_std_over_noise"]["median"]


def test_matvis_file_default_lmax_is_the_reach(matvis_file, bench):
    """Without lmax, from_uvdata models every baseline: lmax = the reach of the longest at 45 MHz, nothing cut."""
    from gcrsky.ingest import from_uvdata

    uvd, _, prior_cl = matvis_file
    prob = from_uvdata(uvd, nside=16, dish_diameter_m=bench.DISH_M, prior=np.concatenate([prior_cl, [prior_cl[-1]] * 8]),
                       band_limit="cut", compress=False, memory_budget=1e9)
    check = prob.config.checks["band_limit"]
    assert prob.lmax == check["reach"] == 20 and check["chosen"] == "reach"
    assert check["rows_cut"] == check["samples_cut"] == check["rows_beyond_lmax"] == 0
    assert prob.antpairs.shape[0] == 6


def test_fit_chi2_error_is_second_order_in_the_wiener_error(cases):
    """A Wiener filter off by delta (an iterative solver's) raises chi2 by exactly delta^T P delta >= 0."""
    prob, a_wf, cov = cases["marginalise"]
    sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    delta = 0.1 * sd * np.random.default_rng(0).standard_normal(sd.shape)
    p = np.asarray(prob.precision_matrix())
    exact = np.asarray(goodness_of_fit(prob, a_wf)["chi2"])
    off = np.asarray(goodness_of_fit(prob, a_wf + delta)["chi2"])
    np.testing.assert_allclose(off - exact, np.einsum("fi,fij,fj->f", delta, p, delta), rtol=1e-6)


def test_run_fit_with_a_flat_prior_counts_the_eigen_rank(small_array, small_response, tmp_path):
    """A flat prior on one snapshot of the small hexagon (lmax 6: 49 parameters, 90 data values per
    channel): the eigen path keeps the constrained directions (measured rank 12) and the fit's dof is
    n_data minus that rank (78), not minus the 49 flat directions; chi2/dof measured 0.81 and 0.83."""
    import dataclasses

    from gcrsky.model import flat_prior
    from gcrsky.run import Draws, Output, RunSpec, Solver, execute

    prob = isotropic_problem(small_array, small_response, np.array([0.0]), seed=3)
    flat = dataclasses.replace(prob, prior=flat_prior(*np.shape(prob.prior.inv_var)))
    summary, _ = execute(flat, RunSpec(Draws(4, 0, 4), Output(tmp_path / "flat"), Solver("eigh")))
    gof, rank = summary.goodness_of_fit, np.asarray(summary.solver["rank"])
    n_data = 2 * np.sum(np.asarray(prob.weights) > 0, axis=(1, 2))
    assert np.all(rank < prob.n) and np.all(rank < n_data)
    np.testing.assert_array_equal(gof["dof"], n_data - rank)
    dof = np.asarray(gof["dof"])
    lo, hi = stats.chi2.ppf(5e-4, dof) / dof, stats.chi2.isf(5e-4, dof) / dof
    assert not gof["rejected"] and np.all((gof["chi2_per_dof"] > lo) & (gof["chi2_per_dof"] < hi))


def test_fit_with_no_degree_of_freedom_left_tests_nothing(cases):
    """As many fitted flat directions as data (the cut case, flat): dof 0, no p-value, not rejected."""
    import dataclasses

    from gcrsky.cli.terminal import fit_line
    from gcrsky.model import flat_prior

    prob, _, _ = cases["cut"]
    flat = dataclasses.replace(prob, prior=flat_prior(*np.shape(prob.prior.inv_var)))
    n_data = 2 * np.sum(np.asarray(prob.weights) > 0, axis=(1, 2))
    gof = goodness_of_fit(flat, np.zeros(np.shape(prob.prior.mean)), rank=n_data)
    assert gof["dof"] == [0.0, 0.0] and gof["p_value"] == [None, None] and not gof["rejected"]
    assert "chi2/dof -, -" in fit_line(gof)


def test_fit_rows_are_labelled_by_the_file_s_antenna_numbers():
    """Issue 39: the fit's outlying rows named antenna indices ("2-4"); a file's rows say its antenna numbers
    (H1C: 0, 1, 11, 12, ...), a problem without them keeps the indices."""
    from types import SimpleNamespace

    from gcrsky.run.fit import _residual_groups

    z2 = np.ones((1, 4, 3))
    z2[0, :, 2] = 50.0  # row 2 (indices 1-2) is the outlier
    count = np.full(z2.shape, 2.0)
    prob = SimpleNamespace(antpairs=np.array([[0, 1], [0, 2], [1, 2]]), pols=None,
                           config=SimpleNamespace(conventions={"antenna_numbers": [0, 11, 12]}))
    got = _residual_groups(prob, z2, count, np.sqrt(z2), 0.01)["rows"]["outliers"]
    assert [o["label"] for o in got] == ["11-12"]
    bare = _residual_groups(SimpleNamespace(antpairs=prob.antpairs, pols=None, config=None), z2, count,
                            np.sqrt(z2), 0.01)["rows"]["outliers"]
    assert [o["label"] for o in bare] == ["1-2"]
