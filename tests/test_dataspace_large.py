"""The in-place data-space set-up (issue 24: partial coverage at lmax 300) against the standard one.

References, independent of the code under test:

* :func:`gcrsky.solvers.blocked.blocked_cholesky` against ``numpy.linalg.cholesky`` (1e-13
  relative: both are backward-stable factorisations of a well-conditioned matrix; panel widths
  that do and do not divide N);
* the per-order Grams of :func:`gcrsky.solvers.dataspace_large.lag_blocks_by_m` against the
  lag-by-lag products ``R_r S Q(lag) R_r^T`` with gcrsky's rotation (1e-13 relative: sums of
  the same terms in another order);
* the in-place state against the standard set-up (its factor, Wiener filter and draws with
  the same key: 1e-10 relative, rounding of two factorisations of the same D) and the Wiener
  filter against a dense NumPy solve of P (1e-8 posterior sigma, as tests/test_dataspace.py);
* the draws' derivative in a noise scale against the standard path's (implicit through the
  matrix-free ``D v`` here, through the stored D there; 1e-7 relative);
* the planner: with a memory budget that holds D once but not D and its factor, the
  in-place set-up is chosen (``gram is None``); misuse gives a clear error.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array
from gcrsky.model import build_problem, compress_problem, isotropic_prior
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.solvers import DataSpaceOptions
from gcrsky.solvers.blocked import blocked_cholesky, triangular_solves
from gcrsky.solvers.dataspace import dataspace_memory_bytes, draw_dataspace, lag_structure, prepare_dataspace
from gcrsky.solvers.dataspace_large import dataspace_large_bytes, lag_blocks_by_m, logdet_no_grad
from gcrsky.sphere import rotate


@pytest.fixture(scope="module")
def system():
    """10-antenna hexagon compressed, 2 channels, lmax 12 (n = 169), 3 LSTs over 0.8 rad (N_d < n)."""
    lmax, nf = 12, 2
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    n = (lmax + 1) ** 2
    cl = 50.0 / (1.0 + np.arange(lmax + 1)) ** 2
    prior = isotropic_prior(np.stack([cl, 2 * cl]), n)
    rng = np.random.default_rng(3)
    truth = np.asarray(prior.inv_var) ** -0.5 * rng.standard_normal((nf, n))
    prob = build_problem(arr, [100e6, 101e6], np.linspace(0.0, 0.8, 3), lmax, 32, a_true=truth, sigma=0.05,
                         prior=prior, key=jax.random.PRNGKey(0))
    s = compress_problem(prob, arr).system()
    assert 2 * s.data.shape[1] * s.data.shape[2] < n
    return s


@pytest.mark.parametrize("n, block, threads", [(300, 64, None), (257, 100, 2), (64, 64, 1), (50, 1000, None)])
def test_blocked_cholesky_equals_numpy(n, block, threads):
    rng = np.random.default_rng(n)
    G = rng.standard_normal((n, n // 2))
    A = G @ G.T + np.eye(n)
    ref = np.linalg.cholesky(A)
    work = np.ascontiguousarray(np.tril(A) + np.triu(rng.standard_normal((n, n)), 1))  # upper triangle: garbage
    L = blocked_cholesky(work, block, threads=threads)
    assert L is work  # in place
    np.testing.assert_allclose(L, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    x = np.asarray(triangular_solves(jnp.asarray(L), jnp.ones((2, n))))
    np.testing.assert_allclose(x, np.linalg.solve(A, np.ones((n, 2))).T, rtol=1e-10)


def test_blocked_cholesky_threads_only_inside_the_call(monkeypatch):
    """The BLAS threads are raised for the factorisation only: the process's setting (gcrsky's CPU set-up keeps
    one thread for the BLAS calls inside XLA's pool) is back after the call, and after a failed one."""
    from threadpoolctl import threadpool_info, threadpool_limits

    from gcrsky.solvers.blocked import THREADS_ENV, blas_threads

    def blas():
        return sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

    with threadpool_limits(limits=1, user_api="blas"):
        before = blas()
        blocked_cholesky(np.eye(64) * 2.0, 16, threads=2)
        assert blas() == before == [1] * len(before)
        bad = np.eye(8)
        bad[5, 5] = -1.0
        with pytest.raises(ValueError, match="not positive definite"):
            blocked_cholesky(bad, 4, threads=2)
        assert blas() == before
    monkeypatch.setenv(THREADS_ENV, "3")
    assert blas_threads() == 3
    for bad_value in ("0", "two"):
        monkeypatch.setenv(THREADS_ENV, bad_value)
        with pytest.raises(ValueError, match=THREADS_ENV):
            blas_threads()
    monkeypatch.delenv(THREADS_ENV)
    assert blas_threads() >= 1


def test_blocked_cholesky_refuses_bad_input():
    A = np.eye(10)
    A[7, 7] = -1.0
    with pytest.raises(ValueError, match="not positive definite .*rows 6-9"):
        blocked_cholesky(A, 3)
    with pytest.raises(ValueError, match="float64"):
        blocked_cholesky(np.eye(4, dtype=np.float32))
    with pytest.raises(ValueError, match="square"):
        blocked_cholesky(np.ones((3, 4)))
    with pytest.raises(ValueError, match="C-contiguous"):
        blocked_cholesky(np.eye(6)[::2, ::2])


