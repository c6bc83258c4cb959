"""The m-factorised visibility products (:mod:`gcrsky.model.mfactor`) against the per-time formulas.

References: ``gcrsky.model.operator._apply_by_time`` / ``_adjoint_by_time`` (rotate the
coefficients once per time, contract with R; independently pinned in
``tests/test_operator.py`` against NumPy), the dot-product identity, loops over draws
and central finite differences.

Tolerances: ``ALG = 1e-12`` relative for algebraic identities on O(1) random inputs
(the sums have ~1e3 terms: float64 rounding ~1e-14).  Finite differences: see
:func:`test_grad_angles_response_finite_differences`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gcrsky.model import LinearSystem, Prior, VisOperator, mfactor
from gcrsky.model.operator import _adjoint_by_time, _apply_by_time, adjoint, apply, uses_mfactor
from gcrsky.model.system import precision_apply

ALG = 1e-12

m_apply = jax.jit(mfactor.apply)
m_adjoint = jax.jit(mfactor.adjoint)


def rel(x, ref) -> float:
    x, ref = np.asarray(x), np.asarray(ref)
    return float(np.max(np.abs(x - ref)) / np.max(np.abs(ref)))


def make_op(seed: int, lmax: int, nbl: int, nt: int, nf: int = 2, frame_in: int | None = None) -> VisOperator:
    """Random complex response, non-uniform angles over several turns (some negative), optional dense frame."""
    rng = np.random.default_rng(seed)
    n = (lmax + 1) ** 2
    R = rng.standard_normal((nf, nbl, n)) + 1j * rng.standard_normal((nf, nbl, n))
    angles = np.sort(rng.uniform(-7.0, 11.0, nt))
    frame = None if frame_in is None else jnp.asarray(rng.standard_normal((n, (frame_in + 1) ** 2)))
    return VisOperator(jnp.asarray(R), jnp.asarray(angles), frame)


def n_par(op: VisOperator) -> int:
    return op.response.shape[2] if op.frame is None else op.frame.shape[1]


def rand_a(op, seed, lead=()):
    return jnp.asarray(np.random.default_rng(seed).standard_normal(lead + (op.response.shape[0], n_par(op))))


def rand_v(op, seed, lead=()):
    rng = np.random.default_rng(seed)
    shape = lead + (op.response.shape[0], op.angles.shape[0], op.response.shape[1])
    return jnp.asarray(rng.standard_normal(shape) + 1j * rng.standard_normal(shape))


@pytest.mark.parametrize("lmax", [0, 1, 2, 7, 8])
def test_apply_adjoint_equal_by_time(lmax):
    """Odd and even lmax (the loops' ranges differ), down to lmax 0; Nf = 2; non-uniform angles."""
    op = make_op(lmax, lmax, 5, 9)
    a, v = rand_a(op, 1), rand_v(op, 2)
    assert rel(m_apply(op, a), _apply_by_time(op, a)) < ALG
    assert rel(m_adjoint(op, v), _adjoint_by_time(op, v)) < ALG


def test_frame_map_applied_before_rotation():
    """A dense frame map (lmax 6 parameters -> lmax 8 response): M first in X, M^T last in X^T."""
    op = make_op(3, 8, 4, 7, frame_in=6)
    a, v = rand_a(op, 4), rand_v(op, 5)
    assert rel(m_apply(op, a), _apply_by_time(op, a)) < ALG
    assert rel(m_adjoint(op, v), _adjoint_by_time(op, v)) < ALG


def test_matrix_free_frame_map():
    """A :class:`~gcrsky.sphere.FrameMap` (Wigner rotations around random per-m blocks; lmax 4 -> 6)."""
    from gcrsky.sphere import wigner_blocks
    from gcrsky.sphere.frames import FrameMap

    rng = np.random.default_rng(30)
    fm = FrameMap(wigner_blocks(6), jnp.asarray(rng.uniform(0, 3, 3)), jnp.asarray(rng.standard_normal((7, 7, 5))),
                  jnp.asarray(rng.uniform(0, 3, 3)))
    base = make_op(31, 6, 4, 7)
    op = base._replace(frame=fm)
    a = jnp.asarray(rng.standard_normal((2, 25)))
    v = rand_v(op, 32)
    assert rel(m_apply(op, a), _apply_by_time(op, a)) < ALG
    assert rel(m_adjoint(op, v), _adjoint_by_time(op, v)) < ALG


def test_dot_product_identity():
    op = make_op(6, 9, 6, 11)
    a, v = rand_a(op, 7), rand_v(op, 8)
    lhs = float(jnp.real(jnp.sum(jnp.conj(v) * m_apply(op, a))))
    rhs = float(jnp.sum(a * m_adjoint(op, v)))
    assert abs(lhs - rhs) < ALG * float(jnp.sum(jnp.abs(v) * jnp.abs(m_apply(op, a))))


def test_batched_equals_looped_and_vmap():
    op = make_op(9, 6, 5, 8)
    ab, vb = rand_a(op, 10, (3,)), rand_v(op, 11, (3,))
    got_a, got_v = m_apply(op, ab), m_adjoint(op, vb)
    assert got_a.shape == (3,) + op.angles.shape[:0] + (2, 8, 5) and got_v.shape == ab.shape
    for i in range(3):
        assert rel(got_a[i], m_apply(op, ab[i])) < ALG
        assert rel(got_v[i], m_adjoint(op, vb[i])) < ALG
    assert rel(jax.vmap(mfactor.apply, (None, 0))(op, ab), got_a) < ALG
    assert rel(jax.vmap(mfactor.adjoint, (None, 0))(op, vb), got_v) < ALG
    nested = m_apply(op, ab.reshape(3, 1, 2, -1))  # any number of leading axes
    assert rel(nested.reshape(got_a.shape), got_a) < ALG


def test_operator_dispatch():
    """``apply`` / ``adjoint`` take the m-factorised route above the cost rule's threshold and
    the per-time one below; both agree with the reference, batches included."""
    big = make_op(12, 12, 12, 17)  # Nt Nbl n = 34476 >= MFACTOR_MIN_WORK
    tiny = make_op(13, 3, 3, 5)
    assert uses_mfactor(big) and not uses_mfactor(tiny)
    for op in (big, tiny):
        a, v = rand_a(op, 14, (2,)), rand_v(op, 15, (2,))
        assert rel(apply(op, a), jax.vmap(_apply_by_time, (None, 0))(op, a)) < ALG
        assert rel(adjoint(op, v), jax.vmap(_adjoint_by_time, (None, 0))(op, v)) < ALG


def test_precision_with_time_varying_noise():
    """``P a`` through the dispatched products (m-factorised here) against the per-time reference."""
    op = make_op(16, 12, 12, 17)
    assert uses_mfactor(op)
    rng = np.random.default_rng(17)
    w = jnp.asarray(rng.uniform(0.1, 3.0, (2, 17, 12)) * (rng.uniform(size=(2, 17, 12)) > 0.2))  # flags too
    n = op.response.shape[2]
    prior = Prior(jnp.zeros((2, n)), jnp.asarray(rng.uniform(0.5, 2.0, (2, n))))
    system = LinearSystem(op, jnp.zeros((2, 17, 12), complex), w, prior)
    a = rand_a(op, 18)
    ref = _adjoint_by_time(op, w * _apply_by_time(op, a)) + prior.inv_var * a
    assert rel(jax.jit(precision_apply)(system, a), ref) < ALG


def test_grad_wrt_a_is_adjoint_and_jvp_is_apply():
    op = make_op(19, 5, 4, 6)
    a, v = rand_a(op, 20), rand_v(op, 21)
    g = jax.grad(lambda x: jnp.real(jnp.sum(jnp.conj(v) * mfactor.apply(op, x))))(a)
    assert rel(g, _adjoint_by_time(op, v)) < ALG
    da = rand_a(op, 22)
    _, t = jax.jvp(lambda x: mfactor.apply(op, x), (a,), (da,))
    assert rel(t, _apply_by_time(op, da)) < ALG


def test_grad_angles_response_finite_differences():
    """Gradients w.r.t. the angles and the response (reverse mode) and a jvp, by central differences.

    Step h = 1e-6.  The functionals are O(10-100) sums of O(1) terms: the rounding error of a
    difference is ~eps |f| / h ~ 1e-8 relative and the truncation error ~h^2 |f'''| ~ 1e-12 m^3
    (m <= 5), so 1e-6 relative leaves a margin of ~100 over both.  (The response enters linearly,
    its differences have no truncation error at all.)
    """
    op = make_op(23, 5, 4, 6)
    a, v = rand_a(op, 24), rand_v(op, 25)
    c = rand_v(op, 26)
    h, tol = 1e-6, 1e-6

    def f(angles, resp):  # through both products
        o = op._replace(angles=angles, response=resp)
        return jnp.real(jnp.sum(jnp.conj(c) * mfactor.apply(o, a))) + jnp.sum(a * mfactor.adjoint(o, v)) ** 2 / 100

    ga, gr = jax.grad(f, argnums=(0, 1))(op.angles, op.response)
    rng = np.random.default_rng(27)
    dt = jnp.asarray(rng.standard_normal(op.angles.shape))
    dr = jnp.asarray(rng.standard_normal(op.response.shape) + 1j * rng.standard_normal(op.response.shape))
    fd_t = (f(op.angles + h * dt, op.response) - f(op.angles - h * dt, op.response)) / (2 * h)
    fd_r = (f(op.angles, op.response + h * dr) - f(op.angles, op.response - h * dr)) / (2 * h)
    assert abs(float(jnp.sum(ga * dt)) - float(fd_t)) < tol * max(1.0, abs(float(fd_t)))
    # f is real of complex R: JAX's grad is df/dRe - i df/dIm, so the directional derivative is Re sum(grad dr)
    assert abs(float(jnp.real(jnp.sum(gr * dr))) - float(fd_r)) < tol * max(1.0, abs(float(fd_r)))
    _, jt = jax.jvp(lambda t: f(t, op.response), (op.angles,), (dt,))
    assert abs(float(jt) - float(fd_t)) < tol * max(1.0, abs(float(fd_t)))
    # and the same gradients through the per-time route
    def f_old(angles, resp):
        o = op._replace(angles=angles, response=resp)
        return jnp.real(jnp.sum(jnp.conj(c) * _apply_by_time(o, a))) + jnp.sum(a * _adjoint_by_time(o, v)) ** 2 / 100

    ga0, gr0 = jax.grad(f_old, argnums=(0, 1))(op.angles, op.response)
    assert rel(ga, ga0) < 1e-10 and rel(gr, gr0) < 1e-10
