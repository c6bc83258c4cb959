"""The joint CG over channels (gcrsky.solvers.joint_cg) against the exact dense joint path.

The problem of tests/test_joint_frequency.py: the 10-antenna hexagon, 12 baselines, lmax 6 (n = 49),
4 channels 100-112 MHz with the log-frequency kernel, noise sigma 2e-3, channel 2 flagged; partial
coverage = 16 equally spaced angles over a third of the day (8 h), full day = 16 angles over 2 pi.
The reference is :func:`gcrsky.solvers.joint.prepare_joint_dense` / ``draw_joint_dense`` (itself
checked against plain NumPy in test_joint_frequency.py), with the same key, so the right-hand sides
match; errors are in units of the dense path's posterior sigma (from its Cholesky factor).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _joint_fixtures import CL, FREQS, LMAX, NT, NU0, N, simulate_joint

from gcrsky.instrument import antpairs, response_matrix
from gcrsky.model.operator import VisOperator
from gcrsky.model.spectral import frequency_prior, log_frequency_kernel
from gcrsky.solvers.info import Result
from gcrsky.solvers.joint import draw_joint_dense, prepare_joint_dense
from gcrsky.solvers.joint_cg import (
    JointCGOptions,
    JointModePreconditioner,
    draw_joint_cg,
    joint_matvec,
    joint_precondition,
    joint_preconditioner,
    prepare_joint_cg,
    wiener_joint_cg,
)

HYPER = (1.2, -2.5, 0.06)  # amplitude, beta, xi
TOL = 1e-10  # CG's bound on the error's P-norm: every mode's error <= 1e-10 posterior sigma
NDRAWS = 3


def _prior(theta=HYPER, mean=None):
    return frequency_prior(CL, log_frequency_kernel(FREQS, NU0, *theta, nugget=1e-2), mean)


@pytest.fixture(scope="module")
def response(small_array):
    return response_matrix(small_array, antpairs(small_array.positions_enu_m.shape[0])[:12], FREQS, LMAX, 32)


def _system(response, frac, seed=5):
    """Data simulated from the joint prior over ``frac`` of the day, channel 2 flagged."""
    op = VisOperator(response, jnp.asarray(2 * np.pi * frac * np.arange(NT) / NT + 0.1))
    prior = _prior(mean=0.05 * np.random.default_rng(11).standard_normal((FREQS.size, N)))
    return simulate_joint(op, prior, seed, flagged=(2,))


class Dense:
    """The dense joint path's Wiener filter, draws, posterior sigma and P-norm of a difference."""

    def __init__(self, system, key):
        st = prepare_joint_dense(system)
        self.a_wf = np.asarray(st.a_wf)
        self.draws = np.asarray(draw_joint_dense(key, st, NDRAWS))
        L, LR, sc = np.asarray(st.chol), np.asarray(st.chol_r), np.asarray(st.sqrt_c)
        G = np.kron(LR, np.diag(sc))  # S = G G^T
        Ginv = np.linalg.inv(G)
        self.chol_p = np.linalg.solve(L, Ginv).T  # P = G^-T L L^T G^-1 = chol_p chol_p^T
        half = np.linalg.solve(L, G.T)  # P^-1 = half^T half
        self.sigma = np.sqrt(np.sum(half**2, axis=0)).reshape(FREQS.size, N)

    def p_norm(self, e):
        """``||e||_P`` for e (Nf, n)."""
        return float(np.linalg.norm(self.chol_p.T @ np.asarray(e).reshape(-1)))


@pytest.fixture(scope="module")
def partial(response):
    system = _system(response, 1.0 / 3.0)
    key = jax.random.PRNGKey(7)
    return system, Dense(system, key), key


# ---------------------------------------------------------------- against the dense path


