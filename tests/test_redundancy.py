"""Redundant-baseline compression (gcrsky.instrument.redundancy) is exact.

Setting: the shared 10-antenna hexagon (rows 3-4-3, 14.6 m, 14 m Gaussian dishes),
lmax 6, nside 32, 100 and 102 MHz (``small_response`` in conftest), 4 rotation
angles, per-time random inverse noise (~1e9, so the data term dominates the prior
and P's condition number is ~5e5), a random proper prior.  45 baselines fall into
14 groups.

Tolerances.  Compression only regroups sums: ``sum_b X_b^H W_b X_b`` becomes
``X_g^H (sum_b W_b) X_g`` and the data pass through one multiply and one divide, so
the compressed P, Wiener rhs and fluctuation covariance differ from the
uncompressed ones by rounding of sums of <= 7 terms: measured 7e-16 (P), 8e-16
(rhs), 1.4e-15 (covariance) of their max entry, with or without flags or a frame
map; the tests use ``EXACT = 1e-12``.  Identical response rows (same vector up to
~2e-15 m of position rounding) agree to 2.3e-15 of the frequency's max |R| (the
check's scale; 3.6e-11 of the worst row's own max, see ``check_redundancy``).
Solutions go through P^-1 (condition ~5e5), so Wiener filters and Cholesky draws
are compared to ``SOLVE = 1e-9`` (measured 6e-12; 1.8e-11 with flags; 5e-14 for
the Problem-level test).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gcrsky.inference import prepare_system, sample_system
from gcrsky.instrument import (
    HERA_LATITUDE_DEG,
    RedundantGroups,
    antpairs,
    check_redundancy,
    gaussian_beam,
    groups_for_array,
    hex_array,
    make_array,
    redundant_groups,
    redundant_responses,
    response_matrix,
    unique_response,
)
from gcrsky.model import LinearSystem, Prior, VisOperator, adjoint, build_problem, compress_problem, compress_system
from gcrsky.model.compress import compress_visibilities
from gcrsky.model.system import fluctuation_rhs, precision_matrix, wiener_rhs
from gcrsky.solvers import CGOptions

NT = 4
EXACT = 1e-12  # products (P, rhs, covariances): measured <= 1e-15
SOLVE = 1e-9  # through P^-1


def rel(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def make_system(response, seed=0, *, frame=None, n_in=None) -> LinearSystem:
    """Random data, per-time inverse noise (~1e9, varying by 4x) and a proper prior (S^-1 in 1-4)."""
    rng = np.random.default_rng(seed)
    nf, nbl, n = response.shape
    n = n if n_in is None else n_in
    shape = (nf, NT, nbl)
    iv = rng.uniform(0.5, 2.0, shape) * 1e9  # data term up to ~1e6 x the prior: P condition ~1e6
    data = rng.normal(size=shape) + 1j * rng.normal(size=shape)
    prior = Prior(jnp.asarray(rng.normal(size=(nf, n))), jnp.asarray(rng.uniform(1.0, 4.0, (nf, n))))
    op = VisOperator(jnp.asarray(response), jnp.asarray(np.linspace(0.0, 1.2, NT)), frame)
    return LinearSystem(op, jnp.asarray(data), jnp.asarray(iv), prior)


def with_flags(system: LinearSystem, groups: RedundantGroups, seed=1) -> LinearSystem:
    """Flag ~20% of samples at random, one whole group at (f=0, t=1) and one baseline throughout."""
    rng = np.random.default_rng(seed)
    iv = np.array(system.inv_noise)
    iv[rng.uniform(size=iv.shape) < 0.2] = 0.0
    big = int(np.argmax(groups.counts))
    iv[0, 1, groups.members(big)] = 0.0
    iv[:, :, groups.members(big)[0]] = 0.0
    data = np.where(iv > 0, np.asarray(system.data), 0.0)  # gcrsky stores flagged data as 0
    return system._replace(data=jnp.asarray(data), inv_noise=jnp.asarray(iv))


@pytest.fixture(scope="module")
def groups(small_response):
    return groups_for_array(small_response.array, small_response.pairs)


@pytest.fixture(scope="module")
def system(small_response):
    return make_system(small_response.response)


# ------------------------------------------------------------------ grouping


def test_groups_match_independent_count(small_response, groups):
    pos, pairs = small_response.array.positions_enu_m, small_response.pairs
    vec = pos[pairs[:, 1]] - pos[pairs[:, 0]]
    keys = [tuple(np.round(v, 6)) for v in vec]  # independent: exact-decimal rounding, 1 um
    uniq = list(dict.fromkeys(keys))  # first-occurrence order
    assert groups.n_groups == len(uniq) == 14
    assert groups.n_baselines == 45 and groups.counts.sum() == 45
    # same partition, same (first-occurrence) order
    np.testing.assert_array_equal(groups.group_of, [uniq.index(k) for k in keys])
    np.testing.assert_array_equal(groups.representative, [keys.index(k) for k in uniq])
    assert np.all(np.diff(groups.representative) > 0)
    np.testing.assert_array_equal(groups.counts, np.bincount(groups.group_of))
    np.testing.assert_allclose(groups.vectors_m, vec[groups.representative], atol=0)
    assert groups.max_offset_m.max() < 1e-13
    # the hexagon's known redundancy: 7 copies of the east 14.6 m baseline
    assert groups.counts.max() == 7
    e = groups.group_of[np.flatnonzero(np.all(np.isclose(vec, [14.6, 0, 0]), axis=1))]
    assert np.unique(e).size == 1 and groups.counts[e[0]] == 7
    # deterministic
    again = groups_for_array(small_response.array, pairs)
    for a, b in zip(groups, again):
        np.testing.assert_array_equal(a, b)


def test_reversed_baseline_not_merged(small_response):
    """(j, i) has the conjugate response of (i, j): a separate group, as documented."""
    pairs = np.array([[0, 1], [1, 2], [1, 0], [2, 1], [4, 5]])
    g = redundant_groups(small_response.array.positions_enu_m, pairs)
    np.testing.assert_array_equal(g.group_of, [0, 0, 1, 1, 0])
    R = response_matrix(small_response.array, pairs, small_response.freqs_hz, small_response.lmax, small_response.nside)
    assert check_redundancy(R, g) < 1e-14
    np.testing.assert_allclose(np.asarray(R[:, 2]), np.conj(np.asarray(R[:, 0])), atol=1e-14 * np.abs(R).max())
    forced = g._replace(group_of=np.zeros(5, np.int64), representative=np.array([0]), counts=np.array([5]))
    with pytest.raises(ValueError, match=r"\(1, 0\)"):
        check_redundancy(R, forced)


def test_perturbed_position_not_merged(small_response):
    """Antenna 5 moved 1 mm east: its baselines lose their partners; forcing them is refused."""
    pos = small_response.array.positions_enu_m.copy()
    pos[5, 0] += 1e-3
    pos_before = pos.copy()
    pairs = small_response.pairs
    g = redundant_groups(pos, pairs)
    np.testing.assert_array_equal(pos, pos_before)  # inputs untouched
    touches5 = np.any(pairs == 5, axis=1)
    for b in np.flatnonzero(touches5):  # no exact partner in the hexagon any more
        assert np.all(g.group_of[~touches5] != g.group_of[b])
    assert g.n_groups > 14
    # forcing the merge with a loose tolerance groups them, and the row check refuses it
    loose = redundant_groups(pos, pairs, tol_m=1e-2)
    assert loose.n_groups == 14
    arr = make_array(pos, HERA_LATITUDE_DEG, gaussian_beam(14.0))
    R = response_matrix(arr, pairs, small_response.freqs_hz, small_response.lmax, small_response.nside)
    with pytest.raises(ValueError, match=r"refusing to merge.*baseline \d+ \((\d, 5|5, \d)\)"):
        compress_system(make_system(R), loose)
    # unique_response refuses too (phase bound 2 pi 1e-3 m nu / c ~ 2e-3 rad)
    with pytest.raises(ValueError, match="phase offset"):
        unique_response(arr, loose, small_response.freqs_hz, small_response.lmax, small_response.nside)


def test_mixed_beams_not_merged(small_response):
    """Antennas 0-4 with 14 m dishes, 5-9 with 12 m: same vectors, different beam pairs."""
    pos = small_response.array.positions_enu_m
    b14, b12 = gaussian_beam(14.0), gaussian_beam(12.0)
    arr = make_array(pos, HERA_LATITUDE_DEG, [b14] * 5 + [b12] * 5)
    pairs = small_response.pairs
    g = groups_for_array(arr, pairs)
    kind = np.array([0] * 5 + [1] * 5)
    vec_groups = groups_for_array(small_response.array, pairs)  # geometry only
    for grp in range(g.n_groups):
        m = g.members(grp)
        assert np.unique(kind[pairs[m, 0]] * 2 + kind[pairs[m, 1]]).size == 1  # one ordered beam pair
        assert np.unique(vec_groups.group_of[m]).size == 1  # one vector
    assert g.n_groups > vec_groups.n_groups
    # an independent count: distinct (rounded vector, beam_i, beam_j)
    vec = pos[pairs[:, 1]] - pos[pairs[:, 0]]
    keys = {(tuple(np.round(v, 6)), kind[i], kind[j]) for v, (i, j) in zip(vec, pairs)}
    assert g.n_groups == len(keys)
    R = response_matrix(arr, pairs, small_response.freqs_hz, small_response.lmax, small_response.nside)
    sys_ = make_system(R)
    c = compress_system(sys_, g)  # the beam-aware groups are exact ...
    assert rel(precision_matrix(c), precision_matrix(sys_)) < EXACT
    with pytest.raises(ValueError, match="refusing to merge"):  # ... the geometric ones are not
        compress_system(sys_, vec_groups)
    # beam labels given directly
    g2 = redundant_groups(pos, pairs, beam_ids=["d14"] * 5 + ["d12"] * 5)
    np.testing.assert_array_equal(g2.group_of, g.group_of)


def test_grouping_errors(small_response):
    pos, pairs = small_response.array.positions_enu_m, small_response.pairs
    with pytest.raises(ValueError, match="tol_m is too large"):
        redundant_groups(pos, pairs, tol_m=20.0)
    with pytest.raises(ValueError, match="beam_ids"):
        redundant_groups(pos, pairs, beam_ids=[0, 1])
    with pytest.raises(ValueError, match="outside"):
        redundant_groups(pos, [[0, 10]])
    with pytest.raises(ValueError, match="tol_m"):
        redundant_groups(pos, pairs, tol_m=-1.0)


# ------------------------------------------------------------------ exactness


def test_rows_identical_within_groups(small_response, groups):
    worst = check_redundancy(small_response.response, groups)
    assert worst < 1e-14  # measured 2.3e-15


def test_precision_and_rhs_equal(system, groups):
    c = compress_system(system, groups)
    assert c.op.response.shape == (2, 14, system.op.response.shape[2])
    assert c.data.shape == c.inv_noise.shape == (2, NT, 14)
    assert c.op.angles is system.op.angles and c.prior is system.prior
    assert rel(precision_matrix(c), precision_matrix(system)) < EXACT
    assert rel(wiener_rhs(c), wiener_rhs(system)) < EXACT
    # group inverse noise is the sum over members
    iv = np.asarray(system.inv_noise)
    for grp in range(groups.n_groups):
        np.testing.assert_allclose(c.inv_noise[..., grp], iv[..., groups.members(grp)].sum(-1), rtol=1e-15)


def test_wiener_filter_and_draws_identical(system, groups, getkey):
    c = compress_system(system, groups)
    key = getkey()
    d0, i0 = sample_system(key, system, 3, method="cholesky")
    d1, i1 = sample_system(key, c, 3, method="cholesky")
    assert rel(i1.a_wf, i0.a_wf) < SOLVE
    assert rel(d1, d0) < SOLVE  # same P -> same Cholesky factor -> same draws for the same key
    # the CG path (matrix-free) converges to the same Wiener filter
    p = prepare_system(c, options=CGOptions(dense=False, preconditioner="nystrom"), tol=1e-8)  # rounding floor ~5e-9 sigma here
    assert bool(np.all(p.wiener.converged))
    assert rel(p.a_wf, i0.a_wf) < 1e-8  # measured 6e-12


def test_flags(system, groups):
    s = with_flags(system, groups)
    c = compress_system(s, groups)
    big = int(np.argmax(groups.counts))
    assert float(c.inv_noise[0, 1, big]) == 0.0 and complex(c.data[0, 1, big]) == 0.0
    assert np.all(np.isfinite(np.asarray(c.data)))
    assert rel(precision_matrix(c), precision_matrix(s)) < EXACT
    assert rel(wiener_rhs(c), wiener_rhs(s)) < EXACT
    a0 = jnp.linalg.solve(precision_matrix(s), wiener_rhs(s)[..., None])
    a1 = jnp.linalg.solve(precision_matrix(c), wiener_rhs(c)[..., None])
    assert rel(a1, a0) < SOLVE
    # flagged samples holding NaN / Inf are ignored by the compression
    bad = np.array(s.data)
    iv = np.asarray(s.inv_noise)
    bad[iv == 0] = np.where(np.arange((iv == 0).sum()) % 2, np.nan, np.inf)
    c_bad = compress_system(s._replace(data=jnp.asarray(bad)), groups)
    np.testing.assert_array_equal(np.asarray(c_bad.data), np.asarray(c.data))


def test_fluctuation_covariance(system, groups):
    """Cov of X^T W^1/2 w + S^-1/2 w_a is X^T W X + S^-1 = P, compressed or not.

    fluctuation_rhs draws ``adjoint(op, sqrt(W) (w_r + i w_i)) + sqrt(S^-1) w_a``; that
    map is linear in the unit normals, so its covariance is J J^T with J its Jacobian
    (exact, no sampling).
    """
    s = with_flags(system, groups)
    c = compress_system(s, groups)

    def cov(sys_):
        shape = sys_.data.shape
        nw = int(np.prod(shape))

        def lin(z):
            wr, wi, wa = z[:nw].reshape(shape), z[nw : 2 * nw].reshape(shape), z[2 * nw :].reshape(sys_.prior.inv_var.shape)
            return adjoint(sys_.op, jnp.sqrt(sys_.inv_noise) * (wr + 1j * wi)) + jnp.sqrt(sys_.prior.inv_var) * wa

        z0 = jnp.zeros(2 * nw + sys_.prior.inv_var.size)
        J = jax.jacfwd(lin)(z0)  # (Nf, n, Nz)
        return jnp.einsum("fiz,fjz->fij", J, J)

    C0, C1 = cov(s), cov(c)
    assert rel(C1, C0) < EXACT
    assert rel(C0, precision_matrix(s)) < EXACT
    # and fluctuation_rhs itself runs on the compressed system (fewer variates, same law)
    fl = fluctuation_rhs(jax.random.PRNGKey(0), c)
    assert fl.shape == s.prior.mean.shape and bool(jnp.all(jnp.isfinite(fl)))


def test_frame_kept(small_response, groups):
    n = small_response.response.shape[2]
    M = jnp.asarray(np.linalg.qr(np.random.default_rng(3).normal(size=(n, n)))[0])
    s = make_system(small_response.response, frame=M)
    c = compress_system(s, groups)
    assert c.op.frame is M
    assert rel(precision_matrix(c), precision_matrix(s)) < EXACT
    assert rel(wiener_rhs(c), wiener_rhs(s)) < EXACT


def test_jit_and_purity(system, groups):
    before = [np.array(x) for x in (system.op.response, system.data, system.inv_noise)]
    c = compress_system(system, groups)
    cj = jax.jit(lambda s: compress_system(s, groups, check=False))(system)
    for a, b in zip(jax.tree_util.tree_leaves(c), jax.tree_util.tree_leaves(cj)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for x, y in zip(before, (system.op.response, system.data, system.inv_noise)):
        np.testing.assert_array_equal(x, np.asarray(y))
    with pytest.raises(TypeError, match="outside jax.jit"):
        jax.jit(lambda s: compress_system(s, groups))(system)
    with pytest.raises(ValueError, match="groups cover"):
        compress_system(system._replace(op=system.op._replace(response=system.op.response[:, :40]),
                                        data=system.data[..., :40], inv_noise=system.inv_noise[..., :40]), groups)
    with pytest.raises(ValueError, match="finite and >= 0"):
        compress_system(system._replace(inv_noise=-system.inv_noise), groups)
    # the core on its own
    d, w = compress_visibilities(system.data, system.inv_noise, jnp.asarray(groups.group_of), groups.n_groups)
    np.testing.assert_array_equal(np.asarray(d), np.asarray(c.data))


# ------------------------------------------------------------------ responses and problems


def test_unique_response(small_response, groups):
    args = (small_response.freqs_hz, small_response.lmax, small_response.nside)
    Ru = unique_response(small_response.array, groups, *args)
    assert Ru.shape == (2, 14, small_response.response.shape[2])
    assert rel(Ru, small_response.response[:, groups.representative]) < 1e-14  # measured 7e-16
    Rs = unique_response(small_response.array, groups, *args, method="sht")
    assert rel(Rs, small_response.response[:, groups.representative]) < 1e-12  # measured 2e-14
    cross, auto = redundant_responses(small_response.array, groups, *args)
    assert rel(cross, small_response.response) < 1e-14
    nant = 10
    auto_full = response_matrix(small_response.array, np.stack([np.arange(nant)] * 2, 1), *args)
    assert rel(auto, auto_full) < 1e-14


def test_compress_problem(small_response, groups, getkey):
    arr = small_response.array
    args = (small_response.freqs_hz, small_response.lmax, small_response.nside)
    cross, auto = redundant_responses(arr, groups, *args)
    n = cross.shape[2]
    rng = np.random.default_rng(5)
    a_true = rng.normal(size=(2, n))
    a_true[:, 0] = 300.0  # a positive monopole dominates: positive autos for the radiometer noise
    prior = Prior(jnp.asarray(a_true + rng.normal(size=a_true.shape)), jnp.full((2, n), 0.5))
    flags = rng.uniform(size=(2, NT, 45)) < 0.2
    flags[1, 2, groups.members(0)] = True  # a whole group flagged at one time
    prob = build_problem(
        arr, small_response.freqs_hz, np.linspace(0, 1.2, NT), *args[1:], a_true=a_true, prior=prior,
        flags=flags, key=getkey(), responses=(cross, auto),
    )
    small = compress_problem(prob, arr)
    assert small.response.shape[1] == 14 and small.data.shape == (2, NT, 14)
    np.testing.assert_array_equal(small.antpairs, prob.antpairs[groups.representative])
    assert float(small.weights[1, 2, 0]) == 0.0 and complex(small.data[1, 2, 0]) == 0.0
    assert bool(jnp.all(jnp.isfinite(small.sigma))) and bool(jnp.all(small.sigma > 0))
    exact = compress_system(prob.system(), groups)
    assert rel(small.system().inv_noise, exact.inv_noise) < 1e-15  # sigma round trip: ~2 ulp
    assert rel(precision_matrix(small.system()), precision_matrix(prob.system())) < EXACT
    assert rel(wiener_rhs(small.system()), wiener_rhs(prob.system())) < EXACT
    # the samplers take it as any Problem
    import gcrsky

    key = getkey()
    p0 = gcrsky.prepare(prob, method="cholesky")
    p1 = gcrsky.prepare(small, method="cholesky")
    assert rel(p1.a_wf, p0.a_wf) < SOLVE
    assert rel(gcrsky.draw(key, p1, 2)[0], gcrsky.draw(key, p0, 2)[0]) < SOLVE
    # unchanged metadata; the original is untouched
    assert small.auto_response is prob.auto_response and small.prior is prob.prior
    assert prob.response.shape[1] == 45
    # from the layout the Problem records (build_problem stores positions and beam labels)
    assert prob.config is None
    small_rec = compress_problem(prob)
    np.testing.assert_array_equal(np.asarray(small_rec.data), np.asarray(small.data))
    np.testing.assert_array_equal(small_rec.antpairs, small.antpairs)
    with pytest.raises(ValueError, match="pass array"):
        compress_problem(dataclasses.replace(prob, antpos_enu_m=None))  # no recorded layout, no array
    # the recorded beam labels count: baselines whose antennas carry other labels are not merged
    split = dataclasses.replace(prob, beam_ids=np.arange(10) % 2)
    assert compress_problem(split).response.shape[1] > small.response.shape[1]
    with pytest.raises(ValueError, match="different antenna pairs"):
        compress_problem(prob, groups=groups_for_array(arr, antpairs(10)[::-1]))


def test_large_hex_counts():
    """37-antenna HERA-like hexagon: 666 baselines, grouping vs an independent count."""
    pos = hex_array((4, 5, 6, 7, 6, 5, 4), 14.6)
    pairs = antpairs(37)
    g = redundant_groups(pos, pairs)
    vec = pos[pairs[:, 1]] - pos[pairs[:, 0]]
    assert g.n_baselines == 666
    assert g.n_groups == len({tuple(np.round(v, 6)) for v in vec})
    assert g.max_offset_m.max() < 1e-13
