"""Tests of the rotation, the visibility operator X and the normal operator P.

References used:
* the complex-alm definition of the rotation ``a_lm exp(i m dphi)`` evaluated in
  NumPy (independent of :func:`gcrsky.sphere.rotate`);
* the response recomputed by quadrature at another reference angle;
* dense linear algebra (``dense_matrix``, ``X^T W X`` by NumPy, eigenvalues);
* the analytic m-mode structure of P for uniform full-day coverage (DESIGN §4);
* the physical sky: a compact blob at RA alpha transits the zenith at LST alpha.

Tolerances: algebraic identities on O(1)-scaled quantities use ``ALG = 1e-12``
relative (float64 rounding over sums of ~1e3 terms is ~1e-14); specific ones are
justified where they appear.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array, response_matrix
from gcrsky.model import LinearSystem, Prior, VisOperator, adjoint, apply, dense_matrix
from gcrsky.model.operator import n_in
from gcrsky.model.system import precision_apply, precision_matrix, precision_matrix_by_time
from gcrsky.solvers.preconditioners import apply_preconditioner, m_block_preconditioner, m_blocks
from gcrsky.sphere import mode_table, n_alm, n_params, real_basis, realify, rotate, rotate_complex_alm, unrealify

ALG = 1e-12
#: Every operator in this file has NT angles, so apply/adjoint/precision_matrix compile once.
NT = 16


# gcrsky's rotate / rotate_complex_alm / apply_preconditioner are not jitted themselves
# (callers jit); jitting them here compiles each once instead of op by op (~5x faster).
rotate_j = jax.jit(rotate)
rotate_complex_alm_j = jax.jit(rotate_complex_alm, static_argnums=2)
apply_preconditioner_j = jax.jit(apply_preconditioner)
precision_apply_j = jax.jit(precision_apply)


def rel_err(x, ref) -> float:
    x, ref = np.asarray(x), np.asarray(ref)
    return float(np.max(np.abs(x - ref)) / np.max(np.abs(ref)))


def numpy_apply(R, angles, a, lmax):
    """Reference X a: rotate complex alm by exp(i m t) in NumPy, realify, contract with R."""
    R, a = np.asarray(R), np.asarray(a)
    m = mode_table(lmax).m[: n_alm(lmax)]
    alm = unrealify(a, lmax)  # (Nf, nalm)
    out = []
    for t in np.asarray(angles):
        rot = realify(alm * np.exp(1j * m * t), lmax)  # (Nf, n)
        out.append(np.einsum("fbk,fk->fb", R, rot))
    return np.stack(out, axis=1)  # (Nf, Nt, Nbl)


@pytest.fixture
def op(small_response, getkey):
    angles = jax.random.uniform(getkey(), (NT,), minval=0.0, maxval=2 * np.pi)
    return VisOperator(small_response.response, angles)


def random_a(key, nf, n):
    return np.asarray(jax.random.normal(key, (nf, n)))


def random_v(key, shape):
    k1, k2 = jax.random.split(key)
    return jax.random.normal(k1, shape) + 1j * jax.random.normal(k2, shape)


# ---------------------------------------------------------------------------- rotation


LMAX_ROT = 10


def test_rotate_equals_complex_alm_rotation(getkey):
    n = n_params(LMAX_ROT)
    a = random_a(getkey(), 3, n)
    for dphi in (0.0, 0.37, -2.1, 5.0):
        via_complex = realify(np.asarray(rotate_complex_alm_j(unrealify(a, LMAX_ROT), dphi, LMAX_ROT)), LMAX_ROT)
        assert rel_err(rotate_j(a, dphi), via_complex) < ALG
        # and against the NumPy definition a_lm exp(i m dphi)
        m = mode_table(LMAX_ROT).m[: n_alm(LMAX_ROT)]
        ref = realify(unrealify(a, LMAX_ROT) * np.exp(1j * m * dphi), LMAX_ROT)
        assert rel_err(rotate_j(a, dphi), ref) < ALG


def test_rotate_orthogonal_composes_and_periodic(getkey):
    n = n_params(LMAX_ROT)
    x, y = 0.8, -2.3
    Qx = np.asarray(rotate_j(np.eye(n), x))  # row i = rotate(e_i, x), i.e. Qx = Q(x)^T
    np.testing.assert_allclose(Qx @ Qx.T, np.eye(n), atol=ALG)
    # transpose is the inverse rotation
    np.testing.assert_allclose(Qx.T, np.asarray(rotate_j(np.eye(n), -x)), atol=ALG)
    a = random_a(getkey(), 2, n)
    assert rel_err(rotate_j(rotate_j(a, x), y), rotate_j(a, x + y)) < ALG
    # 2 pi: errors ~ m * 2 pi * eps ~ 1e-14 for m <= 10
    assert rel_err(rotate_j(a, 2 * np.pi), a) < ALG
    assert rel_err(rotate_j(a, -4 * np.pi), a) < ALG
    # m = 0 entries never change
    m0 = mode_table(LMAX_ROT).m == 0
    np.testing.assert_array_equal(np.asarray(rotate_j(a, x))[:, m0], a[:, m0])


def test_rotation_shifts_the_map_to_smaller_ra(getkey):
    """rotate(a, d) is the sky I'(ra) = I(ra + d): a feature at RA alpha moves to alpha - d."""
    n = n_params(LMAX_ROT)
    a = random_a(getkey(), 1, n)[0]
    rng = np.random.default_rng(0)
    theta = jnp.asarray(np.arccos(rng.uniform(-1, 1, 50)))
    phi = jnp.asarray(rng.uniform(0, 2 * np.pi, 50))
    d = 0.9
    lhs = real_basis(LMAX_ROT, theta, phi) @ rotate_j(a, d)
    rhs = real_basis(LMAX_ROT, theta, phi + d) @ a
    assert rel_err(lhs, rhs) < ALG


