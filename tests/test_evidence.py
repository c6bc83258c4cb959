"""The log evidence, hyperparameter fits, the spectral template, JAX beams, checked systems (issue 11).

References, independent of gcrsky's solvers: ``scipy.stats.multivariate_normal.logpdf``
of the realified unflagged data for the evidence (1e-8 relative: the dense paths
agree to ~1e-15), central finite differences for its gradient, dense NumPy sums for
the spectral template, ``scipy.optimize.minimize`` on the dense evidence for the fit,
and the exact (Cholesky) evidence for stochastic Lanczos quadrature.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _hyper_fixtures import LMAX, NSIDE, PATHS, THETA, central, numpy_log_evidence, scaled, small_problem
from scipy import optimize

import gcrsky
from gcrsky.inference import log_evidence_system
from gcrsky.instrument import (
    HERA_LATITUDE_DEG,
    JaxGaussianBeam,
    analytic_response,
    antpairs,
    gaussian_beam,
    hex_array,
    make_array,
)
from gcrsky.model import build_problem, isotropic_prior
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.solvers import CGOptions, CholeskyOptions, MModeOptions, SLQOptions
from gcrsky.solvers.info import Result


@pytest.fixture(scope="module")
def base():
    return small_problem().system()


# ---------------------------------------------------------------- the log evidence


@pytest.fixture(scope="module")
def flagged():
    flags = np.random.default_rng(7).random((2, 2 * LMAX + 3, 45)) < 0.2
    return small_problem(flags=flags).system()


@pytest.mark.parametrize("path", ["cholesky", "eigh"])
def test_log_evidence_equals_numpy_with_flags(flagged, path):
    ref = numpy_log_evidence(flagged)
    got = np.asarray(gcrsky.log_evidence(flagged, options=PATHS[path]))
    assert np.max(np.abs(got - ref) / np.abs(ref)) < 1e-8


def test_log_evidence_mmode_and_auto(base):
    ref = numpy_log_evidence(base)
    for opts in (MModeOptions(), None):
        got, info = gcrsky.log_evidence(base, options=opts, return_info=True)
        assert np.max(np.abs(np.asarray(got) - ref) / np.abs(ref)) < 1e-8
        assert np.all(np.asarray(info.stderr) == 0)


@pytest.mark.parametrize("path", ["cholesky", "eigh", "mmode"])
def test_log_evidence_gradient_equals_finite_differences(base, flagged, path):
    system = base if path == "mmode" else flagged

    @jax.jit
    def f(t):
        return jnp.sum(log_evidence_system(scaled(system, t), options=PATHS[path])[0])

    g = np.asarray(jax.grad(f)(THETA))
    fd = central(lambda t: float(f(jnp.asarray(t))), np.asarray(THETA))
    assert np.max(np.abs(g - fd)) < 1e-6 * np.max(np.abs(fd)), (g, fd)


@pytest.mark.parametrize("path", ["cholesky", "mmode"])
def test_log_evidence_hessian_equals_finite_differences_of_its_gradient(base, path):
    """Second order (the fit's Laplace covariance): the log-det JVP and the implicit solves
    differentiate again; central differences of the exact gradient (h = 1e-4: truncation
    ~1e-8 relative) are the reference."""
    f = jax.jit(lambda t: jnp.sum(log_evidence_system(scaled(base, t), options=PATHS[path])[0]))
    hess = np.asarray(jax.jit(jax.hessian(f))(THETA))
    grad = jax.jit(jax.grad(f))
    fd = np.stack([(np.asarray(grad(THETA + 1e-4 * e)) - np.asarray(grad(THETA - 1e-4 * e))) / 2e-4
                   for e in np.eye(2)])
    assert np.max(np.abs(hess - fd)) < 1e-6 * np.max(np.abs(fd)), (hess, fd)


def test_improper_evidence_is_an_error(base):
    flat = base._replace(prior=base.prior._replace(inv_var=base.prior.inv_var.at[0, 3].set(0.0)))
    with pytest.raises(ValueError, match="evidence is improper.*frequency 0, parameter 3"):
        gcrsky.log_evidence(flat)


@pytest.fixture(scope="module")
def bigger():
    """n = 81 > the Nystrom rank used here, so SLQ has a non-trivial remainder to estimate."""
    return small_problem(nf=1, nt=8, seed=2, lmax=8).system()  # 8 LSTs over the day: no m-mode (Nt <= 2 lmax)


@pytest.mark.slow
def test_slq_within_three_standard_errors_on_20_seeds(bigger):
    """Each of 20 probe seeds lands within 3 of its own standard errors of the exact value.

    For Gaussian errors the chance that one of 20 exceeds 3 sigma is 5%; the seeds are
    fixed, so the test is deterministic.  The mean squared z is also checked: about 1
    for honest error bars (chi^2_20 / 20: below 0.3 or above 4 with probability ~1e-3
    together); error bars 2x too large or 2x too small must fail it (negative controls:
    the first is what reporting the standard error of log det P, not of -1/2 log det P,
    gave).
    """
    exact = float(gcrsky.log_evidence(bigger, options=CholeskyOptions())[0])
    opts, slq = CGOptions(tol=1e-10, sketch_size=16, dense=False), SLQOptions(probes=32, lanczos=20)
    run = jax.jit(lambda k: log_evidence_system(bigger, options=opts, slq=slq, key=k))  # one compilation
    z = []
    for seed in range(20):
        v, info = run(jax.random.PRNGKey(seed))
        z.append((float(v[0]) - exact) / float(info.stderr[0]))
    z = np.array(z)

    def honest(z):
        return bool(np.all(np.abs(z) < 3) and 0.3 < np.mean(z**2) < 4.0)

    assert honest(z), (z, np.mean(z**2))
    assert not honest(z / 2) and not honest(z * 2), np.mean(z**2)


@pytest.mark.slow
def test_slq_gradient_is_unbiased(bigger):
    """The mean of SLQ's gradient over seeds equals the exact gradient within its standard error."""
    exact = np.asarray(jax.grad(lambda t: log_evidence_system(scaled(bigger, t), options=CholeskyOptions())[0][0])(THETA))
    opts, slq = CGOptions(tol=1e-10, sketch_size=16, dense=False), SLQOptions(probes=16, lanczos=20)
    grad = jax.jit(jax.grad(lambda t, k: log_evidence_system(scaled(bigger, t), options=opts, slq=slq, key=k)[0][0]))
    g = np.stack([np.asarray(grad(THETA, jax.random.PRNGKey(s))) for s in range(12)])
    sem = g.std(axis=0, ddof=1) / np.sqrt(g.shape[0])
    assert np.all(np.abs(g.mean(axis=0) - exact) < 4 * sem + 1e-9 * np.abs(exact)), (g.mean(0), exact, sem)


# ---------------------------------------------------------------- hyperparameters


def test_prior_from_cl_is_the_jax_twin_of_isotropic_prior():
    cl = 30.0 / (1.0 + np.arange(LMAX + 1)) ** 2
    a = gcrsky.prior_from_cl(jnp.asarray(cl))
    b = isotropic_prior(cl, (LMAX + 1) ** 2)
    np.testing.assert_allclose(np.asarray(a.inv_var), b.inv_var, rtol=1e-15)
    np.testing.assert_allclose(np.asarray(gcrsky.power_law_cl(2.0, 1.5, 3)), 2.0 * np.arange(1, 5) ** -1.5,
                               rtol=1e-15)
    g = jax.grad(lambda amp: jnp.sum(gcrsky.prior_from_cl(gcrsky.power_law_cl(amp, 2.0, LMAX)).inv_var))(3.0)
    assert np.isfinite(float(g)) and float(g) < 0


@pytest.mark.slow
def test_fit_recovers_the_noise_scale_and_agrees_with_scipy():
    """Data simulated with 4x the nominal noise variance: the fit of log(scale) finds it
    within its Laplace error bar, and SciPy's optimiser on the same dense evidence agrees."""
    prob = small_problem(nf=1, seed=11)
    true_scale = 4.0
    noisy = build_problem(make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0)), prob.freqs_hz,
                          prob.lsts_rad, LMAX, NSIDE, a_true=prob.prior.mean, sigma=0.05, noise_scale=true_scale,
                          prior=prob.prior, key=jax.random.PRNGKey(12))
    nominal = noisy.system()._replace(inv_noise=noisy.system().inv_noise * true_scale)  # claims sigma = 0.05

    def make(theta):
        return gcrsky.model.scale_noise(nominal, jnp.exp(theta["log_noise"]))

    fit = gcrsky.fit_hyperparameters(make, {"log_noise": jnp.asarray(0.0)})
    assert fit.converged, fit.message
    est, err = float(fit.theta["log_noise"]), float(fit.std["log_noise"])
    assert abs(est - np.log(true_scale)) < 3 * err, (est, np.log(true_scale), err)
    ref = optimize.minimize(lambda x: -float(log_evidence_system(make({"log_noise": jnp.asarray(x[0])}),
                                                                 options=CholeskyOptions())[0][0]), [0.0],
                            method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12})
    assert abs(est - ref.x[0]) < 1e-5 * max(1.0, abs(ref.x[0]))
    assert fit.covariance.shape == (1, 1)
    bare = gcrsky.fit_hyperparameters(make, {"log_noise": jnp.asarray(0.0)}, covariance=False)  # no Hessian
    assert float(bare.theta["log_noise"]) == est and bool(bare.converged)
    assert bool(jnp.all(jnp.isnan(bare.covariance))) and bool(jnp.isnan(bare.std["log_noise"]))


