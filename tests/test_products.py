"""The standard products of a run: HEALPix FITS maps, healpy alm, pyradiosky skyh5.

References: healpy's own readers (``read_map``, ``read_alm``), astropy's FITS headers and
``pyradiosky.SkyModel.from_file``; the arrays they return must equal what gcrsky wrote
(and what ``results.h5`` holds) bit for bit: every file stores float64.

The writers are tested on random arrays (fast); one small run (lmax 8, nside 32, 20
draws in batches of 8; :func:`gcrsky.run.execute`, what ``gcrsky run`` calls, without
report hooks: the products are the run layer's own) checks that the products equal the
run's own numbers, and a run of the same problem without a truth or configuration (as a
run on real data will be; through the compatibility form
:func:`gcrsky.paper.pipeline.run_problem`, with the paper's hook) still writes them.
The run-based tests are marked ``slow`` (the problem and the run take ~10 s on 2 cores).
"""

from __future__ import annotations

import dataclasses
import warnings
from types import SimpleNamespace

import h5py
import healpy as hp
import numpy as np
import pytest
from astropy.io import fits

from gcrsky.io import (
    freq_column_names,
    healpix_skymodel,
    read_draws,
    write_alm_fits,
    write_healpix_fits,
    write_skyh5,
)
from gcrsky.sphere import n_params, realify, unrealify
from gcrsky.sphere.maps import alm_to_map, posterior_maps

pyradiosky = pytest.importorskip("pyradiosky")

FREQS = np.array([100e6, 102e6])
NSAMPLES, BATCH = 20, 8


def _quiet():
    """Warnings as errors, except pyradiosky's note on negative Stokes I (random maps)."""
    warnings.simplefilter("error")
    warnings.filterwarnings("ignore", message="Some Stokes I values are negative")


# ---------------------------------------------------------------- the writers


def test_column_names():
    assert freq_column_names(FREQS) == ["FREQ_100.000MHZ", "FREQ_102.000MHZ"]
    assert freq_column_names([1e8, 1e8]) == ["FREQ_100.000MHZ_0", "FREQ_100.000MHZ_1"]


@pytest.mark.parametrize("frame, value", [("idealised", "IDEALISED"), ("icrs", "ICRS")])
def test_healpix_fits_round_trip(tmp_path, frame, value):
    rng = np.random.default_rng(1)
    maps = rng.standard_normal((2, hp.nside2npix(8))) * 100.0
    path = tmp_path / "m.fits"
    with warnings.catch_warnings():
        _quiet()  # no card truncated, nothing else odd
        write_healpix_fits(path, maps, FREQS, frame=frame, lmax=12, content="test maps",
                           extra_header=[("NDRAWS", 7, "draws")])
        back = hp.read_map(path, field=None, dtype=None)
    assert back.dtype == np.float64
    np.testing.assert_array_equal(back, maps)
    h = fits.getheader(path, 1)
    assert (h["COORDSYS"], h["FRAME"], h["ORDERING"], h["PIXTYPE"]) == ("C", value, "RING", "HEALPIX")
    assert (h["NSIDE"], h["LMAX"], h["NFREQ"], h["NDRAWS"]) == (8, 12, 2, 7)
    assert (h["FREQ1"], h["FREQ2"]) == (100e6, 102e6)
    assert (h["TTYPE1"], h["TTYPE2"]) == ("FREQ_100.000MHZ", "FREQ_102.000MHZ")
    assert h["TUNIT1"] == h["TUNIT2"] == "K"
    assert h["CONTENT"] == "test maps"
    assert not list(tmp_path.glob(".*"))  # no temporary file left


def test_healpix_fits_rejects_bad_shapes(tmp_path):
    with pytest.raises(ValueError, match="Nf = 2"):
        write_healpix_fits(tmp_path / "m.fits", np.zeros((3, 768)), FREQS, frame="icrs", lmax=4, content="x")
    with pytest.raises(ValueError, match="frame must be one of"):
        write_healpix_fits(tmp_path / "m.fits", np.zeros((2, 768)), FREQS, frame="galactic", lmax=4, content="x")
    assert not list(tmp_path.iterdir())