def test_rotate_traced_angle_vmap_and_jit(getkey):
    n = n_params(LMAX_ROT)
    a = random_a(getkey(), 2, n)
    angles = jnp.linspace(-3, 3, 5)
    batched = jax.jit(jax.vmap(rotate, in_axes=(None, 0)))(a, angles)
    for i, t in enumerate(angles):
        assert rel_err(batched[i], rotate_j(a, float(t))) < ALG


# ---------------------------------------------------------------- the operator X


def test_apply_matches_numpy_reference(op, small_response, getkey):
    nf, _, n = op.response.shape
    a = random_a(getkey(), nf, n)
    ref = numpy_apply(op.response, op.angles, a, small_response.lmax)
    V = apply(op, a)
    assert V.shape == (nf, op.angles.shape[0], op.response.shape[1])
    assert rel_err(V, ref) < ALG


def test_apply_is_linear(op, getkey):
    nf, _, n = op.response.shape
    a, b = random_a(getkey(), nf, n), random_a(getkey(), nf, n)
    alpha, beta = 1.7, -0.3
    assert rel_err(apply(op, alpha * a + beta * b), alpha * apply(op, a) + beta * apply(op, b)) < ALG


def test_adjoint_dot_product(op, getkey):
    """<X a, v> = Re(vdot(v, X a)) equals a . X^T v (the realified inner product)."""
    nf, nbl, n = op.response.shape
    for _ in range(3):
        a = random_a(getkey(), nf, n)
        v = random_v(getkey(), (nf, op.angles.shape[0], nbl))
        lhs = jnp.vdot(v, apply(op, a)).real
        rhs = jnp.sum(a * adjoint(op, v))
        scale = jnp.linalg.norm(apply(op, a)) * jnp.linalg.norm(v)  # Cauchy-Schwarz bound
        assert abs(lhs - rhs) < ALG * scale


def test_dense_matrix_agrees_with_apply_and_adjoint(op, getkey):
    nf, nbl, n = op.response.shape
    X = dense_matrix(op)
    assert X.shape == (nf, op.angles.shape[0], nbl, n)
    a = random_a(getkey(), nf, n)
    assert rel_err(jnp.einsum("ftbk,fk->ftb", X, a), apply(op, a)) < ALG
    v = random_v(getkey(), (nf, op.angles.shape[0], nbl))
    # realified transpose: X^T v = Re(X)^T Re(v) + Im(X)^T Im(v) = Re(X^H v)
    assert rel_err(jnp.einsum("ftbk,ftb->fk", jnp.conj(X), v).real, adjoint(op, v)) < ALG


def test_apply_rejects_bad_shapes(op):
    nf, nbl, n = op.response.shape
    with pytest.raises(ValueError):
        apply(op, jnp.zeros((nf, n + 1)))
    with pytest.raises(ValueError):
        adjoint(op, jnp.zeros((nf, op.angles.shape[0] + 1, nbl), complex))


