"""The realified normal (precision) operator and right-hand sides of the GCR system.

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

from functools import lru_cache, partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .layout import lmax_from_nparams, mode_table
from .operator import VisOperator, adjoint, apply, n_in, response_at
from .prior import Prior

__all__ = [
    "LinearSystem",
    "precision_apply",
    "precision_matrix",
    "wiener_rhs",
    "fluctuation_rhs",
    "MBlockPreconditioner",
    "m_block_preconditioner",
    "apply_preconditioner",
    "precondition_one",
    "NystromPreconditioner",
    "nystrom_preconditioner",
    "data_apply",
    "check_float64",
    "require_x64",
]


class LinearSystem(NamedTuple):
    """Everything the posterior of the coefficients depends on.

    Attributes:
        op: the visibility operator (response (Nf, Nbl, n), angles (Nt,)).
        data: (Nf, Nt, Nbl) complex visibilities (flagged samples finite, e.g. 0).
        inv_noise: (Nf, Nt, Nbl) per-component inverse noise variance ``w / sigma^2``.
        prior: :class:`~gcrsky.prior.Prior` with mean and inverse variance (Nf, n).
    """

    op: VisOperator
    data: jax.Array
    inv_noise: jax.Array
    prior: Prior


def require_x64(what: str = "gcrsky") -> None:
    """Raise unless JAX's 64-bit mode is on (the normal equations reach condition ~1e9)."""
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            f"{what} needs float64: call jax.config.update('jax_enable_x64', True) at start-up "
            "(before creating any JAX array); float32 loses the posterior's low-l modes"
        )


def check_float64(*arrays) -> None:
    """Raise if any floating array is not 64-bit: the system's condition number reaches ~1e9."""
    for x in arrays:
        dt = jnp.asarray(x).dtype if not hasattr(x, "dtype") else x.dtype
        if jnp.issubdtype(dt, jnp.floating) and dt != jnp.float64:
            raise TypeError(
                f"gcrsky's linear algebra needs float64 but got {dt}: enable x64 with "
                "jax.config.update('jax_enable_x64', True) before creating arrays"
            )
        if jnp.issubdtype(dt, jnp.complexfloating) and dt != jnp.complex128:
            raise TypeError(
                f"gcrsky's linear algebra needs complex128 but got {dt}: enable x64 with "
                "jax.config.update('jax_enable_x64', True) before creating arrays"
            )


def precision_apply(system: LinearSystem, a: jax.Array) -> jax.Array:
    """Matrix-free ``P a`` for a (Nf, n); cost O(Nf Nt Nbl n)."""
    v = apply(system.op, a)
    return adjoint(system.op, system.inv_noise * v) + system.prior.inv_var * a


def _time_terms(op: VisOperator, inv_noise: jax.Array):
    """Per-time (X_t, W_t) pairs for a scan: X_t (Nf, Nbl, n) complex."""
    return (lambda t: response_at(op, t)), jnp.moveaxis(inv_noise, 1, 0)  # (Nt, Nf, Nbl)


@jax.jit
def precision_matrix(system: LinearSystem) -> jax.Array:
    """Dense P, (Nf, n, n), accumulated over times (memory O(Nf n^2 + Nf Nbl n))."""
    op = system.op
    nf, n = op.response.shape[0], n_in(op)
    xt, w_t = _time_terms(op, system.inv_noise)

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


# ---------------------------------------------------------------- preconditioner


@lru_cache(maxsize=32)
def m_blocks(lmax: int):
    """Index table of the m-blocks: (lmax+1, B) indices into the realified vector, and a mask.

    Block m holds Re a_lm (l = m..lmax) then Im a_lm (m > 0); padded to the largest size B.
    """
    tab = mode_table(lmax)
    blocks = [np.flatnonzero(tab.m == m) for m in range(lmax + 1)]
    B = max(len(b) for b in blocks)
    idx = np.zeros((lmax + 1, B), np.int64)
    mask = np.zeros((lmax + 1, B), bool)
    for m, b in enumerate(blocks):
        idx[m, : len(b)] = b
        mask[m, : len(b)] = True
    return idx, mask


class MBlockPreconditioner(NamedTuple):
    """Cholesky factors of the m-diagonal blocks of P (exact for full-day uniform coverage).

    Attributes:
        chol: (Nf, lmax+1, B, B) lower Cholesky factors (padding rows are identity).
        idx: (lmax+1, B) realified indices of each block; mask: (lmax+1, B) valid entries.
    """

    chol: jax.Array
    idx: jax.Array
    mask: jax.Array


@jax.jit
def m_block_preconditioner(system: LinearSystem) -> MBlockPreconditioner:
    """Build the m-block preconditioner in O(Nt Nbl lmax^3) without forming P.

    A flat prior with unconstrained directions makes blocks singular; a relative
    jitter of 1e-12 of the block's largest diagonal keeps the factor finite so the
    solver can run and report non-convergence instead of producing NaN.
    """
    op = system.op
    nf, n = op.response.shape[0], n_in(op)
    lmax = lmax_from_nparams(n)
    idx_np, mask_np = m_blocks(lmax)
    idx, mask = jnp.asarray(idx_np), jnp.asarray(mask_np)
    M, B = idx.shape
    xt, w_t = _time_terms(op, system.inv_noise)
    fm = mask.astype(op.response.real.dtype)

    def body(acc, tw):
        t, w = tw
        Xg = xt(t)[:, :, idx] * fm  # (Nf, Nbl, M, B)
        return acc + jnp.einsum("fbmi,fb,fbmj->fmij", jnp.conj(Xg), w, Xg).real, None

    blocks, _ = jax.lax.scan(body, jnp.zeros((nf, M, B, B), fm.dtype), (op.angles, w_t))
    sinv = system.prior.inv_var[:, idx] * fm  # (Nf, M, B)
    blocks = blocks + jax.vmap(jax.vmap(jnp.diag))(sinv)
    diag = jnp.diagonal(blocks, axis1=-2, axis2=-1)
    scale = jnp.max(diag, axis=-1, keepdims=True)
    jitter = 1e-12 * scale + (1.0 - fm)  # identity on padding
    blocks = blocks + jax.vmap(jax.vmap(jnp.diag))(jitter)
    return MBlockPreconditioner(jnp.linalg.cholesky(blocks), idx, mask)


