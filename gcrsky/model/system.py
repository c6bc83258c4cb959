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

from .operator import VisOperator, adjoint, apply, n_in, response_at
from .prior import Prior

__all__ = [
    "LinearSystem",
    "check_system",
    "data_apply",
    "fluctuation_rhs",
    "precision_apply",
    "precision_matrix",
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
    """Dense P, (Nf, n, n), accumulated over times (memory O(Nf n^2 + Nf Nbl n))."""
    op = system.op
    nf, n = op.response.shape[0], n_in(op)
    xt, w_t = time_terms(op, system.inv_noise)

    def body(acc, tw):
        t, w = tw
        X = xt(t)
        return acc + jnp.einsum("fbk,fb,fbj->fkj", jnp.conj(X), w, X).real, None

    acc, _ = jax.lax.scan(body, jnp.zeros((nf, n, n), op.response.real.dtype), (op.angles, w_t))
    return acc + jax.vmap(jnp.diag)(system.prior.inv_var)


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

    Checks: every floating leaf is float64 / complex128; the shapes agree (response
    (Nf, Nbl, n_resp), angles (Nt,), data and inv_noise (Nf, Nt, Nbl), prior (Nf, n)
    with ``n`` what the operator takes); ``inv_noise`` is finite and ``>= 0``; the data
    are finite wherever ``inv_noise > 0`` (flagged samples may hold anything only if
    they were cleaned, i.e. are finite: NaN times a zero weight is NaN); the prior's
    mean is finite and its inverse variance finite and ``>= 0``; angles finite.
    Traced systems are passed through unchecked (call it outside ``jit``).

    Returns:
        the system, unchanged.
    """
    leaves = jax.tree_util.tree_leaves(system)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return system
    for path, x in jax.tree_util.tree_flatten_with_path(system)[0]:
        dt = np.asarray(x).dtype
        if dt.kind in "fc" and dt not in (np.float64, np.complex128):
            raise ValueError(f"system{jax.tree_util.keystr(path)} is {dt}: gcrsky's solves need float64 / "
                             "complex128 (enable jax_enable_x64 before creating arrays)")
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
                         "(gcrsky.model.clean_data) and flag bad ones")
    for name in ("mean", "inv_var"):
        x = np.asarray(getattr(system.prior, name))
        bad = ~np.isfinite(x) | ((x < 0) if name == "inv_var" else False)
        if bad.any():
            f, k = np.argwhere(bad)[0]
            raise ValueError(f"prior.{name} must be finite{' and >= 0' if name == 'inv_var' else ''}; "
                             f"{int(bad.sum())} entries are not, first at (freq {f}, parameter {k}): {x[f, k]!r}")
    if not np.all(np.isfinite(np.asarray(op.angles))):
        raise ValueError("op.angles must be finite")
    return system