def test_vmap_over_coefficients_equals_loop(op, getkey):
    nf, _, n = op.response.shape
    A = jax.random.normal(getkey(), (4, nf, n))
    batched = jax.vmap(apply, in_axes=(None, 0))(op, A)
    for i in range(4):
        assert rel_err(batched[i], apply(op, A[i])) < ALG


def test_vmap_over_angle_sets_equals_loop(small_response, getkey):
    R = small_response.response
    a = random_a(getkey(), R.shape[0], R.shape[2])
    angle_sets = jax.random.uniform(getkey(), (3, NT), maxval=2 * np.pi)
    batched = jax.vmap(lambda ang: apply(VisOperator(R, ang), a))(angle_sets)
    for i in range(3):
        assert rel_err(batched[i], apply(VisOperator(R, angle_sets[i]), a)) < ALG


def test_jvp_in_angles(op, small_response, getkey):
    """d(X a)/d(angles): JVP vs the analytic derivative and vs central differences.

    Analytic: d/dt [a_lm exp(i m t)] = i m a_lm exp(i m t).  Central differences with
    h = 1e-5 have truncation error ~ h^2 m^3 / 6 ~ 4e-9 (m <= 6) and rounding
    ~ eps / h ~ 2e-11, relative: tolerance 1e-7.
    """
    nf, _, n = op.response.shape
    lmax = small_response.lmax
    a = random_a(getkey(), nf, n)
    tangent = jax.random.normal(getkey(), op.angles.shape)
    f = lambda ang: apply(VisOperator(op.response, ang), a)  # noqa: E731
    _, jvp = jax.jvp(f, (op.angles,), (tangent,))
    m = mode_table(lmax).m[: n_alm(lmax)]
    alm = unrealify(np.asarray(a), lmax)
    R = np.asarray(op.response)
    analytic = np.stack(
        [
            tangent[i] * np.einsum("fbk,fk->fb", R, realify(1j * m * alm * np.exp(1j * m * t), lmax))
            for i, t in enumerate(np.asarray(op.angles))
        ],
        axis=1,
    )
    assert rel_err(jvp, analytic) < ALG
    h = 1e-5
    fd = (f(op.angles + h * tangent) - f(op.angles - h * tangent)) / (2 * h)
    assert rel_err(jvp, fd) < 1e-7


# --------------------------------------------- quadrature: rotation == recomputed response


def test_rotation_equals_recomputed_response(small_array, small_response):
    """R(lst_ref = d) must equal R(0) rotated by d, up to pixel-quadrature error.

    The rotated grid samples the sky at other points, so the two differ by the
    quadrature error of the integrand beam x fringe x Y_lm.  Its band limit is set
    by the longest baseline (43.8 m = 14.9 wavelengths at 102 MHz, 2 pi b/lambda ~ 94)
    plus the beam; HEALPix equal-weight quadrature converges spectrally once
    nside resolves it.  Measured (lmax 6, d = 0.7 rad): nside 16 -> 0.76 (aliased),
    nside 32 -> 1.8e-8, nside 64 -> 1.2e-13 (rounding).  Asserted: monotone
    decrease, < 1e-6 at nside 32 and < 1e-11 at nside 64 (~50x margins).
    """
    pairs, freqs, lmax = small_response.pairs, small_response.freqs_hz, small_response.lmax
    d = 0.7
    errs = {}
    for nside in (16, 32, 64):
        if nside == small_response.nside:
            R0 = small_response.response
        else:
            R0 = response_matrix(small_array, pairs, freqs, lmax, nside)
        Rd = response_matrix(small_array, pairs, freqs, lmax, nside, lst_ref_rad=d)
        Rrot = dense_matrix(VisOperator(R0, jnp.asarray([d])))[:, 0]
        errs[nside] = float(jnp.linalg.norm(Rrot - Rd) / jnp.linalg.norm(Rd))
    print("relative error of rotated vs recomputed response:", errs)
    assert errs[16] > errs[32] > errs[64]
    assert errs[32] < 1e-6
    assert errs[64] < 1e-11


