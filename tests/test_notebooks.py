"""Every code cell of the tutorial notebooks runs (no Jupyter needed)."""

import json
import pathlib

import pytest

NOTEBOOKS = sorted((pathlib.Path(__file__).parents[1] / "notebooks").glob("*.ipynb"))

#: Notebooks run at reduced size: values set right after the first code cell (which
#: holds the notebook's parameters) has run, before every later cell.
OVERRIDES = {
    "standard_case.ipynb": {"LMAX": 8, "NSIDE": 32, "NSAMPLES": 20},
    "hyperparameters.ipynb": {"LMAX": 8, "NSIDE": 32, "GRID": 4, "STEPS": 8},
    "gibbs.ipynb": {"LMAX": 8, "NSIDE": 32, "STEPS": 1500, "NUTS_WARMUP": 150, "NUTS_SAMPLES": 300},
    "point_sources.ipynb": {"LMAX": 8, "NSIDE": 32, "STEPS": 1500},
    "real_data.ipynb": {"LMAX": 8, "BAND_LIMIT": "marginalise", "NSIDE": 64, "NSAMPLES": 20},  # nside 64: the kept fringes resolved
    "frequency.ipynb": {"NCHAN": 12, "LMAX": 4, "NTIMES": 10, "FLAG_BLOCKS": ((3, 2), (7, 2)), "NDRAWS": 100},
    "calibration.ipynb": {"HEX_ROWS": (2, 3), "LMAX": 4, "NSIDE": 16, "STEPS": 1000, "BURN": 200,
                          "H1C_LMAX": 8, "H1C_STEPS": 100, "H1C_BURN": 100},
}

#: Notebooks that read the real HERA files (skipped where ../shared/data/real is absent).
from conftest import REAL  # noqa: E402

NEEDS_REAL = {"real_data.ipynb", "calibration.ipynb"}


def test_every_notebook_is_run_and_checked():
    assert {p.name for p in NOTEBOOKS} == set(CHECKS) and NEEDS_REAL <= set(CHECKS)


def _check_quickstart(ns):
    import numpy as np

    assert np.median(ns["frac"][ns["strip"]]) < 0.1
    assert np.median(ns["std_map"][ns["strip"]]) < np.median(ns["std_map"][~ns["strip"]])


def _check_standard_case(ns):
    import os

    import numpy as np

    assert ns["draws"].shape == (2, 20, (8 + 1) ** 2)
    assert np.all(np.isfinite(ns["draws"]))
    m = ns["metrics"]
    assert m["frac_diff_centre_median"] < 0.1
    assert m["frac_diff_fwhm_median"] < 0.1
    assert m["frac_diff_centre_median"] < m["frac_diff_sky_median"]  # the beam region is the well-measured part
    assert ns["ring_ra"].shape == (4 * 32,)
    for name in ("fig4_sky_maps.png", "fig5_beam_region.png", "fig6_slice.png"):
        assert os.path.getsize(os.path.join(ns["FIGDIR"], name)) > 10_000


def _check_hyperparameters(ns):
    import numpy as np

    fit, fit_b = ns["fit"], ns["fit_b"]
    assert fit.converged and fit_b.converged
    # the simulated scales (0, 0) lie within 4 Laplace sigma of the fit
    assert np.all(np.abs(np.asarray(fit.theta)) < 4 * np.asarray(fit.std)), (fit.theta, fit.std)
    assert abs(ns["d_fit"] - 14.0) < 4 * ns["d_fit"] * float(fit_b.std[0])
    assert abs(ns["beta_fit"] + 2.5) < 4 * float(fit_b.std[1])
    assert ns["surface"].shape == (4, 4) and np.all(np.isfinite(ns["surface"]))


def _check_gibbs(ns):
    import numpy as np

    # the free C_l chain (uniform prior): finite, positive, and at this small size (lmax 8) its 99%
    # intervals hold the simulated sky's sigma_l at all but at most one degree (at lmax 20 they do at
    # 14 of 20: poorly seen degrees and a non-Gaussian sky, see the notebook)
    assert np.all(np.isfinite(ns["cls"])) and np.all(ns["cls"][:, 1:] > 0)
    assert ns["inside"].sum() >= len(ns["inside"]) - 1, (ns["inside"], ns["ratio"])
    # Gibbs and collapsed NUTS agree on (log A, alpha) within 4 combined Monte-Carlo errors
    for g, n, name in ((ns["g_logA"], ns["n_logA"], "log A"), (ns["g_alpha"], ns["n_alpha"], "alpha")):
        se = np.sqrt(g.var() / ns["ess_g"][name] + n.var() / ns["ess_n"][name])
        assert abs(g.mean() - n.mean()) < 4 * se, (name, g.mean(), n.mean(), se)
    assert ns["draws"].shape[:2] == (20, 1)
    # Gibbs + joint moves: accepted at a useful rate, and the same posterior as NUTS (4 combined MC errors)
    assert 0.05 < ns["accept"] < 0.95, ns["accept"]
    for j, n, name in ((ns["j_logA"], ns["n_logA"], "log A"), (ns["j_alpha"], ns["n_alpha"], "alpha")):
        se = np.sqrt(j.var() / ns["ess_j"][name] + n.var() / ns["ess_n"][name])
        assert abs(j.mean() - n.mean()) < 4 * se, (name, j.mean(), n.mean(), se)


