"""Tests of gcrsky.model.noise and gcrsky.model.prior (and normal.check_float64).

Statistical tests use fixed keys, so they are deterministic; each states the
false-alarm rate it would have under fresh randomness (a z-score bound of 5
is a two-sided false-alarm rate of 5.7e-7; chi-square bounds are quantiles).
"""

from __future__ import annotations

import healpy as hp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import chi2

from gcrsky.base import check_float64
from gcrsky.model import draw_noise, flat_prior, isotropic_prior, paper_prior
from gcrsky.model.noise import clean_data, inverse_variance, radiometer_sigma
from gcrsky.sphere import mode_table, n_params, realify, unrealify

Z = 5.0  # two-sided false-alarm rate 2 * norm.sf(5) = 5.7e-7 per check


# ----------------------------------------------------------------------- radiometer


def test_radiometer_sigma_conventions():
    vii = np.array([[100.0, 250.0], [80.0, 3000.0]])
    vjj = np.array([[200.0, 150.0], [90.0, 10.0]])
    dt, dnu = 60.0, 1e6
    per = radiometer_sigma(vii, vjj, dt, dnu)
    total = radiometer_sigma(vii, vjj, dt, dnu, convention="total")
    # E|n|^2 = V_ii V_jj / (dt dnu) = 2 sigma^2 (DESIGN §3)
    np.testing.assert_allclose(total**2, vii * vjj / (dt * dnu), rtol=1e-15)
    np.testing.assert_allclose(per**2, vii * vjj / (2 * dt * dnu), rtol=1e-15)
    np.testing.assert_allclose(total / per, np.sqrt(2.0), rtol=1e-15)
    np.testing.assert_array_equal(radiometer_sigma(vii, vjj, dt, dnu, convention="per_component"), per)
    # broadcasting autos of different shapes
    assert radiometer_sigma(vii[:, :1], vjj, dt, dnu).shape == (2, 2)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(auto_i=-1.0, auto_j=1.0, dt_s=1.0, dnu_hz=1.0),
        dict(auto_i=1.0, auto_j=0.0, dt_s=1.0, dnu_hz=1.0),
        dict(auto_i=1.0, auto_j=1.0, dt_s=0.0, dnu_hz=1.0),
        dict(auto_i=1.0, auto_j=1.0, dt_s=1.0, dnu_hz=-1.0),
        dict(auto_i=1.0, auto_j=1.0, dt_s=1.0, dnu_hz=1.0, convention="rms"),
    ],
)
def test_radiometer_sigma_rejects_bad_input(kwargs):
    with pytest.raises(ValueError):
        radiometer_sigma(**kwargs)


def test_draw_noise_convention(getkey):
    """Re and Im each N(0, sigma^2), independent: E|n|^2 = 2 sigma^2.

    With N = 2e5 samples of heterogeneous sigma, u = |n|^2 / (2 sigma^2) ~ Exp(1)
    (mean 1, variance 1), so mean(u) has std 1/sqrt(N) = 2.2e-3; the bound is Z
    sigmas (false alarm 5.7e-7).  The reference code's (randn + i randn)/sqrt(2)
    convention would give mean(u) = 0.5, i.e. 224 sigmas off.
    """
    N = 200_000
    sigma = jnp.asarray(np.random.default_rng(0).uniform(0.1, 10.0, N))
    n = np.asarray(draw_noise(getkey(), sigma))
    assert n.dtype == np.complex128 and n.shape == (N,)
    s = np.asarray(sigma)
    u = np.abs(n) ** 2 / (2 * s**2)
    se = 1 / np.sqrt(N)
    assert abs(u.mean() - 1) < Z * se
    # each component separately has unit variance after scaling (chi2_N / N: std sqrt(2/N))
    for comp in (n.real, n.imag):
        x = comp / s
        assert abs(x.mean()) < Z * se
        assert abs(np.mean(x**2) - 1) < Z * np.sqrt(2 / N)
    # Re and Im uncorrelated
    assert abs(np.mean(n.real * n.imag / s**2)) < Z * se
    # shape follows sigma, fresh keys give fresh noise
    n2 = np.asarray(draw_noise(getkey(), sigma))
    assert not np.allclose(n, n2)


# ------------------------------------------------------------------------ weights, NaNs


def test_inverse_variance_with_weights():
    rng = np.random.default_rng(1)
    sigma = rng.uniform(0.5, 2.0, (2, 3, 4))
    np.testing.assert_allclose(inverse_variance(sigma), 1 / sigma**2, rtol=1e-15)
    w = rng.uniform(0, 1, sigma.shape)
    w[0, 1, :] = 0.0  # a flagged time
    w[1, :, 2] = 1.0
    iv = inverse_variance(sigma, w)
    np.testing.assert_allclose(iv, w / sigma**2, rtol=1e-15)
    assert np.all(iv[0, 1, :] == 0.0)  # flagged -> exactly zero
    # weights broadcast (e.g. per-baseline flags)
    wb = np.array([1.0, 0.0, 1.0, 0.5])
    np.testing.assert_allclose(inverse_variance(sigma, wb), wb / sigma**2, rtol=1e-15)


