"""The visibility operator X and its adjoint, as pure jitted functions.

``X`` maps realified coefficients ``a`` (Nf, n) to complex model visibilities
(Nf, Nt, Nbl): ``V[f, t, b] = sum_k R[f, b, k] rotate(a[f], angle[t])_k``.  X is
never materialised per time; :func:`dense_matrix` builds it for small problems
and tests.  The adjoint is the realified transpose: for complex ``v``,
``X^T v = sum_t rotate(Re(R^H v_t), -angle_t)`` so that
``<X a, v> = Re sum conj(v) X a = a . X^T v``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .rotation import rotate

__all__ = ["VisOperator", "apply", "adjoint", "dense_matrix"]


class VisOperator(NamedTuple):
    """A linear visibility operator (a PyTree of arrays; pass it through jit/vmap).

    Attributes:
        response: (Nf, Nbl, n) complex response at the reference angle.
        angles: (Nt,) rotation angles ``lst - lst_ref`` in radians.
    """

    response: jax.Array
    angles: jax.Array


def _check(op: VisOperator, a: jax.Array) -> None:
    nf, _, n = op.response.shape
    if a.shape[-2:] != (nf, n):
        raise ValueError(f"coefficients have shape {a.shape}, expected (..., {nf}, {n})")


@jax.jit
def apply(op: VisOperator, a: jax.Array) -> jax.Array:
    """Model visibilities ``X a``: (Nf, n) real -> (Nf, Nt, Nbl) complex."""
    _check(op, a)
    arot = jax.vmap(lambda t: rotate(a, t), out_axes=1)(op.angles)  # (Nf, Nt, n)
    return jnp.einsum("fbk,ftk->ftb", op.response, arot.astype(op.response.dtype))


@jax.jit
def adjoint(op: VisOperator, v: jax.Array) -> jax.Array:
    """Realified adjoint ``X^T v``: (Nf, Nt, Nbl) complex -> (Nf, n) real."""
    nf, nbl, n = op.response.shape
    if v.shape != (nf, op.angles.shape[0], nbl):
        raise ValueError(f"visibilities have shape {v.shape}, expected {(nf, op.angles.shape[0], nbl)}")
    y = jnp.einsum("fbk,ftb->ftk", jnp.conj(op.response), v).real  # (Nf, Nt, n)
    back = jax.vmap(lambda yt, t: rotate(yt, -t), in_axes=(1, 0), out_axes=1)(y, op.angles)
    return back.sum(axis=1)


@jax.jit
def dense_matrix(op: VisOperator) -> jax.Array:
    """Materialise X: (Nf, Nt, Nbl, n) complex with ``V = einsum('ftbk,fk->ftb', X, a)``.

    Memory Nf*Nt*Nbl*n complex; for small problems and tests.
    """
    # X_t = R rot_t  ->  rows of R rotated by -t (rot_t^T = rot_{-t})
    def one(t):
        return rotate(op.response.real, -t) + 1j * rotate(op.response.imag, -t)

    return jax.vmap(one, out_axes=1)(op.angles)
