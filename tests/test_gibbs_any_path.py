"""A Gibbs step on any solver path, and the scalar-hyperparameter state (issue 37, item 4).

References are independent of the code under test: the dense posterior from NumPy
(``P`` from ``problem.precision_matrix()``, its Cholesky and solves), a data-space
Gaussian density ``N(d; X a0, s N + A X S X^T)`` built from the dense response, and
``gcrsky.log_evidence(..., method="cholesky")`` on the system with the scales applied.

Statistical tests: draws whitened by the dense posterior, ``w = L^T (a - a_wf)`` with
``L L^T = P``, are exactly N(0, I).  With D draws of n parameters in Nf channels the sum
of ``|w|^2`` is chi-square with ``D n Nf`` degrees of freedom and ``D |mean(w)|^2`` chi-square
with ``n Nf``; each is tested two-sided at a false-alarm rate of 1e-4 (2 tests for each of
5 paths in gcr_step and in sky_step: <= 2e-3 in all for the file).  The negative controls
(draws of a system whose noise is 30% larger, or sky_step draws against the posterior of the
wrong spectrum) fail them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import isotropic_problem
from scipy import stats

import gcrsky
from gcrsky.inference import (
    prepare_scalar,
    scalar_draw,
    scalar_log_evidence,
    scalar_quadratics,
)
from gcrsky.model import Prior, dense_matrix, scale_noise, with_prior
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.solvers import CGOptions
from gcrsky.solvers.registry import PATHS

ALPHA = 1e-4  # false-alarm rate of each statistical test
NDRAWS = 300


@pytest.fixture(scope="module")
def full_day(small_array, small_response):
    """Uniform full-day coverage (every path applies, the m-mode path included), lmax 6, 2 channels."""
    nt = 2 * small_response.lmax + 3
    return isotropic_problem(small_array, small_response, 2 * np.pi * np.arange(nt) / nt, seed=3)


def _scaled(system, s, A):
    """The system with noise variance times s and prior variance times A ((Nf,) or scalars)."""
    nf = system.data.shape[0]
    s = np.broadcast_to(np.asarray(s, float), (nf,))
    A = np.broadcast_to(np.asarray(A, float), (nf,))
    out = scale_noise(system, jnp.asarray(s)[:, None, None])
    return with_prior(out, Prior(system.prior.mean, system.prior.inv_var / jnp.asarray(A)[:, None]))


def _dense_posterior(system):
    """NumPy: (a_wf (Nf, n), lower Cholesky factor L of P (Nf, n, n))."""
    P = np.asarray(precision_matrix(system))
    b = np.asarray(wiener_rhs(system))
    a = np.stack([np.linalg.solve(P[f], b[f]) for f in range(P.shape[0])])
    return a, np.linalg.cholesky(P)


def _whiten(draws, a_wf, L):
    """``L^T (a - a_wf)`` for draws (Nf, D, n)."""
    return np.einsum("fij,fdi->fdj", L, np.asarray(draws) - a_wf[:, None, :])


def _chi2_ok(value, dof):
    lo, hi = stats.chi2.ppf([ALPHA / 2, 1 - ALPHA / 2], dof)
    return lo <= value <= hi


def _gaussian_ok(w):
    """Whitened draws (Nf, D, n) are N(0, I): variance and mean tests (the module's docstring)."""
    nf, d, n = w.shape
    return _chi2_ok(np.sum(w**2), nf * d * n) and _chi2_ok(d * np.sum(np.mean(w, axis=1) ** 2), nf * n)


def _chain(system, options, key, ndraws=NDRAWS):
    """``ndraws`` independent gcr_step draws from the prior mean (vmapped over keys, jitted)."""
    state = gcrsky.gcr_init(system.prior.mean)
    step = jax.jit(jax.vmap(lambda k: gcrsky.gcr_step(k, state, system, options=options)))
    out, info = step(jax.random.split(key, ndraws))
    return np.swapaxes(np.asarray(out.position), 0, 1), info  # (Nf, D, n)


# ---------------------------------------------------------------- gcr_step on every path


@pytest.mark.parametrize("name", list(PATHS))
def test_gcr_step_draws_the_dense_posterior_on_every_path(full_day, name):
    """Every registered path's options work in gcr_step (none listed here by hand: the registry's),
    and its draws have the dense posterior's mean and covariance."""
    system = full_day.system()
    options = PATHS[name].options_type()
    if isinstance(options, CGOptions):
        options = CGOptions(dense=False, tol=1e-10)
    draws, info = _chain(system, options, jax.random.PRNGKey(11))
    assert bool(np.all(np.asarray(info.converged))), name
    assert np.asarray(info.converged).shape == (NDRAWS, 2)  # SolveInfo with (Nf,) fields per step
    a_wf, L = _dense_posterior(system)
    assert _gaussian_ok(_whiten(draws, a_wf, L)), name


def test_gcr_step_negative_control(full_day):
    """Draws of a system with 30% more noise fail the test against the true posterior."""
    system = full_day.system()
    draws, _ = _chain(scale_noise(system, 1.3), gcrsky.CholeskyOptions(), jax.random.PRNGKey(12))
    a_wf, L = _dense_posterior(system)
    assert not _gaussian_ok(_whiten(draws, a_wf, L))


def test_gcr_step_cholesky_is_the_dense_formula(full_day):
    """One Cholesky step is ``a_wf + L^-T z`` with the dense NumPy a_wf and factor L of P, and z the path's
    documented deviates (``normal(split(key, 1)[0], (Nf, n))``): ``L^T (a - a_wf) = z``."""
    system = full_day.system()
    key = jax.random.PRNGKey(5)
    state = gcrsky.gcr_init(system.prior.mean)
    a, info = gcrsky.gcr_step(key, state, system, options=gcrsky.CholeskyOptions())
    assert a.position.shape == system.prior.mean.shape and bool(np.all(np.asarray(info.converged)))
    a_wf, L = _dense_posterior(system)
    z = np.asarray(jax.random.normal(jax.random.split(key, 1)[0], system.prior.mean.shape))
    w = _whiten(np.asarray(a.position)[:, None, :], a_wf, L)[:, 0]
    np.testing.assert_allclose(w, z, rtol=0, atol=1e-8)  # posterior-sigma units: rounding of n = 49 solves


def test_gcr_step_refuses_pc_off_cg(full_day):
    system = full_day.system()
    with pytest.raises(ValueError, match="pc="):
        gcrsky.gcr_step(jax.random.PRNGKey(0), gcrsky.gcr_init(system.prior.mean), system,
                        options=gcrsky.CholeskyOptions(), pc=object())


# ---------------------------------------------------------------- the scalar state


SCALES = [(1.0, 1.0), (2.5, 0.3), (0.4, 7.0), ((0.8, 1.6), (2.0, 0.5))]  # last: per channel (Nf,)


def _dataspace_log_evidence(system):
    """NumPy: ``log N(d; X a0, N + X S X^T)`` over the real and imaginary parts, per channel."""
    X = np.asarray(dense_matrix(system.op))  # (Nf, Nt, Nbl, n)
    out = []
    for f in range(X.shape[0]):
        Xf = X[f].reshape(-1, X.shape[-1])
        Xr = np.concatenate([Xf.real, Xf.imag])
        w = np.asarray(system.inv_noise[f]).ravel()
        d = np.asarray(system.data[f]).ravel()
        r = np.concatenate([d.real, d.imag]) - Xr @ np.asarray(system.prior.mean[f])
        C = np.diag(np.concatenate([1 / w, 1 / w])) + (Xr / np.asarray(system.prior.inv_var[f])) @ Xr.T
        out.append(stats.multivariate_normal(np.zeros(r.size), C).logpdf(r))
    return np.array(out)


@pytest.mark.parametrize("s, A", SCALES)
def test_scalar_evidence_is_the_exact_evidence(full_day, s, A):
    system = full_day.system()
    state = prepare_scalar(system)
    got = np.asarray(scalar_log_evidence(state, jnp.asarray(s), jnp.asarray(A)))
    scaled = _scaled(system, s, A)
    ref = np.asarray(gcrsky.log_evidence(scaled, method="cholesky"))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * np.max(np.abs(ref)))  # |log p| ~ 1e3: ~1e-6 absolute
    np.testing.assert_allclose(got, _dataspace_log_evidence(scaled), rtol=0, atol=1e-8 * np.max(np.abs(ref)))