def test_alm_fits_round_trip(tmp_path):
    lmax = 9
    a = np.random.default_rng(2).standard_normal((2, n_params(lmax)))
    path = tmp_path / "alm.fits"
    with warnings.catch_warnings():
        _quiet()
        write_alm_fits(path, a, lmax, FREQS, frame="icrs", content="test alm")
    for i in range(2):
        alm = hp.read_alm(path, hdu=i + 1)
        np.testing.assert_array_equal(alm, unrealify(a[i], lmax))
        np.testing.assert_array_equal(realify(alm, lmax), a[i])
        h = fits.getheader(path, i + 1)
        assert h["EXTNAME"] == freq_column_names(FREQS)[i] and h["FREQ"] == FREQS[i]
        assert (h["LMAX"], h["MMAX"], h["COORDSYS"], h["FRAME"]) == (lmax, lmax, "C", "ICRS")
        assert h["TUNIT2"] == h["TUNIT3"] == "K"
    np.testing.assert_array_equal(hp.read_alm(path, hdu=(1, 2)), unrealify(a, lmax))


@pytest.mark.parametrize("frame", ["idealised", "icrs"])
def test_skyh5_round_trip(tmp_path, frame):
    nside = 4
    rng = np.random.default_rng(3)
    maps = 50.0 + rng.random((2, hp.nside2npix(nside)))
    std = rng.random(maps.shape)
    path = tmp_path / "sky.skyh5"
    with warnings.catch_warnings():
        _quiet()
        write_skyh5(path, maps, FREQS, frame=frame, history="unit test.", std_maps=std)
        sky = pyradiosky.SkyModel.from_file(path)
    assert sky == healpix_skymodel(maps, FREQS, frame=frame, history="unit test.", std_maps=std)
    assert sky.component_type == "healpix" and sky.nside == nside and sky.hpx_order == "ring"
    np.testing.assert_array_equal(sky.hpx_inds, np.arange(maps.shape[1]))
    assert str(sky.frame).lower() == "icrs"
    assert sky.stokes.unit == "K" and sky.stokes_error.unit == "K"
    np.testing.assert_array_equal(sky.stokes[0].value, maps)
    np.testing.assert_array_equal(sky.stokes[1:].value, 0.0)
    np.testing.assert_array_equal(sky.stokes_error[0].value, std)
    np.testing.assert_array_equal(sky.freq_array.to_value("Hz"), FREQS)
    assert sky.spectral_type == "full"
    assert "unit test." in sky.history
    assert ("co-rotating" in sky.history) == (frame == "idealised")


# ---------------------------------------------------------------- a small run


@pytest.fixture(scope="module")
def problem():
    from gcrsky.sim import Config, problem_from_config

    return problem_from_config(Config(lmax=8, nside=32).validate())


@pytest.fixture(scope="module")
def run(problem, tmp_path_factory):
    from gcrsky.run import Draws, Output, RunSpec, execute

    out = tmp_path_factory.mktemp("products")
    summary, _ = execute(problem, RunSpec(Draws(NSAMPLES, 0, BATCH), Output(out, plots=False)))
    return out, summary.to_json()


@pytest.mark.slow
def test_run_writes_the_products(run):
    out, summary = run
    for name in ("posterior_mean.fits", "posterior_std.fits", "posterior_mean_alm.fits", "posterior_mean.skyh5"):
        assert (out / name).is_file(), name
    assert set(summary["products"].values()) >= {"posterior_mean.fits", "posterior_mean.skyh5", "results.h5"}
    assert summary["run"]["frame"] == "idealised"
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporaries left


