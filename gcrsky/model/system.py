"""The linear system of the posterior: precision operator and right-hand sides (GCR).

With ``X_r, X_i`` the real and imaginary parts of the visibility operator acting on
realified coefficients, ``W = diag(w / sigma^2)`` the per-component inverse noise
variance and ``S^-1`` the diagonal prior precision:

* precision  ``P = X_r^T W X_r + X_i^T W X_i + S^-1``
* Wiener rhs ``b = X_r^T W d_r + X_i^T W d_i + S^-1 a0``
* GCR rhs    ``b + X_r^T W^1/2 w_r + X_i^T W^1/2 w_i + S^-1/2 w_a``, all ``w ~ N(0, I)``,
  so that the solution has covariance exactly ``P^-1``.

Everything is a pure function of a :class:`LinearSystem` PyTree; frequencies are
independent blocks (leading axis Nf).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..sphere.modes import lmax_from_nparams, mode_table, n_alm
from .operator import VisOperator, adjoint, apply, from_response_frame, n_in, response_at
from .prior import Prior

__all__ = [
    "INPUT_FAULTS",
    "LinearSystem",
    "check_system",
    "data_apply",
    "fluctuation_rhs",
    "input_faults",
    "precision_apply",
    "precision_data_matrix",
    "precision_matrix",
    "precision_matrix_by_time",
    "time_terms",
    "wiener_rhs",
]


class LinearSystem(NamedTuple):
    """Everything the posterior of the coefficients depends on.

    Attributes:
        op: the visibility operator (response (Nf, Nbl, n), angles (Nt,)).
        data: (Nf, Nt, Nbl) complex visibilities (flagged samples finite, e.g. 0).
        inv_noise: (Nf, Nt, Nbl) per-component inverse noise variance ``w / sigma^2``.
        prior: :class:`~gcrsky.model.Prior` with mean and inverse variance (Nf, n).
    """

    op: VisOperator
    data: jax.Array
    inv_noise: jax.Array
    prior: Prior


def precision_apply(system: LinearSystem, a: jax.Array) -> jax.Array:
    """Matrix-free ``P a`` for a (Nf, n); cost O(Nf Nt Nbl n)."""
    v = apply(system.op, a)
    return adjoint(system.op, system.inv_noise * v) + system.prior.inv_var * a


def time_terms(op: VisOperator, inv_noise: jax.Array):
    """Per-time terms for a ``lax.scan`` over times: ``(t -> X_t, W_t)``.

    ``X_t`` is the (Nf, Nbl, n) complex response at angle ``t``; ``W_t`` the inverse
    noise moved to a leading time axis, (Nt, Nf, Nbl).
    """
    return (lambda t: response_at(op, t)), jnp.moveaxis(inv_noise, 1, 0)  # (Nt, Nf, Nbl)


@jax.jit
def precision_matrix(system: LinearSystem) -> jax.Array:
    """Dense P, (Nf, n, n), by m-blocks of rows (:func:`precision_data_matrix`) plus ``S^-1``.

    Cost ``~8 Nf Nbl n^2`` flop, independent of the number of times (the per-time sum,
    :func:`precision_matrix_by_time`, costs ``4 Nf Nt Nbl n^2`` and is used for
    ``Nt <= 2``); memory ``O(Nf n^2 + Nf Nbl n)``.  Exact for any noise weights, frame
    map and angles, and differentiable in all of them.
    """
    if system.op.angles.shape[0] <= 2:
        return precision_matrix_by_time(system)
    return precision_data_matrix(system.op, system.inv_noise) + jax.vmap(jnp.diag)(system.prior.inv_var)


@jax.jit
def precision_matrix_by_time(system: LinearSystem) -> jax.Array:
    """Dense P accumulated over times, ``sum_t X_t^H W_t X_t + S^-1`` (the reference construction).

    Cost ``4 Nf Nt Nbl n^2``; kept as the independent check of
    :func:`precision_matrix` and for benchmarks.
    """
    op = system.op
    nf, n = op.response.shape[0], n_in(op)
    xt, w_t = time_terms(op, system.inv_noise)

    def body(acc, tw):
        t, w = tw
        X = xt(t)
        return acc + jnp.einsum("fbk,fb,fbj->fkj", jnp.conj(X), w, X).real, None

    acc, _ = jax.lax.scan(body, jnp.zeros((nf, n, n), op.response.real.dtype), (op.angles, w_t))
    return acc + jax.vmap(jnp.diag)(system.prior.inv_var)


def _m_layout(lmax: int):
    """Static tables of the realified layout by order m (:mod:`gcrsky.sphere.modes`).

    Returns ``(partner, sign, m, end)``: ``partner[k]`` the index holding the other part
    of entry k's coefficient (itself for m = 0); ``sign[k]`` = +1 on real parts with
    m > 0, -1 on imaginary parts, 0 on m = 0; ``m[k]`` the order of entry k; ``end[m]``
    one past the last real-part index of order m (its imaginary parts end at
    ``end[m] + nalm - lmax - 1``).  Order m has ``lmax + 1 - m`` entries of each part.
    """
    mt = mode_table(lmax)
    nalm = n_alm(lmax)
    k = np.arange(mt.m.size)
    partner = np.where(mt.m == 0, k, np.where(mt.is_imag, k - nalm + lmax + 1, k + nalm - lmax - 1))
    sign = np.where(mt.m == 0, 0.0, np.where(mt.is_imag, -1.0, 1.0))
    end = np.cumsum(np.arange(lmax + 1, 0, -1))
    return partner, sign, mt.m, end


#: The orders m >= 1 are done in this many loops, each with a fixed row window (the
#: largest block in its range): 1.25x the products' minimal work, four compiled bodies.
_M_LOOPS = 4


def precision_data_matrix(op: VisOperator, inv_noise: jax.Array) -> jax.Array:
    """The data term ``X^T W X`` (Nf, n, n) of P, built one order m of rows at a time.

    A rotation about the pole turns each coefficient pair by ``m t``, so the
    response at time t is ``X_t[b, k] = R[b, k] cos(m_k t) + B[b, k] sin(m_k t)``
    with ``B[b, k] = sign_k R[b, partner_k]`` (:func:`_m_layout`).  Then

        (X^T W X)[k, j] = Re sum_b ( conj(R_bk) [Wcc_b R_bj + Wcs_b B_bj]
                                     + conj(B_bk) [Wsc_b R_bj + Wss_b B_bj] )

    with the time kernels ``Wcs_b(m, m') = sum_t w_tb cos(m t) sin(m' t)`` (and the
    like) evaluated at ``(m_k, m_j)``.  For the rows of one order m these are one real
    matrix product over ``4 Nbl``: ``~8 Nbl n^2`` flop in all (1.25x that with the
    fixed row windows of the loops), whatever the number of times.  A frame map M
    enters as ``M^T (.) M``.

    The rows of order m are two contiguous runs (real and imaginary parts).  Each loop
    iteration writes a fixed-size window that ends at the run's end; the rows it
    overruns belong to lower orders, which come later (orders run downwards), so they
    are overwritten with their own values.
    """
    nf, nbl, n_resp = op.response.shape
    lmax = lmax_from_nparams(n_resp)
    nalm = n_alm(lmax)
    partner, sign, m_of, end = _m_layout(lmax)
    R = op.response
    dt = R.real.dtype
    B = R[..., partner] * jnp.asarray(sign, dt)
    ms = jnp.arange(lmax + 1, dtype=dt)
    ph = op.angles[:, None] * ms[None, :]  # (Nt, lmax+1)
    cos, sin = jnp.cos(ph), jnp.sin(ph)
    w = inv_noise.astype(dt)
    lhs_all = jnp.concatenate([R.real, R.imag, B.real, B.imag], axis=1)  # (Nf, 4 Nbl, n)
    end = jnp.asarray(end)

    def rhs(m):
        """(Nf, 4 Nbl, n): what the rows of order m multiply."""
        wc = w * cos[:, m][None, :, None]
        ws = w * sin[:, m][None, :, None]
        kcc, kcs = jnp.einsum("ftb,tn->fbn", wc, cos)[..., m_of], jnp.einsum("ftb,tn->fbn", wc, sin)[..., m_of]
        ksc, kss = jnp.einsum("ftb,tn->fbn", ws, cos)[..., m_of], jnp.einsum("ftb,tn->fbn", ws, sin)[..., m_of]
        z = kcc * R + kcs * B  # pairs with conj(R) of the rows
        zp = ksc * R + kss * B  # pairs with conj(B) of the rows
        return jnp.concatenate([z.real, z.imag, zp.real, zp.imag], axis=1)

    def rows(P, start, size, r):
        lhs = jax.lax.dynamic_slice_in_dim(lhs_all, start, size, axis=2)
        blk = jnp.einsum("fbk,fbj->fkj", lhs, r)
        return jax.lax.dynamic_update_slice_in_dim(P, blk, start, axis=1)

    P = jnp.zeros((nf, n_resp, n_resp), dt)
    if lmax > 0:
        edges = np.unique(np.linspace(1, lmax + 1, _M_LOOPS + 1).astype(int))
        for lo, hi in zip(edges[-2::-1], edges[:0:-1]):  # ranges from the highest orders down
            size = lmax + 1 - int(lo)

            def body(i, P, hi=int(hi), size=size):
                m = hi - 1 - i
                r = rhs(m)
                P = rows(P, end[m] - size, size, r)
                return rows(P, end[m] - size + nalm - lmax - 1, size, r)

            P = jax.lax.fori_loop(0, int(hi - lo), body, P)
    P = rows(P, 0, lmax + 1, rhs(0))  # order 0: real parts only
    if op.frame is None:
        return P
    Y = from_response_frame(op, P)  # P M: (Nf, n_resp, n)
    return jnp.swapaxes(from_response_frame(op, jnp.swapaxes(Y, -1, -2)), -1, -2)


@jax.jit
def wiener_rhs(system: LinearSystem) -> jax.Array:
    """``X^T W d + S^-1 a0``, (Nf, n)."""
    return adjoint(system.op, system.inv_noise * system.data) + system.prior.inv_var * system.prior.mean


@jax.jit
def fluctuation_rhs(key: jax.Array, system: LinearSystem) -> jax.Array:
    """``X_r^T W^1/2 w_r + X_i^T W^1/2 w_i + S^-1/2 w_a`` with unit normal w's, (Nf, n).

    Note both components of the data-space noise have unit variance (not 1/2):
    the reference code's ``(randn + 1j randn)/sqrt(2)`` halves this term's variance.
    """
    kr, ki, ka = jax.random.split(key, 3)
    shape = system.data.shape
    dt = system.inv_noise.dtype
    wd = jax.random.normal(kr, shape, dt) + 1j * jax.random.normal(ki, shape, dt)
    wa = jax.random.normal(ka, system.prior.inv_var.shape, dt)
    return adjoint(system.op, jnp.sqrt(system.inv_noise) * wd) + jnp.sqrt(system.prior.inv_var) * wa


def data_apply(system: LinearSystem, a: jax.Array) -> jax.Array:
    """Data part of the precision, ``X^T W X a`` for a (Nf, n)."""
    return adjoint(system.op, system.inv_noise * apply(system.op, a))


def check_system(system: LinearSystem) -> LinearSystem:
    """Check a (possibly hand-edited) system on the host; raise ``ValueError`` naming what is wrong.

    Checks: every floating leaf is float64 / complex128; the data complex, the noise, prior and angles
    real; the shapes agree (response
    (Nf, Nbl, n_resp), angles (Nt,), data and inv_noise (Nf, Nt, Nbl), prior (Nf, n)
    with ``n`` what the operator takes); ``inv_noise`` is finite and ``>= 0``; the data
    are finite wherever ``inv_noise > 0`` (flagged samples may hold anything only if
    they were cleaned, i.e. are finite: NaN times a zero weight is NaN); the prior's
    mean is finite and its inverse variance finite and ``>= 0``; angles finite.
    Under a trace (``jit``, ``vmap``, ``grad``) the types and shapes are checked (they are static) and the
    values are not (call it outside ``jit`` for those), and the values of a
    system spread over processes (arrays not fully addressable here) are not read; the value checks
    have a traceable twin, :func:`input_faults`, which the system tier folds into its result
    codes there (:data:`gcrsky.solvers.Result.BAD_INPUT`).  Cheap: host NumPy on the data,
    noise, prior and angles (the response's dtype is read without copying it).

    Returns:
        the system, unchanged.
    """
    for path, x in jax.tree_util.tree_flatten_with_path(system)[0]:
        dt = np.dtype(x.dtype) if hasattr(x, "dtype") else np.asarray(x).dtype
        if dt.kind in "fc" and dt not in (np.float64, np.complex128):
            raise ValueError(f"system{jax.tree_util.keystr(path)} is {dt}: gcrsky's solves need float64 / "
                             "complex128 (enable jax_enable_x64 before creating arrays)")
    kinds = {"data": ("c", "complex: the visibilities (a real array would drop their imaginary parts' constraint)"),
             "inv_noise": ("f", "real: an inverse variance"), "prior.mean": ("f", "real: realified coefficients"),
             "prior.inv_var": ("f", "real: an inverse variance"), "op.angles": ("f", "real: rotation angles")}
    for name, (kind, why) in kinds.items():
        x = system
        for part in name.split("."):
            x = getattr(x, part)
        dt = np.dtype(x.dtype) if hasattr(x, "dtype") else np.asarray(x).dtype
        if dt.kind != kind:
            raise ValueError(f"{name} is {dt}; it must be {why}")
    op = system.op
    nf, nbl = op.response.shape[:2]
    nt = np.shape(op.angles)[0] if np.ndim(op.angles) == 1 else None
    if nt is None:
        raise ValueError(f"op.angles must be 1-d (Nt,), got shape {np.shape(op.angles)}")
    want = (nf, nt, nbl)
    for name in ("data", "inv_noise"):
        if tuple(np.shape(getattr(system, name))) != want:
            raise ValueError(f"{name} has shape {np.shape(getattr(system, name))}, expected (Nf, Nt, Nbl) = {want}")
    n = n_in(op)
    for name in ("mean", "inv_var"):
        if tuple(np.shape(getattr(system.prior, name))) != (nf, n):
            raise ValueError(f"prior.{name} has shape {np.shape(getattr(system.prior, name))}, expected (Nf, n) = "
                             f"{(nf, n)}")
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(system)):
        return system  # under a trace: types and shapes were checked above; the values are judged in the computation
    values = (system.data, system.inv_noise, system.prior.mean, system.prior.inv_var, op.angles)
    if not all(getattr(x, "is_fully_addressable", True) for x in values):
        return system  # spread over processes (multi-host sharding): the values are judged in the computation
    w = np.asarray(system.inv_noise)
    bad = ~np.isfinite(w) | (w < 0)
    if bad.any():
        f, t, b = np.argwhere(bad)[0]
        raise ValueError(f"inv_noise must be finite and >= 0 (0 = flagged); {int(bad.sum())} entries are not, "
                         f"first at (freq {f}, time {t}, baseline {b}): {w[f, t, b]!r}")
    d = np.asarray(system.data)
    bad = ~np.isfinite(d)
    if bad.any():
        f, t, b = np.argwhere(bad)[0]
        where = "an unflagged" if w[f, t, b] > 0 else "a flagged"
        raise ValueError(f"data has {int(bad.sum())} non-finite samples, first {where} one at (freq {f}, time {t}, "
                         f"baseline {b}): {d[f, t, b]!r}; store flagged samples as 0 "
                         "(gcrsky.model.noise.clean_data) and flag bad ones")
    for name in ("mean", "inv_var"):
        x = np.asarray(getattr(system.prior, name))
        bad = ~np.isfinite(x) | ((x < 0) if name == "inv_var" else False)
        if bad.any():
            f, k = np.argwhere(bad)[0]
            raise ValueError(f"prior.{name} must be finite{' and >= 0' if name == 'inv_var' else ''}; "
                             f"{int(bad.sum())} entries are not, first at (freq {f}, parameter {k}): {x[f, k]!r}")
    if not np.all(np.isfinite(np.asarray(op.angles))):
        raise ValueError("op.angles must be finite")
    with jax.ensure_compile_time_eval():  # concrete here, even when called inside another function's trace
        bad = np.asarray(_response_faults(op.response))  # reduced where it lives (no host copy of the response)
    if bad.any():
        raise ValueError(f"op.response has non-finite entries in channel(s) {np.flatnonzero(bad).tolist()} (a NaN or "
                         "Inf beam value or frequency): rebuild the response")
    return system


def _response_faults(response) -> jax.Array:
    """(Nf,) True where a channel's response holds a NaN or Inf."""
    return ~jnp.all(jnp.isfinite(response), axis=tuple(range(1, response.ndim)))


#: The inputs :func:`input_faults` judges (the keys of its result), with what is wrong when one is bad.
INPUT_FAULTS = {
    "data": "data has non-finite samples (NaN or Inf; flagged samples too: NaN times a zero weight is NaN, "
            "store them as 0)",
    "inv_noise": "inv_noise is non-finite or negative (0 = flagged)",
    "prior.mean": "prior.mean is non-finite",
    "prior.inv_var": "prior.inv_var is non-finite or negative",
    "op.angles": "op.angles are non-finite",
    "op.response": "op.response has non-finite entries",
}


def input_faults(system: LinearSystem) -> dict[str, jax.Array]:
    """The value checks of :func:`check_system` as traceable per-channel flags (usable inside ``jit``).

    Returns:
        ``{name: (Nf,) bool}`` for each input in :data:`INPUT_FAULTS`: True where channel
        f's input is bad: ``data`` not finite (anywhere, flagged samples included, as
        :func:`check_system` refuses them: ``0 * NaN`` poisons the Wiener right-hand side),
        ``inv_noise`` non-finite or ``< 0``, ``prior.mean`` non-finite, ``prior.inv_var``
        non-finite or ``< 0``, ``op.angles`` non-finite (every channel), ``op.response`` non-finite.  Elementwise
        reductions only (no host callback, no gradient: the flags are booleans).
    """
    w, iv = system.inv_noise, system.prior.inv_var
    nf = jnp.shape(w)[0]
    return {
        "data": ~jnp.all(jnp.isfinite(system.data), axis=(-2, -1)),
        "inv_noise": ~jnp.all(jnp.isfinite(w) & (w >= 0), axis=(-2, -1)),
        "prior.mean": ~jnp.all(jnp.isfinite(system.prior.mean), axis=-1),
        "prior.inv_var": ~jnp.all(jnp.isfinite(iv) & (iv >= 0), axis=-1),
        "op.angles": jnp.broadcast_to(~jnp.all(jnp.isfinite(system.op.angles)), (nf,)),
        "op.response": _response_faults(system.op.response),
    }
