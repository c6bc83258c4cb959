"""CG preconditioners: prior-whitened randomized Nystrom, m-block Cholesky and the window.

All are PyTrees built once per system and applied per frequency inside CG
(:mod:`gcrsky.solvers.cg`).  The Nystrom sketch is the default for proper priors:
it never exceeds the matrix it approximates (``M <= P``), which makes CG's stopping
rule a rigorous bound on the error's P-norm.  m-blocks serve flat priors (exact for
uniform full-day coverage, an estimate otherwise).  The window preconditioner
(:mod:`gcrsky.solvers.window`, block-banded in m, for large partial coverage) has no
``M <= P``: CG stops on the prior norm ``sqrt(r^T S r)`` instead (:func:`stop_norm`),
rigorous because ``P >= S^-1``.
"""

from __future__ import annotations

import logging
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..model.operator import n_in
from ..model.system import LinearSystem, data_apply, time_terms
from ..sphere.modes import lmax_from_nparams, order_slots
from .window import WindowPreconditioner, resolve_bandwidth, window_preconditioner, window_solve

__all__ = [
    "MBlockPreconditioner",
    "NystromPreconditioner",
    "apply_preconditioner",
    "inverse_bound",
    "m_block_preconditioner",
    "m_blocks",
    "make_preconditioner",
    "nystrom_preconditioner",
    "precondition_one",
    "resolve_preconditioner",
    "stop_norm",
]

#: The preconditioners by name (``"auto"`` resolves to one of the first two).
KINDS = ("nystrom", "mblock", "window")


def m_blocks(lmax: int):
    """Index table of the m-blocks: (lmax+1, B) indices into the realified vector, and a mask
    (:func:`gcrsky.sphere.modes.order_slots`: block m holds Re a_lm, l = m..lmax, then Im a_lm, m > 0)."""
    return order_slots(lmax)


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
    xt, w_t = time_terms(op, system.inv_noise)
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
    dt = (pc.chol if isinstance(pc, (MBlockPreconditioner, WindowPreconditioner)) else getattr(pc, "U", r)).dtype
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
    if isinstance(pc, WindowPreconditioner):
        return window_solve(pc, f, r)
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


#: Sketch products formed at once by :func:`nystrom_preconditioner` (its transient memory is this many
#: operator applications', ``~2 x 8 Nf Nt n_resp`` bytes each).
SKETCH_BATCH = 8


@partial(jax.jit, static_argnames=("sketch_size",))
def nystrom_preconditioner(system: LinearSystem, sketch_size: int = 128, key: jax.Array | None = None,
                           precision=None):
    """Build a :class:`NystromPreconditioner` with ``sketch_size`` matrix-free (or dense) products.

    Args:
        system: the linear system; every ``prior.inv_var`` must be > 0.
        sketch_size: sketch size k (clipped to n).  The standard case's whitened data term has
            ~55 eigenvalues above 2, so 128 leaves CG a handful of iterations.
        key: PRNG key of the random test matrix (default PRNGKey(0)).
        precision: optional dense P (Nf, n, n) to use instead of matrix-free products.
    """
    nf, n = system.prior.mean.shape
    k = min(int(sketch_size), n)
    key = jax.random.PRNGKey(0) if key is None else key
    sh = 1.0 / jnp.sqrt(system.prior.inv_var)  # (Nf, n); inf where flat
    om = jax.random.normal(key, (nf, n, k), sh.dtype)
    om = jnp.linalg.qr(om)[0]
    if precision is not None:
        Y = jnp.einsum("fij,fj,fjk->fik", precision, sh, om) * sh[..., None] - om
    else:
        # SKETCH_BATCH products at a time: all k at once hold k rotated copies of the sky per time
        # (measured > 17 GB at 61 antennas, lmax 287, 30 times: the CLI's CG fallback on a file)
        cols = jnp.moveaxis(jax.lax.map(lambda v: data_apply(system, sh * v), jnp.moveaxis(om, 2, 0),
                                        batch_size=min(SKETCH_BATCH, k)), 0, 2)
        Y = cols * sh[..., None]
    # the shift: eps x the sketch's size, at least eps (a channel without data has Y = 0: Cholesky of 0 was NaN and
    # a valid prior-only system was reported NONFINITE); eigenvalues below eps of P's unit floor do not matter
    nu = jnp.finfo(sh.dtype).eps * jnp.maximum(jnp.linalg.norm(Y, axis=(1, 2), keepdims=True), 1.0)
    Yn = Y + nu * om
    C = jnp.linalg.cholesky(jnp.einsum("fik,fil->fkl", om, Yn))
    B = jax.vmap(lambda c, y: jax.scipy.linalg.solve_triangular(c, y.T, lower=True).T)(C, Yn)
    U, s, _ = jnp.linalg.svd(B, full_matrices=False)
    lam = jnp.maximum(s**2 - nu[..., 0], 0.0)
    return NystromPreconditioner(U, lam, sh)