def blob_alm(lmax, theta0, phi0, sigma):
    """Realified alm of an axisymmetric Gaussian-smoothed spot at (theta0, phi0)."""
    from scipy.special import sph_harm_y

    tab = mode_table(lmax)
    nalm = n_alm(lmax)
    ell, m = tab.ell[:nalm], tab.m[:nalm]
    alm = np.exp(-0.5 * ell * (ell + 1) * sigma**2) * np.conj(sph_harm_y(ell, m, theta0, phi0))
    return realify(alm, lmax)


def test_rotation_direction_blob_transits_at_its_ra():
    """A compact source at (RA alpha, dec = site latitude) peaks in an autocorrelation at LST alpha.

    The beam is axisymmetric about the zenith and the blob about its centre, so
    the auto-visibility V(lst) is symmetric about the transit; the peak is
    located by a parabola through the three best samples of a 0.5 deg scan.
    Pixelisation (nside 32, 1.8 deg pixels) can shift it by a small fraction of a
    pixel; tolerance 0.1 deg (the wrong sign would put it at -alpha, 115 deg away).
    The same blob at the mirrored declination (+30.7 deg, 61 deg = 5.3 blob sigmas
    from the zenith track) must give a peak > 100 times fainter (the band-limited
    blob's ringing, b_16 = 4e-3, sets the floor; measured ratio: see the print).
    """
    lmax, nside = 16, 32
    array = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    R = response_matrix(array, np.array([[0, 0]]), [100e6], lmax, nside)
    alpha = 1.0
    lat = np.deg2rad(HERA_LATITUDE_DEG)
    step = np.deg2rad(0.5)
    lsts = np.arange(720) * step

    def scan(dec):
        a = jnp.asarray(blob_alm(lmax, np.pi / 2 - dec, alpha, 0.2))[None]
        return np.asarray(apply(VisOperator(R, jnp.asarray(lsts)), a).real[0, :, 0])

    v = scan(lat)
    i = int(np.argmax(v))
    y0, y1, y2 = v[i - 1], v[i], v[(i + 1) % v.size]
    peak = lsts[i] + step * 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    print(f"blob at RA {np.rad2deg(alpha):.3f} deg peaks at LST {np.rad2deg(peak):.4f} deg")
    assert abs(np.rad2deg(peak - alpha)) < 0.1
    v_mirror = scan(-lat)
    print(f"mirrored-declination blob: peak ratio {v_mirror.max() / v.max():.2e}")
    assert v_mirror.max() < 1e-2 * v.max()


# ----------------------------------------------------------------- the normal operator P


def make_system(op, key, *, time_dependent=True, prior=True):
    nf, nbl, _ = op.response.shape
    n = n_in(op)
    nt = op.angles.shape[0]
    k1, k2, k3, k4 = jax.random.split(key, 4)
    if time_dependent:
        inv_noise = jax.random.uniform(k1, (nf, nt, nbl), minval=0.5, maxval=2.0)
    else:
        inv_noise = jnp.broadcast_to(jax.random.uniform(k1, (nf, 1, nbl), minval=0.5, maxval=2.0), (nf, nt, nbl))
    # scale the data term so it dominates some directions and the prior others
    inv_noise = inv_noise * (1e3 / jnp.max(jnp.abs(op.response)) ** 2)
    inv_var = jax.random.uniform(k2, (nf, n), minval=0.1, maxval=10.0) if prior else jnp.zeros((nf, n))
    mean = jax.random.normal(k3, (nf, n))
    data = random_v(k4, (nf, nt, nbl))
    return LinearSystem(op, data, inv_noise, Prior(mean, inv_var))


def test_precision_apply_matches_dense(op, getkey):
    system = make_system(op, getkey())
    P = precision_matrix(system)
    nf, _, n = op.response.shape
    # independent dense reference: Re(X^H W X) + S^-1 from the materialised X
    X = np.asarray(dense_matrix(op))
    W = np.asarray(system.inv_noise)
    ref = np.einsum("ftbk,ftb,ftbj->fkj", np.conj(X), W, X).real + np.stack(
        [np.diag(d) for d in np.asarray(system.prior.inv_var)]
    )
    assert rel_err(P, ref) < ALG
    for _ in range(3):
        a = random_a(getkey(), nf, n)
        assert rel_err(precision_apply_j(system, a), np.einsum("fij,fj->fi", P, a)) < ALG


