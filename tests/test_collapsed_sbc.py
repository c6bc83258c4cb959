"""Simulation-based calibration (Talts et al. 2018) of the collapsed sampler: NUTS on the evidence, then a | theta.

Per replicate: ``theta = (log A, alpha)`` from a proper Gaussian hyperprior, ``log A ~ N(log 200,
0.5^2)``, ``alpha ~ N(2, 0.5^2)``, for the power law ``C_l = A (l + 1)^-alpha`` at l >= 1 (the
monopole's ``C_0 = 200 K^2`` known and fixed); the sky ``a ~ N(0, C_l)``
(:func:`gcrsky.prior_from_cl`); data simulated through the small problem's response and noise
(``_hyper_fixtures.small_problem(nf=1)``: the 10-antenna hexagon, lmax 4, one channel, 11 LSTs over
a day, sigma = 0.05).  Then the collapsed sampler exactly as :func:`sample_hyperparameters` runs it
(:func:`~gcrsky.inference.collapsed.nuts_chain` on
:func:`~gcrsky.inference.collapsed.flat_log_density`, i.e. the library's exact log evidence plus the
log hyperprior, from the hyperprior mean): ``WARMUP = 200`` steps of window adaptation (dense mass
matrix, target acceptance 0.8), ``L * THIN = 38`` NUTS samples kept every ``THIN = 2``-th (``L =
19``), and one exact draw of ``a | theta_i, d`` per kept ``theta_i``
(:func:`draw_given_hyperparameters`, Cholesky).  Ranks of the truth among the L draws, ``R = 256``
replicates, go through :func:`gcrsky.checks.sbc.rank_pvalues` (exact KS / dispersion / bias tests,
Bonferroni family p-value).  All replicates (those of control 1 too) run vmapped in one jitted
program: one compilation (10-30 s on 2 cores), one run.  Measured: 75 s for this file (49 s of CPU)
on the 2 cores shared with other jobs.

Functionals (F = 8, fixed before any data): ``log A`` and ``alpha``; the coefficients ``a_10, a_20,
a_40``; two eigenvectors of the data term ``X^T W X``: the largest non-degenerate eigenvalue (0.51
K^-2, data-dominated: the prior's precision along it is 0.06 K^-2 at the hyperprior mean) and the
smallest (6.6e-10 K^-2, against the prior's 0.02: a direction the array does not see,
prior-dominated); and ``C_4 hat`` (:func:`gcrsky.inference.cl_hat`
at l = 4, the sky's power at the degree the power law extrapolates furthest: a quadratic functional,
sensitive to the coupling of ``a`` and ``theta``).

Settings.  Hyperprior width against the data: the power law over l = 1..4 is nearly degenerate (even
a perfectly measured sky pins one combination of ``log A`` and ``alpha`` only), so the evidence's
expected Fisher information at the hyperprior mean has eigenvalues 7.3 and 0.08 against the
hyperprior's 4: the data dominate one direction, the hyperprior the other (measured: the mean
posterior covariance has standard deviations 0.31 and 0.50 along its principal axes, 0.42 and 0.38
per component, against the hyperprior's 0.5).  ``A = 200`` balances the two uses of the data: at
``A = 40`` they carry less information on ``theta`` than the hyperprior (Fisher 2.7), at ``A = 1000``
most modes sit far above the noise, the evidence hardly depends on the noise level and control 1
failed far less clearly (measured in trials).  ``R = 256``: the null standard deviation of a
functional's mean z^2 is ``sqrt(2 / R) = 0.09``, so a mean z^2 of 1.5 (draws about 20% too narrow)
fails the family threshold; ``L = 19`` keeps the chain short (38 samples after the warm-up), the
randomised PIT making the tests exact at any L; ``R_CTRL = 128`` is enough for control 1.
Thinning: the raw chain's lag-1 autocorrelation, averaged over replicates, is 0.06-0.08 and its lag
2 about 0 (measured; the 38-sample means bias both by about -0.03), so the kept draws are close to
independent; the valid run's mean z^2 per functional is 0.90-1.21 (independent draws: 1).
``MAX_DOUBLINGS = 3`` (at most 7 leapfrog steps per NUTS step, blackjax's default 10): under
``vmap`` every step costs the batch's largest tree, and at depth 10, though 97.6% of the steps used
at most 7 leapfrog steps (mean 4.1), the batch's largest tree averaged 14-17 leapfrog steps per NUTS
step (up to 31): twice the cost.  A
capped tree is still an exact MCMC kernel (Stan's max_treedepth); measured at depth 3: mean 3.9
leapfrog steps, mean acceptance 0.92, no divergence after the warm-up.

The family p-value has a false-alarm rate <= ``ALPHA = 1e-3`` at the threshold used, and the seeds
are fixed, so the outcome is deterministic.  Measured (seed 0): valid ``p_family = 0.55``, mean
z^2 per functional (log A, alpha, a_10, a_20, a_40, data eig, prior eig, C_4 hat) = 0.96, 0.92,
0.91, 0.90, 1.21, 1.09, 1.09, 0.90.  Negative controls that must fail at the same threshold:

1. NUTS on a wrong density, the evidence with the noise variance times 1/4 (sigma halved), the
   replicates (``R_CTRL = 128``) simulated from the right model and ``a`` drawn from the right
   ``a | theta_i, d``: ``p_family = 2.7e-9``; the chain attributes the excess data variance to the
   sky (mean z of log A -0.41, of alpha +0.53, of C_4 hat -0.57; mean z^2 1.34, 1.28, 1.28).  The
   opposite error (variance times 4) fails less clearly: ``p_family = 1.9e-5`` (128 other
   replicates, measured once).
2. The sky drawn at a fixed ``theta`` (the hyperprior mean) instead of at each NUTS sample, from the
   same replicates and chains (no second NUTS run): ``p_family = 1.6e-16``, carried by ``C_4 hat``
   (mean z^2 1.96); the linear functionals barely see it (1.23 at most), as the posterior of
   ``theta`` is not far from its prior.

With seeds 1 and 2: valid 1.0 and 0.83, control 1 9e-12 and 4.7e-10, control 2 7e-17 and 2e-19.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _hyper_fixtures import small_problem

import gcrsky
from gcrsky.checks.sbc import rank_pvalues
from gcrsky.inference import cl_hat
from gcrsky.inference.collapsed import draw_given_hyperparameters, flat_log_density, nuts_chain
from gcrsky.model.noise import draw_noise
from gcrsky.model.operator import apply
from gcrsky.model.system import precision_matrix

LMAX, R, R_CTRL, L, THIN, WARMUP, MAX_DOUBLINGS = 4, 256, 128, 19, 2, 200, 3
MU = np.array([np.log(200.0), 2.0])  # hyperprior mean of theta = (log A, alpha)
SD = np.array([0.5, 0.5])  # and its standard deviations
NOISE_CTRL = 0.25  # control 1: NUTS's evidence has the noise variance times this
ALPHA = 1e-3
SEED = 0


def cl_of(theta):
    """C_l = A (l + 1)^-alpha for l >= 1, the monopole's C_0 = exp(MU[0]) known and fixed."""
    ell1 = jnp.arange(1, LMAX + 2, dtype=jnp.float64)
    return (jnp.exp(theta[0]) * ell1 ** (-theta[1])).at[0].set(float(np.exp(MU[0])))


