"""Hierarchical sampling (issue 12): sigma_l, the C_l conditionals, the power-law move and the
(a, C_l) Gibbs kernel.

References: healpy's ``alm2cl`` for sigma_l; SciPy's inverse-gamma for ``C_l | a`` (KS tests at
a false-alarm rate of 1e-3 each, with the two priors' shapes swapped as the negative control
that must fail); dense quadrature of the exact marginal for the power-law slope; dense NumPy
algebra for the exactness of the kernel's a-step.
"""

from __future__ import annotations

import healpy as hp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _hyper_fixtures import small_problem
from scipy import stats

import gcrsky
from gcrsky.inference import cl_hat, gibbs_init, gibbs_setup, gibbs_step, sample_cl, sample_power_law
from gcrsky.inference.cl import power_law_log_marginal
from gcrsky.inference.gibbs import _a_step, _fluctuation
from gcrsky.model.system import fluctuation_rhs, precision_matrix, wiener_rhs
from gcrsky.solvers import CGOptions, CholeskyOptions

P_FALSE_ALARM = 1e-3


def realified_sky(lmax, cl, seed=0, nf=1):
    prior = gcrsky.prior_from_cl(jnp.asarray(np.broadcast_to(cl, (nf, lmax + 1))))
    z = np.random.default_rng(seed).standard_normal((nf, (lmax + 1) ** 2))
    return jnp.asarray(z / np.sqrt(np.asarray(prior.inv_var)))


def test_cl_hat_equals_healpy_alm2cl():
    lmax = 7
    a = realified_sky(lmax, 1.0 / (1.0 + np.arange(lmax + 1)) ** 2, nf=2)
    got = np.asarray(cl_hat(a))
    for f in range(2):
        ref = hp.alm2cl(np.asarray(gcrsky.unrealify(np.asarray(a[f]), lmax)))
        np.testing.assert_allclose(got[f], ref, rtol=1e-13)


@pytest.mark.parametrize("prior", ["uniform", "jeffreys"])
def test_sample_cl_is_the_inverse_gamma_conditional(prior):
    """KS of 4000 draws per l against scipy's inverse-gamma; the other prior's shape must fail."""
    lmax = 6
    a = realified_sky(lmax, 2.0 / (1.0 + np.arange(lmax + 1)) ** 1.5)[0]
    keys = jax.random.split(jax.random.PRNGKey(1), 4000)
    draws = np.asarray(jax.vmap(lambda k: sample_cl(k, a, prior=prior, monopole=7.0))(keys))
    sig = np.asarray(cl_hat(a))
    offset = {"uniform": -2, "jeffreys": 0}
    other = "jeffreys" if prior == "uniform" else "uniform"
    assert np.all(draws[:, 0] == 7.0)  # the monopole is kept
    for ell in (1, 2, 6):
        scale = (2 * ell + 1) * sig[ell] / 2
        right = stats.invgamma((2 * ell + 1 + offset[prior]) / 2, scale=scale)
        wrong = stats.invgamma((2 * ell + 1 + offset[other]) / 2, scale=scale)
        assert stats.kstest(draws[:, ell], right.cdf).pvalue > P_FALSE_ALARM, ell
        assert stats.kstest(draws[:, ell], wrong.cdf).pvalue < P_FALSE_ALARM, ell  # negative control


