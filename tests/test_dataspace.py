"""The data-space exact path (DESIGN section 10) against the primal path and dense algebra.

Problems with fewer real data values than parameters (``N_d = 2 Nt Nbl < n``: a few
LSTs of the redundancy-compressed 10-antenna hexagon at lmax 10-12, one of them with
flags, one in ICRS with a frame map).  References, independent of the data-space code:

* the Wiener filter: a dense NumPy solve of ``P a = b`` (1e-8 posterior sigma; the
  data-space solve is a Cholesky factorisation of a matrix with eigenvalues >= 1, so
  it is exact to rounding, measured ~1e-13);
* the log evidence: scipy's multivariate normal density of the realified data
  (1e-8 relative, as the primal paths' test), and the primal Cholesky path;
* its gradient and Hessian in (log noise scale, log prior scale): central finite
  differences (the evidence's third derivatives are O(1), h = 1e-5: truncation
  ~1e-10 relative) and the primal path's;
* the Wiener filter's derivative: dense ``P^-1 (db - dP a)``;
* draws: whitened by the dense posterior factor (``y = L^T (a - a_wf)`` is N(0, I)
  exactly), chi-square tests of their dispersion at ALPHA = 1e-3 (Bonferroni over the
  three tests), with a negative control (the draw without its noise term ``z``, whose
  covariance is too small along the data-dominated directions) that must fail.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _hyper_fixtures import THETA, central, dense_wiener_derivative, numpy_log_evidence, scaled
from scipy import stats

import gcrsky
from gcrsky.inference import log_evidence_system
from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array
from gcrsky.model import build_problem, compress_problem, isotropic_prior
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.solvers import (
    CholeskyOptions,
    DataSpaceOptions,
    DataSpaceState,
    choose_path,
    path_memory_bytes,
    plan_sampler,
)
from gcrsky.solvers.dataspace import data_size, dataspace_matrix, draw_dataspace, from_rows, prepare_dataspace, to_rows
from gcrsky.solvers.plan import DENSE_MEMORY_FRACTION

ALPHA = 1e-3
SOLVE = 1e-8  # posterior sigma


def _problem(lmax, nt, *, flags=None, times=None, seed=0):
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    n, nf = (lmax + 1) ** 2, 2
    cl = 50.0 / (1.0 + np.arange(lmax + 1)) ** 2
    prior = isotropic_prior(np.stack([cl, 2 * cl]), n)
    rng = np.random.default_rng(seed)
    prior = prior._replace(mean=np.asarray(prior.inv_var) ** -0.5 * rng.standard_normal((nf, n)))
    truth = np.asarray(prior.mean) + np.asarray(prior.inv_var) ** -0.5 * rng.standard_normal((nf, n))
    kw = {}
    if times is not None:
        from astropy.coordinates import EarthLocation

        kw = dict(times=times, location=EarthLocation.from_geodetic(21.4283, HERA_LATITUDE_DEG, 1073.0))
        lsts = None
    else:
        lsts = np.linspace(0.0, 0.8, nt)
    prob = build_problem(arr, [100e6, 101e6], lsts, lmax, 32, a_true=truth, sigma=0.05, prior=prior,
                         flags=flags, key=jax.random.PRNGKey(seed), **kw)
    return compress_problem(prob, arr)


@pytest.fixture(scope="module")
def partial():
    """lmax 10 (n = 121), 2 LSTs over 46 min, compressed: N_d = 2 x 2 x Nbl_unique < n; some samples flagged."""
    p = _problem(10, 2)
    sys0 = p.system()
    flags = np.zeros(sys0.inv_noise.shape, bool)
    flags[0, 1, :3] = True
    flags[1, 0, 5] = True
    return sys0._replace(inv_noise=jnp.where(flags, 0.0, sys0.inv_noise),
                         data=jnp.where(flags, 1e3 + 0j, sys0.data))  # garbage under the flags must not matter


@pytest.fixture(scope="module")
def icrs():
    """ICRS parameters (a frame map), 2 observing times 0.7 h apart, lmax 8 (n = 81; N_d = 56)."""
    import astropy.units as u
    from astropy.time import Time

    times = Time("2026-03-01T00:00:00") + np.array([0.0, 0.7]) * u.hour
    return _problem(8, 2, times=times).system()


def _dense(system):
    P = np.asarray(precision_matrix(system))
    b = np.asarray(wiener_rhs(system))
    a = np.stack([np.linalg.solve(P[f], b[f]) for f in range(P.shape[0])])
    sig = np.stack([np.sqrt(np.diag(np.linalg.inv(P[f]))) for f in range(P.shape[0])])
    return P, a, sig


def test_fixtures_are_in_the_data_space_regime(partial, icrs):
    for s in (partial, icrs):
        assert data_size(s) < s.prior.mean.shape[-1], (data_size(s), s.prior.mean.shape)
    assert np.any(np.asarray(partial.inv_noise) == 0)


def test_rows_layout_round_trips(partial):
    v = partial.data
    u = to_rows(v)
    assert u.shape == (v.shape[0], data_size(partial))
    np.testing.assert_array_equal(np.asarray(from_rows(u, *v.shape[1:])), np.asarray(v))
    np.testing.assert_array_equal(np.asarray(u[:, : v.shape[2]]), np.asarray(v[:, 0].real))


@pytest.mark.parametrize("chunk", [None, 1])
def test_data_space_matrix_is_dense_algebra(icrs, chunk):
    """D = I + W^1/2 X S X^T W^1/2 from the dense realified X (time chunks of 1 or all)."""
    from gcrsky.model import dense_matrix

    X = np.asarray(dense_matrix(icrs.op))  # (Nf, Nt, Nbl, n)
    W = np.asarray(icrs.inv_noise)
    D = np.asarray(dataspace_matrix(icrs, chunk))
    for f in range(X.shape[0]):
        Y = np.sqrt(W[f])[..., None] * X[f]
        Yr = np.stack([Y.real, Y.imag], axis=1).reshape(-1, X.shape[-1])  # row t*2Nbl + p*Nbl + b
        ref = np.eye(Yr.shape[0]) + Yr @ np.diag(1.0 / np.asarray(icrs.prior.inv_var[f])) @ Yr.T
        assert np.max(np.abs(D[f] - ref)) < 1e-12 * np.max(np.abs(ref))


def test_channel_groups_equal_all_channels_at_once(icrs, monkeypatch):
    """D formed for one group of channels at a time (a lax.map over groups, the last one padded; each group's
    rows materialised) equals D formed for every channel at once by pairs of time chunks: 3 channels in
    groups of 2 (one padding channel) and of 1."""
    import gcrsky.solvers.dataspace as ds

    three = jax.tree_util.tree_map(lambda a: jnp.concatenate([a, a[:1]]) if a.ndim and a.shape[0] == 2 else a, icrs)
    assert three.data.shape[0] == 3 and three.op.response.shape[0] == 3
    assert ds.channel_group(three, 1) is None  # small: every channel at once (pairs of time chunks)
    whole = np.asarray(dataspace_matrix(three, 1))
    per_channel = ds._group_channel_bytes(three)
    for g in (2, 1):
        monkeypatch.setattr(ds, "GROUP_BYTES", g * per_channel + 1)
        jax.clear_caches()  # the group size is read when dataspace_matrix is traced
        assert ds.channel_group(three, 1) == g
        grouped = np.asarray(dataspace_matrix(three, 1))
        np.testing.assert_allclose(grouped, whole, rtol=0, atol=1e-12 * np.max(np.abs(whole)))
    np.testing.assert_array_equal(whole[2], whole[0])  # the copied channel


def test_stationary_shortcut_equals_the_general_construction(partial, icrs):
    """One block per distinct lag (no frame map, S commutes with rotations about the pole) gives the D of
    the per-time blocks to rounding; it is not used with a frame map or a prior that does not commute."""
    from gcrsky.solvers.dataspace import lag_structure

    lags = lag_structure(partial)
    assert lags is not None and lags.lags.shape == (3,)  # 2 times: lags -dt, 0, dt
    D = np.asarray(dataspace_matrix(partial))
    np.testing.assert_allclose(np.asarray(dataspace_matrix(partial, None, lags)), D, rtol=0, atol=1e-13 * np.abs(D).max())
    assert lag_structure(icrs) is None  # frame map
    iv = partial.prior.inv_var
    odd = partial._replace(prior=partial.prior._replace(inv_var=iv.at[:, -1].multiply(2.0)))  # one Im part only
    assert lag_structure(odd) is None
    e1 = gcrsky.log_evidence(partial, options=DataSpaceOptions())
    e2 = gcrsky.log_evidence(partial, options=DataSpaceOptions(stationary=False))
    np.testing.assert_allclose(np.asarray(e1), np.asarray(e2), rtol=1e-12)


@pytest.mark.parametrize("fixture", ["partial", "icrs"])
def test_wiener_filter_equals_the_dense_solve(fixture, request):
    system = request.getfixturevalue(fixture)
    _, a_ref, sig = _dense(system)
    # icrs: the stationary proxy + CG (tests/test_dataspace_proxy.py), which stops at the options' tol
    opts = DataSpaceOptions(tol=SOLVE / 10) if fixture == "icrs" else None
    st = gcrsky.prepare(system, method="dataspace", options=opts)
    assert isinstance(st, DataSpaceState)
    assert np.max(np.abs(np.asarray(st.a_wf) - a_ref) / sig) < SOLVE
    assert np.all(np.asarray(st.wiener.converged))
    assert np.all(np.asarray(st.wiener.err_sigma) < SOLVE)  # its own error report agrees


@pytest.mark.parametrize("fixture", ["partial", "icrs"])
def test_log_evidence_equals_scipy_and_the_primal_path(fixture, request):
    system = request.getfixturevalue(fixture)
    ref = numpy_log_evidence(system)
    got, info = gcrsky.log_evidence(system, method="dataspace", return_info=True)
    primal = gcrsky.log_evidence(system, method="cholesky")
    assert np.max(np.abs(np.asarray(got) - ref) / np.abs(ref)) < 1e-8
    assert np.max(np.abs(np.asarray(got) - np.asarray(primal)) / np.abs(ref)) < 1e-8
    assert np.all(np.asarray(info.stderr) == 0)
    # Sylvester: log det D = log det(I + H) of the primal path
    _, pinfo = gcrsky.log_evidence(system, method="cholesky", return_info=True)
    np.testing.assert_allclose(np.asarray(info.logdet_whitened), np.asarray(pinfo.logdet_whitened), rtol=1e-10)


def test_log_evidence_gradient_and_hessian(partial):
    f = jax.jit(lambda t: jnp.sum(log_evidence_system(scaled(partial, t), options=DataSpaceOptions())[0]))
    fp = jax.jit(lambda t: jnp.sum(log_evidence_system(scaled(partial, t), options=CholeskyOptions())[0]))
    g = np.asarray(jax.grad(f)(THETA))
    fd = central(lambda t: float(f(jnp.asarray(t))), np.asarray(THETA))
    assert np.max(np.abs(g - fd)) < 1e-6 * np.max(np.abs(fd)), (g, fd)
    np.testing.assert_allclose(g, np.asarray(jax.grad(fp)(THETA)), rtol=1e-8, atol=1e-10 * np.max(np.abs(g)))
    hess = np.asarray(jax.jit(jax.hessian(f))(THETA))
    np.testing.assert_allclose(hess, np.asarray(jax.jit(jax.hessian(fp))(THETA)), rtol=1e-7,
                               atol=1e-9 * np.max(np.abs(hess)))


def test_wiener_filter_derivative_equals_dense_algebra(partial):
    """Differentiating through the data-space solve: d a_wf / d theta = P^-1 (db - dP a)."""
    def a_wf(t):
        return prepare_dataspace(scaled(partial, t), DataSpaceOptions()).a_wf

    J = np.moveaxis(np.asarray(jax.jacfwd(a_wf)(THETA)), -1, 0)  # (2, Nf, n)
    ref = dense_wiener_derivative(partial, np.asarray(THETA))
    _, _, sig = _dense(scaled(partial, THETA))
    assert np.max(np.abs(J - ref) / sig) < 1e-7
    Jr = np.moveaxis(np.asarray(jax.jacrev(a_wf)(THETA)), -1, 0)  # reverse mode: through the checkpointed D
    assert np.max(np.abs(Jr - ref) / sig) < 1e-7


def _whitened_draws(system, draws_fn, ndraws=3000):
    P, a_wf, _ = _dense(system)
    out = []
    for f in range(P.shape[0]):
        L = np.linalg.cholesky(P[f])
        out.append((np.asarray(draws_fn(ndraws)[f]) - a_wf[f]) @ L)
    return out


def _dispersion_p(y, U):
    """Two-sided chi-square p-value of sum |U^T y_j|^2 ~ chi2(k N) (y_j iid N(0, I) under H0)."""
    s = np.sum((y @ U) ** 2)
    dof = U.shape[1] * y.shape[0]
    return 2 * min(stats.chi2.cdf(s, dof), stats.chi2.sf(s, dof))


def _directions(system, f, k=8):
    """Orthonormal whitened directions fixed before the draws: the k most data-dominated, the k most
    prior-dominated, and all (eigenvectors of L^-1 S^-1 L^-T, smallest eigenvalue = least prior)."""
    P = np.asarray(precision_matrix(system))[f]
    L = np.linalg.cholesky(P)
    Li = np.linalg.inv(L)
    _, V = np.linalg.eigh(Li @ np.diag(np.asarray(system.prior.inv_var)[f]) @ Li.T)
    return {"data": V[:, :k], "prior": V[:, -k:], "all": np.eye(P.shape[0])}


def test_draws_have_the_exact_posterior_covariance(partial):
    st = prepare_dataspace(partial)
    ys = _whitened_draws(partial, lambda m: draw_dataspace(jax.random.PRNGKey(11), st, m)[0])
    for f, y in enumerate(ys):
        for name, U in _directions(partial, f).items():
            p = _dispersion_p(y, U)
            assert p > ALPHA / 6, (f, name, p)  # 2 channels x 3 tests: familywise false alarm <= ALPHA
        assert np.max(np.abs(y.mean(0))) < stats.norm.isf(ALPHA / (2 * y.size / y.shape[0])) / np.sqrt(y.shape[0])


def test_negative_control_draws_without_the_noise_term_fail(partial):
    """The Hoffman-Ribak draw with z = 0 (the data's noise realisation left out) is too narrow along
    the data-dominated directions; the same test must reject it."""
    from gcrsky.solvers.dataspace import whitened_adjoint, whitened_apply
    from gcrsky.solvers.dense import cholesky_solve

    st = prepare_dataspace(partial)
    s = 1.0 / partial.prior.inv_var
    sw = jnp.sqrt(partial.inv_noise)

    def wrong(m):
        keys = jax.random.split(jax.random.PRNGKey(11), m)

        def one(k):
            delta = jnp.sqrt(s) * jax.random.normal(jax.random.split(k)[0], s.shape)
            x = cholesky_solve(st.gram, st.chol, whitened_apply(partial, sw, delta))
            return st.a_wf + delta - s * whitened_adjoint(partial, sw, x)

        return jnp.moveaxis(jax.vmap(one)(keys), 0, 1)

    y = _whitened_draws(partial, wrong)[0]
    assert _dispersion_p(y, _directions(partial, 0)["data"]) < 1e-12


def test_draw_key_scheme_and_jit(partial):
    st = prepare_dataspace(partial)
    key = jax.random.PRNGKey(5)
    d3 = np.asarray(draw_dataspace(key, st, 3)[0])
    sub = jax.random.split(key, 3)[2]
    one = np.asarray(draw_dataspace(sub, st, 1)[0])  # a batch of one uses split(sub, 1)[0], not sub itself
    assert not np.allclose(one[:, 0], d3[:, 2])
    d_jit = np.asarray(jax.jit(lambda k, s: draw_dataspace(k, s, 3)[0])(key, st))
    np.testing.assert_allclose(d_jit, d3, rtol=1e-12, atol=1e-12)
    assert st.rows is not None  # small: Y = W^1/2 X is kept for the draws
    mf = prepare_dataspace(partial, DataSpaceOptions(materialize=False))
    assert mf.rows is None  # the matrix-free draws: the same numbers
    np.testing.assert_allclose(np.asarray(draw_dataspace(key, mf, 3)[0]), d3, rtol=1e-12, atol=1e-12)
    # the user tier draws a bucket of 4 (the next power of two) keyed fold_in(key, 0), truncated to 3
    draws, info = gcrsky.sample(key, partial, 3, method="dataspace")
    d4 = np.asarray(draw_dataspace(jax.random.fold_in(key, 0), st, 4)[0])
    np.testing.assert_allclose(np.asarray(draws), d4[:, :3], rtol=1e-12, atol=1e-12)
    assert np.all(np.asarray(info.draws.converged))


def test_flat_prior_is_refused_with_the_reason(partial):
    flat = partial._replace(prior=partial.prior._replace(inv_var=partial.prior.inv_var.at[1, 4].set(0.0)))
    with pytest.raises(ValueError, match="proper prior.*frequency 1, parameter 4"):
        gcrsky.prepare(flat, method="dataspace")
    assert plan_sampler(flat).method == "eigh"  # auto never picks it for a flat prior


def test_auto_picks_data_space_where_it_is_cheaper_and_says_why(partial):
    # lmax 16, one LST: N_d = 28 against n = 289, the dense P costs more to build and factor
    one = _problem(16, 1).system()
    plan = plan_sampler(one)
    assert plan.method == "dataspace", plan.reason
    assert f"N_d = {data_size(one)}" in plan.reason and "n = 289" in plan.reason
    # at lmax 6 (n = 49, N_d = 28) the dense path is cheaper for 200 draws (each data-space draw needs Y and Y^T)
    small = _problem(6, 1).system()
    plan = plan_sampler(small)
    assert plan.method == "cholesky" and "cheaper than dataspace" in plan.reason, plan.reason
    # ... unless the dense P does not fit: then data space is the only direct path left
    budget = 0.9 * path_memory_bytes(partial, "cholesky") / DENSE_MEMORY_FRACTION
    assert path_memory_bytes(partial, "dataspace") < DENSE_MEMORY_FRACTION * budget
    plan = plan_sampler(partial, budget=budget)
    assert plan.method == "dataspace" and "dense P + factor would need" in plan.reason
    # more data than parameters: never data space
    big = _problem(4, 6).system()
    assert data_size(big) > big.prior.mean.shape[-1]
    assert plan_sampler(big).method == "cholesky"
    assert isinstance(choose_path(partial, "dataspace"), DataSpaceOptions)


def test_options_validate():
    with pytest.raises(ValueError, match="time_chunk"):
        DataSpaceOptions(time_chunk=0)
    with pytest.raises(ValueError, match="throw"):
        DataSpaceOptions(throw=1)
    with pytest.raises(ValueError, match="stationary"):
        DataSpaceOptions(stationary="yes")
    with pytest.raises(ValueError, match="materialize"):
        DataSpaceOptions(materialize=1)


# ---------------------------------------------------------------- memory: the estimate, the chunk, the refusal


@pytest.fixture(scope="module")
def icrs_long():
    """ICRS parameters, 6 observing times over 1 h, lmax 8: chunks of 1-6 times differ."""
    import astropy.units as u
    from astropy.time import Time

    times = Time("2026-03-01T00:00:00") + np.linspace(0.0, 1.0, 6) * u.hour
    return _problem(8, 6, times=times).system()


@pytest.mark.parametrize("chunk", [1, 4])
def test_rows_formed_by_chunks_give_the_same_set_up(icrs_long, chunk):
    """Y materialised chunk by chunk into one buffer, D from it by row blocks: equal to the pairwise-block D
    and to Y formed for all times at once; the factor and Wiener filter equal the non-materialised path's."""
    from gcrsky.solvers.dataspace import _chunk_rows, sqrt_weights

    ref = prepare_dataspace(icrs_long, DataSpaceOptions(materialize=False, time_chunk=6, proxy=False))
    st = prepare_dataspace(icrs_long, DataSpaceOptions(materialize=True, time_chunk=chunk, proxy=False))
    nt = icrs_long.data.shape[1]
    rows_all = _chunk_rows(icrs_long.op, sqrt_weights(icrs_long), jnp.arange(nt))
    np.testing.assert_allclose(np.asarray(st.rows), np.asarray(rows_all), rtol=0, atol=1e-14 * float(jnp.abs(rows_all).max()))
    np.testing.assert_allclose(np.asarray(st.gram), np.asarray(ref.gram), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(st.a_wf), np.asarray(ref.a_wf), rtol=1e-10, atol=1e-12)
    assert st.options.time_chunk == chunk and st.options.materialize


# each chunk and each mode once (the full 3 x 2 grid cost ~2 min of compilation in the suite for no other case)
@pytest.mark.parametrize("chunk,materialize", [(1, False), (3, True), (6, False)])
def test_estimate_bounds_the_compiled_set_up(icrs_long, chunk, materialize):
    """The planner's estimate bounds XLA's memory analysis of the compiled set-up (its temporaries plus its
    outputs: D, the factor, Y, the Wiener filter) at every chunk; benchmarks/dataspace_memory.py does the
    same at lmax 60-185 and against the process's peak."""
    from gcrsky.solvers.dataspace import _prepare_dataspace, dataspace_memory_bytes

    opts = DataSpaceOptions(time_chunk=chunk, materialize=materialize)
    ma = _prepare_dataspace.lower(icrs_long, opts, None, materialize).compile().memory_analysis()
    if ma is None:
        pytest.skip("this backend gives no memory analysis")
    used = ma.temp_size_in_bytes + ma.output_size_in_bytes
    est = dataspace_memory_bytes(icrs_long, 1, materialize, chunk)
    assert used <= est, (used, est)
    # a bound, not a refusal of everything: the rows' transient and Y are counted about twice over XLA's (the
    # process's peak, benchmarks/dataspace_memory.py)
    assert est < 4 * used + 2e7


def test_chunk_follows_the_budget_and_what_cannot_fit_is_refused(icrs_long):
    from gcrsky.base.memory import InsufficientMemoryError
    from gcrsky.solvers.dataspace import choose_time_chunk, dataspace_memory_bytes
    from gcrsky.solvers.path import AUTO_MEMORY_FRACTION

    opts = DataSpaceOptions(materialize=False, proxy=False)  # the general construction (no stationary proxy)
    est = [dataspace_memory_bytes(icrs_long, 1, False, c) for c in range(1, 7)]
    assert all(b > a for a, b in zip(est, est[1:]))  # more times at once, more memory
    assert choose_time_chunk(icrs_long, opts, 1e15) == 6  # all times fit (6 <= MAX_TIME_CHUNK)
    assert choose_time_chunk(icrs_long, opts, 1.01 * est[2] / AUTO_MEMORY_FRACTION) == 3
    assert choose_time_chunk(icrs_long, DataSpaceOptions(time_chunk=2), 1.0) == 2  # given: kept
    st = prepare_dataspace(icrs_long, opts, memory_budget=1.01 * est[1] / AUTO_MEMORY_FRACTION)
    assert st.options.time_chunk == 2
    with pytest.raises(InsufficientMemoryError, match="rows formed 1 time.*method='cg'"):
        prepare_dataspace(icrs_long, opts, memory_budget=0.5 * est[0])