@pytest.mark.parametrize("bad", [-0.1, 1.5, np.nan, np.inf])
def test_inverse_variance_rejects_bad_weights(bad):
    sigma = np.ones((1, 2, 3))
    w = np.ones_like(sigma)
    w[0, 1, 2] = bad
    with pytest.raises(ValueError):
        inverse_variance(sigma, w)


@pytest.mark.parametrize("bad", [0.0, -1.0, np.nan, np.inf])
def test_inverse_variance_rejects_bad_sigma(bad):
    sigma = np.ones((1, 2, 3))
    sigma[0, 0, 1] = bad
    with pytest.raises(ValueError):
        inverse_variance(sigma)


def test_clean_data_flagged_nan_replaced():
    rng = np.random.default_rng(2)
    d = rng.standard_normal((2, 3, 4)) + 1j * rng.standard_normal((2, 3, 4))
    iv = np.ones(d.shape)
    iv[1, 2, 3] = 0.0
    iv[0, 0, 0] = 0.0
    d_bad = d.copy()
    d_bad[1, 2, 3] = np.nan
    d_bad[0, 0, 0] = complex(np.inf, 0)
    out = clean_data(d_bad, iv)
    assert np.all(np.isfinite(out))
    assert out[1, 2, 3] == 0 and out[0, 0, 0] == 0
    keep = np.ones(d.shape, bool)
    keep[1, 2, 3] = keep[0, 0, 0] = False
    np.testing.assert_array_equal(out[keep], d[keep])
    # the caller's array is not mutated
    assert np.isnan(d_bad[1, 2, 3])


def test_clean_data_unflagged_nan_raises_with_location():
    d = np.ones((2, 3, 4), complex)
    iv = np.ones(d.shape)
    d[1, 2, 3] = np.nan
    d[1, 1, 0] = np.nan
    iv[1, 1, 0] = 0.0  # this one is flagged and fine
    with pytest.raises(ValueError, match=r"1 non-finite unflagged.*\(1, 2, 3\)"):
        clean_data(d, iv)


# ------------------------------------------------------------------------------- priors


def test_paper_prior_std_and_scale(getkey):
    rng = np.random.default_rng(3)
    a_true = rng.standard_normal((2, 49)) * np.array([[30.0] * 10 + [1.0] * 39])  # some |a| > 5, some < 5
    key = getkey()
    pr = paper_prior(a_true, key)
    std = np.maximum(0.1 * np.abs(a_true), 0.5)
    assert np.any(0.1 * np.abs(a_true) > 0.5) and np.any(0.1 * np.abs(a_true) < 0.5)
    np.testing.assert_allclose(pr.inv_var, 1 / std**2, rtol=1e-15)
    # prior_scale multiplies the variance, and leaves the mean (same key) alone
    pr100 = paper_prior(a_true, key, prior_scale=100.0)
    np.testing.assert_allclose(pr100.inv_var, 1 / (100 * std**2), rtol=1e-15)
    np.testing.assert_array_equal(pr100.mean, pr.mean)
    # frac and floor are honoured
    pr2 = paper_prior(a_true, key, frac=0.2, floor_std=1.0)
    np.testing.assert_allclose(pr2.inv_var, 1 / np.maximum(0.2 * np.abs(a_true), 1.0) ** 2, rtol=1e-15)


def test_paper_prior_mean(getkey):
    rng = np.random.default_rng(4)
    a_true = rng.standard_normal((2, 961)) * 20.0
    key = getkey()
    pr = paper_prior(a_true, key)
    std = np.maximum(0.1 * np.abs(a_true), 0.5)
    # keep_true_monopole (default): entry 0 is l = m = 0
    assert mode_table(30).ell[0] == 0
    np.testing.assert_array_equal(pr.mean[:, 0], a_true[:, 0])
    # the rest is a0 ~ N(a_true, S): standardised residuals are N(0, 1)
    z = ((pr.mean - a_true) / std)[:, 1:].ravel()
    N = z.size
    assert abs(z.mean()) < Z / np.sqrt(N)
    lo, hi = chi2.ppf([1e-6, 1 - 1e-6], N)  # two-sided false alarm 2e-6
    assert lo < np.sum(z**2) < hi
    # without keep_true_monopole the monopole is drawn too
    pr_free = paper_prior(a_true, key, keep_true_monopole=False)
    assert np.all(pr_free.mean[:, 0] != a_true[:, 0])
    np.testing.assert_array_equal(pr_free.mean[:, 1:], pr.mean[:, 1:])
    # zero_mean
    np.testing.assert_array_equal(paper_prior(a_true, key, zero_mean=True).mean, 0.0)
    # the caller's array is not modified
    a_copy = a_true.copy()
    paper_prior(a_true, key)
    np.testing.assert_array_equal(a_true, a_copy)


