"""Tests of gcrsky.sphere.real_basis against healpy and scipy.

References:
* healpy ``alm2map`` at HEALPix pixel centres (independent SHT library);
* scipy ``sph_harm_y_all`` at random off-grid directions, including within
  1e-8 rad of the poles and exactly on them.  The real-basis formula used for the
  reference (Y_l0, 2 Re Y_lm, -2 Im Y_lm) is itself pinned against healpy's
  complex synthesis in ``tests/test_layout.py``.

Tolerance: ``REL = 1e-10`` of the largest basis-map value.  The three-term
Legendre recursion accumulates rounding ~ l * eps ~ 1e-14 at l = 96; scipy's own
recursion is similarly accurate, so 1e-10 leaves a wide margin while still
failing for any wrong normalisation, phase or index (errors of order 1).
"""

from __future__ import annotations

import healpy as hp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.special import sph_harm_y_all

from gcrsky.sphere import legendre_table, mode_table, n_params, real_basis, realify

REL = 1e-10


def scipy_real_basis(lmax: int, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(Npix, n) real basis maps from scipy's complex Y_lm (independent reference)."""
    tab = mode_table(lmax)
    y = sph_harm_y_all(lmax, lmax, theta, phi)  # (lmax+1, 2 lmax+1, Npix); y[l, m] for m >= 0
    ylm = y[tab.ell, tab.m]  # (n, Npix)
    f = np.where(tab.m[:, None] == 0, ylm.real, np.where(tab.is_imag[:, None], -2 * ylm.imag, 2 * ylm.real))
    return f.T


def random_directions(rng, npts: int):
    """Random directions, plus points at and near both poles (colatitude, longitude)."""
    theta = np.arccos(rng.uniform(-1, 1, npts))
    phi = rng.uniform(0, 2 * np.pi, npts)
    near = np.array([0.0, 1e-12, 1e-8, 1e-4, 0.01, np.pi - 0.01, np.pi - 1e-6, np.pi - 1e-10, np.pi])
    theta = np.concatenate([theta, near])
    phi = np.concatenate([phi, rng.uniform(0, 2 * np.pi, near.size)])
    return theta, phi


@pytest.mark.parametrize("lmax, npts", [(0, 50), (1, 50), (20, 200), (96, 40)])
def test_real_basis_vs_scipy_off_grid(lmax, npts):
    rng = np.random.default_rng(lmax)
    theta, phi = random_directions(rng, npts)
    F = np.asarray(real_basis(lmax, jnp.asarray(theta), jnp.asarray(phi)))
    assert F.shape == (theta.size, n_params(lmax))
    ref = scipy_real_basis(lmax, theta, phi)
    err = np.max(np.abs(F - ref)) / np.max(np.abs(ref))
    assert err < REL, f"lmax={lmax}: max relative error {err:.2e}"
    # on the poles only m = 0 survives.  At theta = pi, sin(pi) = 1.2e-16 in float64 and
    # Pbar_l1 / sin(theta) ~ l^1.5 <= 1e3, so m = 1 maps reach ~1e-13 there: atol 1e-12.
    tab = mode_table(lmax)
    pole = (theta == 0.0) | (theta == np.pi)
    assert np.all(np.abs(F[np.ix_(pole, tab.m > 0)]) < 1e-12)


@pytest.mark.parametrize("lmax, nside, npix_sub", [(20, 16, None), (96, 64, 400)])
def test_real_basis_vs_healpy_alm2map(lmax, nside, npix_sub):
    rng = np.random.default_rng(100 + lmax)
    nalm = hp.Alm.getsize(lmax)
    alm = rng.standard_normal(nalm) + 1j * rng.standard_normal(nalm)
    alm[: lmax + 1] = alm[: lmax + 1].real
    m = hp.alm2map(alm, nside, lmax=lmax)
    pix = np.arange(m.size) if npix_sub is None else rng.choice(m.size, npix_sub, replace=False)
    # include the pixels nearest the poles
    pix = np.unique(np.concatenate([pix, [0, 1, 2, 3, m.size - 4, m.size - 1]]))
    theta, phi = hp.pix2ang(nside, pix)
    F = real_basis(lmax, jnp.asarray(theta), jnp.asarray(phi))
    ours = np.asarray(F @ jnp.asarray(realify(alm, lmax)))
    err = np.max(np.abs(ours - m[pix])) / np.max(np.abs(m))
    assert err < REL, f"lmax={lmax}: relative error {err:.2e} vs healpy"


def test_legendre_table_orthonormal():
    """Pbar_lm are orthonormal on [-1, 1] w.r.t. 2 pi dx (Gauss-Legendre, exact for this degree)."""
    lmax = 12
    x, w = np.polynomial.legendre.leggauss(lmax + 2)
    tab = np.asarray(legendre_table(lmax, jnp.asarray(x)))  # [l, p, m]
    for m in range(lmax + 1):
        P = tab[m:, :, m]  # (l, p)
        gram = 2 * np.pi * (P * w[None, :]) @ P.T
        np.testing.assert_allclose(gram, np.eye(lmax + 1 - m), atol=1e-12)
    # zero above the diagonal (m > l)
    for l in range(lmax + 1):
        assert np.all(tab[l, :, l + 1 :] == 0.0)


def test_gradients_match_finite_differences():
    """d real_basis / d(theta, phi) via check_grads (central differences, away from the poles).

    check_grads compares forward- and reverse-mode derivatives with finite
    differences of step 1e-4 at float64 tolerances (its default ~1e-5 relative
    for second-order-accurate differences of an O(1) smooth function).
    """
    lmax = 8
    rng = np.random.default_rng(7)
    theta = jnp.asarray([0.3, 1.0, 1.6, 2.5, 2.9])
    phi = jnp.asarray(rng.uniform(0, 2 * np.pi, 5))

    check_grads(lambda th, ph: real_basis(lmax, th, ph), (theta, phi), order=1, modes=("fwd", "rev"))


def test_theta_derivative_closed_form():
    """d/dtheta of the l=1, m=1 real basis map (-sqrt(3/2pi) sin th cos ph) is analytic.

    Includes both poles, where the derivative is finite and nonzero (a derivative
    computed through sqrt(1 - cos^2 theta) would be NaN there).
    """
    theta = jnp.asarray([0.0, 0.4, 1.2, 2.2, np.pi])
    phi = jnp.asarray([0.7, 0.1, 2.0, 4.0, 1.9])
    jac = jax.vmap(jax.grad(lambda th, ph: real_basis(1, th[None], ph[None])[0, 2]))(theta, phi)
    expect = -np.sqrt(3 / (2 * np.pi)) * np.cos(theta) * np.cos(phi)
    np.testing.assert_allclose(np.asarray(jac), expect, rtol=1e-13)