@pytest.mark.parametrize("s, A", SCALES[1:])
def test_scalar_draws_are_exact(full_day, s, A):
    """scalar_draw is affine in the key's normal deviates z (documented key scheme), a = m + T z: fitting m and
    T exactly from n + 11 draws (a linear solve, no Monte Carlo), m is the dense Wiener filter of the scaled
    system and T T^T its posterior covariance P^-1."""
    system = full_day.system()
    state = prepare_scalar(system)
    key = jax.random.PRNGKey(7)
    nf, n = system.prior.mean.shape
    nd = n + 11
    draws = np.asarray(scalar_draw(key, state, jnp.asarray(s), jnp.asarray(A), nd))
    assert draws.shape == (nf, nd, n)
    z = np.asarray(jax.random.normal(key, (nf, nd, n)))
    a_wf, L = _dense_posterior(_scaled(system, s, A))
    for f in range(nf):
        Z = np.concatenate([np.ones((nd, 1)), z[f]], axis=1)
        coef = np.linalg.lstsq(Z, draws[f], rcond=None)[0]  # (n + 1, n): [m; T^T]
        m, T = coef[0], coef[1:].T
        cov = np.linalg.inv(L[f] @ L[f].T)
        sig = np.sqrt(np.diag(cov))
        assert np.max(np.abs(m - a_wf[f]) / sig) < 1e-8
        np.testing.assert_allclose((T @ T.T) / np.outer(sig, sig), cov / np.outer(sig, sig), atol=1e-8)


