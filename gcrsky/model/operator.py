"""The visibility operator X and its adjoint, as pure jitted functions.

``X`` maps realified coefficients ``a`` (Nf, n) to complex model visibilities
(Nf, Nt, Nbl): ``V[f, t, b] = sum_k R[f, b, k] rotate(a[f], angle[t])_k``.  X is
never materialised per time; :func:`dense_matrix` builds it for small problems
and tests.  The adjoint is the realified transpose: for complex ``v``,
``X^T v = sum_t rotate(Re(R^H v_t), -angle_t)`` so that
``<X a, v> = Re sum conj(v) X a = a . X^T v``.  Both are computed m-factorised
(:mod:`gcrsky.model.mfactor`: a rotation about the pole is a phase per order m, so the
sums over l are done once and only the Fourier sums over m per time) except for tiny
problems (:func:`uses_mfactor`); the per-time formulas stay as ``_apply_by_time`` /
``_adjoint_by_time``, the tests' reference.

With an optional fixed ``frame`` map ``M`` from the parameters' frame (e.g. ICRS,
:mod:`gcrsky.sphere.frames`) to the co-rotating one, ``X a = R rotate(M a)`` and the
adjoint gains ``M^T``.  ``M`` is either a dense real (n_resp, n) array or a
:class:`gcrsky.sphere.FrameMap` (Wigner-D rotations and aberration, applied
matrix-free in O(lmax^3)).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..sphere.frames import FrameMap, apply_frame, frame_lmax, transpose_frame
from ..sphere.rotation import rotate
from . import mfactor

__all__ = ["VisOperator", "apply", "adjoint", "dense_matrix", "response_at", "n_in", "to_response_frame", "from_response_frame", "frame_shape", "uses_mfactor",
           "MFACTOR_MIN_TIMES", "MFACTOR_MIN_WORK"]


class VisOperator(NamedTuple):
    """A linear visibility operator (a PyTree of arrays; pass it through jit/vmap).

    Attributes:
        response: (Nf, Nbl, n_resp) complex response at the reference angle.
        angles: (Nt,) rotation angles ``lst - lst_ref`` in radians.
        frame: None, a real (n_resp, n) array or a :class:`gcrsky.sphere.FrameMap`:
            the map from the parameters' frame to the co-rotating frame of the
            response (applied before the rotation).
    """

    response: jax.Array
    angles: jax.Array
    frame: jax.Array | None = None


def frame_shape(frame) -> tuple[int, int]:
    """``(n_resp, n_in)`` of a frame map (dense array or :class:`FrameMap`)."""
    if isinstance(frame, FrameMap):
        lin, lout = frame_lmax(frame)
        return (lout + 1) ** 2, (lin + 1) ** 2
    if frame.ndim != 2:
        raise ValueError(f"a dense frame map must be 2-d (n_resp, n), got shape {frame.shape}")
    return frame.shape


def n_in(op: VisOperator) -> int:
    """Length of the parameter vector the operator acts on."""
    return op.response.shape[2] if op.frame is None else frame_shape(op.frame)[1]


def _check(op: VisOperator, a: jax.Array) -> None:
    nf = op.response.shape[0]
    n = n_in(op)
    if a.shape[-2:] != (nf, n):
        raise ValueError(f"coefficients have shape {a.shape}, expected (..., {nf}, {n})")
    if op.frame is not None and frame_shape(op.frame)[0] != op.response.shape[2]:
        raise ValueError(f"frame map has {frame_shape(op.frame)[0]} outputs, the response {op.response.shape[2]} modes")


def to_response_frame(op: VisOperator, a: jax.Array) -> jax.Array:
    """``M a`` (or ``a`` without a frame map): parameters -> co-rotating coefficients."""
    if op.frame is None:
        return a
    return apply_frame(op.frame, a) if isinstance(op.frame, FrameMap) else a @ op.frame.T


def from_response_frame(op: VisOperator, b: jax.Array) -> jax.Array:
    """``M^T b`` (or ``b``): transpose of :func:`to_response_frame`, real (..., n_resp) -> (..., n)."""
    if op.frame is None:
        return b
    return transpose_frame(op.frame, b) if isinstance(op.frame, FrameMap) else b @ op.frame


#: The m-factorised products (:mod:`gcrsky.model.mfactor`) are used from this many
#: times up (and from :data:`MFACTOR_MIN_WORK` up); below, the per-time formulas.
MFACTOR_MIN_TIMES = 4
#: ... and from this product ``Nt * Nbl * n`` up (tiny problems are overhead-bound: the
#: per-time route's one einsum beats the m-factorised loops there).
MFACTOR_MIN_WORK = 2**15


def uses_mfactor(op: VisOperator) -> bool:
    """Whether :func:`apply` / :func:`adjoint` take the m-factorised route for ``op`` (static shapes).

    The rule (measured in ``benchmarks/operator_products.py``): m-factorised when
    ``Nt >= MFACTOR_MIN_TIMES`` and ``Nt * Nbl * n_resp >= MFACTOR_MIN_WORK``.
    """
    nf, nbl, n = op.response.shape
    nt = op.angles.shape[0]
    return nt >= MFACTOR_MIN_TIMES and nt * nbl * n >= MFACTOR_MIN_WORK


def _batched(fn, x, tail: int):
    """``fn`` on (..., *tail) by vmapping over the leading axes (none: ``fn(x)``)."""
    for _ in range(x.ndim - tail):
        fn = jax.vmap(fn)
    return fn(x)


@jax.jit
def apply(op: VisOperator, a: jax.Array) -> jax.Array:
    """Model visibilities ``X a``: (..., Nf, n) real -> (..., Nf, Nt, Nbl) complex.

    Leading axes are a batch of draws.  m-factorised (:func:`gcrsky.model.mfactor.apply`,
    one pass over the response for the whole batch) when :func:`uses_mfactor`, else the
    per-time formula (:func:`_apply_by_time`); the two agree to rounding.
    """
    _check(op, a)
    if uses_mfactor(op):
        return mfactor.apply(op, a)
    return _batched(lambda x: _apply_by_time(op, x), a, 2)


@jax.jit
def adjoint(op: VisOperator, v: jax.Array) -> jax.Array:
    """Realified adjoint ``X^T v``: (..., Nf, Nt, Nbl) complex -> (..., Nf, n) real (same routes as :func:`apply`)."""
    nf, nbl, n = op.response.shape
    if v.shape[-3:] != (nf, op.angles.shape[0], nbl):
        raise ValueError(f"visibilities have shape {v.shape}, expected (..., {(nf, op.angles.shape[0], nbl)})")
    if uses_mfactor(op):
        return mfactor.adjoint(op, v)
    return _batched(lambda x: _adjoint_by_time(op, x), v, 3)


@jax.jit
def _apply_by_time(op: VisOperator, a: jax.Array) -> jax.Array:
    """Reference ``X a`` by rotating ``a`` once per time: (Nf, n) -> (Nf, Nt, Nbl).

    Cost ``~8 Nf Nt Nbl n`` flop, memory Nf Nt n; kept for small problems and as the
    tests' reference for the m-factorised route.
    """
    _check(op, a)
    a = to_response_frame(op, a)
    arot = jax.vmap(lambda t: rotate(a, t), out_axes=1)(op.angles)  # (Nf, Nt, n)
    return jnp.einsum("fbk,ftk->ftb", op.response, arot.astype(op.response.dtype))


@jax.jit
def _adjoint_by_time(op: VisOperator, v: jax.Array) -> jax.Array:
    """Reference ``X^T v`` per time: (Nf, Nt, Nbl) -> (Nf, n), ``sum_t rotate(Re(R^H v_t), -t)``."""
    nf, nbl, n = op.response.shape
    if v.shape != (nf, op.angles.shape[0], nbl):
        raise ValueError(f"visibilities have shape {v.shape}, expected {(nf, op.angles.shape[0], nbl)}")
    y = jnp.einsum("fbk,ftb->ftk", jnp.conj(op.response), v).real  # (Nf, Nt, n)
    back = jax.vmap(lambda yt, t: rotate(yt, -t), in_axes=(1, 0), out_axes=1)(y, op.angles).sum(axis=1)
    return from_response_frame(op, back)


@jax.jit
def dense_matrix(op: VisOperator) -> jax.Array:
    """Materialise X: (Nf, Nt, Nbl, n) complex with ``V = einsum('ftbk,fk->ftb', X, a)``.

    Memory Nf*Nt*Nbl*n complex; for small problems and tests.
    """
    # X_t = R rot_t  ->  rows of R rotated by -t (rot_t^T = rot_{-t})
    return jax.vmap(lambda t: response_at(op, t), out_axes=1)(op.angles)


def response_at(op: VisOperator, t) -> jax.Array:
    """``X_t = R rot_t M``: (Nf, Nbl, n) complex response at rotation angle ``t``."""
    X = rotate(op.response.real, -t) + 1j * rotate(op.response.imag, -t)
    if op.frame is None:
        return X
    return from_response_frame(op, X.real) + 1j * from_response_frame(op, X.imag)
