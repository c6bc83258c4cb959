"""Gains sampled with the sky from files (issue 23): a matvis simulation with known gains, as UVH5 plus calfits.

The simulation (:func:`gcrsky.checks.uvsim.simulate_uvdata`, matvis, an independent simulator):
7 antennas (hexagon, 14.6 m spacing) with 14 m Gaussian dishes at HERA, 2 channels at 120 and
121 MHz, 12 integrations over 1.5 h, a sky drawn from an isotropic prior ``C_l = 50 / (1 + l)^2``
K^2 at lmax 6 (the degree sampled: representable, ``band_limit`` "truncate" is right), matvis
nside 32 and gcrsky nside 32 (forward error 2.5e-5 of the rms, measured), radiometer noise of
10 s x 100 kHz (the cross-visibilities' rms is ~40 sigma: noise dominates the simulators'
disagreement by 1e3).  The known gains (:func:`gcrsky.checks.gainsim.corrupt_with_gains`):
5 % rms amplitude and 5 deg rms phase per antenna and feed, linear across the band and the
1.5 h (Legendre modes), applied to the noisy file (the noise scales with them: the autos'
radiometer sigma stays right).  The file is read with ``compress=False`` (gains are per
antenna: merged redundant rows would average different gains) as ``xx``.

Checks (the statistics are :mod:`tests.test_gains`'):

* the corruption against pyuvdata: ``uvcalibrate`` with the true calfits / calh5 undoes it (rounding);
* the joint chain (sky, gains on 2 x 2 Legendre modes, scale; collapsed sweep): the whitened
  mean ``z^2`` of the truth along the sky's 16 most data-dominated directions, and of the true
  gain perturbations (put in the chain's gauge), both within the chi-square range (below);
* negative control: the sky posterior that ignores the gains fails the sky check by far, and
  unit gains (what it assumes) lie far outside the gain posterior;
* the truth-calibrated file (``cal=`` the true calfits): the plain sky posterior passes;
* the posterior-mean gains written as calfits (:func:`gcrsky.io.write_gain_calibration`), read by
  pyuvdata and applied by ``uvcalibrate`` to the corrupted file: what they leave of the true
  gains (the overall amplitude per channel, set by the priors, aside) is as large as the
  posterior's own spread, not more.

Tolerances: ``mean z^2`` of K unit normals is chi^2_K / K; the range is its two-sided 0.1 %
quantiles (a false alarm once in 1000 seeds for exact draws), the upper end widened by 25 % for
the chain's Monte-Carlo error in the covariance (as in :mod:`tests.test_gains`).  Seeds are fixed.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

pytest.importorskip("matvis")

from gcrsky.checks.gainsim import corrupt_with_gains, smooth_gains  # noqa: E402
from gcrsky.checks.matvis import HERA_SITE, observing_times, site  # noqa: E402
from gcrsky.checks.uvsim import simulate_uvdata  # noqa: E402
from gcrsky.inference import gain_init, gain_setup, gibbs_setup, joint_gain_step, recentre  # noqa: E402
from gcrsky.instrument import gaussian_beam, hex_array  # noqa: E402
from gcrsky.io.uvdata import from_uvdata  # noqa: E402
from gcrsky.model import gain_model, isotropic_prior, n_gain_params, perturbations, unit_gains  # noqa: E402
from gcrsky.model.operator import dense_matrix  # noqa: E402

LMAX, NSIDE = 6, 32
FREQS = np.array([120e6, 121e6])
NT, HOURS = 12, 1.5
DT_S, DNU_HZ = 10.0, 1e5
CL = 50.0 / (1.0 + np.arange(LMAX + 1)) ** 2
MODES = (2, 2)  # gain modes (frequency, time): complete across 2 channels; a linear drift in time
N_DIR = 8  # data-dominated sky directions per channel
BURN, KEEP = 300, 1500


def _chi2_range(k: int) -> tuple[float, float]:
    """The two-sided 0.1 % range of chi^2_k / k, the upper end x 1.25 for the chain's Monte-Carlo error."""
    return stats.chi2.ppf(0.0005, k) / k, 1.25 * stats.chi2.ppf(0.9995, k) / k


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The clean simulation, the corrupted file (UVH5) and the true gains (calfits and calh5)."""
    d = tmp_path_factory.mktemp("gainfiles")
    n = (LMAX + 1) ** 2
    prior = isotropic_prior(np.tile(CL, (FREQS.size, 1)), n)
    truth = np.asarray(prior.inv_var) ** -0.5 * np.random.default_rng(1).standard_normal((FREQS.size, n))
    sim = simulate_uvdata(hex_array((2, 3, 2)), site(*HERA_SITE), observing_times("2025-03-21T18:00:00", HOURS, NT),
                          FREQS, gaussian_beam(14.0), truth, LMAX, nside_matvis=NSIDE, pols=("xx", "yy", "xy", "yx"),
                          dt_s=DT_S, dnu_hz=DNU_HZ, noise_seed=0)
    cor, cal = corrupt_with_gains(sim.uvdata, amp=0.05, phase_deg=5.0, delay_modes=2, time_modes=2, seed=3)
    paths = {"data": d / "corrupted.uvh5", "calfits": d / "true.calfits", "calh5": d / "true.calh5", "dir": d}
    cor.write_uvh5(str(paths["data"]))
    cal.write_calfits(str(paths["calfits"]))
    cal.write_calh5(str(paths["calh5"]))
    return {"sim": sim, "truth": truth, "corrupted": cor, "cal": cal, "paths": paths}


def _read(path, **kw):
    return from_uvdata(str(path), lmax=LMAX, nside=NSIDE, dish_diameter_m=14.0, compress=False, pol="xx", prior=CL,
                       noise="autos", flux_scale="off", **kw)


@pytest.fixture(scope="module")
def problem(files):
    return _read(files["paths"]["data"])


def test_smooth_gains_have_the_asked_rms_and_are_smooth():
    f, t = np.linspace(100e6, 110e6, 11), np.linspace(0.0, 0.05, 9)
    g = smooth_gains(5, f, t, amp=0.05, phase_deg=5.0, delay_modes=2, time_modes=2, seed=1)
    assert g.shape == (5, 11, 9, 2)
    np.testing.assert_allclose(np.sqrt(np.mean((np.abs(g) - 1) ** 2)), 0.05, rtol=1e-12)
    np.testing.assert_allclose(np.rad2deg(np.sqrt(np.mean(np.angle(g) ** 2))), 5.0, rtol=1e-12)
    # a = |g| - 1 and phi are bilinear in (frequency, time): their second differences vanish along each axis
    a, phi = np.abs(g) - 1, np.angle(g)
    for x in (a, phi):
        assert np.abs(np.diff(x, 2, axis=1)).max() < 1e-12 and np.abs(np.diff(x, 2, axis=2)).max() < 1e-12
    # a different seed, different gains; delay_modes=1: constant across the band
    assert np.abs(smooth_gains(5, f, t, seed=2) - g).max() > 0.01
    np.testing.assert_allclose(np.diff(smooth_gains(5, f, t, delay_modes=1), axis=1), 0, atol=1e-15)


def test_corruption_is_pyuvdatas_convention_and_uvcalibrate_undoes_it(files):
    """V_ij,pq -> g_i,p conj(g_j,q) V_ij,pq for every product (checked row by row against the UVCal's gain_array),
    and pyuvdata's uvcalibrate with the true calfits / calh5 gives the uncorrupted (noisy) data back to rounding."""
    from pyuvdata import UVCal, utils
    from pyuvdata.utils import uvcalibrate

    clean, cor, cal = files["sim"].uvdata, files["corrupted"], files["cal"]
    times = np.unique(clean.time_array)
    feed = {"x": 0, "y": 1}
    rng = np.random.default_rng(0)
    for k in rng.choice(clean.Nblts, 40, replace=False):
        i, j, t = int(clean.ant_1_array[k]), int(clean.ant_2_array[k]), int(np.searchsorted(times, clean.time_array[k]))
        for p, num in enumerate(clean.polarization_array):
            a, b = utils.polnum2str(int(num))
            want = cal.gain_array[i, :, t, feed[a]] * np.conj(cal.gain_array[j, :, t, feed[b]]) * clean.data_array[k, :, p]
            np.testing.assert_allclose(cor.data_array[k, :, p], want, rtol=1e-13)
    scale = np.abs(clean.data_array).max()
    for name in ("calfits", "calh5"):
        back = uvcalibrate(_uvdata(files["paths"]["data"]), UVCal.from_file(str(files["paths"][name])),
                           inplace=False)
        np.testing.assert_allclose(back.data_array, clean.data_array, rtol=0, atol=1e-12 * scale)
    # the corruption is not a no-op: 5 % gains move the data by ~40 x 5 % sigma
    assert np.abs(cor.data_array - clean.data_array).max() > 0.02 * scale


def _uvdata(path):
    from pyuvdata import UVData

    return UVData.from_file(str(path))
