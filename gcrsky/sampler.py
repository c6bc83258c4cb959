"""Wiener filter and Gaussian constrained realisations (GCR): CG and Cholesky.

Two exact samplers share one interface and one :class:`SolveInfo`:

* ``"cg"``: preconditioned conjugate gradients, vmapped over draws, matrix-free or
  with a dense P.  Convergence is judged in *posterior-sigma units*: iterate until
  ``sqrt(r^T M^-1 r) <= tol``.  With the default prior-whitened Nystrom
  preconditioner ``M <= P`` in the Loewner order (a Nystrom sketch never exceeds the
  matrix it approximates), so ``r^T M^-1 r >= r^T P^-1 r = ||x - x*||_P^2``: a rigorous
  bound on the error's P-norm, which itself bounds every mode's error in units of
  its posterior std.  With the m-block preconditioner (flat priors) the same number
  is only an estimate (measured 100x optimistic on the standard case), so pass a
  smaller ``tol`` there.  jax.scipy.sparse.linalg.cg implements the same recurrence
  but reports neither iterations nor residual, so it is written out here with
  ``lax.while_loop`` (tests check the two agree).
* ``"cholesky"``: ``P = L L^T``; ``a = a_wf + L^-T z`` with ``z ~ N(0, I)``. The exact
  reference, and the fast path when n^2 fits in memory.

Draw ``i`` of a batch uses ``jax.random.split(key, ndraws)[i]``: a fixed key
reproduces the same draws.

For nesting in a user's JAX Gibbs loop: :func:`gcr_init` / :func:`gcr_step`
(blackjax style: ``step(key, state, system) -> (state, info)``), pure and
jittable, usable inside ``lax.scan``.
"""

from __future__ import annotations

import logging
from functools import partial
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp

from .normal import (
    LinearSystem,
    check_float64,
    fluctuation_rhs,
    m_block_preconditioner,
    nystrom_preconditioner,
    precision_apply,
    precision_matrix,
    precondition_one,
    wiener_rhs,
)

__all__ = [
    "SolveInfo",
    "pcg",
    "wiener_filter_system",
    "sample_system",
    "PreparedSampler",
    "prepare_sampler",
    "draw",
    "GCRState",
    "gcr_init",
    "gcr_step",
    "make_preconditioner",
    "resolve_preconditioner",
]

DEFAULT_TOL = 1e-6  # posterior-sigma units (P-norm of the error, estimated)


class SolveInfo(NamedTuple):
    """How a solve went (arrays have the batch shape of the solve, e.g. (Nf,) or (Nf, ndraws)).

    Attributes:
        iterations: CG iterations taken (0 for Cholesky).
        err_sigma: ``sqrt(r^T M^-1 r)`` from the *true* final residual ``b - P x``, in
            posterior-sigma units: an upper bound on the error's P-norm with the
            Nystrom preconditioner, an estimate with m-blocks (see module docstring).
        rel_residual: ``||b - P x|| / ||b||``.
        converged: ``err_sigma <= tol`` and no breakdown (non-positive curvature,
            which signals a singular or indefinite P, e.g. a flat prior).
    """

    iterations: jax.Array
    err_sigma: jax.Array
    rel_residual: jax.Array
    converged: jax.Array


