"""The beam block with the overall amplitude inferred (issue 41 with DESIGN section 14): data in the
correlator's units, ``d = u X(theta) a + n`` with ``u`` per channel unknown.

References: the nominal model's evidence over ``u`` (:func:`gcrsky.inference.amplitude.log_evidence_over_u`,
the data-space marginal, an eigendecomposition of the data-space Gram matrix, on a grid across the prior's
range) against the primal evidence (dense Cholesky of the precision: another algebra) integrated on a fine
grid; the block's Laplace evidence over ``(theta, ln u)`` against importance
sampling of the exact integrand; the collapsed chain against the truth it simulated.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_beam_block import _small_world

from gcrsky.inference import log_evidence_system
from gcrsky.inference.amplitude import (
    LOG_U_RANGE,
    amplitude_eigen,
    amplitude_log_prior,
    amplitude_setup,
    log_evidence_over_u,
    log_marginal,
    scale_response,
)
from gcrsky.inference.beams import (
    beam_collapsed_step,
    beam_init,
    beam_log_evidence,
    beam_log_prior,
    beam_step,
    beam_system,
)
from gcrsky.solvers import CholeskyOptions

#: The data's units: ``U`` correlator units per K sr (as a raw file's: the amplitude is far from 1).
U = 370.0


def _raw(theta_scale):
    """:func:`test_beam_block._small_world` (4 dishes, lmax 4, 8 tilt coefficients) in units ``U`` times its own."""
    system, block, theta = _small_world(theta_scale)
    return system._replace(data=system.data * U, inv_noise=system.inv_noise / U**2), block, theta


@pytest.fixture(scope="module")
def raw():
    return _raw(0.1)


@pytest.fixture(scope="module")
def laplace(raw):
    """The block's Laplace evidence with the amplitude, BFGS then Newton on the primal path (computed once)."""
    system, block, _ = raw
    return beam_log_evidence(system, block, amplitude=True, newton_steps=10)


def test_the_nominal_evidence_over_the_amplitude_equals_the_primal_evidence_on_a_grid(raw):
    """Pointwise the data-space marginal at ``u`` equals the primal evidence (to 1e-7 of ~300 nats: two
    algebras in float64); integrated over ``ln u`` across the prior's range (the two-level grid) it equals
    Simpson's rule on 801 primal evaluations across +-10 sd (measured: 3.5e-9 apart); the maximum is
    within 4 sd of the truth ``ln U``."""
    from scipy.integrate import simpson

    system, block, _ = raw
    nom = beam_system(system, block, jnp.zeros_like(block.prior_mean))
    ev = log_evidence_over_u(nom)
    assert bool(np.all(ev.identified))
    fixed = amplitude_setup(nom)
    eig = amplitude_eigen(fixed)

    @jax.jit
    def primal(x):
        return log_evidence_system(scale_response(nom, x[None]), options=CholeskyOptions(), check=False)[0][0]

    for x in (float(ev.log_u[0]), float(ev.log_u[0]) + 0.3):
        a = float(log_marginal(fixed, eig, jnp.array([x]))[0])
        assert abs(a - float(primal(jnp.asarray(x)))) < 1e-7, (a, float(primal(jnp.asarray(x))))
    mu, sd = float(ev.log_u[0]), float(ev.sd[0])
    assert abs(mu - np.log(U)) < 4 * sd, (mu, np.log(U), sd)
    xs = np.linspace(mu - 10 * sd, mu + 10 * sd, 801)
    lp = np.asarray(jax.vmap(primal)(jnp.asarray(xs)))
    top = lp.max()
    ref = top + np.log(simpson(np.exp(lp - top), x=xs)) - np.log(LOG_U_RANGE[1] - LOG_U_RANGE[0])
    assert abs(float(ev.log_z[0]) - ref) < 1e-5, (float(ev.log_z[0]), ref)


