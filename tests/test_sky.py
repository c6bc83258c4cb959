"""Tests of gcrsky.sim.sky: truth skies from pyradiosky's GSM map (offline) and GSM2016.

No test may touch the network: the ``no_network`` fixture makes every socket
name lookup / connection fail *and records it*, so an attempted download is a
test failure rather than a hang.
"""

from __future__ import annotations

import importlib.resources
import logging
import socket
import sys
from pathlib import Path

import h5py
import healpy as hp
import numpy as np
import pytest
from scipy.stats import chi2 as chi2_dist

try:
    import gcrsky  # noqa: F401
except ImportError:  # running from outside the repo without an install
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gcrsky.sim import sky
from gcrsky.sim.sky import SkyTruth, gsm2016_available, sky_truth
from gcrsky.sphere import alm_to_map, mode_table, realify, unrealify

NSIDE_SRC = 8
LMAX_DATA = 2 * NSIDE_SRC  # 16


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    """Fail fast (and remember) any attempt to resolve or connect."""
    attempts = []

    def refuse(*args, **kwargs):
        attempts.append(args)
        raise OSError("network access attempted in a gcrsky test")

    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket.socket, "connect", refuse)
    yield attempts
    assert not attempts, f"test attempted network access: {attempts}"


@pytest.fixture(scope="module")
def src():
    """The shipped file read independently of gcrsky (h5py): freqs (Hz), Stokes I (K), lat/lon."""
    path = importlib.resources.files("pyradiosky").joinpath("data/gsm_icrs.skyh5")
    with h5py.File(str(path), "r") as f:
        assert f["Data/stokes"].attrs["unit"] in ("K", b"K")
        stokes = f["Data/stokes"][()]
        freqs = f["Header/freq_array"][()]
        inds = f["Header/hpx_inds"][()]
        lat = f["Header/lat"][()]
        lon = f["Header/lon"][()]
    assert int(np.asarray(inds).size) == hp.nside2npix(NSIDE_SRC)
    np.testing.assert_array_equal(inds, np.arange(inds.size))
    return dict(freqs=freqs, maps=stokes[0], qu_v=stokes[1:], lat=lat, lon=lon)


def _sub_alm(a_real: np.ndarray, lmax: int, lcut: int) -> np.ndarray:
    """Complex healpy-ordered alm of ``a_real`` (realified, lmax) truncated to l <= lcut."""
    return hp.resize_alm(unrealify(np.asarray(a_real), lmax), lmax, lmax, lcut, lcut)


# --------------------------------------------------------------------------
# the source file itself
# --------------------------------------------------------------------------


def test_source_file_layout(src):
    """RING ordering (stored pixel centres match healpy RING), 10 channels 50-150 MHz, only Stokes I."""
    theta, phi = hp.pix2ang(NSIDE_SRC, np.arange(hp.nside2npix(NSIDE_SRC)), nest=False)
    np.testing.assert_allclose(np.pi / 2 - theta, src["lat"], atol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (phi - src["lon"]))), 0, atol=1e-12)
    np.testing.assert_allclose(src["freqs"], np.linspace(50e6, 150e6, 10))
    assert np.all(src["qu_v"] == 0)
    assert np.all(src["maps"] > 0)


# --------------------------------------------------------------------------
# reproduction of the source map
# --------------------------------------------------------------------------


