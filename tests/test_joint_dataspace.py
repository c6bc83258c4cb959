"""The joint data-space paths over channels (issue 25, item 2): dense and per m.

The problem (as tests/test_joint_frequency.py): the shared 10-antenna hexagon (``small_array``), 12 of
its baselines, lmax 6 (n = 49), 4 channels 100-112 MHz, a log-frequency kernel prior with xi = 0.06
(the channels strongly coupled), noise sigma 2e-3.  Two systems:

* partial coverage (10 of 16 angles over the day) with channel 2 fully flagged and ~10 % of the other
  samples flagged at random: the dense data-space path (the per-m path must refuse it);
* full-day coverage (16 equally spaced angles, Nt > 2 lmax) with channel 1 fully flagged: both paths.

References: plain NumPy (the explicit realified operator of every channel, the joint precision
``blockdiag(X^T W X) + kron(R^-1, diag(c)^-1)``, and ``N(d; X a0, N + X S X^T)`` by ``slogdet``), and the
a-space joint paths of :mod:`gcrsky.solvers.joint`.  Tolerances: Wiener filters 1e-8 posterior sigma
(measured 1e-13: the a-space joint precision's condition number is ~6e3, the partial system's D's ~2e2),
evidence 1e-8 relative (measured 1e-14), gradients against central differences rtol 1e-5 (measured
<= 1.2e-7).  Draws: chi-square tests of the whitened draws, false-alarm rate ALPHA each, and a negative
control (the same sampler with the coupling dropped, ``R -> diag(R)``) that must fail (measured p = 0.0
on both tests and both paths; the true samplers' p-values were 0.56 / 0.70 and 0.21 / 0.09).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _joint_fixtures import CL, FREQS, LMAX, NT, NU0, N, simulate_joint
from scipy import stats

from gcrsky.instrument import antpairs, response_matrix
from gcrsky.model.operator import VisOperator, apply
from gcrsky.model.spectral import frequency_prior, log_frequency_kernel
from gcrsky.solvers.joint import JointSystem, joint_log_evidence_dense, prepare_joint_dense
from gcrsky.solvers.joint_dataspace import (
    draw_joint_dataspace,
    draw_joint_dataspace_mmode,
    joint_dataspace_log_evidence,
    joint_dataspace_log_evidence_mmode,
    joint_dataspace_matrix,
    prepare_joint_dataspace,
    prepare_joint_dataspace_mmode,
)

NT_PART = 10
HYPER = (1.2, -2.5, 0.06)  # A, beta, xi
NUGGET = 1e-2


def _prior(theta=HYPER, mean=None, coupled=True):
    R = log_frequency_kernel(FREQS, NU0, *theta, nugget=NUGGET)
    if not coupled:
        R = jnp.diag(jnp.diag(R))
    return frequency_prior(CL, R, mean)


def _system(op, prior, seed, flag_channel, flag_fraction=0.0):
    """Data drawn from ``prior``; channel ``flag_channel`` weight 0, a fraction of other samples too."""
    return simulate_joint(op, prior, seed, flagged=(flag_channel,), flag_fraction=flag_fraction)


class Reference:
    """Plain NumPy joint posterior and evidence of a JointSystem."""

    def __init__(self, system: JointSystem):
        nf = FREQS.size
        basis = np.zeros((N, nf, N))
        for k in range(N):
            basis[k, :, k] = 1.0
        cols = np.asarray(jax.vmap(lambda a: apply(system.op, a))(jnp.asarray(basis)))  # (n, Nf, Nt, Nbl)
        w = np.asarray(system.inv_noise).reshape(nf, -1)
        d = np.asarray(system.data).reshape(nf, -1)
        R, c = np.asarray(system.prior.freq_cov), np.asarray(system.prior.mode_var)
        a0 = np.asarray(system.prior.mean).reshape(-1)
        P = np.kron(np.linalg.inv(R), np.diag(1.0 / c))
        b = P @ a0
        Xall, ds, ws = [], [], []
        for f in range(nf):
            cf = cols[:, f].reshape(N, -1).T
            X = np.concatenate([cf.real, cf.imag])
            wf, df = np.concatenate([w[f], w[f]]), np.concatenate([d[f].real, d[f].imag])
            sl = slice(f * N, (f + 1) * N)
            P[sl, sl] += X.T @ (wf[:, None] * X)
            b[sl] += X.T @ (wf * df)
            keep = wf > 0
            Xf = np.zeros((keep.sum(), nf * N))
            Xf[:, sl] = X[keep]
            Xall.append(Xf), ds.append(df[keep]), ws.append(wf[keep])
        self.P = P
        self.a_wf = np.linalg.solve(P, b).reshape(nf, N)
        self.sigma = np.sqrt(np.diag(np.linalg.inv(P))).reshape(nf, N)
        X = np.concatenate(Xall)
        C = np.diag(1.0 / np.concatenate(ws)) + X @ np.kron(R, np.diag(c)) @ X.T
        r = np.concatenate(ds) - X @ a0
        self.log_evidence = -0.5 * (r @ np.linalg.solve(C, r) + np.linalg.slogdet(C)[1] + r.size * np.log(2 * np.pi))


@pytest.fixture(scope="module")
def op(small_array):
    pairs = antpairs(small_array.positions_enu_m.shape[0])[:12]
    resp = response_matrix(small_array, pairs, FREQS, LMAX, 32)
    return VisOperator(resp, jnp.asarray(2 * np.pi * np.arange(NT) / NT + 0.1))


@pytest.fixture(scope="module")
def mean():
    return 0.05 * np.random.default_rng(11).standard_normal((FREQS.size, N))


@pytest.fixture(scope="module")
def partial(op, mean):
    part = op._replace(angles=op.angles[:NT_PART])
    system = _system(part, _prior(mean=mean), seed=3, flag_channel=2, flag_fraction=0.1)
    return system, Reference(system), prepare_joint_dataspace(system)


@pytest.fixture(scope="module")
def fullday(op, mean):
    system = _system(op, _prior(mean=mean), seed=5, flag_channel=1)
    return system, Reference(system), prepare_joint_dataspace(system), prepare_joint_dataspace_mmode(system)


def _sigma_err(a, ref):
    return (np.abs(np.asarray(a) - ref.a_wf) / ref.sigma).max()


def _rel(ev, ref):
    return abs(float(ev) - ref.log_evidence) / abs(ref.log_evidence)


def test_dense_equals_numpy_and_a_space_partial_flagged(partial):
    system, ref, st = partial
    nd = 2 * NT_PART * 12
    D = np.asarray(st.gram)
    np.testing.assert_array_equal(D, np.asarray(joint_dataspace_matrix(system)))
    assert D.shape == (FREQS.size * nd,) * 2
    w = np.asarray(system.inv_noise)
    rows = np.stack([w, w], axis=-2).reshape(-1)  # the row layout: t 2 Nbl + p Nbl + b, channel-major
    flagged = np.flatnonzero(rows == 0)  # flagged rows are identity rows, decoupled
    assert flagged.size > nd  # channel 2 and some samples of the others
    assert np.array_equal(D[flagged], np.eye(D.shape[0])[flagged])
    a_space = prepare_joint_dense(system)
    assert _sigma_err(st.a_wf, ref) < 1e-8 and _sigma_err(a_space.a_wf, ref) < 1e-8
    assert (np.abs(np.asarray(st.a_wf) - np.asarray(a_space.a_wf)) / ref.sigma).max() < 1e-8
    assert _rel(joint_dataspace_log_evidence(st), ref) < 1e-8
    assert _rel(joint_log_evidence_dense(a_space), ref) < 1e-8
    # the fully flagged channel is inpainted through R: the neighbours' data move it off the prior mean
    prior_sd = np.sqrt(np.asarray(system.prior.freq_cov)[2, 2] * np.asarray(system.prior.mode_var))
    assert (np.abs(np.asarray(st.a_wf)[2] - np.asarray(system.prior.mean)[2]) / prior_sd).max() > 0.1


def test_per_m_and_dense_equal_numpy_fullday(fullday):
    system, ref, st, sm = fullday
    assert sm.chol.shape == (LMAX + 1, FREQS.size * 4 * 12, FREQS.size * 4 * 12)
    for a in (st.a_wf, sm.a_wf):
        assert _sigma_err(a, ref) < 1e-8, _sigma_err(a, ref)
    for ev in (joint_dataspace_log_evidence(st), joint_dataspace_log_evidence_mmode(sm)):
        assert _rel(ev, ref) < 1e-8, (float(ev), ref.log_evidence)
    # log det D is the same on both data-space paths (the per-m blocks hold all of it)
    ld_dense = 2 * np.sum(np.log(np.diag(np.asarray(st.chol))))
    ld_m = 2 * np.sum(np.log(np.diagonal(np.asarray(sm.chol), axis1=-2, axis2=-1)))
    assert abs(ld_dense - ld_m) < 1e-9 * abs(ld_dense)


def test_per_m_refuses_partial_coverage_and_flags(partial, fullday):
    with pytest.raises(ValueError, match="per-m joint data-space path .*coverage is not uniform"):
        prepare_joint_dataspace_mmode(partial[0])
    system = fullday[0]
    w = np.asarray(system.inv_noise).copy()
    w[0, 3, 2] = 0.0  # one flagged sample: the noise is no longer constant in time
    with pytest.raises(ValueError, match="per-m joint data-space path .*inverse noise varies in time"):
        prepare_joint_dataspace_mmode(system._replace(inv_noise=jnp.asarray(w)))
    bad = system.prior._replace(mode_var=-system.prior.mode_var)
    for prepare in (prepare_joint_dataspace, prepare_joint_dataspace_mmode):
        with pytest.raises(ValueError, match="mode_var"):
            prepare(system._replace(prior=bad))
        with pytest.raises(MemoryError, match="joint data space .* needs"):  # D is 1536 (dense) or 192 square
            prepare(system, memory_budget=1e5)


NDRAWS = 300
ALPHA = 1e-3  # false-alarm rate of each chi-square test


def _pvalues(draws, ref):
    """Two-sided p-values of two chi-square tests of the whitened draws ``L^T (a - a_wf)`` (P = L L^T):
    the sum of squares (dof NDRAWS n Nf) and the sample mean (sqrt(ndraws) mean ~ N(0, I), dof n Nf)."""
    z = (np.asarray(draws).reshape(NDRAWS, -1) - ref.a_wf.reshape(-1)) @ np.linalg.cholesky(ref.P)
    nd, dim = z.shape
    p1 = stats.chi2.cdf(np.sum(z**2), nd * dim)
    p2 = stats.chi2.cdf(nd * np.sum(z.mean(axis=0) ** 2), dim)
    return 2 * min(p1, 1 - p1), 2 * min(p2, 1 - p2)


def test_draws_whitened_chi_square_and_negative_control(partial, fullday, getkey):
    system, ref, st = partial
    assert min(_pvalues(draw_joint_dataspace(getkey(), st, NDRAWS), ref)) > ALPHA
    fsys, fref, _, sm = fullday
    assert min(_pvalues(draw_joint_dataspace_mmode(getkey(), sm, NDRAWS), fref)) > ALPHA
    # negative control: the same sampler with the channels decoupled (R -> diag R): its draws scatter
    # about their own Wiener filter with the wrong covariance, and the whitened test must fail
    # (measured p-values 0.0 in float64 on both tests, for both paths)
    unc = _prior(mean=system.prior.mean, coupled=False)
    st0 = prepare_joint_dataspace(system._replace(prior=unc))
    assert max(_pvalues(draw_joint_dataspace(getkey(), st0, NDRAWS), ref)) < ALPHA
    sm0 = prepare_joint_dataspace_mmode(fsys._replace(prior=unc))
    assert max(_pvalues(draw_joint_dataspace_mmode(getkey(), sm0, NDRAWS), fref)) < ALPHA


def test_evidence_gradient_matches_finite_differences(partial, fullday):
    theta0 = np.array(HYPER)
    for system, ev in ((partial[0], joint_dataspace_log_evidence), (fullday[0], joint_dataspace_log_evidence_mmode)):
        vg = jax.jit(jax.value_and_grad(lambda t, s=system, e=ev: e(s._replace(prior=_prior(t, mean=s.prior.mean)),
                                                                       check=False)))  # one compile per path
        g = np.asarray(vg(jnp.asarray(theta0))[1])
        fd = np.zeros(3)
        for i in range(3):
            e = np.zeros(3)
            e[i] = 1e-5 * abs(theta0[i])
            fd[i] = (float(vg(jnp.asarray(theta0 + e))[0]) - float(vg(jnp.asarray(theta0 - e))[0])) / (2 * e[i])
        # central differences: truncation ~h^2 f''' and rounding ~eps |f| / h ~ 1e-6 here
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-4)