def test_scalar_evidence_gradient_matches_finite_differences(full_day):
    """d log p / d(log s, log A) by jax.grad against central differences (step 1e-5: truncation ~1e-10,
    rounding ~1e-16 |log p| / 1e-5 ~ 1e-8 relative of a gradient of order 10-1000)."""
    state = prepare_scalar(full_day.system())
    f = jax.jit(lambda t: jnp.sum(scalar_log_evidence(state, jnp.exp(t[0]), jnp.exp(t[1]))))
    t0 = jnp.array([np.log(1.3), np.log(0.6)])
    g = np.asarray(jax.grad(f)(t0))
    h = 1e-5
    fd = np.array([(f(t0 + h * e) - f(t0 - h * e)) / (2 * h) for e in np.eye(2)])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6)
    # and per channel through vmap over scales: the same as two calls
    both = jax.vmap(lambda s: scalar_log_evidence(state, s, 1.0))(jnp.array([0.9, 1.1]))
    np.testing.assert_allclose(np.asarray(both[1]), np.asarray(scalar_log_evidence(state, 1.1, 1.0)), rtol=1e-14)


def test_scalar_quadratics_are_the_direct_sums(full_day):
    system = full_day.system()
    state = prepare_scalar(system)
    a = np.asarray(scalar_draw(jax.random.PRNGKey(3), state, 1.0, 1.0))[:, 0]
    X = np.asarray(dense_matrix(system.op))
    r = np.asarray(system.data) - np.einsum("ftbk,fk->ftb", X, a)
    data = np.sum(np.asarray(system.inv_noise) * np.abs(r) ** 2, axis=(1, 2))
    prior = np.sum(np.asarray(system.prior.inv_var) * (a - np.asarray(system.prior.mean)) ** 2, axis=-1)
    q = scalar_quadratics(state, a)
    np.testing.assert_allclose(np.asarray(q.data), data, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(q.prior), prior, rtol=1e-10)


def test_flat_prior_refused(full_day):
    system = full_day.system()
    flat = with_prior(system, Prior(system.prior.mean, system.prior.inv_var.at[:, 0].set(0.0)))
    with pytest.raises(ValueError, match="proper prior"):
        prepare_scalar(flat)


# ---------------------------------------------------------------- a user's Gibbs loop over (a, s, A)

A_SHAPE, A_SCALE = 1.0, 1e-2  # weak inverse-gamma prior on A (Jeffreys 1/A is improper at A -> 0: the
# likelihood tends to a constant there); Jeffreys 1/s on the noise scale


def _gibbs_chain(state, key, nsteps):
    """(a, s, A) | d by Gibbs with the scalar state: a | s, A exact; s | a and A | a inverse-gamma."""
    nf, n = state.prior_mean.shape

    def step(carry, k):
        s, A = carry
        ka, ks, kA = jax.random.split(k, 3)
        a = scalar_draw(ka, state, s, A)[:, 0]
        q = scalar_quadratics(state, a)
        s = 0.5 * q.data / jax.random.gamma(ks, 0.5 * state.n_data)
        A = (A_SCALE + 0.5 * q.prior) / jax.random.gamma(kA, A_SHAPE + 0.5 * n, (nf,))
        return (s, A), (s, A)

    ones = jnp.ones(nf)
    return jax.jit(lambda k: jax.lax.scan(step, (ones, ones), jax.random.split(k, nsteps))[1])(key)