def test_precision_by_m_equals_dense_reference_with_frame_map(op, getkey):
    """The m-block construction against P from the materialised X_t M, time-dependent weights.

    A dense random frame map (n_resp -> n = n_resp - 5 inputs) exercises ``M^T P M``;
    the per-time sum :func:`precision_matrix_by_time` is the second reference.
    """
    nf, nbl, n_resp = op.response.shape
    M = jax.random.normal(getkey(), (n_resp, n_resp - 5))
    op_f = VisOperator(op.response, op.angles, M)
    system = make_system(op_f, getkey())
    X = np.asarray(dense_matrix(op_f))  # (Nf, Nt, Nbl, n): includes M
    W = np.asarray(system.inv_noise)
    ref = np.einsum("ftbk,ftb,ftbj->fkj", np.conj(X), W, X).real + np.stack(
        [np.diag(d) for d in np.asarray(system.prior.inv_var)])
    assert rel_err(precision_matrix(system), ref) < ALG
    assert rel_err(precision_matrix_by_time(system), ref) < ALG


def test_precision_by_m_gradients_match_finite_differences(small_response, getkey):
    """``d <G, P>`` in the angles, the weights and the response: jax.grad vs central differences.

    The derivative of P through the m-block construction is a different program from the
    per-time sum's; both must agree with finite differences (step 1e-5 on O(1) inputs:
    truncation ~1e-10 and rounding ~1e-11 relative to the ~1e2 derivative, so 1e-7).
    """
    lmax = 4
    n = n_params(lmax)
    R = small_response.response[:1, :6, :n]
    nbl = R.shape[1]
    angles = jax.random.uniform(getkey(), (5,), minval=0.0, maxval=2 * np.pi)
    W = jax.random.uniform(getkey(), (1, 5, nbl), minval=0.5, maxval=2.0)
    G = jax.random.normal(getkey(), (1, n, n))
    prior = Prior(jnp.zeros((1, n)), jnp.ones((1, n)))
    R = R / jnp.max(jnp.abs(R))

    def f(x, kind, fn):
        r, t, w = R, angles, W
        if kind == "angles":
            t = x
        elif kind == "weights":
            w = x
        else:
            r = x
        P = fn(LinearSystem(VisOperator(r, t), jnp.zeros(w.shape, complex), w, prior))
        return jnp.sum(G * P)

    for kind, x0 in (("angles", angles), ("weights", W), ("response", R)):
        d = jax.random.normal(getkey(), x0.shape, x0.real.dtype)
        if kind == "response":
            d = d + 1j * jax.random.normal(getkey(), x0.shape)
        h = 1e-5
        fd = (f(x0 + h * d, kind, precision_matrix) - f(x0 - h * d, kind, precision_matrix)) / (2 * h)
        g = jax.grad(f)(x0, kind, precision_matrix)
        # for complex inputs JAX's grad is df/dx - i df/dy, so the directional derivative is Re(g d)
        ad = jnp.sum(jnp.real(g * d))
        g_ref = jax.grad(f)(x0, kind, precision_matrix_by_time)
        assert abs(float(ad - fd)) < 1e-7 * abs(float(fd)), (kind, float(ad), float(fd))
        assert rel_err(g, g_ref) < ALG, kind


def test_precision_symmetric_positive_definite(op, getkey):
    system = make_system(op, getkey())
    P = np.asarray(precision_matrix(system))
    for f in range(P.shape[0]):
        np.testing.assert_allclose(P[f], P[f].T, rtol=0, atol=ALG * np.abs(P[f]).max())
        evals = np.linalg.eigvalsh(P[f])
        # P = (PSD data term) + S^-1, so by Weyl every eigenvalue >= min S^-1;
        # eigvalsh's absolute error is ~ n eps ||P|| ~ 1e-13 ||P||
        floor = np.asarray(system.prior.inv_var[f]).min()
        assert evals.min() >= floor - 1e-12 * np.abs(evals).max()
        # and the data term is really there (not a trivially diagonal P)
        assert evals.max() > 100 * np.asarray(system.prior.inv_var[f]).max()