def test_wiener_and_draws_equal_dense(partial):
    """Draws with "auto" (Nystrom on partial coverage), the Wiener filter with the m-blocks too."""
    system, ref, key = partial
    mb = prepare_joint_cg(system, JointCGOptions(tol=TOL, preconditioner="mblock"))
    assert bool(mb.wiener.converged) and float(mb.wiener.err_sigma) <= TOL
    assert (np.abs(np.asarray(mb.a_wf) - ref.a_wf) / ref.sigma).max() < 1e-8
    st = prepare_joint_cg(system, JointCGOptions(tol=TOL))
    assert st.options.preconditioner == "nystrom"
    draws, info = draw_joint_cg(key, st, NDRAWS)
    assert bool(info.wiener.converged) and float(info.wiener.err_sigma) <= TOL
    assert np.all(np.asarray(info.draws.converged)) and np.asarray(info.draws.err_sigma).max() <= TOL
    # measured 1.5e-11 sigma (CG's error below its 1e-10 bound, plus the dense solve's rounding ~3e-13)
    err = np.abs(np.asarray(st.a_wf) - ref.a_wf) / ref.sigma
    assert err.max() < 1e-8, err.max()
    derr = np.abs(np.asarray(draws) - ref.draws) / ref.sigma
    assert derr.max() < 1e-8, derr.max()
    # the rigorous bound: the true error's P-norm within the reported err_sigma (measured 7.3e-11 <= 7.6e-11;
    # 1e-11 allows for the reference's own rounding)
    assert ref.p_norm(np.asarray(st.a_wf) - ref.a_wf) <= float(info.wiener.err_sigma) + 1e-11


def test_matvec_and_mode_preconditioner_are_their_matrices(partial):
    """M u against the dense whitened M (from the dense factor), and the mode preconditioner's blocks
    against I + c_k L_R^T diag_nu(H_nu,kk) L_R built from M's own diagonal blocks (full-day H here)."""
    system, ref, _ = partial
    st = prepare_joint_dense(system)
    L = np.asarray(st.chol)
    M = L @ L.T
    u = np.random.default_rng(0).standard_normal((FREQS.size, N))
    got = np.asarray(joint_matvec(system, st.chol_r, st.sqrt_c, jnp.asarray(u))).reshape(-1)
    # measured 4e-16 of the largest entry (rounding)
    np.testing.assert_allclose(got, M @ u.reshape(-1), rtol=0, atol=1e-12 * np.abs(M @ u.reshape(-1)).max())
    full = _system(system.op.response, 1.0)
    dfull = prepare_joint_dense(full)
    Lf = np.asarray(dfull.chol)
    Mf = (Lf @ Lf.T).reshape(FREQS.size, N, FREQS.size, N)
    pc = joint_preconditioner(full, "mode")
    assert isinstance(pc, JointModePreconditioner)
    B = np.asarray(pc.chol) @ np.swapaxes(np.asarray(pc.chol), -1, -2)  # (n, Nf, Nf)
    k = np.arange(N)
    want = Mf[:, k, :, k]  # (n, Nf, Nf): M's entries between channels at the same mode
    # the m-mode approximation equals the true H at full day to rounding (measured 3e-16 of the largest entry)
    np.testing.assert_allclose(B, want, rtol=0, atol=1e-12 * np.abs(want).max())


def test_nystrom_never_exceeds_m_and_mblock_does(partial):
    """The Nystrom stop is a bound because M_pc <= M, i.e. M_pc^-1 - M^-1 >= 0 (here a rank-32 sketch of the
    8 h system: measured min eigenvalue -6e-14, rounding of the O(1) entries); negative control: the m-block preconditioner
    on 8 h coverage is no lower bound (measured min eigenvalue -0.99), which is why it stops on ||r||_2."""
    system, ref, _ = partial
    st = prepare_joint_dense(system)
    L = np.asarray(st.chol)
    Minv = np.linalg.inv(L @ L.T)
    eye = jnp.eye(FREQS.size * N).reshape(-1, FREQS.size, N)
    lows = {}
    for kind, kw in (("nystrom", dict(sketch_size=32)), ("mblock", {})):
        pc = joint_preconditioner(system, kind, **kw)
        Pinv = np.asarray(jax.vmap(lambda e, pc=pc: joint_precondition(pc, e))(eye)).reshape(eye.shape[0], -1)
        lows[kind] = np.linalg.eigvalsh(0.5 * (Pinv + Pinv.T) - Minv).min()
    assert lows["nystrom"] > -1e-12, lows
    assert lows["mblock"] < -1e-3, lows


