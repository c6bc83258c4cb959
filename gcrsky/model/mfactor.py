"""m-factorised visibility products: ``X a`` and ``X^T v`` in O(Nbl n + Nt Nbl lmax).

A rotation about the pole is a phase per order m (:func:`gcrsky.sphere.rotate` turns
each realified pair ``(Re a_lm, Im a_lm)`` by ``m t``: ``re -> re c - im s``,
``im -> re s + im c``), so with ``c_m(t) = cos(m t)``, ``s_m(t) = sin(m t)`` the
visibility of :func:`gcrsky.model.apply` is

    V[f, t, b] = sum_m c_m(t) U[f, b, m] + s_m(t) W[f, b, m],
    U[f, b, m] = sum_{k in m} R[f, b, k] a[k],   W[f, b, m] = sum_{k in m} R[f, b, k] (J a)[k],

where ``k in m`` runs over the realified entries of order m (real and imaginary
parts) and ``J`` is the quarter turn of each pair: ``(J a)[Re_lm] = -Im a_lm``,
``(J a)[Im_lm] = +Re a_lm`` (0 for m = 0).  So ``U = sum_l R_re re_lm + R_im im_lm``
and ``W = sum_l R_im re_lm - R_re im_lm``, with ``R_re`` / ``R_im`` the response
columns of the Re / Im entries of (l, m).  The adjoint (``<X a, v> = Re sum conj(v)
X a = a . X^T v``) runs the steps backwards: ``Vc[b, m] = sum_t c_m(t) v[t, b]``,
``Vs`` likewise with ``s_m``, ``q_c[k] = Re sum_b conj(R[b, k]) Vc[b, m_k]`` (``q_s``
from ``Vs``) and ``X^T v = q_c + J^T q_s = q_c - J q_s``.

Cost: ``~8 Nf Nbl n`` flop per vector for U, W (one pass over R for all draws of a
batch: the per-order products have ``2 k`` columns for ``k`` draws), plus
``O(Nf Nt Nbl lmax)`` for the Fourier sums (real (Nt x lmax+1) cos / sin matrix
products; the angles are arbitrary, so no FFT), instead of ``~8 Nf Nt Nbl n`` per
vector for the per-time route.

The per-order sums over l.  In the realified layout the entries of order m are two
contiguous runs of ``lmax + 1 - m`` entries (the real parts, then, ``nalm - lmax - 1``
further on, the imaginary parts).  The orders are done in a few ``lax.scan`` /
``fori_loop`` s (:data:`N_LOOPS` over m >= 1, plus m = 0), each with a fixed window
that ends at the run's end and is as wide as the loop's longest run; the entries of
other orders inside a window are masked out of the coefficients.  So the transient
memory is one window of the response, (Nf, Nbl, 2 window) complex per order, the flops
are ``<= 1.25x`` the minimum with 4 loops and the program size does not grow with
lmax.  Measured alternatives (``benchmarks/operator_products.py --variants``): a
padded (lmax+1, 2 (lmax+1)) grid of R gathered per call (2x R of transient memory)
and the triangle packing (order m with order lmax - m in one row, a 1x R copy per
call) were slower on the 2-core CPU (lmax 100, 630 baselines, 30 times: 267 and 180
ms against 37 ms for one vector, 343 and 197 against 100 ms for 16; lmax 300: 4.4 and
2.7 s against 0.35 s; lmax 100, 45 baselines, 1000 times: 14 and 24 against 16 ms):
writing a fresh R-sized array each call costs more than the whole product.  Static
per-order slices (one product per order) were as fast as these loops at lmax 100 but
took 7.6 s to compile, growing with lmax.

Only ``op.frame is None`` is the m-factorised product itself; with a frame map ``M``
the frame is applied first (``X a = R rot_t(M a)``, the frame acts before the
rotation: :func:`to_response_frame` before, :func:`from_response_frame` after the adjoint), exactly as the
per-time route does.

Everything is traced (angles, response, coefficients): ``jit``, ``vmap``, ``grad`` and
``jvp`` go through.  Under ``vmap`` the draws end up as extra columns of the same
per-order products.  Costs measured against the per-time route (2026-12-03, the shared
2-core CPU at load ~12-16, so +-50 %): reverse mode through the *response* is the one
place it loses (lmax 60, 300 baselines, 30 times: ``grad`` of ``X a`` and ``X^T v``
w.r.t. response and angles 230-280 ms against 140-150 ms, while the forward products
take 9-15 against 64-74 ms; each loop's transpose starts its own R-sized cotangent);
and it compiles slower (``jit(precision_apply)`` 2.8-3.9 s against 0.4-0.6 s,
its gradient w.r.t. the whole system 7-11 s against 1.3-1.4 s, at lmax 6 and 40).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..sphere.frames import FrameMap, apply_frame, transpose_frame
from ..sphere.modes import lmax_from_nparams, n_alm

__all__ = ["N_LOOPS", "Layout", "adjoint", "apply", "from_response_frame", "layout", "order_sums",
           "order_sums_transpose", "to_response_frame"]

#: Loops over the orders m >= 1, each with its own fixed window (the widest run of its
#: range): the flops are ``<= (1 + 1/N_LOOPS)`` the minimum; N_LOOPS compiled bodies.
N_LOOPS = 4


class Layout(NamedTuple):
    """Static (NumPy) tables of the realified layout by order, for one lmax.

    Attributes:
        lmax: the band limit.
        start: (lmax+2,) ``start[m]`` the index of the first real part of order m
            (``start[lmax+1] = nalm``); the run of order m is ``start[m]..start[m+1]-1``.
        off: ``nalm - lmax - 1``: the imaginary part of entry k (real part, m >= 1) is at ``k + off``.
        order: (n,) the order m of every realified entry.
        partner: (n,) the index of the other part of the entry's pair (itself for m = 0).
        sign: (n,) ``J``'s sign: ``(J a)[k] = sign[k] a[partner[k]]`` (-1 on real parts,
            +1 on imaginary parts, 0 for m = 0).
        ranges: the ``(lo, hi)`` order ranges (m >= 1) of the loops.
    """

    lmax: int
    start: np.ndarray
    off: int
    order: np.ndarray
    partner: np.ndarray
    sign: np.ndarray
    ranges: tuple


@functools.lru_cache(maxsize=64)
def layout(lmax: int) -> Layout:
    """:class:`Layout` for ``lmax`` (cached)."""
    L = int(lmax)
    nalm = n_alm(L)
    off = nalm - L - 1
    start = np.concatenate([[0], np.cumsum(np.arange(L + 1, 0, -1))]).astype(np.int64)
    order = np.concatenate([np.repeat(np.arange(L + 1), np.arange(L + 1, 0, -1)),
                            np.repeat(np.arange(1, L + 1), np.arange(L, 0, -1))]).astype(np.int64)
    k = np.arange(order.size)
    is_im = k >= nalm
    partner = np.where(order == 0, k, np.where(is_im, k - off, k + off))
    sign = np.where(order == 0, 0.0, np.where(is_im, 1.0, -1.0))
    ranges = ()
    if L > 0:
        edges = np.unique(np.linspace(1, L + 1, N_LOOPS + 1).astype(int))
        ranges = tuple((int(lo), int(hi)) for lo, hi in zip(edges[:-1], edges[1:]))
    return Layout(L, start, off, order, partner, sign, ranges)


def _windows(lay: Layout, m, width: int):
    """Starts of the real- and imaginary-part windows of order ``m`` (traced or static)."""
    end = jnp.asarray(lay.start)[m + 1] if isinstance(m, jax.Array) else int(lay.start[m + 1])
    return end - width, end + lay.off - width


def _masked(x: jax.Array, order: jax.Array, s, width: int, m) -> jax.Array:
    """``x[..., s:s+width, :]`` with the rows of other orders than ``m`` zeroed."""
    keep = jax.lax.dynamic_slice_in_dim(order, s, width) == m
    return jax.lax.dynamic_slice_in_dim(x, s, width, axis=-2) * keep[:, None]


def order_sums(R: jax.Array, X: jax.Array, lmax: int) -> jax.Array:
    """Per-order sums ``Y[m, f, b, c] = sum_{k of order m} R[f, b, k] X[f, k, c]``.

    Args:
        R: (Nf, Nbl, n) complex response, ``n = (lmax+1)^2``.
        X: (Nf, n, C) real columns (e.g. ``[a, J a]`` for each draw).
        lmax: the band limit (static).

    Returns:
        (lmax+1, Nf, Nbl, C) complex.
    """
    lay = layout(lmax)
    order = jnp.asarray(lay.order)
    X = X.astype(R.real.dtype)

    def part(s, width: int, m):
        Xw = _masked(X, order, s, width, m)
        Rw = jax.lax.dynamic_slice_in_dim(R, s, width, axis=-1)
        return jnp.einsum("fbj,fjc->fbc", Rw.real, Xw) + 1j * jnp.einsum("fbj,fjc->fbc", Rw.imag, Xw)

    def one(m, width: int, with_im: bool):
        s_re, s_im = _windows(lay, m, width)
        return part(s_re, width, m) + part(s_im, width, m) if with_im else part(s_re, width, m)

    outs = [one(0, lmax + 1, False)[None]]
    for lo, hi in lay.ranges:
        width = lmax + 1 - lo
        outs.append(jax.lax.scan(lambda _, m, w=width: (None, one(m, w, True)), None, jnp.arange(lo, hi))[1])
    return jnp.concatenate(outs, axis=0)


def order_sums_transpose(R: jax.Array, Z: jax.Array, lmax: int) -> jax.Array:
    """Transpose of :func:`order_sums` in the real inner product: ``Q[f, k, c] = Re sum_b conj(R[f, b, k]) Z[m_k, f, b, c]``.

    Args:
        R: (Nf, Nbl, n) complex response.
        Z: (lmax+1, Nf, Nbl, C) complex.
        lmax: the band limit (static).

    Returns:
        (Nf, n, C) real.
    """
    lay = layout(lmax)
    order = jnp.asarray(lay.order)
    nf, _, n = R.shape
    out = jnp.zeros((nf, n, Z.shape[-1]), R.real.dtype)

    def add(out, s, width: int, m, z):
        Rw = jax.lax.dynamic_slice_in_dim(R, s, width, axis=-1)
        q = jnp.einsum("fbj,fbc->fjc", Rw.real, z.real) + jnp.einsum("fbj,fbc->fjc", Rw.imag, z.imag)
        q = q * (jax.lax.dynamic_slice_in_dim(order, s, width) == m)[:, None]
        cur = jax.lax.dynamic_slice_in_dim(out, s, width, axis=-2)
        return jax.lax.dynamic_update_slice_in_dim(out, cur + q, s, axis=-2)

    out = add(out, 0, lmax + 1, 0, Z[0])
    for lo, hi in lay.ranges:
        width = lmax + 1 - lo

        def body(m, out, width=width):
            s_re, s_im = _windows(lay, m, width)
            return add(add(out, s_re, width, m, Z[m]), s_im, width, m, Z[m])

        out = jax.lax.fori_loop(lo, hi, body, out)
    return out


def _phases(angles: jax.Array, lmax: int, dtype) -> jax.Array:
    """(Nt, lmax+1, 2): ``cos(m t)``, ``sin(m t)`` for every angle t (radians) and order m."""
    ph = angles.astype(dtype)[:, None] * jnp.arange(lmax + 1, dtype=dtype)
    return jnp.stack([jnp.cos(ph), jnp.sin(ph)], axis=-1)


def to_response_frame(op, a: jax.Array) -> jax.Array:
    """``M a`` (``a`` without a frame map), (..., n) -> (..., n_resp); as :func:`gcrsky.model.operator.to_response_frame`
    (repeated here: :mod:`gcrsky.model.operator` imports this module, not the other way round)."""
    if op.frame is None:
        return a
    return apply_frame(op.frame, a) if isinstance(op.frame, FrameMap) else a @ op.frame.T


def from_response_frame(op, b: jax.Array) -> jax.Array:
    """``M^T b`` (``b`` without a frame map): the transpose of :func:`to_response_frame`."""
    if op.frame is None:
        return b
    return transpose_frame(op.frame, b) if isinstance(op.frame, FrameMap) else b @ op.frame


def _flatten(x: jax.Array, tail: int):
    """(..., *tail) -> ((K, *tail), leading shape), K the product of the leading axes (1 if none)."""
    lead = x.shape[: x.ndim - tail]
    return x.reshape((-1,) + x.shape[x.ndim - tail :]), lead


def apply(op, a: jax.Array) -> jax.Array:
    """m-factorised ``X a``: real (..., Nf, n) -> complex (..., Nf, Nt, Nbl).

    ``op`` is a :class:`~gcrsky.model.VisOperator` (response (Nf, Nbl, n_resp)
    complex, angles (Nt,) radians, optional frame map applied first).  Leading axes of
    ``a`` are a batch of draws: one pass over the response for all of them.  Equal to
    the per-time formula to rounding (``tests/test_mfactor.py``).
    """
    R = op.response
    nf, nbl, n_resp = R.shape
    a = to_response_frame(op, a)
    if a.shape[-2:] != (nf, n_resp):
        raise ValueError(f"coefficients have shape {a.shape}, expected (..., {nf}, {n_resp}) after the frame map")
    lay = layout(lmax_from_nparams(n_resp))
    dt = R.real.dtype
    ak, lead = _flatten(a.astype(dt), 2)  # (K, Nf, n)
    K = ak.shape[0]
    X = jnp.stack([ak, jnp.asarray(lay.sign, dt) * ak[..., lay.partner]], axis=-1)  # (K, Nf, n, 2 [a, Ja])
    X = jnp.moveaxis(X, 0, -2).reshape(nf, n_resp, K * 2)
    Y = order_sums(R, X, lay.lmax).reshape(lay.lmax + 1, nf, nbl, K, 2)  # U, W
    V = jnp.einsum("tmq,mfbkq->kftb", _phases(op.angles, lay.lmax, dt).astype(Y.dtype), Y)
    return V.reshape(lead + V.shape[1:])


def adjoint(op, v: jax.Array) -> jax.Array:
    """m-factorised realified adjoint ``X^T v``: complex (..., Nf, Nt, Nbl) -> real (..., Nf, n).

    Leading axes are a batch, as in :func:`apply`; a frame map's transpose is applied last.
    """
    R = op.response
    nf, nbl, n_resp = R.shape
    nt = op.angles.shape[0]
    if v.shape[-3:] != (nf, nt, nbl):
        raise ValueError(f"visibilities have shape {v.shape}, expected (..., {nf}, {nt}, {nbl})")
    lay = layout(lmax_from_nparams(n_resp))
    dt = R.real.dtype
    vk, lead = _flatten(v, 3)  # (K, Nf, Nt, Nbl)
    K = vk.shape[0]
    cs = _phases(op.angles, lay.lmax, dt).astype(jnp.result_type(vk.dtype, dt))
    Z = jnp.einsum("tmq,kftb->mfbkq", cs, vk).reshape(lay.lmax + 1, nf, nbl, K * 2)  # Vc, Vs
    q = order_sums_transpose(R, Z, lay.lmax).reshape(nf, n_resp, K, 2)
    qc, qs = jnp.moveaxis(q[..., 0], -1, 0), jnp.moveaxis(q[..., 1], -1, 0)  # (K, Nf, n)
    out = from_response_frame(op, qc - jnp.asarray(lay.sign, dt) * qs[..., lay.partner])
    return out.reshape(lead + out.shape[1:])
