"""Tests of the exact m-mode solver (gcrsky.solvers.mmode, DESIGN §4, issue 5).

References: the dense precision matrix :func:`gcrsky.model.system.precision_matrix`, a dense
NumPy solve for the Wiener filter and the dense Cholesky factor for whitening draws.
The problem is the shared small one (10-antenna hexagon, lmax 6, nside 32, two
frequencies) observed with Nt = 2 lmax + 3 equally spaced LSTs over the whole day and
per-baseline, time-constant noise chosen so the data term is comparable to the prior.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from gcrsky.instrument import antpairs, response_matrix
from gcrsky.model import LinearSystem, VisOperator, isotropic_prior
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.solvers import MModeOptions, mmode_check
from gcrsky.solvers.mmode import (
    block_solve,
    blocks_to_dense,
    draw_mmode,
    is_mmode_diagonal,
    mmode_blocks,
    mmode_buckets,
    mmode_wiener_and_draws,
    prepare_mmode,
)
from gcrsky.sphere import lmax_from_nparams, mode_table

#: total false-alarm rate of the statistical test of the draws, split over its parts
FALSE_ALARM = 1e-3


def full_day_system(response, seed=0, nt=None, sigma_scale=3e-3, offset=0.3):
    """Uniform full-day LSTs, time-stationary per-(freq, baseline) noise, isotropic prior."""
    R = jnp.asarray(response)
    nf, nbl, n = R.shape
    lmax = lmax_from_nparams(n)
    nt = 2 * lmax + 3 if nt is None else nt
    rng = np.random.default_rng(seed)
    angles = offset + 2 * np.pi * np.arange(nt) / nt
    sigma = sigma_scale * rng.uniform(0.5, 2.0, (nf, nbl))
    w = np.broadcast_to(1.0 / sigma[:, None, :] ** 2, (nf, nt, nbl)).copy()
    cl = np.tile(1.0 / (1.0 + np.arange(lmax + 1)) ** 2, (nf, 1))
    prior = isotropic_prior(cl, n, mean=0.1 * rng.normal(size=(nf, n)))
    data = (rng.normal(size=(nf, nt, nbl)) + 1j * rng.normal(size=(nf, nt, nbl))) * 0.01
    return LinearSystem(VisOperator(R, jnp.asarray(angles)), jnp.asarray(data), jnp.asarray(w), prior)


@pytest.fixture(scope="module")
def system(small_response):
    return full_day_system(small_response.response)


@pytest.fixture(scope="module")
def dense_P(system):
    return np.asarray(precision_matrix(system))


def test_blocks_equal_dense_precision(system, dense_P, small_response):
    lmax = small_response.lmax
    assert mmode_check(system).ok and is_mmode_diagonal(system)
    prior_diag = np.stack([np.diag(x) for x in np.asarray(system.prior.inv_var)])
    data_P = dense_P - prior_diag
    # the data term is not negligible next to the prior (else the test would be vacuous)
    assert np.abs(data_P).max() > 0.1 * np.asarray(system.prior.inv_var).max()
    bb = mmode_blocks(system)
    # lmax 6 < the default quantum: one bucket of every order, padded to lmax+1 per half
    assert len(bb.arrays) == 1
    blocks = np.asarray(bb.arrays[0])
    assert blocks.shape == (2, lmax + 1, 2 * (lmax + 1), 2 * (lmax + 1))
    Pb = blocks_to_dense(bb)
    rel = np.abs(Pb - dense_P).max() / np.abs(dense_P).max()
    rel_data = np.abs((Pb - prior_diag) - data_P).max() / np.abs(data_P).max()
    assert rel < 1e-10 and rel_data < 1e-10, (rel, rel_data)
    # the dense P has (to rounding) nothing outside the m-blocks
    m = mode_table(lmax).m
    off = m[:, None] != m[None, :]
    assert np.abs(dense_P[:, off]).max() < 1e-12 * np.abs(data_P).max()
    # padding is identity and decoupled
    blocks_sym = np.abs(blocks - np.swapaxes(blocks, -1, -2)).max()
    assert blocks_sym < 1e-12 * np.abs(blocks).max()
    assert np.all(blocks[:, 0, lmax + 1 :, lmax + 1 :] == np.eye(lmax + 1))


@pytest.mark.parametrize("lmax,quantum", [(12, 4), (20, 8), (20, 3)])
def test_bucketed_blocks_equal_dense_precision(small_array, lmax, quantum):
    """Several buckets with padding: the blocks are P's m-blocks to 1e-12, padding is identity and
    decoupled, and the Wiener filter, the draws' whitening and the log det agree with the dense P."""
    pairs = antpairs(small_array.positions_enu_m.shape[0])
    sysl = full_day_system(response_matrix(small_array, pairs, np.array([100e6, 110e6]), lmax, 32))
    lay = mmode_buckets(lmax, quantum)
    assert len(lay.orders) >= 3 and lay.waste > 0  # several buckets, some padded
    assert lay.orders[0][0] == 0 and lay.orders[-1][1] == lmax + 1
    bb = mmode_blocks(sysl, quantum)
    assert [a.shape[1:] for a in bb.arrays] == [(g, s, s) for g, s in lay.shapes]
    P = np.asarray(precision_matrix(sysl))
    Pb = blocks_to_dense(bb)
    assert np.abs(Pb - P).max() < 1e-12 * np.abs(P).max()
    for a, mask in zip(bb.arrays, lay.mask):
        a = np.asarray(a)
        pad = ~mask[None, :, :, None] | ~mask[None, :, None, :]
        eye = np.broadcast_to(np.eye(a.shape[-1], dtype=bool), a.shape)
        assert np.all(a[pad & eye] == 1.0) and np.all(a[pad & ~eye] == 0.0)
    # through the factors: Wiener filter, whitened draws and log det against the dense P
    opts = MModeOptions(bucket=quantum)
    prep = prepare_mmode(sysl, opts)
    ref = np.linalg.solve(P, np.asarray(wiener_rhs(sysl))[..., None])[..., 0]
    err = np.asarray(prep.a_wf) - ref
    assert np.all(np.sqrt(np.einsum("fi,fij,fj->f", err, P, err)) < 1e-8)
    x = np.asarray(block_solve(prep.chol, jnp.asarray(P[:, :, 0] * 0 + np.arange(P.shape[1]))))
    np.testing.assert_allclose(np.einsum("fij,fj->fi", P, x), np.broadcast_to(np.arange(P.shape[1]), x.shape),
                               rtol=0, atol=1e-9 * P.shape[1])
    draws, info = draw_mmode(jax.random.PRNGKey(3), prep, 4)
    assert np.all(np.asarray(info.draws.converged))
    # L_m^-T z has covariance P^-1 exactly: P^1/2-whitening the draws gives back unit normals of the
    # same norm, i.e. (x - a_wf)^T P (x - a_wf) = |z|^2 summed over the buckets' real entries
    d = np.asarray(draws) - np.asarray(prep.a_wf)[:, None, :]
    quad = np.einsum("fdi,fij,fdj->fd", d, P, d)
    z = np.asarray(jax.random.normal(jax.random.PRNGKey(3), (2, sum(g * s for g, s in lay.shapes), 4)))
    real = np.concatenate([m.ravel() for m in lay.mask])
    zsq = np.sum(z[:, real] ** 2, axis=1)
    np.testing.assert_allclose(quad, zsq, rtol=1e-9)
    logdet = np.linalg.slogdet(P)[1]
    got = sum(np.sum(np.log(np.diagonal(np.asarray(a), axis1=-2, axis2=-1)), axis=(1, 2)) for a in prep.chol.arrays)
    np.testing.assert_allclose(2 * got, logdet, rtol=1e-12)