def test_an_amplitude_the_data_do_not_determine_is_refused(raw):
    """Data that are noise alone (no sky: the model's best amplitude is 0, at the prior's end): the nominal evidence
    says ``identified`` False, and the block's evidence refuses, naming it (a Laplace fit there would be garbage)."""
    system, block, _ = raw
    rng = np.random.default_rng(5)
    sd = np.asarray(system.inv_noise) ** -0.5
    noise = sd * (rng.standard_normal(sd.shape) + 1j * rng.standard_normal(sd.shape)) / np.sqrt(2)
    empty = system._replace(data=jnp.asarray(noise))
    ev = log_evidence_over_u(beam_system(empty, block, jnp.zeros_like(block.prior_mean)))
    assert not bool(np.any(ev.identified))
    with pytest.raises(ValueError, match="do not determine the overall amplitude"):
        beam_log_evidence(empty, block, amplitude=True, newton_steps=2)


def test_the_block_s_laplace_evidence_with_the_amplitude_against_importance_sampling(raw, laplace):
    """Laplace over ``(theta, ln u)`` (k = 9) against importance sampling of ``p(d | theta, u) p(theta) p(ln u)``
    (4000 draws from the Laplace Gaussian widened 1.3x): within 0.05 + 3 standard errors.  The block is asked
    for (log Bayes factor > 10; measured 153.5, as without the amplitude: 154); dishes that share the nominal
    beam: < 0 (the Occam penalty)."""
    system, block, theta = raw
    ev = laplace
    assert bool(ev.converged)
    assert ev.covariance.shape == (theta.size + 1,) * 2
    mean = np.concatenate([np.asarray(ev.theta).ravel(), np.asarray(ev.log_u)])
    L = np.linalg.cholesky(1.3**2 * np.asarray(ev.covariance))
    z = np.random.default_rng(0).standard_normal((4000, mean.size))
    samples = mean + z @ L.T
    log_q = -0.5 * np.sum(z**2, 1) - np.sum(np.log(np.diag(L))) - 0.5 * mean.size * np.log(2 * np.pi)

    def log_target(flat):
        th, lu = jnp.reshape(flat[:-1], block.prior_mean.shape), flat[-1:]
        lz = log_evidence_system(beam_system(system, block, th, lu), options=CholeskyOptions(), check=False)[0]
        return jnp.sum(lz) + beam_log_prior(block, th) + amplitude_log_prior(lu)

    lw = np.asarray(jax.jit(jax.vmap(log_target))(jnp.asarray(samples))) - log_q
    w = np.exp(lw - lw.max())
    log_z_is = lw.max() + np.log(w.mean())
    se = w.std() / w.mean() / np.sqrt(w.size)
    assert abs(float(ev.log_z) - log_z_is) < 0.05 + 3 * se, (float(ev.log_z), log_z_is, se)
    assert float(ev.log_bayes_factor) > 10.0, float(ev.log_bayes_factor)
    system0, block0, _ = _raw(0.0)
    assert float(beam_log_evidence(system0, block0, amplitude=True, newton_steps=10).log_bayes_factor) < 0.0


def test_the_collapsed_chain_with_the_amplitude_covers_the_truth(raw, laplace):
    """300 steps of the collapsed chain over ``(theta, ln u)`` with the Laplace proposal widened 1.1x, from a
    proposal draw: every coefficient's and ``ln u``'s truth within 4.5 posterior sd (9 parameters; for an exact
    Gaussian posterior a false alarm has probability ~6e-5); acceptance above 30 % (measured ~60 %)."""
    system, block, theta = raw
    ev = laplace
    mean = jnp.concatenate([ev.theta.reshape(-1), ev.log_u])
    chol = 1.1 * jnp.linalg.cholesky(ev.covariance)
    x0 = mean + chol @ jax.random.normal(jax.random.PRNGKey(1), mean.shape)
    state = beam_init(system.prior.mean, block, theta=x0[:-1].reshape(theta.shape), log_u=x0[-1:])

    @jax.jit
    def run(state, keys):
        def body(s, k):
            s, acc = beam_collapsed_step(k, s, system, block, (mean, chol))
            return s, (s.theta, s.log_u, acc)
        return jax.lax.scan(body, state, keys)

    _, (th, lu, acc) = run(state, jax.random.split(jax.random.PRNGKey(2), 300))
    th, lu = np.asarray(th)[50:], np.asarray(lu)[50:]
    assert float(np.mean(acc)) > 0.3, float(np.mean(acc))
    z_th = (th.mean(0) - theta) / th.std(0)
    z_u = (lu.mean(0) - np.log(U)) / lu.std(0)
    assert np.max(np.abs(z_th)) < 4.5 and abs(float(z_u[0])) < 4.5, (z_th, z_u)
    with pytest.raises(ValueError, match="collapsed"):
        beam_step(jax.random.PRNGKey(0), state, system, block)
    with pytest.raises(ValueError, match="proposal has 8 parameters"):
        beam_collapsed_step(jax.random.PRNGKey(0), state, system, block, (mean[:-1], chol[:-1, :-1]))