def test_sample_cl_monopole_rules_and_conjugate_prior():
    a = realified_sky(3, 1.0)
    with pytest.raises(ValueError, match="uniform prior's l = 0 conditional is improper"):
        sample_cl(jax.random.PRNGKey(0), a, prior="uniform")
    with pytest.raises(ValueError, match="hyper="):
        sample_cl(jax.random.PRNGKey(0), a, prior="jeffreys", hyper=(1.0, 1.0))
    # the conjugate prior IG(k, s) with k = s = 0 is Jeffreys (drawn by jax.random.gamma rather than
    # as a sum of squared normals): two-sample KS at 1e-3, and a shifted shape must differ
    keys = jax.random.split(jax.random.PRNGKey(3), 4000)
    ig = np.asarray(jax.vmap(lambda k: sample_cl(k, a, prior="inverse_gamma", hyper=(0.0, 0.0)))(keys))[:, 0, 2]
    jf = np.asarray(jax.vmap(lambda k: sample_cl(k, a, prior="jeffreys"))(jax.random.split(jax.random.PRNGKey(4),
                                                                                          4000)))[:, 0, 2]
    assert stats.ks_2samp(ig, jf).pvalue > P_FALSE_ALARM
    ig1 = np.asarray(jax.vmap(lambda k: sample_cl(k, a, prior="inverse_gamma", hyper=(1.0, 0.0)))(keys))[:, 0, 2]
    assert stats.ks_2samp(ig1, jf).pvalue < P_FALSE_ALARM


def test_power_law_move_samples_the_exact_slope_marginal():
    """A slice chain on alpha | a (A integrated out) against the marginal by dense quadrature.

    The chain is thinned by 4 (1-D slice sampling decorrelates within a step or two,
    measured lag-1 autocorrelation ~0.1), then KS at 1e-3; the negative control, the same
    samples against the marginal of a sky with a different slope, must fail.
    """
    lmax = 12
    ell1 = 1.0 + np.arange(lmax + 1)
    a = realified_sky(lmax, 3.0 * ell1**-2.0, seed=4)[0]
    step = jax.jit(lambda k, al: sample_power_law(k, a, al, alpha_range=(0.0, 5.0)))

    def chain(key, n):
        def body(al, k):
            amp, al = step(k, al)
            return al, (amp, al)

        return jax.lax.scan(body, jnp.asarray(2.5), jax.random.split(key, n))[1]

    amp, alpha = (np.asarray(x) for x in jax.jit(chain, static_argnums=1)(jax.random.PRNGKey(0), 8000))
    grid = np.linspace(0.0, 5.0, 4001)
    logm = np.asarray(jax.vmap(lambda x: power_law_log_marginal(x, a))(jnp.asarray(grid)))
    pdf = np.exp(logm - logm.max())
    cdf = np.cumsum(pdf)
    cdf /= cdf[-1]
    thinned = alpha[::4]
    assert stats.kstest(thinned, lambda x: np.interp(x, grid, cdf)).pvalue > P_FALSE_ALARM
    other = realified_sky(lmax, 3.0 * ell1**-1.0, seed=4)[0]
    logo = np.asarray(jax.vmap(lambda x: power_law_log_marginal(x, other))(jnp.asarray(grid)))
    cdfo = np.cumsum(np.exp(logo - logo.max()))
    cdfo /= cdfo[-1]
    assert stats.kstest(thinned, lambda x: np.interp(x, grid, cdfo)).pvalue < P_FALSE_ALARM
    # A | alpha, a is inverse-gamma (shape N/2, scale S(alpha)): S(alpha) / A ~ Gamma(N/2), draw by draw
    sig = np.asarray(cl_hat(a))
    ell = np.arange(lmax + 1)
    use = ell >= 1
    k = (2 * ell + 1) * use
    scales = np.array([np.sum(k * sig * ell1**al) / 2 for al in alpha])
    assert stats.kstest(scales / amp, stats.gamma(k.sum() / 2).cdf).pvalue > P_FALSE_ALARM


@pytest.fixture(scope="module")
def system():
    return small_problem().system()


@pytest.mark.parametrize("options", [CholeskyOptions(), CGOptions(tol=1e-11, dense=False),
                                     CGOptions(tol=1e-11, dense=True)], ids=["cholesky", "cg", "cg-dense"])