def _grid_means(state):
    """E[s], E[A] per channel from p(s, A | d) on a (log s, log A) grid (the exact evidence)."""
    ls = jnp.linspace(-0.6, 0.6, 481)
    lA = jnp.linspace(-5.0, 4.0, 721)
    S, AA = jnp.meshgrid(ls, lA, indexing="ij")
    logev = jax.vmap(lambda x, y: scalar_log_evidence(state, jnp.exp(x), jnp.exp(y)))(S.ravel(), AA.ravel())
    # density of (log s, log A): Jeffreys on s is flat in log s; IG(A_SHAPE, A_SCALE) on A times the Jacobian A
    logw = np.asarray(logev) + np.asarray(-A_SHAPE * AA.ravel() - A_SCALE * jnp.exp(-AA.ravel()))[:, None]
    w = np.exp(logw - logw.max(axis=0))
    w /= w.sum(axis=0)
    edge = w.reshape(S.shape + (-1,))
    assert edge[[0, -1]].max() < 1e-12 and edge[:, [0, -1]].max() < 1e-12  # the grid holds the posterior
    return np.exp(np.asarray(S).ravel()) @ w, np.exp(np.asarray(AA).ravel()) @ w


def _batch_mean_error(x, nbatch=40):
    """The chain mean's standard error from batch means, per column of x (T, Nf)."""
    b = x[: x.shape[0] // nbatch * nbatch].reshape(nbatch, -1, x.shape[1]).mean(axis=1)
    return b.std(axis=0, ddof=1) / np.sqrt(nbatch)


@pytest.fixture(scope="module")
def standard():
    """The standard case at lmax 6 (n = 49, 2 channels, N_d = 900): data that inform ~23 directions, so
    both s and A are well determined (the isotropic fixture's data barely inform A)."""
    return gcrsky.standard_case(lmax=6, nside=32)


def test_gibbs_loop_over_scales_matches_the_evidence_grid(standard):
    """Marginal means of s and A from 4000 Gibbs steps agree with the exact grid within 4.5 batch-means
    errors (a t statistic with 39 dof: false alarm ~6e-5 per comparison, 4 comparisons)."""
    state = prepare_scalar(standard.system())
    s, A = (np.asarray(x)[200:] for x in _gibbs_chain(state, jax.random.PRNGKey(21), 4200))
    es, eA = _grid_means(state)
    for chain, exact in ((s, es), (A, eA)):
        err = _batch_mean_error(chain)
        assert np.all(np.abs(chain.mean(axis=0) - exact) < 4.5 * err), (chain.mean(axis=0), exact, err)
    # a negative control: the grid of a system whose noise is 30% larger is far outside the chain's error
    es_wrong, _ = _grid_means(prepare_scalar(scale_noise(standard.system(), 1.3)))
    assert np.all(np.abs(s.mean(axis=0) - es_wrong) > 10 * _batch_mean_error(s))


# ---------------------------------------------------------------- the hierarchical kernel on every path


@pytest.mark.parametrize("name", list(PATHS))
def test_sky_step_on_every_path_draws_the_dense_posterior(full_day, name):
    """gibbs_setup with any registered path's options: sky_step's draws for a new spectrum (not the system's)
    and for new data have the dense posterior's mean and covariance for that prior and those data."""
    from gcrsky.inference import gibbs_setup, sky_step
    from gcrsky.model import prior_from_cl

    system = full_day.system()
    options = PATHS[name].options_type()
    if isinstance(options, CGOptions):
        options = CGOptions(dense=False, tol=1e-10)
    fixed = gibbs_setup(system, options=options, sketch_size=32)
    nf, n = system.prior.mean.shape
    cl = jnp.tile(80.0 / (1.0 + jnp.arange(7.0)) ** 2, (nf, 1))  # 1.6x the system's own spectrum
    data = system.data * 1.05
    step = jax.jit(jax.vmap(lambda k: sky_step(k, fixed, system.prior.mean, cl=cl, data=data)))
    a, info = step(jax.random.split(jax.random.PRNGKey(13), NDRAWS))
    assert bool(np.all(np.asarray(info.converged))), name
    target = with_prior(system._replace(data=data), Prior(system.prior.mean, prior_from_cl(cl).inv_var))
    a_wf, L = _dense_posterior(target)
    assert _gaussian_ok(_whiten(np.swapaxes(np.asarray(a), 0, 1), a_wf, L)), name
    # negative control: the same draws against the posterior of the system's own spectrum fail
    a_own, L_own = _dense_posterior(system._replace(data=data))
    assert not _gaussian_ok(_whiten(np.swapaxes(np.asarray(a), 0, 1), a_own, L_own)), name