def test_the_evidence_with_the_amplitude_needs_the_eager_newton_steps(raw):
    system, block, _ = raw
    with pytest.raises(ValueError, match="newton_steps"):
        beam_log_evidence(system, block, amplitude=True)


def test_the_data_space_grams_give_the_exact_marginal_and_the_same_laplace_evidence(raw, laplace):
    """:func:`beam_gram_log_evidence` (the marginal from the response sets' data-space Grams) equals the primal
    evidence of :func:`beam_system` (dense Cholesky of the precision) with flagged samples, any beams and any
    amplitude (measured: 2e-6 nats of ~1200 apart at most, rounding of two algebras at signal-to-noise ~1e3);
    the Laplace evidence by Newton's steps on it alone (no BFGS) equals BFGS-then-Newton on the primal path."""
    from gcrsky.inference.beams import beam_gram, beam_gram_log_evidence

    system, block, theta = raw
    w = np.asarray(system.inv_noise).copy()
    w[0, 3, 2] = 0.0
    w[0, 7, :] = 0.0  # a flagged sample and a flagged time
    flagged = system._replace(inv_noise=jnp.asarray(w))
    gram = beam_gram(flagged, block)
    for th, lu in ((theta, None), (2 * theta, jnp.array([np.log(U) + 0.7])), (0 * theta, jnp.array([-0.3]))):
        a = float(beam_gram_log_evidence(gram, block, jnp.asarray(th), lu)[0])
        b = float(log_evidence_system(beam_system(flagged, block, jnp.asarray(th), lu), options=CholeskyOptions(),
                                      check=False)[0][0])
        assert abs(a - b) < 1e-5 * max(1.0, abs(b) / 1000), (a, b)
    ref = laplace
    fast = beam_log_evidence(system, block, amplitude=True, newton_steps=30, gram=beam_gram(system, block))
    assert bool(fast.converged)
    assert abs(float(fast.log_z) - float(ref.log_z)) < 1e-4 and abs(float(fast.log_z_nominal) - float(ref.log_z_nominal)) < 1e-6
    cov = np.asarray(ref.covariance)  # the two maxima agree to ~1e-5 of a posterior sd: the Hessians to ~1e-4
    np.testing.assert_allclose(np.asarray(fast.covariance), cov, rtol=0, atol=1e-4 * np.max(np.abs(cov)))
    system1, block1, _ = _small_world(0.1)  # in its own units: the amplitude fixed at 1
    ref0 = beam_log_evidence(system1, block1, newton_steps=10)
    fast0 = beam_log_evidence(system1, block1, newton_steps=30, gram=beam_gram(system1, block1))
    assert bool(fast0.converged) and abs(float(fast0.log_bayes_factor) - float(ref0.log_bayes_factor)) < 1e-4


def test_the_grams_marginal_has_the_gradient_of_finite_differences(raw):
    """``jax.grad`` of :func:`beam_gram_log_evidence` in ``(theta, ln u)`` (what Newton's steps and the Laplace
    covariance use) against central differences of step 1e-5 (relative agreement 1e-5: the differences' own
    truncation and rounding at values ~300)."""
    from gcrsky.inference.beams import beam_gram, beam_gram_log_evidence

    system, block, theta = raw
    gram = beam_gram(system, block)
    shape = block.prior_mean.shape

    @jax.jit
    def f(x):
        return beam_gram_log_evidence(gram, block, x[:-1].reshape(shape), x[-1:])[0]

    x0 = jnp.concatenate([jnp.asarray(theta).ravel(), jnp.array([np.log(U) + 0.1])])
    g = np.asarray(jax.grad(f)(x0))
    h = 1e-5
    fd = np.array([(float(f(x0.at[i].add(h))) - float(f(x0.at[i].add(-h)))) / (2 * h) for i in range(x0.size)])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-5 * np.max(np.abs(fd)))