def _check_point_sources(ns):
    import numpy as np

    assert ns["fluxes"].shape == (1500 - 200, 2, 3) and ns["sky"].shape == (1300, 2, (8 + 1) ** 2)
    # the two-block chain reproduces the dense joint Gaussian: 48 z-scores (means, variances, flux-sky
    # covariances; MC error from each series' ESS) below 4, a false-alarm rate of ~3e-3
    assert ns["z_all"].shape == (2, 24) and np.abs(ns["z_all"]).max() < 4.0, ns["z_all"]
    # the blocks are correlated (canonical correlations 0.29-0.49 at lmax 8, 0.58-0.66 at lmax 20)
    assert ns["canon"].max() > 0.25
    # the flux posteriors hold the truth (exact joint mean within 4 sd), and the chain's means are close
    for mhz, j, truth, m, sd, chain_mean, chain_sd, ess, corr in ns["rows"]:
        assert abs(m - truth) < 4 * sd and abs(chain_mean - m) < 4 * sd / np.sqrt(ess), (mhz, j)
    # the sky alone absorbs the sources (far off the truth at their positions); the joint model does not
    assert np.abs(ns["pull_only"]).max() > 10, ns["pull_only"]
    assert np.all(np.abs(ns["t_joint"] - ns["t_true"]) < 4 * ns["sd_joint"])


def _check_real_data(ns):
    import numpy as np

    # RFI: FM (~106 MHz) and ORBCOMM (137.5 MHz) flagged, the clean band's excess near 1
    assert 137.5 in ns["flagged_mhz"] and any(105.0 < f < 108.0 for f in ns["flagged_mhz"])
    assert 0.8 < np.nanmedian(ns["excess"][~np.isin(ns["freqs_mhz"], ns["flagged_mhz"])]) < 1.5
    # the redundant solutions leave the data ~250x below the GSM's autos: outside the bounds
    assert ns["fs"]["ratio"] < 0.01 and not ns["fs"]["within"]
    # the model is rejected (here, marginalised at lmax 8: the lower tail), and the dense eigen-decomposition
    # of the whitened data covariance gives the run's chi2 (an independent route, to rounding)
    assert ns["gof"]["rejected"]
    chi2 = ns["contrib"].sum() / ns["r"].size
    assert abs(chi2 - ns["gof"]["chi2_per_dof"][0]) < 1e-6 * ns["gof"]["chi2_per_dof"][0]
    assert np.all(np.isfinite(ns["draws"])) and ns["draws"].shape == (1, 20, 81)
    assert ns["std_map"][ns["centre"]] < ns["std_map"][ns["far"]]  # the data constrain the zenith patch


def _check_calibration(ns):
    import numpy as np
    from scipy import stats

    # part 1: the true gains and the sky along its K most data-dominated directions, whitened by the joint
    # chain's draws, give mean z^2 within the chi-square range of P (K) terms (two-sided 0.1 %), widened by
    # 25 % for the chain's Monte-Carlo error (the bound of tests/test_gains.py)
    def within(z2, k):
        return stats.chi2.ppf(0.0005, k) / k < z2 < 1.25 * stats.chi2.ppf(0.9995, k) / k

    P, K = ns["P"], ns["E"].shape[0]
    assert within(ns["z2_gains"], P), (ns["z2_gains"], P)
    assert within(ns["z2_sky"], K), (ns["z2_sky"], K)
    # ignoring the gains biases the sky by far (hundreds; 10x the upper bound)
    assert ns["z2_ignore"] > 10 * 1.25 * stats.chi2.ppf(0.9995, K) / K, ns["z2_ignore"]
    # the gauge: plain Gibbs crawls along the overall amplitude (its spread far too small); the gauge move
    # restores the spread and multiplies the ESS
    assert ns["s0_gauge"].std() > 3 * ns["s0_plain"].std(), (ns["s0_gauge"].std(), ns["s0_plain"].std())
    assert ns["ess_gauge"] > 3 * ns["ess_plain"], (ns["ess_gauge"], ns["ess_plain"])
    # the east-west phase gradient is pinned by the sky's rotation, the north-south one less so
    assert ns["grad_ratio_sim"][0] < 0.2 and ns["grad_ratio_sim"][0] < ns["grad_ratio_sim"][1] < 1.0, ns["grad_ratio_sim"]
    # part 2 (H1C): the crosses' flux scale (q x the autos' ratio) is finite and positive, with a 95 % interval
    # bounded on both sides under a flat prior on q (the GSM prior mean pins it) that reaches no higher than ~Jy
    # (measured: 0.006-1.07 at lmax 8, 0.003-0.34 at lmax 16); the autos' ratio far below Jy
    flux = ns["flux"]
    assert np.all(np.isfinite(flux)) and np.all(flux > 0)
    assert 0 < ns["flux_lo"] < np.median(flux) < ns["flux_hi"] < 2.0, (ns["flux_lo"], ns["flux_hi"])
    assert ns["ratio"] < 0.01
    assert ns["ess_flux"] > 20, ns["ess_flux"]
    # the gains stay prior-dominated on this 1.6-minute snapshot: the phase gradients and the median direction
    assert np.all(ns["grad_ratio_h1c"] > 0.8), ns["grad_ratio_h1c"]
    assert np.median(ns["ratio_h1c"]) > 0.8, ns["ratio_h1c"]