def make_preconditioner(system: LinearSystem, kind: str, precision=None, sketch_size: int = 128,
                        pc_dtype: str = "float64", bandwidth="auto"):
    """Build the named preconditioner: ``"nystrom"``, ``"window"`` (proper prior needed) or ``"mblock"``.

    Args:
        system: the linear system.
        kind: ``"nystrom"``, ``"mblock"`` or ``"window"`` (resolve ``"auto"`` first with
            :func:`resolve_preconditioner`).
        precision: optional dense P (Nf, n, n) for the Nystrom sketch's products.
        sketch_size: Nystrom sketch size.
        bandwidth: window bandwidth B (an integer >= 0, or ``"auto"``:
            :func:`gcrsky.solvers.window.resolve_bandwidth`).
        pc_dtype: ``"float32"`` stores and applies it in single precision (built in
            float64, then rounded).  That is safe: CG's iterates, products and the
            convergence test stay float64, so the answer is as exact as with a float64
            preconditioner; only the iteration count can change (measured in
            ``benchmarks/float32.py``).
    """
    if kind == "nystrom":
        pc = nystrom_preconditioner(system, sketch_size=sketch_size, precision=precision)
    elif kind == "mblock":
        pc = m_block_preconditioner(system)
    elif kind == "window":
        pc = window_preconditioner(system, resolve_bandwidth(system, bandwidth))
    else:
        raise ValueError(f"preconditioner must be 'nystrom', 'mblock' or 'window', got {kind!r}")
    if pc_dtype not in ("float64", "float32"):
        raise ValueError(f"pc_dtype must be 'float64' or 'float32', got {pc_dtype!r}")
    if pc_dtype == "float32":
        pc32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32) if jnp.issubdtype(x.dtype, jnp.floating) else x, pc)
        pc = pc32._replace(svar=pc.svar) if isinstance(pc, WindowPreconditioner) else pc32  # the stop stays float64
    return pc


def resolve_preconditioner(system: LinearSystem, kind: str = "auto", *, warn: bool = True) -> str:
    """Concrete choice for ``"auto"``: Nystrom if every mode has a proper prior, else m-blocks.

    Host-side (inspects the prior's values); under a trace, where the values are
    unknown, ``"auto"`` means ``"nystrom"`` (pass ``"mblock"`` for a flat prior).
    Logs a warning for a flat prior, whose P may be singular (unless ``warn=False``),
    and refuses Nystrom there.
    """
    if kind not in ("auto", *KINDS):
        raise ValueError(f"preconditioner must be 'auto', 'nystrom', 'mblock' or 'window', got {kind!r}")
    if isinstance(system.prior.inv_var, jax.core.Tracer):
        return "nystrom" if kind == "auto" else kind
    nflat = int(np.sum(np.asarray(system.prior.inv_var) <= 0))  # NumPy: the caller may be tracing
    if nflat and warn:
        logging.getLogger(__name__).warning(
            "flat prior (S^-1 = 0) in %d modes: P may be singular; directions the data do not "
            "constrain have no posterior and solves along them are reported as unconverged",
            nflat,
        )
    if kind != "auto":
        if kind in ("nystrom", "window") and nflat:
            raise ValueError(f"the {kind} preconditioner needs S^-1 > 0 in every mode; use 'mblock' for a flat prior")
        return kind
    return "mblock" if nflat else "nystrom"


def inverse_bound(pc, f) -> jax.Array:
    """An upper bound on ``lambda_max(M_f^-1)`` for frequency ``f`` (traced index allowed).

    Nystrom: ``M^-1 = S^1/2 [U diag(1/(1+lam)) U^T + (I - U U^T)] S^1/2`` and the bracket
    is at most I, so ``max S_ii``.  m-blocks: ``1 / min_m sigma_min(L_m)^2`` (exact).
    Window: ``M >= S^-1`` so ``M^-1 <= S``, ``max S_ii`` (which also bounds ``lambda_max(S)``,
    the weight of its stop norm).
    """
    if isinstance(pc, WindowPreconditioner):
        return jnp.max(pc.svar[f].astype(jnp.float64))
    if isinstance(pc, NystromPreconditioner):
        return jnp.max(pc.scale[f].astype(jnp.float64) ** 2)
    if isinstance(pc, MBlockPreconditioner):
        s = jnp.linalg.svd(pc.chol[f].astype(jnp.float64), compute_uv=False)  # (M, B)
        return 1.0 / jnp.min(s[..., -1]) ** 2
    raise TypeError(f"unknown preconditioner {type(pc).__name__}")


def stop_norm(pc, f):
    """CG's stopping quantity for preconditioner ``pc``: None (``r^T M^-1 r``) or ``r -> r^T N r``.

    Nystrom (``M <= P``) and m-blocks keep ``r^T M^-1 r`` (None).  The window preconditioner
    does not satisfy ``M <= P``, so ``r^T M^-1 r`` need not bound ``r^T P^-1 r`` (the error's
    squared P-norm); ``P >= S^-1`` gives ``r^T P^-1 r <= r^T S r``, the rigorous stop used there.
    ``f``: the frequency (traced index allowed).
    """
    if isinstance(pc, WindowPreconditioner):
        svar = pc.svar[f]
        return lambda r: jnp.vdot(r, svar.astype(r.dtype) * r).real
    return None