@pytest.mark.slow
def test_fits_maps_equal_results_h5(run, problem):
    out, _ = run
    mean = hp.read_map(out / "posterior_mean.fits", field=None, dtype=None)
    std = hp.read_map(out / "posterior_std.fits", field=None, dtype=None)
    with h5py.File(out / "results.h5", "r") as h:
        np.testing.assert_array_equal(mean, h["maps/wiener"][()])
        np.testing.assert_array_equal(std, h["maps/std"][()])
        wf, draws = h["wiener_filter"][()], h["draws"][()]
    assert mean.shape == std.shape == (2, hp.nside2npix(32))
    # what they are: the Wiener filter's map, and the per-pixel std over the draws (as today's maps/std)
    np.testing.assert_array_equal(mean, alm_to_map(wf, 8, 32))
    np.testing.assert_array_equal(std, posterior_maps(draws, 8, 32)[1])
    for name, ndraws in (("posterior_mean.fits", NSAMPLES), ("posterior_std.fits", NSAMPLES)):
        h = fits.getheader(out / name, 1)
        assert (h["COORDSYS"], h["FRAME"], h["NSIDE"], h["LMAX"], h["NDRAWS"]) == ("C", "IDEALISED", 32, 8, ndraws)
        assert (h["FREQ1"], h["FREQ2"]) == tuple(np.asarray(problem.freqs_hz))
        assert h["TUNIT1"] == h["TUNIT2"] == "K"
        assert h["METHOD"] == "cholesky"
    assert fits.getheader(out / "posterior_mean.fits", 1)["MEANTYPE"] == "WIENER"


@pytest.mark.slow
def test_alm_equals_the_wiener_filter(run):
    out, _ = run
    wf = read_draws(out / "results.h5").wiener_filter
    alm = hp.read_alm(out / "posterior_mean_alm.fits", hdu=(1, 2))
    np.testing.assert_array_equal(alm, unrealify(wf, 8))
    np.testing.assert_array_equal(realify(alm, 8), wf)


@pytest.mark.slow
def test_skyh5_equals_the_maps(run):
    out, _ = run
    sky = pyradiosky.SkyModel.from_file(out / "posterior_mean.skyh5")
    mean = hp.read_map(out / "posterior_mean.fits", field=None, dtype=None)
    std = hp.read_map(out / "posterior_std.fits", field=None, dtype=None)
    np.testing.assert_array_equal(sky.stokes[0].to_value("K"), mean)
    np.testing.assert_array_equal(sky.stokes_error[0].to_value("K"), std)
    np.testing.assert_array_equal(sky.freq_array.to_value("Hz"), FREQS)
    assert str(sky.frame).lower() == "icrs" and "co-rotating" in sky.history and sky.nside == 32


def test_parameter_frame():
    from gcrsky.run import parameter_frame

    assert parameter_frame(SimpleNamespace(frame=None)) == "idealised"
    assert parameter_frame(SimpleNamespace(frame=object())) == "icrs"  # real times: a frame map from ICRS


@pytest.mark.slow
def test_run_without_truth_or_config(problem, tmp_path, capsys):
    """A problem with neither truth nor configuration (real data): draws, maps and products, no metrics."""
    from gcrsky.paper.pipeline import run_problem

    bare = dataclasses.replace(problem, a_true=None, config=None)
    summary, prods = run_problem(bare, tmp_path, nsamples=6, seed=0, batch=4, method="cholesky", plots=True,
                                 build_s=0.0, extra_settings={"data": "test"})
    for name in ("results.h5", "summary.json", "posterior_mean.fits", "posterior_std.fits",
                 "posterior_mean_alm.fits", "posterior_mean.skyh5"):
        assert (tmp_path / name).is_file(), name
    assert summary["config"] is None and summary["frac_diff_centre_median"] is None and summary["figures"] == {}
    assert any("no figures" in w for w in summary["warnings"])
    from gcrsky.cli.terminal import print_summary

    print_summary(summary, tmp_path, prods.written)  # the CLI's report copes without metrics
    assert "posterior_mean.skyh5" in capsys.readouterr().out
    with h5py.File(tmp_path / "results.h5", "r") as h:
        assert "truth" not in h and "mode_z" not in h and "truth" not in h["maps"]
        np.testing.assert_array_equal(h["maps/wiener"][()], hp.read_map(tmp_path / "posterior_mean.fits",
                                                                          field=None, dtype=None))