@pytest.mark.parametrize(
    "kwargs", [dict(frac=0.0), dict(floor_std=-1.0), dict(prior_scale=0.0), dict(floor_std=0.0)]
)
def test_paper_prior_rejects_bad_parameters(kwargs, getkey):
    a_true = np.zeros((1, 4))  # floor_std = 0 with a zero mode gives a zero std
    with pytest.raises(ValueError):
        paper_prior(a_true, getkey(), **kwargs)


def test_isotropic_prior_variances():
    lmax = 5
    n = n_params(lmax)
    cl = np.array([[5.0, 4.0, 3.0, 2.0, 1.5, 1.0], [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]])
    pr = isotropic_prior(cl, n)
    tab = mode_table(lmax)
    for k in range(n):
        expect = cl[:, tab.ell[k]] * (1.0 if tab.m[k] == 0 else 0.5)
        np.testing.assert_allclose(1 / pr.inv_var[:, k], expect, rtol=1e-15)
    np.testing.assert_array_equal(pr.mean, 0.0)
    with pytest.raises(ValueError):
        isotropic_prior(cl[:, :-1], n)
    with pytest.raises(ValueError):
        isotropic_prior(-cl, n)


def test_isotropic_prior_matches_healpy_synalm():
    """Realified healpy.synalm draws have the variances isotropic_prior states.

    K = 4000 draws: each mode's sample variance s2 satisfies K s2 / var ~ chi2_K;
    bounds at the 1e-7 / 1 - 1e-7 quantiles, so over n = 64 modes the overall
    false-alarm rate is < 1.3e-5.  A factor-2 error (C_l vs C_l / 2) would be ~60
    standard errors off.
    """
    lmax, K = 7, 4000
    n = n_params(lmax)
    cl = 1.0 / (1.0 + np.arange(lmax + 1)) ** 1.5
    pr = isotropic_prior(cl, n)
    np.random.seed(5)  # healpy.synalm draws from NumPy's global generator
    try:
        draws = np.stack([realify(hp.synalm(cl, lmax=lmax), lmax) for _ in range(K)])
    finally:
        np.random.seed(None)
    s2 = np.mean(draws**2, axis=0)  # the mean is known to be zero
    stat = K * s2 * pr.inv_var[0]
    lo, hi = chi2.ppf([1e-7, 1 - 1e-7], K)
    assert np.all((stat > lo) & (stat < hi)), np.sort(stat / K)[[0, -1]]


def test_isotropic_prior_draws_have_right_alm2cl(getkey):
    """Draws a = sqrt(S) z have healpy alm2cl spectra consistent with C_l.

    For one draw, (2l+1) Chat_l / C_l ~ chi2_{2l+1}; summing over K = 300 draws
    gives chi2_{K(2l+1)}.  Per-l bounds at the 1e-6 quantiles: overall false-alarm
    rate < 2.2e-5 for 11 degrees.
    """
    lmax, K = 10, 300
    n = n_params(lmax)
    cl = np.linspace(10.0, 1.0, lmax + 1)
    pr = isotropic_prior(cl, n)
    z = np.asarray(jax.random.normal(getkey(), (K, n)))
    a = pr.mean + z / np.sqrt(pr.inv_var)  # (K, n)
    alm = unrealify(a, lmax)
    chat = np.stack([hp.alm2cl(x, lmax=lmax) for x in alm])  # (K, lmax+1)
    ell = np.arange(lmax + 1)
    stat = np.sum((2 * ell + 1) * chat / cl, axis=0)
    dof = K * (2 * ell + 1)
    assert np.all(stat > chi2.ppf(1e-6, dof)) and np.all(stat < chi2.isf(1e-6, dof)), stat / dof


def test_flat_prior():
    pr = flat_prior(2, 16)
    assert pr.inv_var.shape == (2, 16) and pr.mean.shape == (2, 16)
    assert np.all(pr.inv_var == 0.0) and np.all(pr.mean == 0.0)
    mean = np.arange(32.0).reshape(2, 16)
    np.testing.assert_array_equal(flat_prior(2, 16, mean=mean).mean, mean)
    assert np.all(flat_prior(2, 16, mean=mean).inv_var == 0.0)


# ------------------------------------------------------------------------- dtype policy


def test_check_float64():
    check_float64(np.zeros(3), jnp.zeros(3, jnp.complex128), np.arange(3), jnp.zeros(2))
    with pytest.raises(TypeError, match="float64"):
        check_float64(np.zeros(3), np.zeros(3, np.float32))
    with pytest.raises(TypeError, match="float64"):
        check_float64(jnp.zeros(3, jnp.float32))
    with pytest.raises(TypeError, match="complex128"):
        check_float64(jnp.zeros(3, jnp.complex64))
    with pytest.raises(TypeError):
        check_float64(np.zeros(3, np.float16))
