"""Collapsed sampling: NUTS on the exact evidence (blackjax), then exact sky draws given theta.

Reference for the 1-D case: the exact posterior of theta = log noise-variance scale,
``exp(sum_f log p(d | theta) + log_prior(theta))`` normalised by trapezoidal quadrature
on a fine grid (4001 points over +-0.6, i.e. +-14 posterior sigma at spacing 0.007
sigma: the quadrature error is far below the Monte Carlo error).  The hyperprior is
a proper Gaussian N(0, 0.1^2), comparable to the likelihood's width (~0.045), so it
visibly shapes the posterior (the negative control depends on that).

Checks (:func:`_compare`), with N_eff from blackjax's ESS (Stan's estimator):

* mean: ``|mean - mu| / (sigma / sqrt(N_eff(theta))) < 4``;
* variance: ``|var_hat - sigma^2| / se < 4`` with ``se = sd((theta - mu)^2) /
  sqrt(N_eff((theta - mu)^2))`` (the ESS of the squared deviations, its own chain);
* shape: a KS test of the chain thinned by ``ceil(N / N_eff)`` (so the kept samples
  are roughly independent, as the KS null distribution assumes; a thinned chain
  with residual positive correlation only makes the test more conservative) against
  the grid CDF, ``p > 1e-3``.

Each check's false-alarm rate is 6e-5 (the two 4-sigma Gaussian checks) or 1e-3 (KS);
together ~1.1e-3 per run, and the seeds are fixed, so the outcome is deterministic.
The negative control runs the same sampler on the log prior with its sign flipped
(a different, still proper posterior: ~1.2x wider, shifted by ~0.2 sigma) and must
fail the same check against the same grid.

Each test compiles one NUTS program (~10-15 s on 2 cores) on the small problem
(10-antenna hexagon, lmax 4, one channel: n = 25).
"""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _hyper_fixtures import scaled, small_problem
from scipy import stats

from gcrsky.inference import sample_system
from gcrsky.inference.collapsed import draw_given_hyperparameters, effective_sample_size, sample_hyperparameters
from gcrsky.inference.hyper import objective
from gcrsky.solvers import CholeskyOptions

PRIOR_MU, PRIOR_SD = 0.0, 0.1
NUM_WARMUP, NUM_SAMPLES = 500, 2000


@pytest.fixture(scope="module")
def base():
    return small_problem(nf=1, lmax=4).system()


def make_1d(base):
    return lambda th: scaled(base, jnp.stack([th["log_noise"], jnp.zeros(())]))


def log_prior(th):
    return -0.5 * ((th["log_noise"] - PRIOR_MU) / PRIOR_SD) ** 2


def flipped_prior(th):
    return -log_prior(th)


@pytest.fixture(scope="module")
def grid(base):
    """The exact 1-D posterior on a fine grid: (points, pdf, cdf, mean, sd)."""
    mk = make_1d(base)
    f = jax.jit(jax.vmap(lambda t: objective(mk, {"log_noise": t}, options=CholeskyOptions(),
                                             log_prior=log_prior)[0]))
    t = np.linspace(-0.6, 0.6, 4001)
    lp = np.asarray(f(jnp.asarray(t)))
    p = np.exp(lp - lp.max())
    p /= np.trapezoid(p, t)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (p[1:] + p[:-1]) * np.diff(t))])
    cdf /= cdf[-1]
    mu = np.trapezoid(t * p, t)
    sd = np.sqrt(np.trapezoid((t - mu) ** 2 * p, t))
    assert p[0] < 1e-30 * p.max() and p[-1] < 1e-30 * p.max()  # the grid holds all the mass
    return t, p, cdf, mu, sd


def _compare(x, grid):
    """z-scores of the mean and variance against the grid posterior and the KS p-value."""
    t, _, cdf, mu, sd = grid
    x = np.asarray(x, np.float64)
    n_eff = float(effective_sample_size(x[None]))
    dev2 = (x - mu) ** 2
    n_eff2 = float(effective_sample_size(dev2[None]))
    z_mean = (x.mean() - mu) / (sd / np.sqrt(n_eff))
    z_var = (dev2.mean() - sd**2) / (dev2.std() / np.sqrt(n_eff2))
    thin = max(1, int(np.ceil(x.size / n_eff)))
    ks = stats.kstest(x[::thin], lambda v: np.interp(v, t, cdf))
    return {"z_mean": z_mean, "z_var": z_var, "ks_p": ks.pvalue, "n_eff": n_eff, "thin": thin}


def _passes(r):
    return abs(r["z_mean"]) < 4 and abs(r["z_var"]) < 4 and r["ks_p"] > 1e-3


