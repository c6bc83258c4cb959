"""``gcrsky run --data FILE --gains sample``: gains sampled with the sky, their draws, calh5 and resume.

A small matvis simulation (7 antennas, 2 channels, 6 times, the sky band-limited at lmax 6)
written as UVH5.  The checks: the gain run's files and shapes; the posterior-mean gains as a
calh5 that pyuvdata reads back equal to the mean of ``gain_draws``; a run killed after its
first batch and resumed gives the uninterrupted run's draws bit for bit (the chain's state
is stored with each batch); a file whose cross-correlations are 2x too bright in amplitude
(4x in ``q``: a flux-scale error the autocorrelations do not share) is caught by the
posterior flux scale, which the correctly scaled file's posterior excludes.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

pytest.importorskip("matvis")

from gcrsky import cli  # noqa: E402
from gcrsky.checks.matvis import HERA_SITE, observing_times, random_sky, site  # noqa: E402
from gcrsky.checks.uvsim import simulate_uvdata  # noqa: E402
from gcrsky.instrument import gaussian_beam, hex_array  # noqa: E402

LMAX = 6
# one constant gain per antenna (the modes these checks were measured with; the default follows the selection,
# tests/test_gains_defaults.py)
GAINS = ["--gains", "sample", "--gain-burn", "30", "--gain-sigma", "0.05", "--gain-modes", "1,1", "--gain-basis",
         "dpss"]
SMALL = ["--dish-diameter", "14", "--lmax", str(LMAX), "--nside", "32", "--nsamples", "12", "--batch", "6",
         "--no-progress", "--no-plots", "--band-limit", "truncate", "--pol", "pI", *GAINS]


def _simulation():
    return simulate_uvdata(hex_array((2, 3, 2)), site(*HERA_SITE), observing_times("2025-03-21T18:00:00", 3.0, 6),
                           np.array([100e6, 101e6]), gaussian_beam(14.0), random_sky(LMAX, 3), LMAX, nside_matvis=32)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The simulated file, and a copy whose cross-correlations are 2x the amplitude (autos untouched)."""
    d = tmp_path_factory.mktemp("gaindata")
    uvd = _simulation().uvdata
    uvd.write_uvh5(str(d / "obs.uvh5"))
    bright = uvd.copy()
    cross = bright.ant_1_array != bright.ant_2_array
    bright.data_array[cross] *= 2.0
    bright.write_uvh5(str(d / "bright.uvh5"))
    return d / "obs.uvh5", d / "bright.uvh5"


@pytest.fixture(scope="module")
def gain_run(files, tmp_path_factory):
    out = tmp_path_factory.mktemp("gainrun")
    rc = cli.main(["run", "--data", str(files[0]), "--out", str(out), *SMALL])
    return out, rc


def test_gains_sample_models_the_feed_products_by_default(files, tmp_path):
    """Without --pol, --gains sample models the file's two feed products jointly (each feed has its own gain);
    a file with one feed product gets that one; --pol given is kept."""
    from types import SimpleNamespace

    from pyuvdata import UVData

    from gcrsky.cli.cmd_data import _feed_products, _gain_inputs

    both = _feed_products(files[0])
    assert both in ("xx,yy", "ee,nn")  # as the file names them (its x_orientation)
    one = UVData.from_file(str(files[0]))
    one.select(polarizations=[-6])  # yy
    one.write_uvh5(str(tmp_path / "yy.uvh5"))
    assert _feed_products(tmp_path / "yy.uvh5") == both.split(",")[1]
    assert _feed_products(tmp_path / "absent.uvh5") == "pI"  # the reader names the problem later
    args = SimpleNamespace(gains="sample", pol=None, data=files[0], no_compress=True, flux_scale="accept",
                           amplitude="fixed")
    _gain_inputs(args)
    assert args.pol == both
    args = SimpleNamespace(gains="sample", pol="pI", data=files[0], no_compress=True, flux_scale="accept",
                           amplitude="fixed")
    _gain_inputs(args)
    assert args.pol == "pI"