def pcg(matvec, precond, b, x0, *, tol: float = DEFAULT_TOL, maxiter: int = 2000):
    """Preconditioned CG for one right-hand side (vectors of any shape).

    The recurrence residual drifts from the true one ``b - P x`` in floating point;
    when the loop stops, CG is restarted once from the true residual ("residual
    replacement"), so the reported error is that of the returned ``x`` and meets
    ``tol`` whenever the iteration budget allows.

    Args:
        matvec: x -> P x (symmetric positive definite).
        precond: r -> M^-1 r (symmetric positive definite).
        b, x0: right-hand side and initial guess.
        tol: stop when ``sqrt(r . M^-1 r) <= tol`` (posterior-sigma units).
        maxiter: hard cap on iterations (both passes together).

    Returns:
        (x, SolveInfo) with scalar info fields.
    """

    def cond(s):
        k, x, r, z, p, rz, bad = s
        return (k < maxiter) & (jnp.sqrt(jnp.abs(rz)) > tol) & (~bad)

    def body(s):
        k, x, r, z, p, rz, bad = s
        Ap = matvec(p)
        pAp = jnp.vdot(p, Ap).real
        bad = ~(pAp > 0)
        alpha = jnp.where(bad, 0.0, rz / jnp.where(bad, 1.0, pAp))
        x = x + alpha * p
        r = r - alpha * Ap
        z = precond(r)
        rz_new = jnp.vdot(r, z).real
        beta = rz_new / jnp.where(rz == 0, 1.0, rz)
        p = z + beta * p
        return k + 1, x, r, z, p, rz_new, bad

    def run(k0, x):
        r = b - matvec(x)
        z = precond(r)
        init = (k0, x, r, z, z, jnp.vdot(r, z).real, jnp.asarray(False))
        k, x, r, z, _, rz, bad = jax.lax.while_loop(cond, body, init)
        return k, x, bad

    k, x, bad1 = run(jnp.asarray(0), x0)
    k, x, bad2 = run(k, x)  # restart from the true residual (exits at once if converged)
    bad = bad1 | bad2
    r = b - matvec(x)
    err = jnp.sqrt(jnp.abs(jnp.vdot(r, precond(r)).real))
    rel = jnp.linalg.norm(r) / jnp.maximum(jnp.linalg.norm(b), jnp.finfo(b.dtype).tiny)
    ok = (err <= tol) & (~bad) & jnp.isfinite(err)
    return x, SolveInfo(k, err, rel, ok)


def _solve_cg(system, precision, pc, b, x0, tol, maxiter):
    """Solve P x = b for b (Nf, n) or (Nf, k, n) batches: CG vmapped over frequencies
    (and over the k right-hand sides); every solve keeps its own iteration count."""

    def one_freq(f, bf, x0f):
        if precision is not None:
            mv = lambda x: precision[f] @ x  # noqa: E731
        else:
            sys_f = _freq_slice(system, f)
            mv = lambda x: precision_apply(sys_f, x[None])[0]  # noqa: E731
        prec = lambda r: precondition_one(pc, f, r)  # noqa: E731
        solve1 = partial(pcg, mv, prec, tol=tol, maxiter=maxiter)
        if bf.ndim == 1:
            return solve1(bf, x0f)
        return jax.vmap(solve1)(bf, x0f)

    return jax.vmap(one_freq)(jnp.arange(b.shape[0]), b, x0)


def make_preconditioner(system: LinearSystem, kind: str, precision=None, rank: int = 128, pc_dtype: str = "float64"):
    """Build the named preconditioner: ``"nystrom"`` (proper prior needed) or ``"mblock"``.

    ``pc_dtype="float32"`` stores and applies it in single precision (built in float64,
    then rounded).  That is safe: CG's iterates, products and the convergence test stay
    float64, so the answer is as exact as with a float64 preconditioner; only the
    iteration count can change (measured in ``benchmarks/float32.py``).
    """
    if kind == "nystrom":
        pc = nystrom_preconditioner(system, rank=rank, precision=precision)
    elif kind == "mblock":
        pc = m_block_preconditioner(system)
    else:
        raise ValueError(f"preconditioner must be 'nystrom' or 'mblock', got {kind!r}")
    if pc_dtype not in ("float64", "float32"):
        raise ValueError(f"pc_dtype must be 'float64' or 'float32', got {pc_dtype!r}")
    if pc_dtype == "float32":
        pc = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32) if jnp.issubdtype(x.dtype, jnp.floating) else x, pc)
    return pc


def resolve_preconditioner(system: LinearSystem, kind: str = "auto") -> str:
    """Concrete choice for ``"auto"``: Nystrom if every mode has a proper prior, else m-blocks.

    Must be called outside jit (inspects the prior's values).
    """
    nflat = int(jnp.sum(system.prior.inv_var <= 0))
    if nflat:
        logging.getLogger(__name__).warning(
            "flat prior (S^-1 = 0) in %d modes: P may be singular; directions the data do not "
            "constrain have no posterior and solves along them are reported as unconverged",
            nflat,
        )
    if kind != "auto":
        if kind == "nystrom" and not bool(jnp.all(system.prior.inv_var > 0)):
            raise ValueError("the Nystrom preconditioner needs S^-1 > 0 in every mode; use 'mblock' for a flat prior")
        return kind
    return "nystrom" if bool(jnp.all(system.prior.inv_var > 0)) else "mblock"


