"""response_matrix_sht (healpy map2alm of each baseline's kernel) against the direct quadrature.

Both compute the same pixel sum over the same HEALPix pixels, weights, beams and
fringe sign; only the summation order differs (healpy sums each ring's FFT, the
quadrature contracts basis maps), so they must agree to rounding: the measured
relative max error is ~2e-15; the tolerance 1e-12 leaves room for platform BLAS/FFT
differences while still catching any scaling, sign or conjugation error (all O(1)).
"""

from __future__ import annotations

import dataclasses

import healpy as hp
import numpy as np
import pytest
from pyuvdata.analytic_beam import UnpolarizedAnalyticBeam

from gcrsky.instrument import (
    HERA_LATITUDE_DEG,
    antpairs,
    gaussian_beam,
    hex_array,
    make_array,
    realified_projection,
    response_matrix,
    response_matrix_sht,
)
from gcrsky.sphere import real_basis

FREQS = (100e6, 102e6)
RTOL = 1e-12


@dataclasses.dataclass(kw_only=True, eq=False)
class TiltedEllipticalBeam(UnpolarizedAnalyticBeam):
    """Elliptical Gaussian power beam centred off zenith (no azimuthal symmetry), frequency dependent."""

    za0: float = 0.25
    az0: float = np.deg2rad(30.0)  # UVBeam azimuth, North of East
    sig_e: float = 0.35
    sig_n: float = 0.15

    def _power_eval(self, *, az_grid, za_grid, f_grid):
        e = np.sin(za_grid) * np.cos(az_grid) - np.sin(self.za0) * np.cos(self.az0)
        n = np.sin(za_grid) * np.sin(az_grid) - np.sin(self.za0) * np.sin(self.az0)
        values = np.exp(-(e**2) / self.sig_e**2 - n**2 / self.sig_n**2) * (f_grid / 1e8) ** 0.5
        data = self._get_empty_data_array(az_grid.shape, beam_type="power")
        for p in range(self.Npols):
            data[0, p] = values
        return data


def _rel_err(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max() / np.abs(b).max())


@pytest.fixture(scope="module")
def hexagon():
    return make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))


def test_realified_projection_convention():
    """healpy a_lm of a real map -> sum_p w_p M_p f_k(p), with f_k gcrsky's real basis."""
    lmax, nside = 7, 8
    rng = np.random.default_rng(1)
    npix = hp.nside2npix(nside)
    m = rng.standard_normal((2, npix))
    alm = np.stack([hp.map2alm(x, lmax=lmax, iter=0, use_weights=False) for x in m])
    theta, phi = hp.pix2ang(nside, np.arange(npix))
    F = np.asarray(real_basis(lmax, theta, phi))
    direct = (4 * np.pi / npix) * m @ F
    assert _rel_err(realified_projection(alm, lmax), direct) < RTOL


@pytest.mark.parametrize(
    "lmax,nside,lst",
    [(6, 32, 0.0), (12, 16, 1.3), (10, 32, -2.1)],
)
def test_matches_direct_quadrature(hexagon, lmax, nside, lst):
    pairs = antpairs(10, autos=True)  # 45 crosses + 10 autos
    direct = response_matrix(hexagon, pairs, FREQS, lmax, nside, lst_ref_rad=lst)
    sht = response_matrix_sht(hexagon, pairs, FREQS, lmax, nside, lst, chunk=8)  # ragged last chunk
    assert sht.shape == direct.shape == (2, 55, (lmax + 1) ** 2)
    assert sht.dtype == direct.dtype
    assert _rel_err(sht, direct) < RTOL


def test_matches_with_asymmetric_mixed_beams():
    """Non-azimuthally-symmetric pyuvdata analytic beam, mixed with Gaussians (A_i != A_j)."""
    dip, gau = TiltedEllipticalBeam(), gaussian_beam(14.0)
    beams = [dip if k % 2 else gau for k in range(10)]
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, beams)
    pairs = antpairs(10)[::3]
    direct = response_matrix(arr, pairs, FREQS, 8, 32, lst_ref_rad=0.7)
    sht = response_matrix_sht(arr, pairs, FREQS, 8, 32, lst_ref_rad=0.7)
    assert _rel_err(sht, direct) < RTOL


def test_bad_inputs(hexagon):
    pairs = antpairs(10)[:3]
    with pytest.raises(ValueError, match="3\\*nside-1"):
        response_matrix_sht(hexagon, pairs, FREQS, 48, 16)
    with pytest.raises(ValueError, match="nside"):
        response_matrix_sht(hexagon, pairs, FREQS, 6, 0)
    with pytest.raises(ValueError, match="lmax"):
        response_matrix_sht(hexagon, pairs, FREQS, -1, 16)
    with pytest.raises(ValueError, match="freqs_hz"):
        response_matrix_sht(hexagon, pairs, [-1e8], 6, 16)
    with pytest.raises(ValueError, match="pairs"):
        response_matrix_sht(hexagon, np.array([[0, 10]]), FREQS, 6, 16)
    with pytest.raises(ValueError, match="chunk"):
        response_matrix_sht(hexagon, pairs, FREQS, 6, 16, chunk=0)


def test_auto_builds_by_transforms_from_the_threshold(hexagon, monkeypatch):
    """``response_matrix(method="auto")`` (the default) is ducc0's route from
    ``RESPONSE_DUCC_MIN_LMAX`` on (every lmax) when ducc0 imports; otherwise the rings sum below
    ``RESPONSE_SHT_MIN_LMAX`` and this module's transforms from it on, bit for bit what
    each route gives when asked by name; the routes agree to RTOL (polarised rows too)."""
    import gcrsky.instrument.response as resp_mod

    pairs = antpairs(10)[::4]
    rings = np.asarray(response_matrix(hexagon, pairs, FREQS, 8, 16, method="rings", pols="xx"))
    sht = np.asarray(response_matrix(hexagon, pairs, FREQS, 8, 16, method="sht", pols="xx"))
    assert _rel_err(sht, rings) < RTOL
    if resp_mod.RESPONSE_DUCC_MIN_LMAX <= 8 and resp_mod._auto_method(8) == "ducc":
        ducc = np.asarray(response_matrix(hexagon, pairs, FREQS, 8, 16, method="ducc", pols="xx"))
        np.testing.assert_array_equal(np.asarray(response_matrix(hexagon, pairs, FREQS, 8, 16, pols="xx")), ducc)
    monkeypatch.setattr(resp_mod, "RESPONSE_DUCC_MIN_LMAX", 10**9)  # as without ducc0
    np.testing.assert_array_equal(np.asarray(response_matrix(hexagon, pairs, FREQS, 8, 16, pols="xx")), rings)
    monkeypatch.setattr(resp_mod, "RESPONSE_SHT_MIN_LMAX", 8)
    np.testing.assert_array_equal(np.asarray(response_matrix(hexagon, pairs, FREQS, 8, 16, pols="xx")), sht)
    with pytest.raises(ValueError, match="method must be"):
        response_matrix(hexagon, pairs, FREQS, 8, 16, method="healpy")