def log_hyperprior(theta):
    return -0.5 * jnp.sum(((theta - MU) / SD) ** 2)


def functionals(base):
    """(names, coefficient indices, the two eigenvector weights (2, n)) of the a-functionals."""
    tab = gcrsky.mode_table(LMAX)
    coeffs = np.array([np.flatnonzero((tab.ell == ell) & (tab.m == 0))[0] for ell in (1, 2, 4)])
    flat = base._replace(prior=base.prior._replace(inv_var=jnp.zeros_like(base.prior.inv_var)))
    lam, U = np.linalg.eigh(np.asarray(precision_matrix(flat))[0])  # the data term X^T W X
    gaps = np.abs(np.diff(lam)) > 1e-2 * lam.max()
    top = max(k for k in range(lam.size) if (k == 0 or gaps[k - 1]) and (k == lam.size - 1 or gaps[k]))
    vecs = np.stack([U[:, top], U[:, 0]])  # data-dominated (non-degenerate), least-seen direction
    names = ("log A", "alpha", "a_10", "a_20", "a_40", f"data eig {lam[top]:.2g}", f"prior eig {lam[0]:.1e}",
             f"C_{LMAX} hat")
    return names, coeffs, vecs


def simulate_and_rank(*, seed=SEED, r=R, r_ctrl=R_CTRL, num_warmup=WARMUP, diagnostics=False):
    """Ranks of ``r`` valid and ``r_ctrl`` control-1 replicates, one jitted program; their p-values.

    Returns a dict: ``names``; ``valid``, ``noise`` (control 1), ``frozen`` (control 2, the valid
    replicates' chains): :func:`rank_pvalues` dicts; ``divergent``: divergent NUTS samples of the
    valid replicates; with ``diagnostics`` the chains (``pos`` (r + r_ctrl, L * THIN, 2)) and
    their :class:`~gcrsky.inference.CollapsedInfo` (``info``).
    """
    base = small_problem(nf=1).system()
    base = base._replace(prior=base.prior._replace(mean=jnp.zeros_like(base.prior.mean)))
    names, coeffs, vecs = functionals(base)
    sigma = jnp.sqrt(1.0 / base.inv_noise)
    mu = jnp.asarray(MU)

    def replicate(key, noise_scale):
        k_th, k_a, k_n, k_chain, k_draw = jax.random.split(key, 5)
        theta = mu + jnp.asarray(SD) * jax.random.normal(k_th, (2,))
        a_true = jax.random.normal(k_a, (1, (LMAX + 1) ** 2)) / jnp.sqrt(gcrsky.prior_from_cl(cl_of(theta)).inv_var)
        data = apply(base.op, a_true) + draw_noise(k_n, sigma)

        def make(th, scale=1.0):
            return base._replace(data=data, inv_noise=base.inv_noise / scale, prior=gcrsky.prior_from_cl(cl_of(th)))

        flat0, _, logd = flat_log_density(lambda th: make(th, noise_scale), mu, log_prior=log_hyperprior)
        pos, _, info = nuts_chain(k_chain, logd, flat0, num_warmup=num_warmup, num_samples=L * THIN,
                                  max_num_doublings=MAX_DOUBLINGS)
        kept = pos[THIN - 1::THIN]  # (L, 2)

        def ranks(th_a):
            a = draw_given_hyperparameters(k_draw, make, th_a)[:, 0, 0, :]  # (L, n), one draw per theta
            fd = jnp.concatenate([kept, a[:, coeffs], a @ vecs.T, cl_hat(a)[:, LMAX:]], axis=1)
            ft = jnp.concatenate([theta, a_true[0, coeffs], vecs @ a_true[0], cl_hat(a_true[0])[LMAX:]])
            return jnp.sum(fd < ft[None, :], axis=0)

        frozen = ranks(jnp.broadcast_to(mu, kept.shape))  # control 2: the a-draws at the prior mean of theta
        return ranks(kept), frozen, pos, info

    scales = jnp.concatenate([jnp.ones(r), jnp.full(r_ctrl, NOISE_CTRL)])
    keys = jax.random.split(jax.random.PRNGKey(seed), r + r_ctrl)
    rk, rk_frozen, pos, info = jax.jit(jax.vmap(replicate))(keys, scales)
    rk, rk_frozen = np.asarray(rk), np.asarray(rk_frozen)
    out = {
        "names": names,
        "divergent": int(np.sum(np.asarray(info.is_divergent)[:r])),  # valid replicates, after the warm-up
        "valid": rank_pvalues(rk[:r], L),
        "noise": rank_pvalues(rk[r:], L),
        "frozen": rank_pvalues(rk_frozen[:r], L),
    }
    if diagnostics:
        out["pos"], out["info"] = np.asarray(pos), info
    return out


@pytest.fixture(scope="module")
def sbc():
    return simulate_and_rank()


@pytest.mark.slow
def test_collapsed_sampler_is_calibrated(sbc):
    assert sbc["valid"]["p_family"] > ALPHA, (sbc["names"], sbc["valid"]["p_functional"])
    assert sbc["divergent"] == 0


@pytest.mark.slow
def test_nuts_on_a_wrong_noise_level_fails(sbc):
    assert sbc["noise"]["p_family"] < ALPHA, (sbc["names"], sbc["noise"]["p_functional"])


@pytest.mark.slow
def test_sky_draws_at_a_fixed_theta_fail(sbc):
    assert sbc["frozen"]["p_family"] < ALPHA, (sbc["names"], sbc["frozen"]["p_functional"])