def _freq_slice(system: LinearSystem, f: int) -> LinearSystem:
    sl = lambda a: jax.lax.dynamic_slice_in_dim(a, f, 1, axis=0)  # noqa: E731
    return LinearSystem(
        op=system.op._replace(response=sl(system.op.response)),
        data=sl(system.data),
        inv_noise=sl(system.inv_noise),
        prior=system.prior._replace(mean=sl(system.prior.mean), inv_var=sl(system.prior.inv_var)),
    )


@partial(jax.jit, static_argnames=("dense", "maxiter", "preconditioner", "rank", "pc_dtype"))
def wiener_filter_system(
    system: LinearSystem,
    *,
    tol: float = DEFAULT_TOL,
    maxiter: int = 5000,
    dense: bool = True,
    preconditioner: str = "nystrom",
    rank: int = 128,
    pc_dtype: str = "float64",
):
    """Wiener filter (posterior mean) by preconditioned CG, started at the prior mean.

    Args:
        preconditioner: ``"nystrom"`` (needs a proper prior) or ``"mblock"`` (any prior);
            :func:`resolve_preconditioner` picks one outside jit.

    Returns:
        (a_wf (Nf, n), SolveInfo with (Nf,) fields).
    """
    check_float64(system.op.response, system.inv_noise)
    precision = precision_matrix(system) if dense else None
    pc = make_preconditioner(system, preconditioner, precision, rank, pc_dtype)
    return _solve_cg(system, precision, pc, wiener_rhs(system), system.prior.mean, tol, maxiter)


class PreparedSampler(NamedTuple):
    """Everything the draws share, computed once (set up once, draw many times).

    Attributes:
        system: the linear system.
        a_wf: (Nf, n) Wiener filter (posterior mean).
        wiener: SolveInfo of the Wiener-filter solve, (Nf,) fields.
        precision: dense P (Nf, n, n), or None (matrix-free CG).
        chol: lower Cholesky factor of P (Nf, n, n) for the Cholesky sampler, else None.
        pc: CG preconditioner, or None for the dense samplers.
        sqrt_cov: (Nf, n, n) ``T`` with ``T T^T = P^+`` for the eigen sampler
            (``delta = T z``), else None.
        rank: (Nf,) number of directions sampled (n unless the eigen sampler found
            P singular), or None.
        mblocks: (Nf, lmax+1, B, B) Cholesky factors of the m-blocks for the m-mode
            sampler (``method="mmode"``, :mod:`gcrsky.mmode`), else None.
        chol_inv_t: (Nf, n, n) ``L^-T`` for the Cholesky sampler (draws are then one
            matrix product, ~3x faster than a triangular solve per batch), else None.
    """

    system: LinearSystem
    a_wf: jax.Array
    wiener: SolveInfo
    precision: jax.Array | None
    chol: jax.Array | None
    pc: object
    sqrt_cov: jax.Array | None = None
    rank: jax.Array | None = None
    mblocks: jax.Array | None = None
    chol_inv_t: jax.Array | None = None

    @property
    def method(self) -> str:
        """Which exact sampler this is: ``"mmode"``, ``"eigh"``, ``"cholesky"`` or ``"cg"``."""
        if self.mblocks is not None:
            return "mmode"
        if self.sqrt_cov is not None:
            return "eigh"
        return "cholesky" if self.chol is not None else "cg"


#: Eigen sampler: eigenvalues below ``EIGH_RCOND * max eigenvalue`` count as zero.  Just
#: above the eigensolver's rounding floor (~n * 1e-16 relative for n ~ 500): every
#: direction the data inform, however weakly, is sampled.
EIGH_RCOND = 1e-12