def test_wiener_filter_equals_dense_solve(system, dense_P):
    prep = prepare_mmode(system)
    b = np.asarray(wiener_rhs(system))
    ref = np.linalg.solve(dense_P, b[..., None])[..., 0]
    err = np.asarray(prep.a_wf) - ref
    # error in posterior-sigma units: sqrt(err^T P err)
    err_sigma = np.sqrt(np.einsum("fi,fij,fj->f", err, dense_P, err))
    assert np.all(err_sigma < 1e-8), err_sigma
    assert np.all(np.asarray(prep.wiener.converged))
    assert np.all(np.asarray(prep.wiener.err_sigma) < 1e-8)


def test_wiener_over_time_chunks_equals_one_chunk(system):
    """The matrix-free products summed over chunks of times (the last one padded with zero weight)
    give the same Wiener filter and residual as over all times at once."""
    from gcrsky.solvers.mmode import _mmode_wiener, mmode_factor, product_time_chunk

    nt = system.op.angles.shape[0]
    assert product_time_chunk(2, nt, 49) == nt and product_time_chunk(2, nt, 49, budget=1.0) == 1
    L = mmode_factor(system)
    a1, _ = _mmode_wiener(system, L, MModeOptions(), nt)
    a4, i4 = _mmode_wiener(system, L, MModeOptions(), 4)  # 17 times: 5 chunks, the last padded
    assert np.abs(np.asarray(a4 - a1)).max() < 1e-12 * np.abs(np.asarray(a1)).max()
    assert np.all(np.asarray(i4.converged)) and np.all(np.asarray(i4.err_sigma) < 1e-8)