def _check_frequency(ns):
    import numpy as np
    from scipy import stats

    table = ns["table"]
    assert all(bool(f.converged) for f in table.fits.values()) and ns["fit"] is table.fits["coupled"]
    # the evidence prefers the coupled prior over independent channels by far (measured +560 nats at this size)
    assert table.coupled - table.independent > 100
    # the fitted index is the sky's: within 0.15 of the truth's power-weighted index (measured -2.41 vs -2.46;
    # the two estimators weight the modes differently), and a correlation length longer than the band
    assert abs(ns["beta_fit"] - ns["beta_truth"]) < 0.15 and ns["xi_fit"] > 0.1
    # inpainting: the independent model's flagged channels are its prior (zero mean: error = the truth's rms),
    # the coupled model's error there is far smaller (measured 76 vs 804 K)
    (cf, _), (inf, _) = ns["err"]["coupled"], ns["err"]["independent"]
    truth_rms = float(np.sqrt(np.mean(ns["obs"].truth[ns["flagged"]] ** 2)))
    assert abs(inf - truth_rms) < 1e-6 * truth_rms and cf < inf / 5
    # the truth's z-scores at the flagged channels' well-constrained coefficients: mean z^2 within the two-sided
    # 0.1 % chi-square range of K terms, widened by 25 % for the draws' Monte-Carlo error (100 draws)
    k = int(ns["narrow"].sum())
    assert k >= 10 and stats.chi2.ppf(0.0005, k) / k / 1.25 < ns["z2_flagged"] < 1.25 * stats.chi2.ppf(0.9995, k) / k


#: The notebooks' claims, checked on their own numbers (every notebook needs an entry).
CHECKS = {
    "quickstart.ipynb": _check_quickstart,
    "standard_case.ipynb": _check_standard_case,
    "hyperparameters.ipynb": _check_hyperparameters,
    "gibbs.ipynb": _check_gibbs,
    "point_sources.ipynb": _check_point_sources,
    "real_data.ipynb": _check_real_data,
    "calibration.ipynb": _check_calibration,
    "frequency.ipynb": _check_frequency,
}


#: Run here; the notebooks on the real files run from tests/test_notebooks_real.py, so that pytest-xdist's
#: ``--dist loadfile`` (one file, one worker) can put the two halves on different workers.
SIMULATED = [p for p in NOTEBOOKS if p.name not in NEEDS_REAL]


@pytest.mark.slow
@pytest.mark.parametrize("path", SIMULATED, ids=[p.name for p in SIMULATED])
def test_notebook_runs(path, monkeypatch):
    run_notebook(path, monkeypatch)


def run_notebook(path, monkeypatch):
    """Every code cell of ``path`` in one namespace (OVERRIDES after the first), then its CHECKS entry."""
    if path.name in NEEDS_REAL:
        if not REAL.is_dir():
            pytest.skip(f"the real HERA files are not at {REAL}")
        monkeypatch.setenv("GCRSKY_REAL_DATA", str(REAL))
    nb = json.loads(path.read_text())
    assert nb["nbformat"] == 4
    ns: dict = {"__name__": "__notebook__"}
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert all(not c.get("outputs") for c in code), "commit notebooks with empty outputs"
    overrides = OVERRIDES.get(path.name, {})
    for i, cell in enumerate(code):
        src = "".join(cell["source"])
        exec(compile(src, f"{path.name}[cell {i}]", "exec"), ns)
        if i == 0 and overrides:
            missing = set(overrides) - set(ns)
            assert not missing, f"{path.name}: first code cell does not define {sorted(missing)}"
            ns.update(overrides)
    CHECKS[path.name](ns)