@pytest.mark.parametrize("m_chunk", [1, 5, 16])
def test_lag_blocks_by_m_equal_the_products(system, m_chunk):
    lags = lag_structure(system)
    R = system.op.response
    Rr = jnp.concatenate([R.real, R.imag], axis=1)
    Rs = Rr / system.prior.inv_var[:, None, :]
    ref = np.stack([np.asarray(jnp.einsum("fak,fbk->fab", Rs, rotate(Rr, lag))) for lag in np.asarray(lags.lags)])
    G = np.asarray(lag_blocks_by_m(system, lags.lags, m_chunk=m_chunk))
    assert G.shape == ref.shape
    np.testing.assert_allclose(G, ref, rtol=0, atol=1e-13 * np.abs(ref).max())


def test_in_place_equals_the_standard_set_up(system):
    std = prepare_dataspace(system, DataSpaceOptions(in_place=False))
    big = prepare_dataspace(system, DataSpaceOptions(in_place=True))
    assert big.gram is None and std.gram is not None and big.options.in_place
    np.testing.assert_allclose(big.chol.L, std.chol, rtol=0, atol=1e-10 * float(jnp.abs(std.chol).max()))
    P, b = np.asarray(precision_matrix(system)), np.asarray(wiener_rhs(system))
    for f in range(P.shape[0]):
        a = np.linalg.solve(P[f], b[f])
        sig = np.sqrt(np.diag(np.linalg.inv(P[f])))
        assert np.max(np.abs(np.asarray(big.a_wf[f]) - a) / sig) < 1e-8
    assert bool(np.all(big.wiener.converged))
    key = jax.random.PRNGKey(5)
    d_std, _ = draw_dataspace(key, std, 7)
    d_big, info = draw_dataspace(key, big, 7)
    np.testing.assert_allclose(d_big, d_std, rtol=0, atol=1e-10 * float(jnp.abs(d_std).max()))
    assert bool(np.all(info.draws.converged))


def test_in_place_draws_differentiate_implicitly(system):
    """d/d(noise scale) of a draw's deviation from a fixed Wiener filter, through the factor of D(1) and the
    matrix-free D(scale): against central differences of fresh in-place set-ups at 1 +- h (h = 1e-5: truncation
    ~h^2 relative, rounding ~1e-16 / h; tolerance 1e-6)."""
    key = jax.random.PRNGKey(2)

    def dev(state, scale):
        s2 = state.system._replace(inv_noise=state.system.inv_noise * scale)
        st = type(state)(s2, state.a_wf, state.wiener, state.gram, state.chol, state.rows, state.options)
        return jnp.sum((draw_dataspace(key, st, 3)[0] - state.a_wf[:, None, :]) ** 2)

    def fresh(scale):
        return prepare_dataspace(system._replace(inv_noise=system.inv_noise * scale), DataSpaceOptions(in_place=True))

    g = jax.grad(lambda sc: dev(fresh(1.0), sc))(1.0)
    h = 1e-5
    fd = (dev(fresh(1.0 + h), 1.0) - dev(fresh(1.0 - h), 1.0)) / (2 * h)
    assert np.isfinite(g) and abs(float(g)) > 0
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_log_det_from_the_factor_has_no_silent_gradient():
    L = jnp.asarray(np.linalg.cholesky(np.eye(3) * 2.0))
    assert np.isclose(float(logdet_no_grad(L)), 3 * np.log(2.0))
    assert np.isnan(float(jax.grad(lambda x: logdet_no_grad(L * x))(1.0)))


def test_planner_takes_the_in_place_set_up_when_only_it_fits(system):
    nlags = int(lag_structure(system).lags.shape[0])
    std = dataspace_memory_bytes(system, 1, False, 1)
    big = dataspace_large_bytes(system, nlags)
    assert big < std
    budget = 0.5 * (std + big) / 0.8  # D + factor do not fit 80% of it (AUTO_MEMORY_FRACTION), D alone does
    state = prepare_dataspace(system, memory_budget=budget)
    assert state.gram is None and bool(np.all(state.wiener.converged))
    state = prepare_dataspace(system, memory_budget=10 * std)
    assert state.gram is not None


def test_in_place_needs_the_stationary_shortcut(system):
    iv = np.asarray(system.prior.inv_var).copy()
    iv[:, -1] *= 2.0  # one Im part with another variance than its Re part: S does not commute with rotations
    bad = system._replace(prior=system.prior._replace(inv_var=jnp.asarray(iv)))
    with pytest.raises(ValueError, match="stationary shortcut"):
        prepare_dataspace(bad, DataSpaceOptions(in_place=True))
    with pytest.raises(ValueError, match="stationary shortcut"):
        prepare_dataspace(system, DataSpaceOptions(in_place=True, stationary=False))
