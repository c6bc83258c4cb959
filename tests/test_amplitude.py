"""The collapsed amplitude sampler (gcrsky.inference.amplitude) against dense Gaussian algebra.

References: the marginal ``log N(y; u B m, I + u^2 B Y S Y^T B^T)`` and the posterior of ``delta`` written
densely with numpy from the Jacobian of the whitened operator (``jax.jacfwd``), and an independent
quadrature (scipy) of the marginal for the grid draws.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

from gcrsky.inference.amplitude import (
    amplitude_eigen,
    amplitude_setup,
    draw_log_u,
    log_marginal,
    sky_given,
    wiener_given,
)
from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array
from gcrsky.model import build_problem, isotropic_prior
from gcrsky.solvers.dataspace import from_rows, sqrt_weights, to_rows, whitened_apply

U_TRUE = np.array([0.003, 0.0025])


def _system(seed=0, lmax=8, nt=3):
    """A hexagon, 2 channels, lmax 8 (n = 81), data = U_TRUE x (the sky) + noise, a model mean a0."""
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    n, nf = (lmax + 1) ** 2, 2
    cl = 50.0 / (1.0 + np.arange(lmax + 1)) ** 2
    prior = isotropic_prior(np.stack([cl, cl]), n)
    rng = np.random.default_rng(seed)
    a0 = 3 * np.asarray(prior.inv_var) ** -0.5 * rng.standard_normal((nf, n))
    truth = a0 + np.asarray(prior.inv_var) ** -0.5 * rng.standard_normal((nf, n))
    prob = build_problem(arr, [100e6, 101e6], np.linspace(0.0, 0.6, nt), lmax, 16, a_true=truth * U_TRUE[:, None],
                         sigma=2e-4, prior=prior._replace(mean=a0), key=jax.random.PRNGKey(seed))
    sys0 = prob.system()
    flags = np.zeros(sys0.inv_noise.shape, bool)
    flags[0, 1, :2] = True
    return sys0._replace(inv_noise=jnp.where(flags, 0.0, sys0.inv_noise), data=jnp.where(flags, 7.0 + 0j, sys0.data))


@pytest.fixture(scope="module")
def system():
    return _system()


@pytest.fixture(scope="module")
def factor(system):
    nf, nt, nbl = system.data.shape
    rng = np.random.default_rng(3)
    return jnp.asarray((1 + 0.05 * rng.standard_normal((nf, nt, nbl))) * np.exp(0.1j * rng.standard_normal((nf, nt, nbl))))


def _dense(system, factor=None):
    """(Y_D (Nf, N_d, n), y (Nf, N_d), m_D (Nf, N_d), keep (Nf, N_d)) dense."""
    sw = sqrt_weights(system)
    nf, n = system.prior.mean.shape
    _, nt, nbl = system.data.shape
    Y = jax.jacfwd(lambda a: whitened_apply(system, sw, a))(jnp.zeros((nf, n)))  # (Nf, N_d, Nf, n)
    Y = np.stack([np.asarray(Y[f, :, f, :]) for f in range(nf)])
    if factor is not None:
        B = jax.vmap(lambda col: to_rows(factor * from_rows(col, nt, nbl)), in_axes=2, out_axes=2)
        Y = np.asarray(B(jnp.asarray(Y)))
    keep = np.asarray(to_rows(jnp.where(system.inv_noise > 0, 1.0 + 1.0j, 0.0)).real) > 0
    y = np.where(keep, np.asarray(to_rows(sw * system.data)), 0.0)
    m = np.einsum("fdk,fk->fd", Y, np.asarray(system.prior.mean))
    return Y, y, m, keep


def _dense_logp(system, u, factor=None):
    Y, y, m, keep = _dense(system, factor)
    s = 1.0 / np.asarray(system.prior.inv_var)
    w = np.asarray(to_rows(jnp.asarray(system.inv_noise, complex) * (1 + 1j)).real)
    out = []
    for f in range(Y.shape[0]):
        k = keep[f]
        Yk = Y[f][k]
        C = np.eye(k.sum()) + u[f] ** 2 * (Yk * s[f]) @ Yk.T
        r = y[f][k] - u[f] * m[f][k]
        out.append(stats.multivariate_normal(np.zeros(k.sum()), C).logpdf(r) + 0.5 * np.sum(np.log(w[f][k])))
    return np.array(out)


def _dense_posterior(system, u, factor=None):
    Y, y, m, keep = _dense(system, factor)
    s = 1.0 / np.asarray(system.prior.inv_var)
    means, precs = [], []
    for f in range(Y.shape[0]):
        Yk = u[f] * Y[f][keep[f]]
        P = np.diag(1.0 / s[f]) + Yk.T @ Yk
        means.append(np.linalg.solve(P, Yk.T @ (y[f][keep[f]] - u[f] * m[f][keep[f]])))
        precs.append(P)
    return np.stack(means), np.stack(precs)


@pytest.mark.parametrize("gains", [False, True])
def test_the_marginal_is_the_dense_gaussian(system, factor, gains):
    f = factor if gains else None
    fixed = amplitude_setup(system)
    eig = amplitude_eigen(fixed, f)
    for u in (U_TRUE, 0.5 * U_TRUE, np.array([1.0, 1e-5])):
        got = np.asarray(log_marginal(fixed, eig, jnp.log(u)))
        np.testing.assert_allclose(got, _dense_logp(system, u, f), rtol=1e-9, atol=1e-6)


def test_the_gradient_in_log_u_matches_finite_differences(system):
    fixed = amplitude_setup(system)
    eig = amplitude_eigen(fixed)
    lu = jnp.log(jnp.asarray(U_TRUE * 1.1))
    g = jax.grad(lambda x: jnp.sum(log_marginal(fixed, eig, x)))(lu)
    h = 1e-6
    fd = [(np.sum(log_marginal(fixed, eig, lu.at[i].add(h))) - np.sum(log_marginal(fixed, eig, lu.at[i].add(-h))))
          / (2 * h) for i in range(2)]
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-6)


def _quadrature_cdf(fixed, eig, f):
    """CDF of ln u_f by scipy's adaptive quadrature of the exact marginal (normalised over its support)."""
    lp = lambda x: float(log_marginal(fixed, eig, jnp.full((2,), x))[f])  # noqa: E731
    xs = np.linspace(np.log(U_TRUE[f]) - 1.0, np.log(U_TRUE[f]) + 1.0, 4001)
    lps = np.array([float(v) for v in log_marginal(fixed, eig, jnp.stack([xs, xs], 1))[:, f]])
    mode = xs[np.argmax(lps)]
    top = lp(mode)
    dens = lambda x: np.exp(lp(x) - top)  # noqa: E731
    lo, hi = xs[lps > lps.max() - 40][[0, -1]]
    Z = integrate.quad(dens, lo, hi, points=[mode], limit=200, epsabs=0, epsrel=1e-10)[0]
    return lambda x: integrate.quad(dens, lo, min(max(x, lo), hi), limit=200, epsabs=0, epsrel=1e-10)[0] / Z