def _prepare_eigh(system: LinearSystem, b: jax.Array, rcond: float) -> PreparedSampler:
    """Eigen-decomposition sampler; for singular P the posterior restricted to range(P)."""
    P = precision_matrix(system)
    lam, V = jnp.linalg.eigh(P)  # ascending, (Nf, n), (Nf, n, n)
    keep = lam > rcond * lam[:, -1:]
    safe = jnp.where(keep, lam, 1.0)
    inv = jnp.where(keep, 1.0 / safe, 0.0)
    coef = jnp.einsum("fji,fj->fi", V, b)  # V^T b
    a_wf = jnp.einsum("fij,fj->fi", V, inv * coef)
    sqrt_cov = V * jnp.where(keep, 1.0 / jnp.sqrt(safe), 0.0)[:, None, :]
    # residual within the sampled subspace, in posterior-sigma units (P^+ norm)
    r_coef = jnp.where(keep, coef - jnp.einsum("fji,fjk,fk->fi", V, P, a_wf), 0.0)
    err = jnp.sqrt(jnp.sum(inv * r_coef**2, axis=1))
    ok = jnp.all(jnp.isfinite(V), axis=(1, 2)) & jnp.isfinite(err)
    nf = b.shape[0]
    winfo = SolveInfo(jnp.zeros(nf, int), err, jnp.linalg.norm(r_coef, axis=1) / jnp.linalg.norm(b, axis=1), ok)
    return PreparedSampler(system, a_wf, winfo, P, None, None, sqrt_cov, jnp.sum(keep, axis=1))


@partial(jax.jit, static_argnames=("method", "dense", "maxiter", "preconditioner", "rank", "pc_dtype"))
def prepare_sampler(
    system: LinearSystem,
    *,
    method: Literal["cg", "cholesky", "eigh", "mmode"] = "cg",
    tol: float = DEFAULT_TOL,
    maxiter: int = 5000,
    dense: bool = True,
    preconditioner: str = "nystrom",
    rank: int = 128,
    rcond: float = EIGH_RCOND,
    pc_dtype: str = "float64",
) -> PreparedSampler:
    """Factorise / precondition P and solve for the Wiener filter, once.

    ``method="cholesky"`` factorises the dense P; ``"cg"`` builds the preconditioner
    (and the dense P if ``dense``); ``"eigh"`` eigen-decomposes the dense P and, if
    P is singular (a flat prior, ``S^-1 = 0``, leaves directions the data do not
    see), samples the posterior restricted to the directions with eigenvalue
    ``> rcond * max``: the others have no information, so they are pinned at 0
    (the minimum-norm solution) and ``PreparedSampler.rank`` says how many were
    kept.  With a proper prior (rank n) it is exact like Cholesky.  ``"mmode"``
    factorises the m-blocks (:mod:`gcrsky.mmode`); it is exact only when
    :func:`gcrsky.mmode.mmode_check` passes, which needs concrete arrays, so check
    before calling (``gcrsky.prepare`` does).  Pass the result to :func:`draw` as
    often as needed.
    """
    check_float64(system.op.response, system.inv_noise)
    nf = system.prior.mean.shape[0]
    b = wiener_rhs(system)
    if method == "eigh":
        return _prepare_eigh(system, b, rcond)
    if method == "mmode":
        from .mmode import _prepare as _prepare_mmode

        pm = _prepare_mmode(system)
        return PreparedSampler(system, pm.a_wf, pm.wiener, None, None, None, mblocks=pm.chol)
    if method == "cholesky":
        P = precision_matrix(system)
        L = jnp.linalg.cholesky(P)
        cho = jax.vmap(lambda l, v: jax.scipy.linalg.cho_solve((l, True), v))
        a_wf = cho(L, b)
        r = b - jnp.einsum("fij,fj->fi", P, a_wf)
        err = jnp.sqrt(jnp.abs(jnp.einsum("fi,fi->f", r, cho(L, r))))
        ok = jnp.all(jnp.isfinite(L), axis=(1, 2))
        winfo = SolveInfo(jnp.zeros(nf, int), err, jnp.linalg.norm(r, axis=1) / jnp.linalg.norm(b, axis=1), ok)
        eye = jnp.eye(L.shape[-1], dtype=L.dtype)
        linv = jax.vmap(lambda l: jax.scipy.linalg.solve_triangular(l, eye, lower=True))(L)
        return PreparedSampler(system, a_wf, winfo, P, L, None, chol_inv_t=jnp.swapaxes(linv, -1, -2))
    if method != "cg":
        raise ValueError(f"method must be 'cg', 'cholesky', 'eigh' or 'mmode', got {method!r}")
    precision = precision_matrix(system) if dense else None
    pc = make_preconditioner(system, preconditioner, precision, rank, pc_dtype)
    a_wf, winfo = _solve_cg(system, precision, pc, b, system.prior.mean, tol, maxiter)
    return PreparedSampler(system, a_wf, winfo, precision, None, pc)