# ---------------------------------------------------------------- the beam and the spectral template


def test_beam_width_derivative_of_the_response_equals_finite_differences():
    pos, pairs = hex_array(), antpairs(10)
    lat = np.deg2rad(HERA_LATITUDE_DEG)
    w = jnp.asarray(np.random.default_rng(4).standard_normal((1, 45, (LMAX + 1) ** 2)))

    @jax.jit
    def f(d):
        R = analytic_response(pos, lat, pairs, [100e6], LMAX, NSIDE, JaxGaussianBeam(diameter_m=d))
        return jnp.sum(w * R.real) + jnp.sum(w * R.imag)

    g = float(jax.grad(f)(14.0))
    h = 1e-4
    fd = (float(f(14.0 + h)) - float(f(14.0 - h))) / (2 * h)
    assert abs(g - fd) < 1e-6 * abs(fd)


def test_spectral_template_is_the_shared_coefficient_posterior(base):
    """P and b of the template system are the sum of the scaled per-channel data terms."""
    freqs = jnp.array([100e6, 101e6])
    beta = -2.5
    tmpl = gcrsky.spectral_template_system(base, freqs, beta)
    s = np.asarray((freqs / freqs[0]) ** beta)
    P = np.asarray(precision_matrix(base))
    D = np.stack([np.diag(v) for v in np.asarray(base.prior.inv_var)])
    b = np.asarray(wiener_rhs(base)) - np.asarray(base.prior.inv_var * base.prior.mean)
    want_P = sum(s[f] ** 2 * (P[f] - D[f]) for f in range(2)) + D[0]
    want_b = sum(s[f] * b[f] for f in range(2)) + np.asarray(base.prior.inv_var[0] * base.prior.mean[0])
    np.testing.assert_allclose(np.asarray(precision_matrix(tmpl))[0], want_P, rtol=1e-12, atol=1e-12 * np.abs(want_P).max())
    np.testing.assert_allclose(np.asarray(wiener_rhs(tmpl))[0], want_b, rtol=1e-12, atol=1e-12 * np.abs(want_b).max())
    # one channel: the template reduces to the per-channel system
    one = gcrsky.spectral_template_system(base._replace(op=base.op._replace(response=base.op.response[:1]),
                                                        data=base.data[:1], inv_noise=base.inv_noise[:1],
                                                        prior=base.prior._replace(mean=base.prior.mean[:1],
                                                                                  inv_var=base.prior.inv_var[:1])),
                                          freqs[:1], beta)
    np.testing.assert_allclose(np.asarray(gcrsky.wiener_filter_system(one, method="cholesky")[0]),
                               np.asarray(gcrsky.wiener_filter_system(base, method="cholesky")[0][:1]), rtol=1e-12)
    # beta differentiates through the samplers and the evidence
    g = jax.grad(lambda bt: jnp.sum(gcrsky.log_evidence(gcrsky.spectral_template_system(base, freqs, bt),
                                                        method="cholesky")))(beta)
    assert np.isfinite(float(g))


