"""``gcrsky run --data FILE`` and ``gcrsky inspect FILE`` on a small matvis-simulated UVH5 file."""

from __future__ import annotations

import json

import h5py
import healpy as hp
import numpy as np
import pytest

pytest.importorskip("matvis")

from gcrsky import cli  # noqa: E402
from gcrsky.checks.matvis import HERA_SITE, observing_times, random_sky, site  # noqa: E402
from gcrsky.checks.uvsim import simulate_uvdata  # noqa: E402
from gcrsky.instrument import gaussian_beam, hex_array  # noqa: E402

LMAX = 6
# the sky is band-limited at LMAX: keeping every baseline (--band-limit truncate) is the right model here;
# the toy sky (a few K) is far from the GSM: the flux-scale check would refuse it (tests/test_datachecks_cli.py)
SMALL = ["--lmax", str(LMAX), "--nside", "32", "--nsamples", "12", "--batch", "6", "--no-progress",
         "--band-limit", "truncate", "--flux-scale", "accept"]


@pytest.fixture(scope="module")
def uvh5(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "obs.uvh5"
    sim = simulate_uvdata(hex_array((2, 3, 2)), site(*HERA_SITE), observing_times("2025-03-21T18:00:00", 3.0, 6),
                          np.array([100e6, 101e6]), gaussian_beam(14.0), random_sky(LMAX, 3), LMAX, nside_matvis=32)
    sim.uvdata.write_uvh5(str(path))
    return path


@pytest.fixture(scope="module")
def data_run(uvh5, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    rc = cli.main(["run", "--data", str(uvh5), "--dish-diameter", "14", "--out", str(out), *SMALL])
    return out, rc


@pytest.mark.slow
def test_run_on_a_file_writes_the_products(data_run, capsys):
    out, rc = data_run
    assert rc == 0
    for name in ("results.h5", "summary.json", "posterior_mean.fits", "posterior_std.fits", "posterior_mean_alm.fits",
                 "posterior_mean.skyh5", "fig4_sky_maps.png"):
        assert (out / name).is_file(), name
    s = json.loads((out / "summary.json").read_text())
    cfg = s["config"]
    assert cfg["pol"] == "pI" and cfg["compressed"] and cfg["noise"] == "autos" and "GSM" in cfg["prior"]
    m = s["metrics"]
    assert 0 < m["std_fwhm_over_sky"] < 1  # the observed strip is better constrained than the rest of the sky
    assert "frac_diff_centre_median" not in m  # no truth, no truth metrics
    with h5py.File(out / "results.h5", "r") as h:
        assert h["draws"].shape == (2, 12, (LMAX + 1) ** 2) and "truth" not in h
        mean = np.asarray(h["maps/wiener"])
    np.testing.assert_allclose(np.stack(hp.read_map(str(out / "posterior_mean.fits"), field=None)), mean, rtol=1e-12)


@pytest.mark.slow
def test_a_second_run_refuses_and_resume_completes(data_run, uvh5, capsys):
    out, _ = data_run
    args = ["run", "--data", str(uvh5), "--dish-diameter", "14", "--out", str(out), *SMALL]
    assert cli.main(args) == cli.EXIT_REFUSED
    assert "--resume" in capsys.readouterr().err
    assert cli.main([*args, "--resume"]) == 0
    assert "already complete" in capsys.readouterr().out
    changed = ["run", "--data", str(uvh5), "--dish-diameter", "12", "--out", str(out), *SMALL, "--resume"]
    assert cli.main(changed) == cli.EXIT_REFUSED
    assert "dish_diameter" in capsys.readouterr().err


def test_inspect(uvh5, capsys):
    assert cli.main(["inspect", str(uvh5), "--lmax", "8"]) == 0
    text = capsys.readouterr().out
    # the simulated file's feed x points East, so pyuvdata names its products ee, nn (-5, -6: xx, yy)
    for key in ("antennas      7", "baselines     21 (9 unique", "times         6", "products      file ee, nn; "
                "modelled pI", "Jy, pol_convention sum", "radiometer (autos)"):
        assert key in text, (key, text)
    assert cli.main(["inspect", str(uvh5), "--json", "--pol", "xx"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["modelled_products"] == ["xx"] and info["n_times"] == 6


def test_bad_data_options_are_refused(uvh5, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--data", str(uvh5), "--out", str(tmp_path / "a")])
    assert e.value.code == 2 and "--beam FILE" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["run", "--data", str(uvh5), "--dish-diameter", "14", "--n-lst", "3", "--out", str(tmp_path / "b")])
    assert "--n-lst" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["run", "--data", str(tmp_path / "missing.uvh5"), "--dish-diameter", "14"])
    assert "no visibility file at" in capsys.readouterr().err
    rc = cli.main(["run", "--data", str(uvh5), "--dish-diameter", "14", "--pol", "I", "--out", str(tmp_path / "c")])
    assert rc == 2 and "pol must be" in capsys.readouterr().err
    assert cli.main(["inspect", str(tmp_path / "missing.uvh5")]) == 2


@pytest.mark.slow
def test_run_on_a_file_records_its_band_limit_and_fit(data_run):
    """matvis's data of a sky band-limited at LMAX, modelled at LMAX: every row is beyond its reach
    (14 m dishes at 100 MHz reach l ~ 60) but the sky has nothing there, and the fit is not rejected."""
    out, _ = data_run
    s = json.loads((out / "summary.json").read_text())
    bl = s["data_checks"]["band_limit"]
    assert bl["mode"] == "truncate" and bl["lmax"] == LMAX and bl["chosen"] == "given" and bl["reach"] > 50
    gof = s["goodness_of_fit"]
    assert len(gof["chi2_per_dof"]) == 2 and not gof["rejected"] and min(gof["p_value"]) > 5e-4


def test_the_default_band_limit_cuts_what_lmax_cannot_represent(uvh5, tmp_path, capsys):
    rc = cli.main(["run", "--data", str(uvh5), "--dish-diameter", "14", "--out", str(tmp_path / "cut"),
                   *SMALL[:-4], "--flux-scale", "accept"])
    assert rc == 2 and "reaches no baseline" in capsys.readouterr().err