def _upper_triangular_product(U: jax.Array, z: jax.Array) -> jax.Array:
    """``U z`` for upper-triangular U (Nf, n, n) and z (ndraws, Nf, n) -> (Nf, ndraws, n).

    In 4 block rows that skip U's zero lower-left blocks: 5/8 of the dense product's
    flops (measured 2.8 vs 4.1 ms for n = 441, 2 channels, 200 draws); the same sums.
    """
    n = U.shape[-1]
    k = 4 if n >= 256 else 1
    edges = [round(i * n / k) for i in range(k + 1)]
    parts = [jnp.einsum("fij,dfj->fdi", U[:, a:b, a:], z[:, :, a:]) for a, b in zip(edges[:-1], edges[1:])]
    return jnp.concatenate(parts, axis=-1)


@partial(jax.jit, static_argnames=("ndraws", "maxiter"))
def draw(key: jax.Array, prepared: PreparedSampler, ndraws: int, *, tol: float = DEFAULT_TOL, maxiter: int = 5000):
    """``ndraws`` exact posterior draws from a :class:`PreparedSampler`.

    Draw ``i`` uses ``jax.random.split(key, ndraws)[i]`` (CG, Cholesky: ``L^-T`` is
    formed once by :func:`prepare_sampler`, to ~cond(L) eps relative).  m-mode:
    ``a_wf + L_m^-T z`` block by block (:func:`gcrsky.mmode.draw_mmode`).  Cholesky:
    ``a_wf + L^-T z``; eigen: ``a_wf + V_r L_r^-1/2 z``; CG: ``a_wf + delta`` with
    ``P delta`` = the GCR fluctuation right-hand side.

    Returns:
        draws (Nf, ndraws, n); info dict: ``"wiener"``, ``"draws"`` (SolveInfo over
        (Nf, ndraws)) and ``"a_wf"``.
    """
    system, a_wf = prepared.system, prepared.a_wf
    nf, n = a_wf.shape
    keys = jax.random.split(key, ndraws)
    if prepared.mblocks is not None:
        from .mmode import PreparedMMode, draw_mmode

        return draw_mmode(key, PreparedMMode(system, a_wf, prepared.wiener, prepared.mblocks), ndraws)
    if prepared.sqrt_cov is not None:
        z = jax.random.normal(key, (nf, n, ndraws), a_wf.dtype)
        delta = jnp.einsum("fij,fjd->fdi", prepared.sqrt_cov, z)  # (Nf, ndraws, n)
        ok = jnp.broadcast_to(prepared.wiener.converged[:, None], (nf, ndraws))
        zeros = jnp.zeros((nf, ndraws))
        dinfo = SolveInfo(jnp.zeros((nf, ndraws), int), zeros, zeros, ok & jnp.all(jnp.isfinite(delta), axis=-1))
    elif prepared.chol is not None:
        z = jax.vmap(lambda k: jax.random.normal(k, (nf, n), a_wf.dtype))(keys)  # (ndraws, Nf, n)
        if prepared.chol_inv_t is not None:  # L^-T z as matrix products
            delta = _upper_triangular_product(prepared.chol_inv_t, z)
        else:
            tri = jax.scipy.linalg.solve_triangular
            delta = jax.vmap(lambda l, zf: tri(l, zf.T, lower=True, trans="T").T, in_axes=(0, 1), out_axes=0)(
                prepared.chol, z
            )
        ok = jnp.broadcast_to(prepared.wiener.converged[:, None], (nf, ndraws))
        zeros = jnp.zeros((nf, ndraws))
        dinfo = SolveInfo(jnp.zeros((nf, ndraws), int), zeros, zeros, ok & jnp.all(jnp.isfinite(delta), axis=-1))
    else:
        fl = jax.vmap(lambda k: fluctuation_rhs(k, system), out_axes=1)(keys)  # (Nf, ndraws, n)
        delta, dinfo = _solve_cg(system, prepared.precision, prepared.pc, fl, jnp.zeros_like(fl), tol, maxiter)
    return a_wf[:, None, :] + delta, {"wiener": prepared.wiener, "draws": dinfo, "a_wf": a_wf}


