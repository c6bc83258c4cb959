"""Tests of the ``gcrsky run`` command on a small, fast variant of the standard case.

One small run (lmax 8, nside 32, 20 draws in batches of 8) is shared by the
checks of its outputs.  nside 32 rather than 16: at nside 16 the longest
baselines alias (see conftest.py); the cost is the same.
"""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import pytest

from gcrsky import cli

SMALL = ["--lmax", "8", "--nside", "32", "--batch", "8", "--no-progress"]
NSAMPLES = 20


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    rc = cli.main(["run", "--out", str(out), "--nsamples", str(NSAMPLES), *SMALL])
    return out, rc


def _finite_numbers(x, path="summary"):
    """Yield (path, value) for every number in a JSON tree."""
    if isinstance(x, dict):
        for k, v in x.items():
            yield from _finite_numbers(v, f"{path}.{k}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from _finite_numbers(v, f"{path}[{i}]")
    elif isinstance(x, (int, float)) and not isinstance(x, bool):
        yield path, x


@pytest.mark.slow
def test_run_writes_everything(small_run):
    out, rc = small_run
    assert rc == 0
    for name in ("results.h5", "summary.json", "fig3_alm_residuals.png", "fig4_sky_maps.png", "fig5_beam_region.png",
                 "posterior_mean.fits", "posterior_std.fits", "posterior_mean_alm.fits", "posterior_mean.skyh5"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name


@pytest.mark.slow
def test_results_h5_layout(small_run):
    out, _ = small_run
    n, nf = 81, 2
    with h5py.File(out / "results.h5", "r") as h:
        assert h["draws"].shape == (nf, NSAMPLES, n)
        for name in ("truth", "wiener_filter", "prior_mean", "prior_inv_var"):
            assert h[name].shape == (nf, n), name
        for name in ("modes/ell", "modes/m", "modes/is_imag"):
            assert h[name].shape == (n,), name
        assert h["freqs_hz"].shape == (nf,)
        assert h["lsts_rad"].shape == (10,)
        assert h["antpairs"].shape == (45, 2)
        assert h["data"].shape == h["sigma"].shape == (nf, 10, 45)
        assert np.iscomplexobj(h["data"][()])
        assert np.isfinite(h["draws"][()]).all()
        cfg = json.loads(h.attrs["config_json"])
        assert cfg["lmax"] == 8 and cfg["nside"] == 32
        assert isinstance(h.attrs["sky_note"], str) and h.attrs["sky_note"]
        # the draws scatter around the Wiener filter
        d, wf = h["draws"][()], h["wiener_filter"][()]
        assert np.all(np.abs(d.mean(axis=1) - wf) <= 5 * d.std(axis=1, ddof=1) / np.sqrt(NSAMPLES) + 1e-9)


@pytest.mark.slow
def test_summary_json(small_run):
    out, _ = small_run
    s = json.loads((out / "summary.json").read_text())
    m = s["metrics"]
    for key in ("frac_diff_centre_median", "frac_diff_fwhm_median", "frac_diff_centre_p90", "frac_diff_fwhm_p90",
                "frac_diff_fwhm_max", "frac_diff_fwhm_within_10pct", "frac_diff_centre_within_5pct", "fwhm_deg"):
        assert isinstance(m[key], float) and math.isfinite(m[key]), key
    assert m["freq_hz"] == 100e6
    assert len(s["per_frequency"]) == 2 and s["per_frequency"][1]["freq_hz"] == 102e6
    for stage in ("build", "wiener", "draws", "maps", "plots", "write"):
        assert s["timings_s"][stage] >= 0, stage
    assert len(s["timings_s"]["draw_batches_s"]) == 3  # ceil(20 / 8)
    sv = s["solver"]
    assert sv["draws"]["n_solves"] == 2 * NSAMPLES
    assert isinstance(sv["all_converged"], bool)
    for k in ("iterations_mean", "iterations_max", "err_sigma_max"):
        assert k in sv["draws"] and k in sv["wiener"]
    assert {"jax", "numpy", "gcrsky"} <= set(s["versions"])
    assert s["config"]["lmax"] == 8 and s["run"]["nsamples"] == NSAMPLES
    assert s["sky_note"]
    assert s["exit_status"] == 0 and s["draws_finite"] is True
    bad = [(p, v) for p, v in _finite_numbers(s) if not math.isfinite(v)]
    assert not bad
    # the standard prior keeps the small case accurate near the beam
    assert m["frac_diff_centre_median"] < 0.05 and m["frac_diff_fwhm_median"] < 0.10


@pytest.mark.slow
def test_draws_depend_only_on_seed_and_batch(small_run, tmp_path):
    """A shorter run with the same seed and batch reproduces the first draws."""
    out, _ = small_run
    rc = cli.main(["run", "--out", str(tmp_path), "--nsamples", "5", "--no-plots", *SMALL])
    assert rc == 0
    with h5py.File(out / "results.h5", "r") as a, h5py.File(tmp_path / "results.h5", "r") as b:
        np.testing.assert_array_equal(b["draws"][()], a["draws"][:, :5])
    assert not (tmp_path / "fig4_sky_maps.png").exists()


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--nsamples", "0"], "nsamples must be >= 1"),
        (["--nsamples", "abc"], "nsamples must be an integer"),
        (["--batch", "0"], "batch must be >= 1"),
        (["--nside", "24"], "nside must be a power of 2"),
        (["--lmax", "0"], "lmax must be >= 1"),
        (["--lmax", "50", "--nside", "8"], "cannot resolve lmax"),
        (["--dish-diameter", "-3"], "dish-diameter must be a positive"),
        (["--noise-scale", "nan"], "noise-scale must be a positive"),
        (["--lst-start", "6", "--lst-stop", "2"], "--lst-stop (2 h) is before --lst-start (6 h)"),
        (["--method", "lu"], "invalid choice"),
        (["--n-lst", "0"], "n-lst must be >= 1"),
    ],
)
def test_bad_arguments(args, needle, capsys, tmp_path):
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--out", str(tmp_path), *args])
    assert e.value.code == 2
    assert needle in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing ran


def test_no_command_is_an_error(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main([])
    assert e.value.code == 2


@pytest.mark.slow
def test_nan_draws_exit_nonzero(monkeypatch, tmp_path, capsys):
    """Non-finite draws: results are still written, the exit status is 1, with a message."""
    import gcrsky.run.draws

    real = gcrsky.run.draws.draw_exactly  # the run draws batch by batch (draw_batch)

    def poisoned(*a, **k):
        d, info = real(*a, **k)
        return d.at[0, 0, 0].set(np.nan), info

    monkeypatch.setattr(gcrsky.run.draws, "draw_exactly", poisoned)
    rc = cli.main(["run", "--out", str(tmp_path), "--nsamples", "4", "--no-plots", *SMALL])
    assert rc == 1
    assert "NaN" in capsys.readouterr().err
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["draws_finite"] is False and s["exit_status"] == 1
    assert (tmp_path / "results.h5").is_file()


@pytest.mark.slow
def test_run_with_real_date(tmp_path):
    """--date: real UTC times of that date, sky in ICRS; the headline still holds."""
    rc = cli.main(["run", "--out", str(tmp_path), "--nsamples", "8", "--no-plots", "--date", "2026-03-21", *SMALL])
    assert rc == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["config"]["obs_date"] == "2026-03-21"
    assert s["frac_diff_centre_median"] < 0.05


def test_bad_date_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--out", str(tmp_path), "--date", "someday", *SMALL])
    assert e.value.code == 2
    assert "obs_date" in capsys.readouterr().err