# ---------------------------------------------------------------- reliability of the pure API


def test_check_system_names_the_problem(base):
    with pytest.raises(ValueError, match=r"inv_noise must be finite and >= 0.*\(freq 1, time 2, baseline 3\)"):
        gcrsky.check_system(base._replace(inv_noise=base.inv_noise.at[1, 2, 3].set(-1.0)))
    with pytest.raises(ValueError, match=r"non-finite samples, first an unflagged one at \(freq 0, time 1"):
        gcrsky.check_system(base._replace(data=base.data.at[0, 1, 0].set(jnp.nan)))
    with pytest.raises(ValueError, match="float32"):
        gcrsky.check_system(base._replace(inv_noise=base.inv_noise.astype(jnp.float32)))
    with pytest.raises(ValueError, match=r"prior.inv_var has shape \(2, 3\)"):
        gcrsky.check_system(base._replace(prior=base.prior._replace(inv_var=base.prior.inv_var[:, :3])))
    with pytest.raises(ValueError, match="prior.mean must be finite"):
        gcrsky.sample(jax.random.PRNGKey(0), base._replace(prior=base.prior._replace(
            mean=base.prior.mean.at[0, 0].set(jnp.inf))), 2)
    assert gcrsky.check_system(base) is base


def test_result_codes_and_throw(base):
    _, info = gcrsky.wiener_filter_system(base, options=CGOptions(tol=1e-14, maxiter=1, preconditioner="mblock"))
    assert set(np.asarray(info.result).tolist()) == {Result.MAX_ITERATIONS}
    flat = base._replace(inv_noise=jnp.zeros_like(base.inv_noise),
                         prior=base.prior._replace(inv_var=jnp.zeros_like(base.prior.inv_var)))
    _, info = gcrsky.wiener_filter_system(flat, options=CGOptions(preconditioner="mblock", maxiter=50))
    assert set(np.asarray(info.result).tolist()) <= {Result.BREAKDOWN, Result.NONFINITE}
    _, info = gcrsky.wiener_filter_system(flat, method="cholesky")
    assert set(np.asarray(info.result).tolist()) == {Result.NONFINITE}
    assert gcrsky.solvers.info.result_names(info) == {"nonfinite": 2}
    with pytest.raises(Exception, match="did not converge"):
        jax.block_until_ready(jax.jit(lambda s: gcrsky.wiener_filter_system(
            s, options=CGOptions(tol=1e-14, maxiter=1, preconditioner="mblock", throw=True))[0])(base))


def test_jax_engine_equals_ours(base):
    a1, i1 = gcrsky.wiener_filter_system(base, options=CGOptions(tol=1e-10, sketch_size=8, preconditioner="nystrom"))
    a2, i2 = gcrsky.wiener_filter_system(base, options=CGOptions(tol=1e-10, sketch_size=8, engine="jax"))
    sig = np.sqrt(np.stack([np.diag(np.linalg.inv(p)) for p in np.asarray(precision_matrix(base))]))
    assert np.max(np.abs(np.asarray(a1 - a2)) / sig) < 2e-10
    assert bool(np.all(np.asarray(i2.converged))) and set(np.asarray(i2.iterations).tolist()) == {-1}
    assert bool(np.all(np.asarray(i1.iterations) > 0))