@pytest.mark.parametrize("ichan", [0, 4, 9])
def test_reproduces_source_map(src, ichan):
    m = src["maps"][ichan]
    t = sky_truth(src["freqs"][ichan], LMAX_DATA, source="pyradiosky")
    assert t.source == "pyradiosky-gsm" and t.lmax_data == LMAX_DATA == t.lmax
    assert t.alm.shape == (1, (LMAX_DATA + 1) ** 2)

    # Monopole: HEALPix pixels have equal area, so a_00 = sqrt(4 pi) x pixel mean exactly.
    np.testing.assert_allclose(t.alm[0, 0] / np.sqrt(4 * np.pi), m.mean(), rtol=1e-6)

    rec = alm_to_map(t.alm, LMAX_DATA, NSIDE_SRC)[0]
    resid = m - rec
    # (a) Unsmoothed: the residual is the map's content above l = 16, which the
    # truth cannot carry.  Estimate that content's rms from the map's own C_l
    # over 16 < l <= 3 nside - 1 (the top of what an nside-8 map holds); the
    # measured ratio is ~1.08 (aliasing from higher l adds a little).
    cl = hp.alm2cl(hp.map2alm(m, lmax=3 * NSIDE_SRC - 1, iter=3))
    ell = np.arange(LMAX_DATA + 1, 3 * NSIDE_SRC)
    rms_high = np.sqrt(np.sum((2 * ell + 1) * cl[ell]) / (4 * np.pi))
    assert resid.std() < 1.3 * rms_high
    assert np.corrcoef(m, rec)[0, 1] > 0.97

    # (b) Large scales, in pixel space (no SHT involved): average both maps over
    # 20-degree discs.  A top hat of that radius suppresses l > 16 by ~10x, so
    # the ~20% unsmoothed residual becomes a few percent (measured 2.4-2.6%).
    vecs = np.array(hp.pix2vec(NSIDE_SRC, np.arange(m.size))).T
    discs = [hp.query_disc(NSIDE_SRC, v, np.radians(20.0)) for v in vecs]
    ms = np.array([m[d].mean() for d in discs])
    rs = np.array([rec[d].mean() for d in discs])
    assert np.std(ms - rs) < 0.05 * np.std(ms)

    # (c) Low l (1..8) against one-pass quadrature sum_p m_p Y*_lm Omega_p, a
    # different estimator: they differ only by quadrature/aliasing error
    # (measured 0.8% of the l = 1..8 norm).
    a_quad = hp.map2alm(m, lmax=8, iter=0)
    a_true = _sub_alm(t.alm[0], LMAX_DATA, 8)
    a_quad[0] = a_true[0] = 0
    assert np.linalg.norm(a_quad - a_true) < 0.02 * np.linalg.norm(a_true)


def test_realified_layout_and_types(src):
    t = sky_truth([100e6, 102e6], 20, source="pyradiosky")
    assert isinstance(t, SkyTruth)
    assert t.alm.dtype == np.float64 and t.alm.shape == (2, 21**2)
    assert t.freqs_hz.shape == (2,) and t.lmax == 20 and t.lmax_data == LMAX_DATA
    # round-trip through the layout module is exact
    np.testing.assert_array_equal(realify(unrealify(t.alm, 20), 20), t.alm)
    # a scalar frequency is one channel; lmax = 0 is the monopole alone
    t0 = sky_truth(100e6, 0, source="pyradiosky")
    assert t0.alm.shape == (1, 1) and t0.lmax_data == 0
    np.testing.assert_allclose(t0.alm[0, 0], t.alm[0, 0], rtol=1e-12)


# --------------------------------------------------------------------------
# frequency interpolation
# --------------------------------------------------------------------------


def _powerlaw_independent(src, nu):
    """Power-law interpolation between the bracketing channels, written out independently."""
    f, maps = src["freqs"], src["maps"]
    i = int(np.nonzero(f <= nu)[0][-1])
    i = min(i, f.size - 2)
    beta = np.log(maps[i + 1] / maps[i]) / np.log(f[i + 1] / f[i])
    return maps[i] * (nu / f[i]) ** beta


@pytest.mark.parametrize("nu", [100e6, 102e6, 57.3e6, 149.9e6])
def test_loglog_interpolation(src, nu):
    expected = _powerlaw_independent(src, nu)
    got = sky._loglog_interp(src["freqs"], src["maps"], np.array([nu]))[0]
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    # a pixel by hand: T = T_i (nu/f_i)^beta, beta from the two channels
    p = 300
    f, maps = src["freqs"], src["maps"]
    i = np.searchsorted(f, nu) - 1
    beta = (np.log(maps[i + 1, p]) - np.log(maps[i, p])) / (np.log(f[i + 1]) - np.log(f[i]))
    np.testing.assert_allclose(got[p], np.exp(np.log(maps[i, p]) + beta * np.log(nu / f[i])), rtol=1e-12)

    # through the public API: the whole expansion is that of the interpolated map
    t = sky_truth([nu], LMAX_DATA, source="pyradiosky")
    np.testing.assert_allclose(t.alm[0, 0] / np.sqrt(4 * np.pi), expected.mean(), rtol=1e-9)
    a = hp.map2alm(expected, lmax=LMAX_DATA, iter=3)
    a[0] = np.sqrt(4 * np.pi) * expected.mean()
    np.testing.assert_allclose(t.alm[0], realify(a, LMAX_DATA), rtol=0, atol=1e-9 * abs(a[0]))