@partial(jax.jit, static_argnames=("ndraws", "method", "dense", "maxiter", "preconditioner", "rank", "pc_dtype"))
def sample_system(
    key: jax.Array,
    system: LinearSystem,
    ndraws: int,
    *,
    method: Literal["cg", "cholesky", "eigh"] = "cg",
    tol: float = DEFAULT_TOL,
    maxiter: int = 5000,
    dense: bool = True,
    preconditioner: str = "nystrom",
    rank: int = 128,
    rcond: float = EIGH_RCOND,
    pc_dtype: str = "float64",
):
    """GCR draws from the exact posterior ``N(a_wf, P^-1)``: :func:`prepare_sampler` then :func:`draw`.

    Both methods return ``a_wf + delta`` with ``Cov(delta) = P^-1``:

    * cg: ``delta`` solves ``P delta = (GCR fluctuation rhs)`` (mean zero, O(1 sigma)
      in every direction, so ``tol`` is directly a fraction of a posterior sigma);
      ``a_wf`` by CG too.  ``dense=True`` forms P once (O(n^2) per matvec);
      ``dense=False`` is matrix-free (O(Nt Nbl n) per matvec).
    * cholesky: ``delta = L^-T z``.
    * eigh: ``delta = V_r Lambda_r^-1/2 z``; for singular P see :func:`prepare_sampler`.

    For many batches, call :func:`prepare_sampler` once and :func:`draw` per batch.

    Returns:
        draws (Nf, ndraws, n); info dict: ``"wiener"`` (SolveInfo over (Nf,)), ``"draws"``
        (SolveInfo over (Nf, ndraws)), ``"a_wf"`` (Nf, n).
    """
    prepared = prepare_sampler(
        system, method=method, tol=tol, maxiter=maxiter, dense=dense, preconditioner=preconditioner, rank=rank,
        rcond=rcond, pc_dtype=pc_dtype,
    )
    return draw(key, prepared, ndraws, tol=tol, maxiter=maxiter)


# ----------------------------------------------------------- Gibbs-style kernel


class GCRState(NamedTuple):
    """State of the GCR kernel: the current coefficients (Nf, n)."""

    position: jax.Array


def gcr_init(position: jax.Array) -> GCRState:
    """Start a chain at ``position`` (Nf, n), e.g. the prior mean."""
    return GCRState(jnp.asarray(position))


def gcr_step(
    key: jax.Array,
    state: GCRState,
    system: LinearSystem,
    *,
    tol: float = DEFAULT_TOL,
    maxiter: int = 5000,
    preconditioner: str = "nystrom",
    rank: int = 128,
    pc=None,
):
    """One exact conditional draw ``a ~ p(a | d, S, N, a0)`` (pure; jit/scan it yourself).

    Solves the full GCR equation by matrix-free preconditioned CG warm-started at
    the previous position (which is typically within a few posterior sigma of the
    new draw).  ``system`` may change between steps (e.g. a Gibbs update of S); the
    preconditioner (static choice ``"nystrom"``, which needs ``S^-1 > 0`` in every mode,
    or ``"mblock"`` for flat priors) is rebuilt each step from it unless a prebuilt
    ``pc`` is passed.  A stale ``pc`` (built for an earlier S) only costs iterations:
    the draw stays exact because convergence is checked against the current system.

    Returns:
        (GCRState, SolveInfo with (Nf,) fields).
    """
    if pc is None:
        pc = make_preconditioner(system, preconditioner, None, rank)
    b = wiener_rhs(system) + fluctuation_rhs(key, system)
    x, info = _solve_cg(system, None, pc, b, state.position, tol, maxiter)
    return GCRState(x), info