def apply_preconditioner(pc, r: jax.Array) -> jax.Array:
    """``M^-1 r`` for r (Nf, n) with any gcrsky preconditioner."""
    return jax.vmap(lambda f, rf: precondition_one(pc, f, rf))(jnp.arange(r.shape[0]), r)


def precondition_one(pc, f, r: jax.Array) -> jax.Array:
    """``M_f^-1 r`` for one frequency ``f`` (traced index) and r (n,).

    Computed in the preconditioner's own precision (float32 if it was stored so) and
    returned in ``r``'s.
    """
    dt = (pc.chol if isinstance(pc, MBlockPreconditioner) else getattr(pc, "U", r)).dtype
    if dt != r.dtype:
        return _precondition(pc, f, r.astype(dt)).astype(r.dtype)
    return _precondition(pc, f, r)


def _precondition(pc, f, r: jax.Array) -> jax.Array:
    if isinstance(pc, MBlockPreconditioner):
        g = r[pc.idx] * pc.mask  # (M, B)
        y = _chol_solve(pc.chol[f], g)
        return jnp.zeros_like(r).at[pc.idx].add(jnp.where(pc.mask, y, 0.0))
    if isinstance(pc, NystromPreconditioner):
        y = pc.scale[f] * r
        c = pc.U[f].T @ y
        return pc.scale[f] * (pc.U[f] @ (c / (pc.lam[f] + 1.0)) + y - pc.U[f] @ c)
    raise TypeError(f"unknown preconditioner {type(pc).__name__}")


def _chol_solve(L: jax.Array, b: jax.Array) -> jax.Array:
    tri = jax.scipy.linalg.solve_triangular
    y = jax.vmap(lambda l, v: tri(l, v, lower=True))(L, b)
    return jax.vmap(lambda l, v: tri(l, v, lower=True, trans="T"))(L, y)


class NystromPreconditioner(NamedTuple):
    """Prior-whitened randomized Nystrom preconditioner (Frangella, Tropp & Udell 2023).

    In whitened variables ``y = S^-1/2 a`` the precision is ``I + H`` with
    ``H = S^1/2 X^T W X S^1/2`` nearly low rank (the data constrain few directions
    of a narrow-strip observation).  With ``H ~ U diag(lam) U^T`` from a rank-``k``
    Nystrom sketch, ``M^-1 = S^1/2 [U diag(1/(1+lam)) U^T + (I - U U^T)] S^1/2`` is
    the exact inverse of the approximation, so ``r^T M^-1 r`` estimates the error's
    P-norm.  Needs a proper prior in every mode (S^-1 > 0).

    Attributes:
        U: (Nf, n, k) orthonormal eigenvectors; lam: (Nf, k) eigenvalues >= 0;
        scale: (Nf, n) ``S^1/2`` diagonal.
    """

    U: jax.Array
    lam: jax.Array
    scale: jax.Array


def data_apply(system: LinearSystem, a: jax.Array) -> jax.Array:
    """Data part of the precision, ``X^T W X a`` for a (Nf, n)."""
    return adjoint(system.op, system.inv_noise * apply(system.op, a))


@partial(jax.jit, static_argnames=("rank",))
def nystrom_preconditioner(system: LinearSystem, rank: int = 128, key: jax.Array | None = None, precision=None):
    """Build a :class:`NystromPreconditioner` with ``rank`` matrix-free (or dense) products.

    Args:
        system: the linear system; every ``prior.inv_var`` must be > 0.
        rank: sketch size k (clipped to n).  The standard case's whitened data term has
            ~55 eigenvalues above 2, so 128 leaves CG a handful of iterations.
        key: PRNG key of the random test matrix (default PRNGKey(0)).
        precision: optional dense P (Nf, n, n) to use instead of matrix-free products.
    """
    nf, n = system.prior.mean.shape
    k = min(int(rank), n)
    key = jax.random.PRNGKey(0) if key is None else key
    sh = 1.0 / jnp.sqrt(system.prior.inv_var)  # (Nf, n); inf where flat
    om = jax.random.normal(key, (nf, n, k), sh.dtype)
    om = jnp.linalg.qr(om)[0]
    if precision is not None:
        Y = jnp.einsum("fij,fj,fjk->fik", precision, sh, om) * sh[..., None] - om
    else:
        cols = jax.vmap(lambda v: data_apply(system, sh * v), in_axes=2, out_axes=2)(om)
        Y = cols * sh[..., None]
    nu = jnp.finfo(sh.dtype).eps * jnp.linalg.norm(Y, axis=(1, 2), keepdims=True)
    Yn = Y + nu * om
    C = jnp.linalg.cholesky(jnp.einsum("fik,fil->fkl", om, Yn))
    B = jax.vmap(lambda c, y: jax.scipy.linalg.solve_triangular(c, y.T, lower=True).T)(C, Yn)
    U, s, _ = jnp.linalg.svd(B, full_matrices=False)
    lam = jnp.maximum(s**2 - nu[..., 0], 0.0)
    return NystromPreconditioner(U, lam, sh)