@pytest.mark.slow
def test_gain_run_writes_gain_draws_and_a_calh5_pyuvdata_reads(gain_run):
    from pyuvdata import UVCal

    out, rc = gain_run
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    g = s["gains"]
    assert s["run"]["method"] == "gains+cholesky" and g["units"] == 7 and g["ndraws"] == 12
    assert g["calibration_file"] == "gains.calh5"
    assert {p["direction"] for p in g["phase_gradients"]} == {"east", "north"}
    assert not s["config"]["compressed"]  # gains are per antenna: every baseline kept
    with h5py.File(out / "results.h5", "r") as h:
        assert h["draws"].shape == (2, 12, (LMAX + 1) ** 2)
        gd = h["gain_draws"][()]
        assert gd.shape == (12, 2, 6, 7) and gd.dtype == np.complex128
        assert h["gain_theta"].shape[0] == 12 and h["gain_scale"].shape == (12, 1)
        units, nums = h["gains/units"][()], h["gains/antenna_numbers"][()]
        q = h["gain_scale"][()] @ h["gains/basis_f"][()].T  # (ndraws, Nf)
        settings = json.loads(h.attrs["run_settings_json"])
    assert settings["gains"]["burn"] == 30 and settings["compress"] is False
    # the summary's flux scale is q(nu) x applied^2 over the draws; calibrated (Jy) data: the amplitude is held,
    # applied 1 (not the autos' ratio, which is recorded beside it)
    applied = g["settings"]["applied"]
    assert applied == 1.0 and g["settings"]["scale_sd"] == pytest.approx(1e-6)
    assert g["autos_flux_ratio"] is not None
    assert g["flux_scale"][0]["mean"] == pytest.approx(np.mean(q[:, 0]) * applied**2, rel=1e-12)
    # the gains' overall amplitude is the square root of q (the gauge: no common real part in x)
    rms = np.sqrt(np.mean(np.abs(gd) ** 2, axis=-1))  # (ndraws, Nf, Nt)
    np.testing.assert_allclose(np.log(rms[:, 0, 0]).mean(), np.log(applied * np.sqrt(q[:, 0])).mean(), atol=0.02)
    cal = UVCal.from_file(str(out / "gains.calh5"))
    assert cal.gain_convention == "divide" and cal.Nfreqs == 2 and cal.Ntimes == 6
    mean = gd.mean(axis=0)  # (Nf, Nt, U)
    for u, (ant, _feed) in enumerate(units):
        idx = list(cal.ant_array).index(int(nums[u]))
        for jones in range(2):  # a pI unit's gain is written to both linear feeds
            np.testing.assert_allclose(cal.gain_array[idx, :, :, jones], mean[:, :, u], rtol=1e-12)