def test_draws_have_exact_covariance(system, dense_P):
    ndraws = 2000
    draws, info = mmode_wiener_and_draws(jax.random.PRNGKey(7), system, ndraws)
    draws = np.asarray(draws)
    nf, n = dense_P.shape[0], dense_P.shape[1]
    assert draws.shape == (nf, ndraws, n)
    assert np.all(np.asarray(info.draws.converged))
    b = np.asarray(wiener_rhs(system))
    a_wf = np.linalg.solve(dense_P, b[..., None])[..., 0]
    L = np.linalg.cholesky(dense_P)
    # y = L^T (x - a_wf) ~ N(0, I) exactly if Cov(x) = P^-1 and E x = a_wf
    y = np.einsum("fji,fdj->fdi", L, draws - a_wf[:, None, :])  # (Nf, ndraws, n)
    alpha = FALSE_ALARM / 3  # three two-sided tests
    # (a) mean: ndraws * |mean(y)|^2 ~ chi2(Nf n)
    k = nf * n
    t_mean = ndraws * np.sum(y.mean(axis=1) ** 2)
    lo, hi = stats.chi2.ppf([alpha / 2, 1 - alpha / 2], k)
    assert lo < t_mean < hi, (t_mean, lo, hi)
    # (b) total sum of squares ~ chi2(Nf ndraws n)
    t_ss = np.sum(y**2)
    lo, hi = stats.chi2.ppf([alpha / 2, 1 - alpha / 2], nf * ndraws * n)
    assert lo < t_ss < hi, (t_ss / (nf * ndraws * n), lo, hi)
    # (c) every whitened coordinate's sum of squares ~ chi2(ndraws) (Bonferroni over Nf n)
    ss = np.sum(y**2, axis=1)
    a1 = alpha / k
    lo, hi = stats.chi2.ppf([a1 / 2, 1 - a1 / 2], ndraws)
    assert lo < ss.min() and ss.max() < hi, (ss.min(), ss.max(), lo, hi)
    # same key, same draws
    again, _ = draw_mmode(jax.random.PRNGKey(7), prepare_mmode(system), ndraws)
    assert np.array_equal(np.asarray(again), draws)


def test_check_refuses_non_block_diagonal_cases(system, small_response):
    lmax = small_response.lmax
    R = system.op.response
    n = R.shape[2]
    nt = system.op.angles.shape[0]
    # partial coverage: 8 h of LST
    part = system._replace(op=VisOperator(R, jnp.asarray(np.linspace(0, 8, nt) * 2 * np.pi / 24)))
    res = mmode_check(part)
    assert not res.ok and "coverage" in res.reason
    # aliasing: Nt = 2 lmax equally spaced angles
    al = full_day_system(R, nt=2 * lmax)
    res = mmode_check(al)
    assert not res.ok and "Nt" in res.reason
    # time-varying noise
    w = np.array(system.inv_noise)
    w[:, 3, :] *= 1.5
    res = mmode_check(system._replace(inv_noise=jnp.asarray(w)))
    assert not res.ok and "noise" in res.reason
    # a flag (zero weight) is time-varying noise too
    w = np.array(system.inv_noise)
    w[0, 2, 5] = 0.0
    assert not is_mmode_diagonal(system._replace(inv_noise=jnp.asarray(w)))
    # a frame map
    framed = system._replace(op=VisOperator(R, system.op.angles, jnp.eye(n)))
    res = mmode_check(framed)
    assert not res.ok and "frame" in res.reason
    with pytest.raises(ValueError, match="not block-diagonal in m: .*coverage"):
        prepare_mmode(part)
    # the repeated-angle uniform cover still passes
    rep = system._replace(
        op=VisOperator(R, jnp.repeat(system.op.angles, 2)), data=jnp.repeat(system.data, 2, axis=1),
        inv_noise=jnp.repeat(system.inv_noise, 2, axis=1),
    )
    assert is_mmode_diagonal(rep)


def test_cost_print_lmax20(small_array):
    """Rough timing (printed, not asserted): m-mode set-up + 200 draws vs dense P + Cholesky."""
    lmax = 20
    pairs = antpairs(small_array.positions_enu_m.shape[0])
    R = response_matrix(small_array, pairs, np.array([100e6]), lmax, 32)
    sysl = full_day_system(R)

    def timed(f):
        jax.block_until_ready(f())  # compile
        t0 = time.perf_counter()
        jax.block_until_ready(f())
        return time.perf_counter() - t0

    t_mm = timed(lambda: draw_mmode(jax.random.PRNGKey(0), prepare_mmode(sysl), 200)[0])
    t_dense = timed(lambda: jnp.linalg.cholesky(precision_matrix(sysl)))
    print(f"\nlmax {lmax} (n {R.shape[2]}, Nt {sysl.op.angles.shape[0]}): m-mode set-up + 200 draws "
          f"{t_mm * 1e3:.1f} ms; dense precision_matrix + Cholesky {t_dense * 1e3:.1f} ms")
    # the two agree on the posterior mean here as well
    prep = prepare_mmode(sysl)
    assert np.all(np.asarray(prep.wiener.err_sigma) < 1e-6)