def test_exact_channel_is_the_channel_map(src):
    got = sky._loglog_interp(src["freqs"], src["maps"], src["freqs"].copy())
    np.testing.assert_array_equal(got, src["maps"])


def test_interpolation_is_between_channels(src):
    """Between two channels each pixel lies between its bracketing values (monotone power law)."""
    f, maps = src["freqs"], src["maps"]
    got = sky._loglog_interp(f, maps, np.array([100e6]))[0]
    lo, hi = np.minimum(maps[4], maps[5]), np.maximum(maps[4], maps[5])
    assert np.all((got >= lo) & (got <= hi))


# --------------------------------------------------------------------------
# Gaussian small-scale extension
# --------------------------------------------------------------------------

LMAX_EXT = 48


@pytest.fixture(scope="module")
def ext_truth():
    return sky_truth([100e6, 102e6, 130e6], LMAX_EXT, source="pyradiosky", extend_seed=7)


def _fit_powerlaw_independent(cl, lmin, lmax):
    """Weighted LSQ of log C_l = log A + alpha log l, weights (2l+1)/2 (inverse variance of log C_l)."""
    ell = np.arange(lmin, lmax + 1)
    sw = np.sqrt((2 * ell + 1) / 2.0)
    design = np.stack([np.ones(ell.size), np.log(ell)], axis=1) * sw[:, None]
    (log_a, alpha), *_ = np.linalg.lstsq(design, np.log(cl[ell]) * sw, rcond=None)
    return np.exp(log_a), alpha


def test_extension_deterministic_and_seeded(ext_truth):
    again = sky_truth([100e6, 102e6, 130e6], LMAX_EXT, source="pyradiosky", extend_seed=7)
    np.testing.assert_array_equal(again.alm, ext_truth.alm)

    other = sky_truth([100e6, 102e6, 130e6], LMAX_EXT, source="pyradiosky", extend_seed=8)
    tab = mode_table(LMAX_EXT)
    ext = tab.ell > LMAX_DATA
    np.testing.assert_array_equal(other.alm[:, ~ext], ext_truth.alm[:, ~ext])
    # different draws: correlation between the seeds' extensions is ~0 (|r| < 5/sqrt(N))
    x, y = ext_truth.alm[0, ext], other.alm[0, ext]
    assert not np.allclose(x, y)
    # whiten per l (the amplitude falls steeply with l), then correlate
    ell = tab.ell[ext]
    rms = {l: np.sqrt(np.mean(np.r_[x[ell == l], y[ell == l]] ** 2)) for l in np.unique(ell)}
    scale = np.array([rms[l] for l in ell])
    r = np.corrcoef(x / scale, y / scale)[0, 1]
    assert abs(r) < 5 / np.sqrt(ext.sum())


def test_extension_leaves_data_modes_untouched(ext_truth):
    plain = sky_truth([100e6, 102e6, 130e6], LMAX_DATA, source="pyradiosky")
    for k in range(3):
        np.testing.assert_array_equal(_sub_alm(ext_truth.alm[k], LMAX_EXT, LMAX_DATA), unrealify(plain.alm[k], LMAX_DATA))
    assert ext_truth.lmax_data == LMAX_DATA and ext_truth.lmax == LMAX_EXT
    assert "extension" in ext_truth.note


def test_extension_nested_in_lmax(ext_truth):
    """For a fixed seed the draw at (l, m) does not depend on the requested lmax."""
    small = sky_truth([100e6, 102e6, 130e6], 30, source="pyradiosky", extend_seed=7)
    for k in range(3):
        np.testing.assert_array_equal(_sub_alm(ext_truth.alm[k], LMAX_EXT, 30), unrealify(small.alm[k], 30))