@pytest.mark.slow
def test_killed_gain_run_resumes_to_the_uninterrupted_draws(gain_run, files, tmp_path):
    ref, _ = gain_run
    out = tmp_path / "killed"
    args = ["run", "--data", str(files[0]), "--out", str(out), *SMALL]
    env = {**os.environ, "GCRSKY_TEST_KILL_AFTER_BATCH": "1", "JAX_ENABLE_X64": "1"}
    p = subprocess.run([sys.executable, "-m", "gcrsky", *args], env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode != 0  # killed by the hook after the first batch
    with h5py.File(out / "results.h5", "r") as h:
        assert int(h.attrs["batches_complete"]) == 1 and h["gain_draws"].shape[0] == 6
    assert cli.main([*args, "--resume"]) == 0
    with h5py.File(ref / "results.h5", "r") as a, h5py.File(out / "results.h5", "r") as b:
        for name in ("draws", "gain_draws", "gain_theta", "gain_scale", "wiener_filter"):
            np.testing.assert_array_equal(a[name][()], b[name][()], err_msg=name)


@pytest.mark.slow
def test_crosses_brighter_than_the_autos_are_caught_by_the_posterior_flux_scale(files, tmp_path):
    """With the amplitude inferred (``--amplitude infer``; on these Jy files it is otherwise held at 1), crosses 2x
    brighter give an amplitude 2x larger (data = q x the model), the autos' ratio unchanged."""
    s = []
    for name, path in (("ref", files[0]), ("bright", files[1])):
        out = tmp_path / name
        assert cli.main(["run", "--data", str(path), "--out", str(out), *SMALL, "--amplitude", "infer"]) == 0
        s.append(json.loads((out / "summary.json").read_text())["flux_scale"])
    assert all(f["source"] == "inferred" for f in s)
    # the autos are the same file's: the check's ratio does not move; the crosses' posterior does, by ~2
    assert s[1]["autos_ratio"] == pytest.approx(s[0]["autos_ratio"], rel=1e-9)
    f0, f1 = s[0]["per_channel"][0], s[1]["per_channel"][0]
    assert 1.5 < f1["u_median"] / f0["u_median"] < 2.7, (f0, f1)
    assert f1["lo95"] > f0["hi95"]  # the intervals exclude each other


def test_calibrated_data_hold_the_amplitude_at_one(gain_run):
    """On Jy data ``--gains sample`` keeps the amplitude fixed (issue 38): q = 1 to the prior's 1e-6."""
    out, rc = gain_run
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["flux_scale"]["source"] == "fixed"
    for f in s["gains"]["flux_scale"]:
        assert abs(f["mean"] - 1.0) < 1e-4, f


def test_gain_options_need_gains_sample_and_a_file(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--gain-modes", "2"])
    assert e.value.code == 2 and "--gains sample" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--gains", "sample"])
    assert e.value.code == 2 and "--data FILE" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--gains", "sample", "--gain-modes", "0"])
    assert e.value.code == 2 and "gain-modes" in capsys.readouterr().err


def test_gain_run_refuses_independent_channels(files, tmp_path, capsys):
    rc = cli.main(["run", "--data", str(files[0]), "--out", str(tmp_path / "c"), *SMALL, "--by-channel"])
    assert rc == 2 and "jointly over the channels" in capsys.readouterr().err


def test_the_sky_above_lmax_goes_through_the_gains_the_radiometer_noise_does_not():
    """marginalise_rows records the marginalised sky's std as ``sigma_sky``; a gain run's noise scales it by |D|,
    and dividing the gains out of the data leaves it in sky units while the radiometer part is divided by |D|."""
    import dataclasses

    import jax.numpy as jnp
    from test_gains import _observation

    from gcrsky.model.bandlimit import marginalise_rows
    from gcrsky.run.gains import gained_problem, noise_at

    prob, _ = _observation()
    rng = np.random.default_rng(0)
    nf, nbl, n = prob.response.shape
    lmax_hi = 6
    resp_hi = jnp.asarray(rng.standard_normal((nf, nbl, (lmax_hi + 1) ** 2)) * 0.1 + 0j)
    marg, sig_hi = marginalise_rows(prob, resp_hi)
    rad2, sky2 = np.asarray(prob.sigma) ** 2, np.broadcast_to(sig_hi[:, None, :] ** 2, prob.sigma.shape)
    np.testing.assert_allclose(np.asarray(marg.sigma_sky) ** 2, sky2, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(marg.sigma) ** 2, rad2 + sky2, rtol=1e-12)
    D = 0.01 * np.exp(1j * rng.uniform(0, 2 * np.pi, prob.data.shape)) * (1 + 0.1 * rng.standard_normal(prob.data.shape))
    np.testing.assert_allclose(np.asarray(noise_at(marg, D).sigma) ** 2, rad2 + np.abs(D) ** 2 * sky2, rtol=1e-10)
    g = gained_problem(marg, D)
    np.testing.assert_allclose(np.asarray(g.sigma) ** 2, rad2 / np.abs(D) ** 2 + sky2, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(g.data), np.asarray(marg.data) / D, rtol=1e-12)
    # without a sky part, the noise is all radiometer: divided by |D|
    plain = dataclasses.replace(prob, sigma_sky=None)
    np.testing.assert_allclose(np.asarray(gained_problem(plain, D).sigma), np.asarray(prob.sigma) / np.abs(D), rtol=1e-12)
