"""Gains sampled with the sky (issue 23): the model, the conditionals, the gauge move, the joint chain.

References and tolerances:

* the gain conditional ``theta | a, s, d`` (built from per-row mode sums and an autodiff Hessian,
  no dense Jacobian) against the dense Jacobian of the model visibilities by ``jax.jacfwd`` and
  NumPy algebra: rounding (1e-12 relative);
* the linearised model against the exact one: their difference is exactly the neglected
  ``q G x_i conj(x_j)`` (rounding), and the exact model's directional derivative at ``theta = 0``
  (central finite differences, step 1e-6: error O(h^2) ~ 1e-12) is the linear model's;
* the sky given gains (:func:`gained_fixed`) against the dense posterior of ``D X``: rounding;
* the scale conditional against 4000 of its own draws (z-scores < 4.5);
* the gauge move's log ratio against the full log posterior (likelihood included) and the
  map's Jacobian by ``jax.jacfwd``: rounding (the likelihood cancels);
* the joint chain on a simulation with known gains (5 % amplitude and 5 deg phase per antenna,
  smooth in frequency, slow in time; the exact model): the true gain perturbations whitened by
  the chain's mean and covariance give ``mean z^2`` within the chi-square range of P terms
  (two-sided 0.1 %), widened by 25 % for the chain's Monte-Carlo error; the sky along its
  data-dominated directions likewise; the negative control (a sky drawn ignoring the gains)
  fails the same sky check by far.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from gcrsky.inference import (
    effective_sample_size,
    gain_init,
    gain_setup,
    gains_step,
    gauge_step,
    gibbs_setup,
    joint_gain_step,
    recentre,
    scale_step,
    sky_step,
)
from gcrsky.inference.gains import gain_conditional, gain_posterior, gained_fixed, scale_conditional, scale_sky_step
from gcrsky.instrument import HERA_LATITUDE_DEG, antpairs, gaussian_beam, hex_array, make_array
from gcrsky.model import (
    build_problem,
    gain_factor,
    gain_model,
    isotropic_prior,
    n_gain_params,
    perturbation_coefficients,
    perturbations,
    phase_gradient_directions,
)
from gcrsky.model.gains import mode_basis
from gcrsky.model.operator import apply, dense_matrix
from gcrsky.solvers import CGOptions


def _random_inputs(rng, nf, nt, nbl):
    c = lambda: rng.standard_normal((nf, nt, nbl)) + 1j * rng.standard_normal((nf, nt, nbl))  # noqa: E731
    return c(), c(), rng.uniform(0.5, 2.0, (nf, nt, nbl))


@pytest.mark.parametrize("kind", ["dpss", "fourier", "legendre"])
def test_mode_basis_orthogonal_unit_rms_constant_first(kind):
    B = mode_basis(7, 3, kind)
    np.testing.assert_allclose(B.T @ B / 7, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(B[:, 0], 1.0, atol=1e-12)
    with pytest.raises(ValueError, match="gain modes"):
        mode_basis(3, 4, kind)
    with pytest.raises(ValueError, match="basis must be"):
        mode_basis(3, 2, "chebyshev")


def test_gauge_fixing_projects_out_the_phase_and_the_channel_amplitude():
    """Every perturbation has no common imaginary part per feed (the unobservable overall phase) and the
    frequency-only modes no common real part (the scale's); what is left is observable: the data-only
    precision of theta for a generic sky is full rank."""
    rng = np.random.default_rng(1)
    pols = ("xx",) * 6 + ("yy",) * 6
    model = gain_model(np.concatenate([antpairs(4)] * 2), 3, 4, (2, 2), pols=pols)
    assert model.amp_proj.shape == (8, 7) and model.phase_proj.shape == (8, 6)
    P = n_gain_params(model)
    assert P == 7 * 2 + 8 * 2 + 6 * 4
    x = perturbations(model, rng.standard_normal(P))
    for feed in (1, 2):
        np.testing.assert_allclose(np.sum(np.asarray(x).imag[..., model.units[:, 1] == feed], axis=-1), 0, atol=1e-12)
    c = perturbation_coefficients(model, rng.standard_normal(P))
    np.testing.assert_allclose(np.sum(np.asarray(c).real[:, :, 0], axis=0), 0, atol=1e-12)
    block = gain_setup(model, sigma=1e6)  # a negligible prior
    d, M, W = _random_inputs(rng, 3, 4, 12)
    prec, _ = gain_conditional(block, d, W, M, np.array([1.0, 0.0]))
    lam = np.linalg.eigvalsh(np.asarray(prec) - np.diag(np.asarray(block.prior_inv_var)))
    assert lam[0] > 1e-6 * lam[-1]


def test_gain_setup_rejects_bad_priors():
    model = gain_model(antpairs(3), 2, 2, (1, 1))
    with pytest.raises(ValueError, match="positive"):
        gain_setup(model, sigma=0.0)
    with pytest.raises(ValueError, match="broadcastable"):
        gain_setup(model, sigma=np.ones(3))
    with pytest.raises(ValueError, match="cross-correlations"):
        gain_model(np.array([[0, 0], [0, 1]]), 2, 2)


def test_gain_conditional_matches_the_dense_jacobian():
    rng = np.random.default_rng(0)
    nf, nt = 3, 5
    model = gain_model(antpairs(4), nf, nt, (2, 3), basis="fourier")
    P = n_gain_params(model)
    gbar = np.exp(0.1j * rng.standard_normal((nf, nt, 4))) * (1 + 0.1 * rng.standard_normal((nf, nt, 4)))
    block = gain_setup(model, sigma=np.array([[0.1, 0.05, 0.02], [0.03, 0.02, 0.01]]), gbar=gbar)
    d, M, W = _random_inputs(rng, nf, nt, 6)
    s = np.array([1.3, -0.2])
    prec, rhs = gain_conditional(block, d, W, M, s)
    J = np.asarray(jax.jacfwd(lambda th: (gain_factor(model, th, s, gbar) * M).ravel())(jnp.zeros(P)))
    r = d.ravel() - np.asarray(gain_factor(model, np.zeros(P), s, gbar) * M).ravel()
    Pref = np.real(J.conj().T @ (W.ravel()[:, None] * J)) + np.diag(np.asarray(block.prior_inv_var))
    bref = np.real(J.conj().T @ (W.ravel() * r))
    np.testing.assert_allclose(prec, Pref, rtol=0, atol=1e-12 * np.abs(Pref).max())
    np.testing.assert_allclose(rhs, bref, rtol=0, atol=1e-12 * np.abs(bref).max())
    # the posterior and the draw (rebuilt from its standard normals)
    mean, cov = gain_posterior(block, d, W, M, s)
    np.testing.assert_allclose(mean, np.linalg.solve(Pref, bref), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cov, np.linalg.inv(Pref), rtol=1e-9, atol=1e-14)


def test_linearised_model_against_the_exact_one():
    rng = np.random.default_rng(2)
    model = gain_model(antpairs(5), 3, 4, (2, 2))
    th = 0.05 * rng.standard_normal(n_gain_params(model))
    gbar = np.exp(0.3j * rng.standard_normal((3, 4, 5)))
    lin, ex = gain_factor(model, th, 1.2, gbar), gain_factor(model, th, 1.2, gbar, exact=True)
    x = perturbations(model, th)
    G = gain_factor(model, 0 * th, 1.2, gbar)
    np.testing.assert_allclose(ex - lin, G * x[..., model.unit_pairs[:, 0]] * np.conj(x[..., model.unit_pairs[:, 1]]),
                               atol=1e-14)
    h = 1e-6
    fd = (gain_factor(model, h * th, 1.2, gbar, exact=True) - gain_factor(model, -h * th, 1.2, gbar, exact=True)) / (2 * h)
    np.testing.assert_allclose(fd, lin - G, atol=1e-9)


# ---------------------------------------------------------------- a small simulated observation


@functools.lru_cache(maxsize=None)
def _observation():
    """5 antennas (14 m Gaussian dishes), 3 channels at 100-102 MHz, 8 LSTs over 1.5 rad, lmax 4, nside 16;
    an isotropic prior C_l = 50 / (1 + l)^2 and a truth drawn from it."""
    arr = make_array(hex_array((2, 3)), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    freqs, lsts, lmax = np.array([100e6, 101e6, 102e6]), np.linspace(0.0, 1.5, 8), 4
    n = (lmax + 1) ** 2
    prior = isotropic_prior(np.tile(50.0 / (1.0 + np.arange(lmax + 1)) ** 2, (3, 1)), n)
    truth = np.asarray(prior.inv_var) ** -0.5 * np.random.default_rng(1).standard_normal((3, n))
    prob = build_problem(arr, freqs, lsts, lmax, 16, a_true=truth, sigma=1.0, prior=prior, key=jax.random.PRNGKey(0))
    return prob, truth


def _true_gains(model, rng):
    """theta of 5 % amplitude and 5 deg phase per antenna (constant mode), 1 % in the slow modes."""
    c = np.zeros((model.units.shape[0], 2, 2), complex)
    c[:, 0, 0] = 0.05 * rng.standard_normal(c.shape[0]) + 1j * np.deg2rad(5.0) * rng.standard_normal(c.shape[0])
    c[:, 1:, :] += 0.01 * (rng.standard_normal((c.shape[0], 1, 2)) + 1j * rng.standard_normal((c.shape[0], 1, 2)))
    c[:, 0, 1] += 0.01 * (rng.standard_normal(c.shape[0]) + 1j * rng.standard_normal(c.shape[0]))
    # in the gauge: no common phase (unobservable), no common amplitude per channel (the scale's, q = 1)
    c.imag -= c.imag.mean(axis=0)
    c.real[:, :, 0] -= c.real[:, :, 0].mean(axis=0)
    P = n_gain_params(model)
    J = np.asarray(jax.jacfwd(lambda t: perturbation_coefficients(model, t).ravel())(jnp.zeros(P)))
    target = np.concatenate([c.ravel().real, c.ravel().imag])
    theta = np.linalg.lstsq(np.concatenate([J.real, J.imag]), target, rcond=None)[0]
    np.testing.assert_allclose(np.concatenate([J.real, J.imag]) @ theta, target, atol=1e-12)
    return theta


@functools.lru_cache(maxsize=None)
def _simulation():
    prob, truth = _observation()
    rng = np.random.default_rng(3)
    model = gain_model(prob.antpairs, 3, 8, (2, 2))
    theta = _true_gains(model, rng)
    V = prob.visibilities(truth)
    sigma = 0.01 * float(jnp.sqrt(jnp.mean(jnp.abs(V) ** 2)))  # noise 1 % of the rms visibility
    data = gain_factor(model, theta, 1.0, exact=True) * V + sigma * (rng.standard_normal(V.shape)
                                                                      + 1j * rng.standard_normal(V.shape))
    system = prob.system()._replace(data=data, inv_noise=jnp.full(V.shape, sigma**-2))
    block = gain_setup(model, sigma=np.array([[0.1, 0.02], [0.02, 0.02]]))
    return system, block, theta, truth


def test_sky_given_gains_matches_the_dense_posterior():
    system, block, theta, _ = _simulation()
    s = jnp.array([1.1, 0.05])
    D = gain_factor(block.model, theta, s)
    X = np.asarray(dense_matrix(system.op))  # (Nf, Nt, Nbl, n)
    A = np.asarray(D)[..., None] * X
    W = np.asarray(system.inv_noise)
    H = np.einsum("ftbk,ftb,ftbj->fkj", A.conj(), W, A).real
    b = np.einsum("ftbk,ftb->fk", A.conj(), W * np.asarray(system.data)).real
    fixed = gained_fixed(gibbs_setup(system), D)
    np.testing.assert_allclose(fixed.data_term, H, rtol=0, atol=1e-10 * np.abs(H).max())
    np.testing.assert_allclose(fixed.data_rhs, b, rtol=0, atol=1e-10 * np.abs(b).max())
    L = np.linalg.cholesky(H + np.stack([np.diag(v) for v in np.asarray(system.prior.inv_var)]))
    np.testing.assert_allclose(fixed.factor, L, rtol=1e-8, atol=1e-10 * np.abs(L).max())
    # the matrix-free CG path: the same system (data d / D, inverse noise W |D|^2), the sketch kept
    cg = gibbs_setup(system, options=CGOptions(dense=False), sketch_size=16)
    gcg = gained_fixed(cg, D)
    np.testing.assert_allclose(gcg.data_rhs, b, rtol=0, atol=1e-10 * np.abs(b).max())
    assert gcg.lowrank is cg.lowrank
    a = jax.random.normal(jax.random.PRNGKey(0), b.shape)
    lhs = adjoint_w(gcg.system, a)
    np.testing.assert_allclose(lhs, np.einsum("fkj,fj->fk", H, a), rtol=0, atol=1e-10 * np.abs(lhs).max())
    # a sweep on the CG path: the sky solves converge with the stale (ungained) sketch; the collapsed
    # sweep needs the dense data term and says so
    state = gain_init(system.prior.mean, block, theta=theta, scale=s)
    new, info = jax.jit(lambda k: joint_gain_step(k, state, cg, block))(jax.random.PRNGKey(1))
    assert bool(jnp.all(info.solve.converged)) and bool(jnp.all(jnp.isfinite(new.sky)))
    with pytest.raises(ValueError, match="Cholesky path"):
        joint_gain_step(jax.random.PRNGKey(1), state, cg, block, collapsed=True)


def adjoint_w(system, a):
    """``X^T W X a`` of a system, matrix-free."""
    from gcrsky.model.operator import adjoint

    return adjoint(system.op, system.inv_noise * apply(system.op, a))


def test_scale_conditional_and_its_draws():
    system, block, theta, truth = _simulation()
    V = apply(system.op, jnp.asarray(truth))
    prec, rhs = scale_conditional(block, system.data, system.inv_noise, V, theta)
    U = np.asarray(gain_factor(block.model, theta, 1.0) * V)
    Uk = np.asarray(block.model.basis_f)[:, :, None, None].transpose(1, 0, 2, 3) * U[None]
    Pref = np.einsum("kftb,ftb,mftb->km", Uk.conj(), np.asarray(system.inv_noise), Uk).real
    np.testing.assert_allclose(prec, Pref, rtol=1e-12)
    fixed = gibbs_setup(system)
    state = gain_init(jnp.asarray(truth), block, theta=theta)
    draws = jax.jit(jax.vmap(lambda k: scale_step(k, state, fixed, block).scale))(jax.random.split(jax.random.PRNGKey(4), 4000))
    mean, cov = np.linalg.solve(Pref, np.asarray(rhs)), np.linalg.inv(Pref)
    z = (np.asarray(draws).mean(0) - mean) / np.sqrt(np.diag(cov) / 4000)
    assert np.all(np.abs(z) < 4.5), z
    np.testing.assert_allclose(np.asarray(draws).std(0), np.sqrt(np.diag(cov)), rtol=0.06)  # 5 sigma of 1/sqrt(2 x 4000)
    # the data follow the exact model: the scale absorbs the linearisation's second-order term, the
    # noise-free least-squares q of the exact model's visibilities on the linear model's (-0.9 % here)
    exact = np.asarray(gain_factor(block.model, theta, 1.0, exact=True) * V)
    W = np.asarray(system.inv_noise)
    q_ls = np.linalg.solve(Pref, np.einsum("kftb,ftb->k", Uk.conj(), W * exact).real)
    assert np.all(np.abs(mean - q_ls) < 5 * np.sqrt(np.diag(cov))), (mean, q_ls)
    assert -0.02 < q_ls[0] - 1.0 < -0.002


def test_gauge_move_ratio_is_the_full_posterior_ratio_with_the_jacobian():
    system, block, theta, truth = _simulation()
    fixed = gibbs_setup(system)
    state = gain_init(jnp.asarray(truth), block, theta=theta, scale=jnp.array([1.0, 0.02]))
    key = jax.random.PRNGKey(7)
    new, _, log_r = gauge_step(key, state, fixed, block, 0.05)
    delta = 0.05 * jax.random.normal(jax.random.split(key)[0], (2,))  # the move's own draw

    def log_post(sky, s):
        D = gain_factor(block.model, theta, s)
        r = system.data - D * apply(system.op, sky)
        pr = system.prior
        return (-0.5 * jnp.sum(system.inv_noise * jnp.abs(r) ** 2) - 0.5 * jnp.sum(pr.inv_var * (sky - pr.mean) ** 2)
                - 0.5 * jnp.sum(block.scale_inv_var * (s - block.scale_mean) ** 2))

    def move(flat):
        sky, s = flat[:-2].reshape(truth.shape), flat[-2:]
        q, qn = block.model.basis_f @ s, block.model.basis_f @ (s + delta)
        return jnp.concatenate([(sky * (q / qn)[:, None]).ravel(), s + delta])

    x0 = jnp.concatenate([jnp.asarray(truth).ravel(), state.scale])
    x1 = move(x0)
    logdet = np.linalg.slogdet(np.asarray(jax.jacfwd(move)(x0)))[1]
    ref = log_post(x1[:-2].reshape(truth.shape), x1[-2:]) - log_post(truth, state.scale) + logdet
    np.testing.assert_allclose(log_r, ref, rtol=1e-6, atol=1e-6)
    # the likelihood is invariant: the model visibilities of an accepted move are unchanged
    if not jnp.allclose(new.scale, state.scale):
        np.testing.assert_allclose(gain_factor(block.model, theta, new.scale) * apply(system.op, new.sky),
                                   gain_factor(block.model, theta, state.scale) * apply(system.op, state.sky),
                                   rtol=1e-10, atol=1e-16)


def test_gains_step_draw_is_the_dense_conditional():
    system, block, theta, truth = _simulation()
    fixed = gibbs_setup(system)
    state = gain_init(jnp.asarray(truth), block)
    key = jax.random.PRNGKey(5)
    new = gains_step(key, state, fixed, block)
    mean, cov = gain_posterior(block, system.data, system.inv_noise, apply(system.op, jnp.asarray(truth)), state.scale)
    z = jax.random.normal(key, mean.shape)
    L = np.linalg.cholesky(np.linalg.inv(np.asarray(cov)))
    np.testing.assert_allclose(new.theta, np.asarray(mean) + np.linalg.solve(L.T, np.asarray(z)), rtol=1e-8, atol=1e-12)


# ---------------------------------------------------------------- the joint chain on the simulation


def _run(fixed, block, state, key, nsteps, gains=True):
    """``nsteps`` sweeps from ``state``: the final state and the draws (sky, theta, scale)."""

    def body(s, k):
        if gains:
            s, _ = joint_gain_step(k, s, fixed, block)
        else:  # negative control: the sky alone, gains ignored (g = 1)
            sky, _ = sky_step(k, fixed, s.sky)
            s = s._replace(sky=sky)
        return s, (s.sky, s.theta, s.scale)

    return jax.lax.scan(body, state, jax.random.split(key, nsteps))


_run_jit = jax.jit(_run, static_argnums=(4, 5))


def _chain(system, block, nsteps, key, gains=True, burn=300):
    """A burn-in of ``burn`` sweeps, re-centred at its second half's mean gains ``theta0``, then ``nsteps``
    kept sweeps: (draws (sky, theta, scale) about the re-centred block, ``theta0``)."""
    fixed = gibbs_setup(system)
    k1, k2 = jax.random.split(key)
    state, (_, th, _) = _run_jit(fixed, block, gain_init(system.prior.mean, block), k1, burn, gains)
    theta0 = jnp.mean(th[burn // 2:], axis=0)
    if gains:
        block, state = recentre(block, state._replace(theta=theta0))
    return _run_jit(fixed, block, state, k2, nsteps, gains)[1], theta0


def _theta_about(model, theta_true, theta0):
    """theta of the perturbation ``(1 + x_true) / (1 + x0) - 1`` about gains re-centred at ``theta0``
    (least squares in the perturbations' span; the rest is second order)."""
    P = n_gain_params(model)
    J = np.asarray(jax.jacfwd(lambda t: perturbations(model, t).ravel())(jnp.zeros(P)))
    x_true, x0 = (np.asarray(perturbations(model, t)) for t in (theta_true, theta0))
    target = ((1 + x_true) / (1 + x0) - 1).ravel()
    A = np.concatenate([J.real, J.imag])
    return np.linalg.lstsq(A, np.concatenate([target.real, target.imag]), rcond=None)[0]


def _whitened_z2(draws, truth):
    m = draws.mean(0)
    L = np.linalg.cholesky(np.cov(draws.T))
    return float(np.mean(np.linalg.solve(L, truth - m) ** 2))


def _data_directions(system, k):
    """The k most data-dominated directions of the sky (prior-whitened data term), as rows (k, Nf n)."""
    X = np.asarray(dense_matrix(system.op))
    H = np.einsum("ftbk,ftb,ftbj->fkj", X.conj(), np.asarray(system.inv_noise), X).real
    sd = np.asarray(system.prior.inv_var) ** -0.5
    rows = []
    for f in range(H.shape[0]):
        lam, V = np.linalg.eigh(sd[f][:, None] * H[f] * sd[f][None, :])
        for v in V[:, ::-1][:, : k // H.shape[0]].T:
            row = np.zeros(H.shape[0] * H.shape[1])
            row[f * H.shape[1]:(f + 1) * H.shape[1]] = v / sd[f]  # a coordinate along a whitened eigenvector
            rows.append(row)
    return np.array(rows)


def test_joint_chain_recovers_known_gains_and_the_sky_and_ignoring_gains_fails():
    system, block, theta, truth = _simulation()
    (sky, th, s), theta0 = _chain(system, block, 1500, jax.random.PRNGKey(11), burn=200)
    sky, th, s = np.asarray(sky), np.asarray(th), np.asarray(s)
    P = theta.size
    lo, hi = stats.chi2.ppf(0.0005, P) / P, 1.25 * stats.chi2.ppf(0.9995, P) / P
    z2_gains = _whitened_z2(th, _theta_about(block.model, theta, theta0))
    assert lo < z2_gains < hi, (z2_gains, lo, hi)
    E = _data_directions(system, 9)
    proj = sky.reshape(sky.shape[0], -1) @ E.T
    z2_sky = _whitened_z2(proj, E @ truth.ravel())
    klo, khi = stats.chi2.ppf(0.0005, 9) / 9, 1.25 * stats.chi2.ppf(0.9995, 9) / 9
    assert klo < z2_sky < khi, (z2_sky, klo, khi)
    assert float(effective_sample_size(s[None, :, 0])) > 100  # the gauge move mixes the amplitude
    # negative control: the sky drawn as if the gains were 1
    sky0 = np.asarray(_chain(system, block, 500, jax.random.PRNGKey(12), gains=False, burn=100)[0][0])
    z2_bad = _whitened_z2(sky0.reshape(sky0.shape[0], -1) @ E.T, E @ truth.ravel())
    assert z2_bad > 10 * khi, z2_bad


def test_phase_gradient_directions_are_unit_and_inside_the_phase_block():
    system, block, _, _ = _simulation()
    pos = hex_array((2, 3))
    T = phase_gradient_directions(block.model, pos)
    np.testing.assert_allclose(np.linalg.norm(T, axis=1), 1.0)
    x = perturbations(block.model, T[0])
    np.testing.assert_allclose(np.asarray(x).real, 0, atol=1e-14)  # a pure phase
    ph = np.asarray(x).imag[0, 0]
    centred = pos[:, 0] - pos[:, 0].mean()
    np.testing.assert_allclose(ph / np.linalg.norm(ph), centred / np.linalg.norm(centred), atol=1e-12)


def test_collapsed_scale_marginal_and_sky_draw_against_dense_algebra():
    """The scale's marginal (sky integrated out) against the dense Gaussian of the realified data, and the
    sky drawn at a fixed scale against the dense conditional (3000 draws: z-scores < 4.5, variances 12 %)."""
    from gcrsky.inference.gains import _log_marginal_q, _whitened

    system, block, theta, _ = _simulation()
    fixed = gibbs_setup(system)
    w = _whitened(fixed, block, jnp.asarray(theta))
    X = np.asarray(dense_matrix(system.op))
    D1 = np.asarray(gain_factor(block.model, theta, 1.0))
    W = np.asarray(system.inv_noise)
    a0, var = np.asarray(system.prior.mean), 1.0 / np.asarray(system.prior.inv_var)

    def dense_log_marginal(q, f):
        A = (q * D1[f])[..., None] * X[f]  # (Nt, Nbl, n)
        Ar = np.concatenate([A.real.reshape(-1, A.shape[-1]), A.imag.reshape(-1, A.shape[-1])])
        d = np.asarray(system.data)[f]
        dr = np.concatenate([d.real.ravel(), d.imag.ravel()])
        cov = Ar @ np.diag(var[f]) @ Ar.T + np.diag(1.0 / np.concatenate([W[f].ravel()] * 2))
        return stats.multivariate_normal(Ar @ a0[f], cov).logpdf(dr)

    for f in range(3):
        qs = jnp.full(3, 0.8), jnp.full(3, 1.15)
        got = float(_log_marginal_q(w, qs[1])[f] - _log_marginal_q(w, qs[0])[f])
        ref = dense_log_marginal(1.15, f) - dense_log_marginal(0.8, f)
        np.testing.assert_allclose(got, ref, rtol=1e-7, atol=1e-6)
    s = jnp.array([1.1, 0.05])
    state = gain_init(system.prior.mean, block, theta=theta, scale=s)
    draws = jax.jit(jax.vmap(lambda k: scale_sky_step(k, state, fixed, block, moves=1, step_size=0.0)[0].sky))(
        jax.random.split(jax.random.PRNGKey(8), 3000))
    q = np.asarray(block.model.basis_f @ s)
    for f in range(3):
        A = (q[f] * D1[f])[..., None] * X[f]
        H = np.einsum("tbk,tb,tbj->kj", A.conj(), W[f], A).real + np.diag(1.0 / var[f])
        b = np.einsum("tbk,tb->k", A.conj(), W[f] * np.asarray(system.data)[f]).real + a0[f] / var[f]
        mean, cov = np.linalg.solve(H, b), np.linalg.inv(H)
        dr = np.asarray(draws)[:, f]
        z = (dr.mean(0) - mean) / np.sqrt(np.diag(cov) / 3000)
        assert np.all(np.abs(z) < 4.5), z
        np.testing.assert_allclose(dr.var(0), np.diag(cov), rtol=0.12)  # 4.6 sigma of sqrt(2 / 3000)


# ---------------------------------------------------------------- SBC of the joint (sky, gains, scale) kernel


@functools.lru_cache(maxsize=None)
def _sbc_problem():
    """4 antennas (6 rows), 1 channel at 100 MHz, 4 LSTs over 1.5 rad, lmax 2, nside 8; noise 10 % of the
    prior's rms visibility; gains on 1 x 2 modes (P = 13), prior 5 %; the scale's prior N(1, 0.1^2)."""
    pos = np.array([[0.0, 0.0, 0.0], [14.6, 0.0, 0.0], [7.3, 12.6, 0.0], [21.9, 12.6, 0.0]])
    arr = make_array(pos, HERA_LATITUDE_DEG, gaussian_beam(14.0))
    lmax, nt = 2, 4
    prior = isotropic_prior((50.0 / (1.0 + np.arange(lmax + 1)) ** 2)[None], (lmax + 1) ** 2)
    prob = build_problem(arr, [100e6], np.linspace(0.0, 1.5, nt), lmax, 8, a_true=np.zeros((1, 9)), sigma=1.0,
                         prior=prior, key=jax.random.PRNGKey(0))
    system = prob.system()
    rms = float(jnp.sqrt(jnp.mean(jnp.abs(apply(system.op, np.asarray(prior.inv_var) ** -0.5)) ** 2)))
    sigma = 0.1 * rms
    system = system._replace(inv_noise=jnp.full(system.data.shape, sigma**-2))
    model = gain_model(prob.antpairs, 1, nt, (1, 2))
    return system, model, sigma


@functools.partial(jax.jit, static_argnames=("n_draws", "thin", "burn"))
def _sbc_ranks(keys, system, sigma, truth_block, sampler_block, n_draws, thin, burn=50):
    """Ranks (M, 5) of the truth among thinned draws of the joint chain (collapsed sweep), one replicate per
    key: truth (a, theta, s) from the priors of ``truth_block``, data from the linear model, the chain from
    the prior mean under ``sampler_block``.  Functionals: s_0, theta_0, theta_-1, a_0, a_4."""
    prior, model = system.prior, truth_block.model
    P = truth_block.prior_inv_var.shape[0]

    def replicate(key):
        ka, kt, ks, kn, kc = jax.random.split(key, 5)
        a = prior.mean + jax.random.normal(ka, prior.mean.shape) / jnp.sqrt(prior.inv_var)
        th = jax.random.normal(kt, (P,)) / jnp.sqrt(truth_block.prior_inv_var)
        s = truth_block.scale_mean + jax.random.normal(ks, (1,)) / jnp.sqrt(truth_block.scale_inv_var)
        d = gain_factor(model, th, s) * apply(system.op, a)
        d = d + sigma * (jax.random.normal(kn, d.shape) + 1j * jax.random.normal(jax.random.fold_in(kn, 1), d.shape))
        fixed = gibbs_setup(system._replace(data=d))

        def body(c, k):
            c, _ = joint_gain_step(k, c, fixed, sampler_block, collapsed=True, gauge_moves=8)
            return c, (c.sky, c.theta, c.scale)

        _, (sk, tt, ss) = jax.lax.scan(body, gain_init(prior.mean, sampler_block), jax.random.split(kc, burn + n_draws * thin))
        sk, tt, ss = (x[burn::thin][:n_draws] for x in (sk, tt, ss))
        f_true = jnp.array([s[0], th[0], th[P - 1], a[0, 0], a[0, 4]])
        f_draw = jnp.stack([ss[:, 0], tt[:, 0], tt[:, P - 1], sk[:, 0, 0], sk[:, 0, 4]], axis=1)
        return jnp.sum(f_draw < f_true, axis=0)

    return jax.vmap(replicate)(keys)


def test_sbc_of_the_joint_kernel_and_a_mis_specified_gain_prior_fails():
    """SBC (Talts et al. 2018; :func:`gcrsky.checks.sbc.rank_pvalues`: exact KS, dispersion and bias tests,
    Bonferroni over 5 functionals) of 200 replicates, 19 draws each thinned by 3 after 50 sweeps: the family
    p-value must exceed 0.01 (a false alarm at most 1 % of seeds; this seed's is fixed).  The control samples
    with a gain prior 4x too narrow (the truths drawn with 5 %): its family p-value must fall below 1e-3."""
    from gcrsky.checks.sbc import rank_pvalues

    system, model, sigma = _sbc_problem()
    block = gain_setup(model, sigma=0.05, scale_mean=1.0, scale_sd=0.1)
    keys = jax.random.split(jax.random.PRNGKey(5), 200)
    good = rank_pvalues(np.asarray(_sbc_ranks(keys, system, sigma, block, block, n_draws=19, thin=3)), 19)
    assert good["p_family"] > 0.01, good
    narrow = gain_setup(model, sigma=0.0125, scale_mean=1.0, scale_sd=0.1)
    bad = rank_pvalues(np.asarray(_sbc_ranks(keys, system, sigma, block, narrow, n_draws=19, thin=3)), 19)
    assert bad["p_family"] < 1e-3, bad


def test_unit_gains_recentre_and_a_calfits_pyuvdata_reads_back(tmp_path):
    """``g_i conj(g_j)`` of :func:`unit_gains` is the exact model's factor, and :func:`recentre` moves the
    linearisation point to it (rounding); the posterior-mean gains
    written as calfits and calh5 read back by pyuvdata (``gain_convention`` divide, both feeds of a pI unit)."""
    from pyuvdata import UVCal

    from gcrsky.ingest.gaincal import posterior_mean_gains
    from gcrsky.io.gaincal import write_gain_calibration
    from gcrsky.model.gains import unit_gains

    rng = np.random.default_rng(9)
    model = gain_model(antpairs(4), 3, 2, (2, 1))
    th = 0.05 * rng.standard_normal((5, n_gain_params(model)))
    s = 1.0 + 0.1 * rng.standard_normal((5, 2))
    gbar = np.exp(0.2j * rng.standard_normal((3, 2, 4)))
    g = unit_gains(model, th[0], s[0], gbar)
    i, j = model.unit_pairs[:, 0], model.unit_pairs[:, 1]
    np.testing.assert_allclose(g[..., i] * np.conj(g[..., j]), gain_factor(model, th[0], s[0], gbar, exact=True),
                               atol=1e-14)
    # re-centring moves the linearisation point to these gains exactly, the prior's centre to -theta
    block = gain_setup(model, sigma=0.05, gbar=gbar)
    moved, st = recentre(block, gain_init(jnp.zeros((3, 4)), block, theta=th[0]))
    np.testing.assert_allclose(gain_factor(model, st.theta, s[0]) * moved.pair_gains,
                               gain_factor(model, th[0], s[0], gbar, exact=True), atol=1e-14)
    np.testing.assert_allclose(moved.prior_mean, -th[0])
    mean = posterior_mean_gains(model, th, s, gbar)
    np.testing.assert_allclose(mean, np.mean([unit_gains(model, t, q, gbar) for t, q in zip(th, s)], axis=0), atol=1e-14)
    site = dict(latitude_deg=HERA_LATITUDE_DEG, longitude_deg=21.428, altitude_m=1051.7)
    for name in ("gains.calfits", "gains.calh5"):
        path = write_gain_calibration(tmp_path / name, mean, model, antenna_numbers=[10, 11, 12, 13],
                                      antenna_names=["A10", "A11", "A12", "A13"], antpos_enu_m=hex_array((2, 2)),
                                      freqs_hz=[100e6, 101e6, 102e6], times_jd=[2459000.1, 2459000.2], **site)
        cal = UVCal.from_file(str(path))
        assert cal.gain_convention == "divide" and list(cal.ant_array) == [10, 11, 12, 13]
        for feed in range(2):
            np.testing.assert_allclose(cal.gain_array[:, :, :, feed], np.moveaxis(mean, 2, 0), rtol=1e-12)
        assert not cal.flag_array.any()
    with pytest.raises(ValueError, match="exists"):
        write_gain_calibration(tmp_path / "gains.calfits", mean, model, antenna_numbers=[10, 11, 12, 13],
                               antenna_names=["A10", "A11", "A12", "A13"], antpos_enu_m=hex_array((2, 2)),
                               freqs_hz=[100e6, 101e6, 102e6], times_jd=[2459000.1, 2459000.2], **site)