def test_a_step_is_the_exact_conditional_draw(system, options):
    """The a-step at a given C_l equals the dense solve of that C_l's GCR equation (same noise).

    Cholesky: ``a_wf + L^-T z`` with NumPy's factor of the dense P; CG: ``P^-1 (b + fluct)`` with
    the step's own fluctuation right-hand side (CG tolerance 1e-11 sigma: 1e-8 relative allowed),
    whose data part is ``F z`` with ``F F^T = H`` (dense) or ``X^T N^-1/2 w`` (matrix-free).
    """
    lmax = 4
    cl = jnp.stack([3.0 / (1.0 + jnp.arange(lmax + 1)) ** 2] * 2)
    inv_var = gcrsky.prior_from_cl(cl).inv_var
    fixed = gibbs_setup(system, options=options, sketch_size=12)
    key = jax.random.PRNGKey(9)
    a, info = jax.jit(_a_step)(key, fixed, cl, system.prior.mean)
    assert np.all(np.asarray(info.converged))
    sys_c = system._replace(prior=system.prior._replace(inv_var=inv_var))
    P = np.asarray(precision_matrix(sys_c))
    b = np.asarray(wiener_rhs(sys_c))
    for f in range(2):
        if isinstance(options, CholeskyOptions):
            z = np.asarray(jax.random.normal(key, system.prior.mean.shape))[f]
            L = np.linalg.cholesky(P[f])
            want = np.linalg.solve(P[f], b[f]) + np.linalg.solve(L.T, z)
        else:
            want = np.linalg.solve(P[f], b[f] + np.asarray(_fluctuation(key, fixed, inv_var))[f])
        np.testing.assert_allclose(np.asarray(a[f]), want, rtol=0, atol=1e-8 * np.abs(want).max())
    if fixed.data_sqrt is not None:  # dense CG draws the data part as F z: F F^T must be H
        F, H = np.asarray(fixed.data_sqrt), np.asarray(fixed.data_term)
        np.testing.assert_allclose(F @ np.swapaxes(F, 1, 2), H, rtol=0, atol=1e-11 * np.abs(H).max())
    elif isinstance(options, CGOptions):  # matrix-free: the data part is X^T N^-1/2 w, as fluctuation_rhs
        np.testing.assert_array_equal(np.asarray(_fluctuation(key, fixed, inv_var)),
                                      np.asarray(fluctuation_rhs(key, sys_c)))


def test_gibbs_chain_runs_in_scan_for_both_families(system):
    fixed = gibbs_setup(system)
    lmax = 4
    cl0 = 3.0 / (1.0 + jnp.arange(lmax + 1)) ** 2

    @jax.jit
    def run(key):
        def body(state, k):
            state, info = gibbs_step(k, state, fixed, family="power_law", alpha_range=(0.0, 6.0))
            return state, (state.cl, state.alpha, info.solve.converged)

        return jax.lax.scan(body, gibbs_init(fixed, cl0, alpha=2.0), jax.random.split(key, 50))[1]

    cls, alphas, ok = run(jax.random.PRNGKey(0))
    assert cls.shape == (50, 2, lmax + 1) and alphas.shape == (50, 2) and bool(np.all(np.asarray(ok)))
    assert np.all(np.isfinite(np.asarray(cls))) and np.all((np.asarray(alphas) > 0) & (np.asarray(alphas) < 6))
    np.testing.assert_array_equal(np.asarray(cls[:, :, 0]), np.broadcast_to(np.asarray(cl0[0]), (50, 2)))
    c0 = float(cl0[0])
    state, info = jax.jit(lambda k: gibbs_step(k, gibbs_init(fixed, cl0), fixed, cl_prior="uniform", monopole=c0))(
        jax.random.PRNGKey(1))
    assert state.cl.shape == (2, lmax + 1) and float(state.cl[0, 0]) == c0
    with pytest.raises(ValueError, match="family"):
        gibbs_step(jax.random.PRNGKey(0), gibbs_init(fixed, cl0), fixed, family="lognormal")