def test_extension_power_spectrum(ext_truth):
    """|a_lm|^2 / C_l over the extension follows chi-square statistics with the fitted C_l."""
    tab = mode_table(LMAX_EXT)
    ext = tab.ell > LMAX_DATA
    ell_ext = tab.ell[ext]
    # per realified entry: m = 0 has variance C_l, Re/Im with m > 0 each C_l / 2
    var_unit = np.where(tab.m[ext] == 0, 1.0, 0.5)
    n_dof = int(ext.sum())
    assert n_dof == (LMAX_EXT + 1) ** 2 - (LMAX_DATA + 1) ** 2
    for k in range(ext_truth.freqs_hz.size):
        cl_data = hp.alm2cl(_sub_alm(ext_truth.alm[k], LMAX_EXT, LMAX_DATA))
        amp, alpha = _fit_powerlaw_independent(cl_data, LMAX_DATA // 2, LMAX_DATA)
        assert -4.0 < alpha < -2.0  # diffuse synchrotron: measured ~ -2.99
        cl_fit = amp * ell_ext.astype(float) ** alpha
        chi2 = np.sum(ext_truth.alm[k, ext] ** 2 / (cl_fit * var_unit))
        # sum of n_dof unit-variance squared normals: mean n_dof, sd sqrt(2 n_dof)
        assert abs(chi2 - n_dof) < 4 * np.sqrt(2 * n_dof), (chi2, n_dof)
        # per l: (2l+1) C_l_hat / C_l ~ chi^2 with 2l+1 dof; every l inside its
        # two-sided 1e-4 quantiles (32 degrees: a shape error, e.g. a wrong
        # slope or a missing factor 2 for m > 0, would push the ends out).
        cl_all = hp.alm2cl(unrealify(ext_truth.alm[k], LMAX_EXT))
        ells = np.arange(LMAX_DATA + 1, LMAX_EXT + 1)
        stat = (2 * ells + 1) * cl_all[ells] / (amp * ells.astype(float) ** alpha)
        lo, hi = chi2_dist.ppf(1e-4, 2 * ells + 1), chi2_dist.ppf(1 - 1e-4, 2 * ells + 1)
        assert np.all((stat > lo) & (stat < hi)), stat / (2 * ells + 1)
        # m = 0 versus m > 0 share of the power: E = 1 each per dof
        m0 = tab.m[ext] == 0
        z2 = ext_truth.alm[k, ext] ** 2 / (cl_fit * var_unit)
        assert abs(z2[m0].sum() - m0.sum()) < 4 * np.sqrt(2 * m0.sum())
        # continuity: the fitted C_l at l = 17 is close to the map's own C_16 .. C_15 level
        assert 0.5 < amp * (LMAX_DATA + 1) ** alpha / np.mean(cl_data[LMAX_DATA - 1 :]) < 1.5


def test_extension_exact_construction(ext_truth):
    """a_lm = sqrt(A l^alpha) z_lm exactly, with the documented draw order of z and the weighted fit."""
    rng = np.random.default_rng(7)
    z = {}
    for ell in range(LMAX_DATA + 1, LMAX_EXT + 1):
        re, im = rng.standard_normal(ell + 1), rng.standard_normal(ell)
        z[(ell, 0, False)] = re[0]
        for m in range(1, ell + 1):
            z[(ell, m, False)] = re[m] / np.sqrt(2)
            z[(ell, m, True)] = im[m - 1] / np.sqrt(2)
    tab = mode_table(LMAX_EXT)
    ext = np.flatnonzero(tab.ell > LMAX_DATA)
    zvec = np.array([z[(tab.ell[i], tab.m[i], bool(tab.is_imag[i]))] for i in ext])
    for k in range(ext_truth.freqs_hz.size):
        cl_data = hp.alm2cl(_sub_alm(ext_truth.alm[k], LMAX_EXT, LMAX_DATA))
        amp, alpha = _fit_powerlaw_independent(cl_data, LMAX_DATA // 2, LMAX_DATA)
        expected = np.sqrt(amp * tab.ell[ext].astype(float) ** alpha) * zvec
        np.testing.assert_allclose(ext_truth.alm[k, ext], expected, rtol=1e-9)


def test_extension_same_unit_draws_across_frequency(ext_truth):
    """a_lm(nu_1) / a_lm(nu_0) depends on l only: one set of unit draws scaled by sqrt(C_l(nu))."""
    tab = mode_table(LMAX_EXT)
    for ell in (LMAX_DATA + 1, 30, LMAX_EXT):
        sel = tab.ell == ell
        for k in (1, 2):
            ratio = ext_truth.alm[k, sel] / ext_truth.alm[0, sel]
            np.testing.assert_allclose(ratio, ratio[0], rtol=1e-10)
    # and the extension gets fainter with frequency, as the map does
    sel = tab.ell == LMAX_EXT
    assert np.all(np.abs(ext_truth.alm[2, sel]) < np.abs(ext_truth.alm[0, sel]))


# --------------------------------------------------------------------------
# input validation
# --------------------------------------------------------------------------


@pytest.mark.parametrize("nu", [40e6, 49.9e6, 150.1e6, 200e6])
def test_out_of_range_frequency(nu):
    with pytest.raises(ValueError, match=r"50\.0+, 150\.0+\] MHz"):
        sky_truth([100e6, nu], 20, source="pyradiosky")
    if not gsm2016_available():
        with pytest.raises(ValueError, match="fell back"):
            sky_truth([nu], 20)


def test_channel_edges_accepted(src):
    t = sky_truth([50e6, 150e6], 4, source="pyradiosky")
    np.testing.assert_allclose(t.alm[:, 0] / np.sqrt(4 * np.pi), src["maps"][[0, -1]].mean(axis=1), rtol=1e-12)


@pytest.mark.parametrize("lmax", [-1, 2.5, 20.0, True, "20", None])
def test_bad_lmax(lmax):
    with pytest.raises(ValueError, match="lmax"):
        sky_truth([100e6], lmax, source="pyradiosky")


def test_numpy_integer_lmax_ok():
    assert sky_truth([100e6], np.int64(3), source="pyradiosky").lmax == 3


@pytest.mark.parametrize(
    "freqs", [[], [100e6, np.nan], [100e6, np.inf], [-100e6], [0.0], [[100e6, 102e6]], ["abc"]]
)
def test_bad_freqs(freqs):
    with pytest.raises(ValueError, match="freqs_hz"):
        sky_truth(freqs, 10, source="pyradiosky")


def test_bad_source_and_seed():
    with pytest.raises(ValueError, match="source"):
        sky_truth([100e6], 10, source="gsm2008")
    with pytest.raises(ValueError, match="extend_seed"):
        sky_truth([100e6], 20, source="pyradiosky", extend_seed=1.5)


# --------------------------------------------------------------------------
# GSM2016 availability and fallback
# --------------------------------------------------------------------------


def test_gsm2016_available_is_bool_offline(no_network):
    assert isinstance(gsm2016_available(), bool)
    assert not no_network


def test_gsm2016_absent_raises_and_auto_falls_back(caplog):
    if gsm2016_available():
        pytest.skip("GSM2016 data are on disk: the absent-data branch cannot be exercised")
    with pytest.raises(RuntimeError, match="not in the astropy download cache"):
        sky_truth([100e6], 20, source="gsm2016")
    with caplog.at_level(logging.WARNING, logger="gcrsky.sim.sky"):
        t = sky_truth([100e6, 102e6], 20)
    assert t.source == "pyradiosky-gsm"
    assert "FALLBACK" in t.note and "not on disk" in t.note
    assert any("falling back" in r.getMessage() for r in caplog.records)
    ref = sky_truth([100e6, 102e6], 20, source="pyradiosky")
    np.testing.assert_array_equal(t.alm, ref.alm)


@pytest.mark.slow
def test_gsm2016_present():
    if not gsm2016_available():
        pytest.skip("GSM2016 data (pygdsm's gsm2016_components.h5) are not on disk; not downloading")
    t = sky_truth([100e6, 102e6], 20, source="gsm2016")
    assert t.source == "gsm2016" and t.lmax_data == 20 and t.alm.shape == (2, 441)
    assert sky_truth([100e6], 4).source == "gsm2016"
    # same sky as the pyradiosky GSM to ~10% in the monopole
    ref = sky_truth([100e6, 102e6], 20, source="pyradiosky")
    np.testing.assert_allclose(t.alm[:, 0], ref.alm[:, 0], rtol=0.1)


# --------------------------------------------------------------------------
# galactic -> equatorial rotation (used by the GSM2016 path), checked offline
# --------------------------------------------------------------------------

# ICRS directions of the north galactic pole and the galactic centre (IAU 1958 / Reid & Brunthaler).
NGP_RADEC = (192.85948, 27.12825)
GC_RADEC = (266.40500, -28.93617)


def _synthetic_galactic_maps(nside):
    """3 + 2 sin(b) + cos(b) cos(l) (+ a quadrupole) in galactic RING pixels, two 'frequencies'."""
    x, y, z = hp.pix2vec(nside, np.arange(hp.nside2npix(nside)))
    base = 3.0 + 2.0 * z + x + 0.5 * (3 * z**2 - 1)
    return np.stack([base, 1.5 * base])


def _radec_unit(ra_deg, dec_deg):
    return np.array(hp.ang2vec(ra_deg, dec_deg, lonlat=True))


def test_galactic_to_equatorial_rotation():
    nside, lmax = 32, 4
    alm = sky._galactic_maps_to_equatorial_alm(_synthetic_galactic_maps(nside), lmax)
    # the same sky built directly in equatorial pixels from the poles' ICRS directions
    v = np.array(hp.pix2vec(nside, np.arange(hp.nside2npix(nside))))
    zg = _radec_unit(*NGP_RADEC) @ v  # sin(b)
    xg = _radec_unit(*GC_RADEC) @ v  # cos(b) cos(l)
    eq = 3.0 + 2.0 * zg + xg + 0.5 * (3 * zg**2 - 1)
    expected = hp.map2alm(eq, lmax=lmax, iter=3)
    expected[0] = np.sqrt(4 * np.pi) * eq.mean()
    # tolerance: healpy's G->C matrix vs the IAU pole/centre directions (<1 arcsec)
    # and nside-32 quadrature of l <= 2 (~1e-6)
    np.testing.assert_allclose(alm[0], expected, atol=2e-5 * np.abs(expected[0]))
    np.testing.assert_allclose(alm[1], 1.5 * alm[0], rtol=1e-12, atol=1e-12)


def test_gsm2016_plumbing_with_fake_pygdsm(monkeypatch):
    """The GSM2016 path with a stand-in for pygdsm: units, frequency unit, frames, no download."""
    import pygdsm.gsm16 as g16

    seen = {}

    class FakeGSM16:
        def __init__(self, **kwargs):
            seen["init"] = kwargs
            seen["path"] = g16.download_from_url_list(["https://example.invalid/x.h5"])

        def generate(self, freqs):
            seen["freqs"] = np.array(freqs)
            maps = _synthetic_galactic_maps(16)[:1] * np.ones((len(np.atleast_1d(freqs)), 1))
            return maps[0] if maps.shape[0] == 1 else maps  # pygdsm squeezes one frequency

    monkeypatch.setattr(g16, "GlobalSkyModel16", FakeGSM16)
    monkeypatch.setattr(sky, "_gsm2016_cached_path", lambda: "/fake/gsm2016_components.h5")
    assert gsm2016_available()

    t = sky_truth([100e6], 6, source="gsm2016")
    assert seen["init"]["freq_unit"] == "Hz" and seen["init"]["data_unit"] == "TRJ"
    assert seen["path"] == "/fake/gsm2016_components.h5"
    np.testing.assert_array_equal(seen["freqs"], [100e6])
    assert t.source == "gsm2016" and t.lmax_data == 6 and t.alm.shape == (1, 49)
    expected = realify(sky._galactic_maps_to_equatorial_alm(_synthetic_galactic_maps(16)[:1], 6), 6)
    np.testing.assert_allclose(t.alm, expected, rtol=1e-12, atol=1e-12)

    t2 = sky_truth([100e6, 102e6], 6)  # auto picks GSM2016 when available
    assert t2.source == "gsm2016" and "FALLBACK" not in t2.note
    with pytest.raises(ValueError, match="GSM2016"):
        sky_truth([5e6], 6, source="gsm2016")