def test_nuts_matches_the_exact_1d_posterior(base, grid):
    out = sample_hyperparameters(jax.random.PRNGKey(1), make_1d(base), {"log_noise": jnp.asarray(0.0)},
                                 NUM_SAMPLES, log_prior=log_prior, num_warmup=NUM_WARMUP)
    x = out.theta["log_noise"]
    assert x.shape == (NUM_SAMPLES,) and out.log_density.shape == (NUM_SAMPLES,)
    r = _compare(x, grid)
    assert _passes(r), r
    assert r["n_eff"] > 300, r  # the Monte Carlo errors above are small
    assert int(np.sum(out.info.is_divergent)) == 0
    # log_density is the objective at the sample
    i = 7
    ref = objective(make_1d(base), {"log_noise": x[i]}, options=CholeskyOptions(), log_prior=log_prior)[0]
    assert abs(float(out.log_density[i]) - float(ref)) < 1e-8 * abs(float(ref))


def test_negative_control_fails_the_same_check(base, grid):
    """Samples of the posterior with the log prior's sign flipped fail against the true grid."""
    out = sample_hyperparameters(jax.random.PRNGKey(1), make_1d(base), {"log_noise": jnp.asarray(0.0)},
                                 NUM_SAMPLES, log_prior=flipped_prior, num_warmup=NUM_WARMUP)
    r = _compare(out.theta["log_noise"], grid)
    assert not _passes(r), r
    assert abs(r["z_var"]) > 6 or r["ks_p"] < 1e-6, r  # failed by a wide margin, not by chance


def test_two_hyperparameters_shapes_and_acceptance(base):
    """(log noise scale, log prior scale): shapes, finite values, acceptance near the target.

    The mean acceptance of the kept samples sits a little above the target: the warm-up
    ends on dual averaging's *averaged* log step size, typically smaller than its last iterate
    (measured here and in the 1-D case: 0.91-0.92 for a target of 0.8).  Allowed:
    [target - 0.1, target + 0.17], i.e. tuned near the target, neither stuck at a tiny
    step (acceptance -> 1) nor a too large one."""
    def mk(th):
        return scaled(base, jnp.stack([th["log_noise"], th["log_prior"]]))

    def lp(th):
        return -0.5 * (th["log_noise"] ** 2 + th["log_prior"] ** 2)

    theta0 = {"log_noise": jnp.asarray(0.1), "log_prior": jnp.asarray(-0.1)}
    out = sample_hyperparameters(jax.random.PRNGKey(2), mk, theta0, 400, log_prior=lp, num_warmup=300,
                                 target_accept=0.8)
    assert out.theta["log_noise"].shape == (400,) and out.theta["log_prior"].shape == (400,)
    assert out.log_density.shape == (400,)
    info = out.info
    assert info.acceptance_rate.shape == (400,) and info.num_integration_steps.shape == (400,)
    assert info.inverse_mass_matrix.shape == (2, 2) and np.ndim(info.step_size) == 0
    for leaf in jax.tree_util.tree_leaves(out):
        assert np.all(np.isfinite(np.asarray(leaf, np.float64)))
    assert 0.7 < float(np.mean(info.acceptance_rate)) < 0.97
    assert int(np.sum(info.is_divergent)) == 0
    assert np.all(np.asarray(info.num_integration_steps) >= 1)
    ess = effective_sample_size(jax.tree.map(lambda v: v[None], out.theta))
    assert set(ess) == {"log_noise", "log_prior"} and all(float(v) > 50 for v in ess.values())
    # the two are different parameters: the samples differ
    assert np.std(np.asarray(out.theta["log_noise"])) < 0.5 * np.std(np.asarray(out.theta["log_prior"]))


def test_draws_given_theta_equal_sample_system(base):
    """Sample i is ``sample_system(split(key, S)[i], make_system(theta_i), ndraws)`` (the exactness
    of those draws is sample_system's own test): equal to 1e-12 relative."""
    mk = make_1d(base)
    thetas = {"log_noise": jnp.array([-0.1, 0.0, 0.2])}
    key = jax.random.PRNGKey(5)
    got = np.asarray(jax.jit(lambda k, th: draw_given_hyperparameters(k, mk, th, ndraws=4))(key, thetas))
    nf, n = base.prior.mean.shape
    assert got.shape == (3, nf, 4, n)
    keys = jax.random.split(key, 3)
    for i in range(3):
        ref, _ = sample_system(keys[i], mk({"log_noise": thetas["log_noise"][i]}), 4, options=CholeskyOptions())
        ref = np.asarray(ref)
        assert np.max(np.abs(got[i] - ref)) < 1e-12 * np.max(np.abs(ref))
    assert not np.allclose(got[0], got[1])  # different keys and thetas: different draws


def test_missing_blackjax_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "blackjax", None)  # an import of it now fails
    with pytest.raises(ImportError, match=r"pip install 'gcrsky\[nuts\]'"):
        sample_hyperparameters(jax.random.PRNGKey(0), lambda th: None, jnp.zeros(1), 10)
    with pytest.raises(ImportError, match=r"gcrsky\[nuts\]"):
        effective_sample_size(np.zeros((1, 10)))