def test_grid_draws_follow_the_marginal_and_a_shifted_law_is_caught(system):
    """KS against the quadrature CDF at 2000 draws (alpha 1e-3); the same draws shifted by 0.3 posterior sd fail."""
    fixed = amplitude_setup(system)
    eig = amplitude_eigen(fixed)
    draws = np.asarray(draw_log_u(jax.random.PRNGKey(5), fixed, eig, 2000))
    for f in range(2):
        cdf = _quadrature_cdf(fixed, eig, f)
        grid = np.quantile(draws[:, f], np.linspace(0.01, 0.99, 41))
        cvals = np.array([cdf(x) for x in grid])
        emp = np.interp(draws[:, f], grid, cvals, left=0.0, right=1.0)  # the CDF at each draw (interpolated)
        p = stats.kstest(emp, "uniform").pvalue
        assert p > 1e-3, (f, p)
        sd = draws[:, f].std()
        shifted = np.interp(draws[:, f] + 0.3 * sd, grid, cvals, left=0.0, right=1.0)
        assert stats.kstest(shifted, "uniform").pvalue < 1e-3
        # the data pin u: the truth within the draws' central 99.9 %
        lo, hi = np.quantile(draws[:, f], [0.0005, 0.9995])
        assert lo < np.log(U_TRUE[f]) < hi, (f, np.exp([lo, hi]), U_TRUE[f])


@pytest.mark.parametrize("gains", [False, True])
def test_the_sky_given_u_is_the_dense_posterior(system, factor, gains):
    """Wiener filter to 1e-9 of the prior sd; draws whitened by the dense precision have mean z^2 = 1
    (2000 draws x 81: sd 0.0035, tolerance 0.02) and a whitened sample mean consistent with 0
    (``N mean(zbar^2)`` ~ chi2_81 / 81, sd 0.16: below 1.6, p ~ 1e-4); the draws at a wrong amplitude (x 0.8) fail
    the latter."""
    f = factor if gains else None
    fixed = amplitude_setup(system)
    eig = amplitude_eigen(fixed, f)
    u = jnp.asarray(U_TRUE)
    mean, P = _dense_posterior(system, U_TRUE, f)
    wf = np.asarray(wiener_given(fixed, eig, u))
    sd = np.asarray(system.prior.inv_var) ** -0.5
    np.testing.assert_allclose(wf / sd, mean / sd, atol=1e-9)
    keys = jax.random.split(jax.random.PRNGKey(2), 2000)
    draws = np.asarray(jax.vmap(lambda k: sky_given(k, fixed, eig, u))(keys))  # (ndraws, Nf, n)
    wrong = np.asarray(jax.vmap(lambda k: sky_given(k, fixed, eig, 0.8 * u))(keys))
    for ch in range(2):
        L = np.linalg.cholesky(P[ch])
        z = (draws[:, ch] - mean[ch]) @ L
        assert abs(np.mean(z**2) - 1.0) < 0.02, np.mean(z**2)
        assert len(z) * np.mean(z.mean(0) ** 2) < 1.6
        zw = (wrong[:, ch] - mean[ch]) @ L
        assert len(zw) * np.mean(zw.mean(0) ** 2) > 3.0