def test_m_block_preconditioner_blocks_equal_dense_blocks(op, small_response, getkey):
    system = make_system(op, getkey())
    P = np.asarray(precision_matrix(system))
    pc = m_block_preconditioner(system)
    idx, mask = m_blocks(small_response.lmax)
    tab = mode_table(small_response.lmax)
    for f in range(P.shape[0]):
        for m in range(idx.shape[0]):
            sel = idx[m][mask[m]]
            assert np.all(tab.m[sel] == m) and sel.size == (small_response.lmax + 1 - m) * (1 if m == 0 else 2)
            L = np.asarray(pc.chol[f, m])
            LLt = L @ L.T
            block = P[f][np.ix_(sel, sel)]
            nb = sel.size
            # the factor carries a relative jitter 1e-12 * max diag on the diagonal
            assert rel_err(LLt[:nb, :nb], block) < 1e-11
            # padding is decoupled from the block
            assert np.all(LLt[:nb, nb:] == 0.0)


def uniform_day_operator(small_response, nt, offset=0.3):
    """nt equally spaced angles over 2 pi, each repeated NT / nt times (keeps NT angles)."""
    angles = offset + 2 * np.pi * np.arange(nt) / nt
    return VisOperator(small_response.response, jnp.asarray(np.repeat(angles, NT // nt)))


def off_block_fraction(P, lmax):
    """(lmax+1, lmax+1): max |P_ij| over i in block m, j in block m' (and all frequencies), / max |P|."""
    P = np.asarray(P)  # (Nf, n, n)
    m = mode_table(lmax).m
    M = lmax + 1
    out = np.zeros((M, M))
    for i in range(M):
        for j in range(M):
            out[i, j] = np.abs(P[:, m == i][:, :, m == j]).max() / np.abs(P).max()
    return out


def test_full_day_coverage_makes_P_block_diagonal_in_m(small_response, getkey):
    """DESIGN §4: uniform full-day coverage + time-independent noise -> P block-diagonal in m.

    Sum_t over Nt equally spaced angles of cos/sin((m +- m') t) vanishes unless
    m +- m' = 0 mod Nt.  With Nt = NT = 16 > 2 lmax every off-diagonal block vanishes
    (to rounding, 1e-12 of max|P|); the m-block preconditioner is then exact.
    """
    lmax = small_response.lmax
    op = uniform_day_operator(small_response, NT)
    system = make_system(op, getkey(), time_dependent=False)
    P = np.asarray(precision_matrix(system))
    frac = off_block_fraction(P, lmax)
    off = frac[~np.eye(lmax + 1, dtype=bool)]
    assert off.max() < ALG, f"largest off-m-block entry {off.max():.2e} of max|P|"
    # the exact preconditioner inverts P, up to its 1e-12 relative diagonal jitter, which
    # perturbs the solution by <= cond(P) * 1e-12 (x10 margin for rounding)
    pc = m_block_preconditioner(system)
    x = random_a(getkey(), *P.shape[:2])
    back = apply_preconditioner_j(pc, np.einsum("fij,fj->fi", P, x))
    cond = max(np.linalg.cond(P[f]) for f in range(P.shape[0]))
    assert rel_err(back, x) < 10 * cond * 1e-12


def test_block_structure_breaks_as_predicted(small_response, getkey):
    """The same check fails where it should: aliasing, partial coverage, time-dependent noise."""
    lmax = small_response.lmax
    offdiag = ~np.eye(lmax + 1, dtype=bool)
    # Nt = 8 distinct angles aliases m + m' = 8: exactly the blocks (2,6), (3,5) couple
    op8 = uniform_day_operator(small_response, 8)
    P = np.asarray(precision_matrix(make_system(op8, getkey(), time_dependent=False)))
    frac = off_block_fraction(P, lmax)
    mm = np.add.outer(np.arange(lmax + 1), np.arange(lmax + 1))
    aliased = (mm == 8) & offdiag
    assert frac[aliased].min() > 1e-6
    assert frac[offdiag & ~aliased].max() < ALG
    # partial coverage like the paper's (NT LSTs over 0-8 h) couples m-blocks strongly
    op_part = VisOperator(small_response.response, jnp.asarray(np.linspace(0, 8, NT) * 2 * np.pi / 24))
    frac = off_block_fraction(precision_matrix(make_system(op_part, getkey())), lmax)
    assert frac[offdiag].max() > 1e-3
    # full-day coverage but time-dependent noise: no longer block-diagonal
    op16 = uniform_day_operator(small_response, NT)
    P = np.asarray(precision_matrix(make_system(op16, getkey(), time_dependent=True)))
    assert off_block_fraction(P, lmax)[offdiag].max() > 1e-6
