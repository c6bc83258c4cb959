"""Frequency-coupled priors and the exact joint samplers over channels (issue 25, items 1-2).

The problem: the shared 10-antenna hexagon (``small_array``), 12 of its baselines, lmax 6
(n = 49), 4 channels 100-112 MHz (log spacing ~0.039), 16 equally spaced angles over the full
day (Nt = 16 > 2 lmax, so the m-mode path applies), noise sigma 2e-3 (the data constrain the
low modes well and leave the high ones to the prior, so the coupling matters).  The
references are plain NumPy: the explicit realified operator of every channel, the joint
precision ``blockdiag(X^T W X) + kron(R^-1, diag(c)^-1)``, and the Gaussian marginal
likelihood ``N(d; X a0, N + X S X^T)`` by ``slogdet``.

Tolerances: the Wiener filters are compared in units of the posterior sigma (1e-8; the joint
precision's condition number here is ~6e3, and float64 solves agree to ~3e-13 sigma, measured),
the evidence relatively (1e-8; measured ~1e-14 against the reference's ``slogdet`` of the
1536-square data covariance).  The draws' tests are chi-square tests with a stated false-alarm
rate (the negative control's mean squared whitened residual is ~8.5, not 1).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _joint_fixtures import CL, FREQS, LMAX, NT, NU0, N, simulate_joint
from scipy import stats

from gcrsky.inference.evidence import log_evidence
from gcrsky.instrument import antpairs, response_matrix
from gcrsky.model.operator import VisOperator, apply
from gcrsky.model.prior import Prior, isotropic_prior
from gcrsky.model.spectral import (
    frequency_prior,
    log_frequency_kernel,
    log_polynomial_basis,
    mode_variance,
    spectral_basis_cov,
)
from gcrsky.model.system import LinearSystem
from gcrsky.solvers.dense import draw_cholesky, prepare_cholesky
from gcrsky.solvers.joint import (
    JointSystem,
    draw_joint_dense,
    draw_joint_mmode,
    joint_log_evidence_dense,
    joint_log_evidence_mmode,
    joint_precision_matrix,
    prepare_joint_dense,
    prepare_joint_mmode,
)
from gcrsky.solvers.options import MModeOptions

HYPER = dict(amplitude=1.2, beta=-2.5, xi=0.06)  # A, beta, xi (log-frequency correlation length)
NUGGET = 1e-2


@pytest.fixture(scope="module")
def op(small_array):
    pairs = antpairs(small_array.positions_enu_m.shape[0])[:12]
    resp = response_matrix(small_array, pairs, FREQS, LMAX, 32)
    return VisOperator(resp, jnp.asarray(2 * np.pi * np.arange(NT) / NT + 0.1))


def _prior(amplitude=HYPER["amplitude"], beta=HYPER["beta"], xi=HYPER["xi"], nugget=NUGGET, mean=None):
    return frequency_prior(CL, log_frequency_kernel(FREQS, NU0, amplitude, beta, xi, nugget=nugget), mean)


def _system(op, prior, seed=3, flagged=()):
    """Data simulated from ``prior`` (truth drawn from the joint prior), channels ``flagged`` weight 0."""
    return simulate_joint(op, prior, seed, flagged=flagged)


def _mean(seed=11):
    return 0.05 * np.random.default_rng(seed).standard_normal((FREQS.size, N))


class Reference:
    """Plain NumPy joint posterior and evidence of a JointSystem."""

    def __init__(self, system: JointSystem):
        op = system.op
        nf = FREQS.size
        basis = np.zeros((N, nf, N))
        for k in range(N):
            basis[k, :, k] = 1.0
        cols = np.asarray(jax.vmap(lambda a: apply(op, a))(jnp.asarray(basis)))  # (n, Nf, Nt, Nbl)
        w = np.asarray(system.inv_noise).reshape(nf, -1)
        d = np.asarray(system.data).reshape(nf, -1)
        R, c = np.asarray(system.prior.freq_cov), np.asarray(system.prior.mode_var)
        a0 = np.asarray(system.prior.mean).reshape(-1)
        Q = np.kron(np.linalg.inv(R), np.diag(1.0 / c))
        P, b, xs, ds, ws = Q.copy(), Q @ a0, [], [], []
        for f in range(nf):
            cf = cols[:, f].reshape(N, -1).T  # (Nt Nbl, n) complex
            X = np.concatenate([cf.real, cf.imag])  # realified (2 Nt Nbl, n)
            wf = np.concatenate([w[f], w[f]])
            df = np.concatenate([d[f].real, d[f].imag])
            sl = slice(f * N, (f + 1) * N)
            P[sl, sl] += X.T @ (wf[:, None] * X)
            b[sl] += X.T @ (wf * df)
            keep = wf > 0
            xs.append(X[keep]), ds.append(df[keep]), ws.append(wf[keep])
        self.P = P
        self.cov = np.linalg.inv(P)
        self.a_wf = np.linalg.solve(P, b).reshape(nf, N)
        self.sigma = np.sqrt(np.diag(self.cov)).reshape(nf, N)
        # the evidence: d ~ N(X a0, N + X S X^T) over the kept samples of all channels
        Xall = np.zeros((sum(x.shape[0] for x in xs), nf * N))
        row = 0
        for f, x in enumerate(xs):
            Xall[row:row + x.shape[0], f * N:(f + 1) * N] = x
            row += x.shape[0]
        C = np.diag(1.0 / np.concatenate(ws)) + Xall @ np.kron(R, np.diag(c)) @ Xall.T
        r = np.concatenate(ds) - Xall @ a0
        _, logdet = np.linalg.slogdet(C)
        self.log_evidence = -0.5 * (r @ np.linalg.solve(C, r) + logdet + r.size * np.log(2 * np.pi))


@pytest.fixture(scope="module")
def coupled(op):
    system = _system(op, _prior(mean=_mean()))
    return system, Reference(system), prepare_joint_dense(system), prepare_joint_mmode(system)


@pytest.fixture(scope="module")
def flagged(op):
    system = _system(op, _prior(mean=_mean()), seed=5, flagged=(2,))
    return system, Reference(system), prepare_joint_dense(system), prepare_joint_mmode(system)


# ---------------------------------------------------------------- the prior


def test_kernel_is_the_formula_and_spd():
    R = np.asarray(log_frequency_kernel(FREQS, NU0, 1.2, -2.5, 0.06, nugget=NUGGET))
    x = np.log(FREQS / NU0)
    want = 1.2 * np.exp(-2.5 * (x[:, None] + x[None, :]) - (x[:, None] - x[None, :]) ** 2 / (2 * 0.06**2))
    want += NUGGET * np.diag(np.diag(want))
    np.testing.assert_allclose(R, want, rtol=1e-14)
    assert np.all(np.linalg.eigvalsh(R) > 0)
    np.testing.assert_allclose(np.asarray(mode_variance(CL)), 1.0 / np.asarray(isotropic_prior(CL[None], N).inv_var[0]),
                               rtol=1e-15)


def test_spectral_basis_is_rank_k_plus_nugget():
    p = np.array([1.0, 0.3, 0.05])
    F = np.asarray(log_polynomial_basis(FREQS, NU0, -2.5, 3))
    x = np.log(FREQS / NU0)
    np.testing.assert_allclose(F[:, 2], (FREQS / NU0) ** -2.5 * x**2, rtol=1e-14)
    R0 = np.asarray(spectral_basis_cov(FREQS, NU0, -2.5, p, nugget=0.0))
    assert np.linalg.matrix_rank(R0, tol=1e-12 * np.abs(R0).max()) == 3  # K < Nf: no proper prior alone
    R = np.asarray(spectral_basis_cov(FREQS, NU0, -2.5, p, nugget=1e-3))
    assert np.linalg.eigvalsh(R).min() > 0
    np.testing.assert_allclose(R, R0 + 1e-3 * np.diag(np.diag(R0)), rtol=1e-14)


# ---------------------------------------------------------------- dense and m-mode against NumPy


@pytest.mark.parametrize("case", ["coupled", "flagged"])
def test_joint_dense_and_mmode_equal_numpy(case, request):
    system, ref, dense, mm = request.getfixturevalue(case)
    mm2 = prepare_joint_mmode(system, MModeOptions(bucket=2))  # 4 buckets, each with padding (m = 0, 2, 4, 6)
    assert len(mm2.chol) == 4 and len(mm.chol) == 1
    for state in (dense, mm, mm2):
        err = np.abs(np.asarray(state.a_wf) - ref.a_wf) / ref.sigma
        assert err.max() < 1e-8, err.max()
    np.testing.assert_allclose(np.asarray(joint_precision_matrix(system)), ref.P, rtol=1e-9,
                               atol=1e-11 * np.abs(ref.P).max())
    key = jax.random.PRNGKey(4)
    d1, d2 = np.asarray(draw_joint_dense(key, dense, 3)), np.asarray(draw_joint_mmode(key, mm2, 3))
    np.testing.assert_allclose(d2, d1, atol=1e-10 * np.abs(d1).max())  # same noise, same posterior
    for ev in (joint_log_evidence_dense(dense), joint_log_evidence_mmode(mm), joint_log_evidence_mmode(mm2)):
        assert abs(float(ev) - ref.log_evidence) < 1e-8 * abs(ref.log_evidence), (float(ev), ref.log_evidence)


def test_bad_inputs_are_refused_naming_them(op):
    system = _system(op, _prior())
    R = np.asarray(system.prior.freq_cov)
    rank3 = spectral_basis_cov(FREQS, NU0, -2.5, np.array([1.0, 0.3, 0.05]), nugget=0.0)
    for bad, match in ((system.prior._replace(freq_cov=R[:3, :3]), "freq_cov has shape"),
                       (system.prior._replace(freq_cov=R + np.triu(R, 1)), "symmetric"),
                       (system.prior._replace(freq_cov=rank3 - 1e-6 * np.eye(4)), "nugget"),
                       (system.prior._replace(mode_var=-system.prior.mode_var), "mode_var")):
        for prepare in (prepare_joint_dense, prepare_joint_mmode):
            with pytest.raises(ValueError, match=match):
                prepare(system._replace(prior=bad))


def test_mmode_refuses_partial_coverage(op):
    system = _system(op, _prior())
    part = system._replace(op=system.op._replace(angles=system.op.angles[:10]), data=system.data[:, :10],
                           inv_noise=system.inv_noise[:, :10])
    with pytest.raises(ValueError, match="m-mode"):
        prepare_joint_mmode(part)


# ---------------------------------------------------------------- draws


NDRAWS = 300
ALPHA = 1e-3  # false-alarm rate of each chi-square test


def _chi2_pvalues(z):
    """Two chi-square tests of whitened draws z (ndraws, N') ~ N(0, I): the sum of squares over all
    (dof ndraws N') and the sample mean (sqrt(ndraws) mean ~ N(0, I), dof N').  Two-sided p-values."""
    nd, dim = z.shape
    s, m = np.sum(z**2), nd * np.sum(z.mean(axis=0) ** 2)
    p1 = stats.chi2.cdf(s, nd * dim)
    p2 = stats.chi2.cdf(m, dim)
    return 2 * min(p1, 1 - p1), 2 * min(p2, 1 - p2)


def test_draws_whitened_chi_square(coupled, getkey):
    system, ref, dense, mm = coupled
    L = np.linalg.cholesky(ref.P)
    key = getkey()
    dd = np.asarray(draw_joint_dense(key, dense, NDRAWS)).reshape(NDRAWS, -1)
    dm = np.asarray(draw_joint_mmode(key, mm, NDRAWS)).reshape(NDRAWS, -1)
    np.testing.assert_allclose(dm, dd, atol=1e-10 * np.abs(dd).max())  # same noise, same exact posterior
    z = (dd - ref.a_wf.reshape(-1)) @ L  # rows: L^T (a - a_wf)
    assert min(_chi2_pvalues(z)) > ALPHA, _chi2_pvalues(z)

    # negative control: the independent-channel posterior (same per-channel prior variances c R_ff, no
    # coupling) must fail the same test
    R = np.asarray(system.prior.freq_cov)
    ind = LinearSystem(system.op, system.data, system.inv_noise,
                       Prior(system.prior.mean, 1.0 / (np.diag(R)[:, None] * np.asarray(system.prior.mode_var)[None])))
    st = prepare_cholesky(ind)
    di, _ = draw_cholesky(getkey(), st, NDRAWS)
    zi = (np.asarray(di).transpose(1, 0, 2).reshape(NDRAWS, -1) - ref.a_wf.reshape(-1)) @ L
    assert max(_chi2_pvalues(zi)) < ALPHA, _chi2_pvalues(zi)


# ---------------------------------------------------------------- gradients


def test_evidence_gradient_matches_finite_differences(op):
    system = _system(op, _prior(mean=_mean()))
    theta0 = np.array([HYPER["amplitude"], HYPER["beta"], HYPER["xi"]])

    def ev(theta, path):
        s = system._replace(prior=_prior(*theta, mean=system.prior.mean))
        return joint_log_evidence_dense(s) if path == "dense" else joint_log_evidence_mmode(s, check=False)

    for path in ("dense", "mmode"):
        g = np.asarray(jax.jit(jax.grad(lambda t, p=path: ev(t, p)))(jnp.asarray(theta0)))
        f = jax.jit(lambda t, p=path: ev(t, p))
        fd = np.zeros(3)
        for i in range(3):
            h = 1e-5 * abs(theta0[i])
            e = np.zeros(3)
            e[i] = h
            fd[i] = (float(f(jnp.asarray(theta0 + e))) - float(f(jnp.asarray(theta0 - e)))) / (2 * h)
        # central differences: truncation ~h^2 f''' and rounding ~eps |f| / h ~ 1e-6 here
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-4)


def test_spectral_basis_evidence_gradient(op):
    system = _system(op, _prior())

    def ev(t):
        R = spectral_basis_cov(FREQS, NU0, t[0], t[1:], nugget=1e-2)
        return joint_log_evidence_dense(system._replace(prior=frequency_prior(CL, R)))

    t0 = np.array([-2.5, 1.0, 0.3, 0.05])
    g = np.asarray(jax.grad(ev)(jnp.asarray(t0)))
    fd = np.zeros(t0.size)
    for i in range(t0.size):
        e = np.zeros(t0.size)
        e[i] = 1e-5 * abs(t0[i])
        fd[i] = (float(ev(jnp.asarray(t0 + e))) - float(ev(jnp.asarray(t0 - e)))) / (2 * e[i])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-4)


# ---------------------------------------------------------------- controls


def test_no_coupling_equals_independent_channels(op):
    """xi far below the channels' log spacing (>= 0.036): R's off-diagonal is < exp(-(0.036/1e-3)^2 / 2) ~ 1e-281,
    and the joint posterior and evidence are those of independent channels with variances c R_ff."""
    prior = _prior(xi=1e-3, mean=_mean())
    system = _system(op, prior, seed=7)
    R = np.asarray(prior.freq_cov)
    assert np.abs(R - np.diag(np.diag(R))).max() < 1e-250
    ind = LinearSystem(system.op, system.data, system.inv_noise,
                       Prior(prior.mean, 1.0 / (np.diag(R)[:, None] * np.asarray(prior.mode_var)[None])))
    st = prepare_cholesky(ind)
    ref = Reference(system)
    for state in (prepare_joint_dense(system), prepare_joint_mmode(system)):
        assert (np.abs(np.asarray(state.a_wf) - np.asarray(st.a_wf)) / ref.sigma).max() < 1e-8
    want = float(np.sum(np.asarray(log_evidence(ind, method="cholesky"))))
    for ev in (joint_log_evidence_dense(system), joint_log_evidence_mmode(system)):
        assert abs(float(ev) - want) < 1e-8 * abs(want)


def test_flagged_channel_is_inpainted_through_r(flagged):
    system, ref, dense, mm = flagged
    f = 2
    prior = system.prior
    prior_sd = np.sqrt(np.asarray(prior.freq_cov)[f, f] * np.asarray(prior.mode_var))
    shift = np.abs(np.asarray(dense.a_wf)[f] - np.asarray(prior.mean)[f]) / prior_sd
    assert shift.max() > 0.1  # the neighbours' data move it (by ~prior sigmas at low l)
    assert np.all(ref.sigma[f] < prior_sd)  # and shrink its variance, every mode
    assert np.median(ref.sigma[f] / prior_sd) < 0.9

    # the independent model: the flagged channel is prior-only
    R = np.asarray(prior.freq_cov)
    ind = LinearSystem(system.op, system.data, system.inv_noise,
                       Prior(prior.mean, 1.0 / (np.diag(R)[:, None] * np.asarray(prior.mode_var)[None])))
    st = prepare_cholesky(ind)
    np.testing.assert_allclose(np.asarray(st.a_wf)[f], np.asarray(prior.mean)[f], rtol=0, atol=1e-14)
    Pf = np.asarray(st.precision)[f]
    np.testing.assert_allclose(np.sqrt(np.diag(np.linalg.inv(Pf))), prior_sd, rtol=1e-10)