# ---------------------------------------------------------------- preconditioning and convergence


NOT_ENOUGH = JointCGOptions(tol=TOL, maxiter=3, preconditioner="none")


def test_preconditioners_cut_iterations_and_auto_choice(response, partial):
    """Unpreconditioned CG needs far more than 3 iterations (measured 63 on 8 h, 57 on the full day); "auto"
    takes the Nystrom sketch on partial coverage (measured 1 iteration) and the m-blocks on the full day
    (M itself there: 1 iteration); the unpreconditioned run capped at 3 is reported as not converged."""
    for system, kind in ((partial[0], "nystrom"), (_system(response, 1.0), "mblock")):
        st = prepare_joint_cg(system, JointCGOptions(tol=TOL))
        assert st.options.preconditioner == kind
        assert bool(st.wiener.converged) and int(st.wiener.iterations) <= 3, st.wiener
        capped = prepare_joint_cg(system, NOT_ENOUGH).wiener
        assert not bool(capped.converged) and int(capped.iterations) == 3


def test_non_convergence_is_reported(partial):
    system, ref, key = partial
    st = prepare_joint_cg(system, NOT_ENOUGH)
    w = st.wiener
    assert not bool(w.converged) and int(w.result) == Result.MAX_ITERATIONS and float(w.err_sigma) > TOL
    # the reported bound still bounds the true error (measured: P-norm error 2.0, err_sigma 70)
    assert ref.p_norm(np.asarray(st.a_wf) - ref.a_wf) <= float(w.err_sigma)


def test_bad_options_are_refused_naming_them(partial):
    system = partial[0]
    for kw, match in ((dict(preconditioner="jacobi"), "preconditioner"), (dict(tol=0.0), "tol"),
                      (dict(maxiter=0), "maxiter"), (dict(throw=1), "throw")):
        with pytest.raises(ValueError, match=match):
            JointCGOptions(**kw)
    with pytest.raises(ValueError, match="JointCGOptions"):
        prepare_joint_cg(system, object())
    with pytest.raises(ValueError, match="unknown joint preconditioner"):
        joint_preconditioner(system, "auto")


# ---------------------------------------------------------------- gradients


def test_wiener_gradient_matches_finite_differences(partial):
    """d/d(beta, xi) of a fixed projection of the CG Wiener filter (implicit, custom_linear_solve) against
    central differences of the same CG at tol 1e-12 (so CG's error, < 1e-12 sigma, is far below the
    differences' truncation ~h^2 and rounding ~1e-16 / h)."""
    system, _, _ = partial
    v = jnp.asarray(np.random.default_rng(1).standard_normal((FREQS.size, N)))
    opts = JointCGOptions(tol=1e-12, preconditioner="mblock")

    def f(t):
        s = system._replace(prior=_prior((HYPER[0], t[0], t[1]), mean=system.prior.mean))
        return jnp.sum(v * wiener_joint_cg(s, opts, check=False)[0])

    t0 = np.array(HYPER[1:])
    g = np.asarray(jax.jit(jax.grad(f))(jnp.asarray(t0)))
    fj = jax.jit(f)
    fd = np.zeros(2)
    for i in range(2):
        e = np.zeros(2)
        e[i] = 1e-5 * abs(t0[i])
        fd[i] = (float(fj(jnp.asarray(t0 + e))) - float(fj(jnp.asarray(t0 - e)))) / (2 * e[i])
    np.testing.assert_allclose(g, fd, rtol=1e-5)  # measured 1e-8 (beta) and 1e-9 (xi) relative
