"""Gibbs kernels (blackjax style): the GCR step, and the hierarchical ``(a, C_l)`` sampler.

``gcr_init(position) -> GCRState`` and ``gcr_step(key, state, system) -> (state, info)``
are pure and jittable, usable inside ``lax.scan``; the library does not jit for
you.  ``system`` may change between steps (e.g. a Gibbs update of the prior), so
each step draws exactly from the current conditional ``a | d, S, N, a0``.  It
rebuilds its preconditioner from ``system`` each call.

The hierarchical kernel alternates ``a | C_l, d`` (exact) and ``C_l | a``
(:mod:`gcrsky.inference.cl`)::

    fixed = gibbs_setup(system)                       # the data term, built once
    state = gibbs_init(fixed, cl0)                    # start at the Wiener filter of cl0
    state, info = gibbs_step(key, state, fixed)       # jit / lax.scan it

Everything that does not depend on ``C_l`` is in :class:`GibbsFixed`: the data term
``H = X^T N^-1 X`` and ``X^T N^-1 d``.  The a-step then costs, on the dense path
(``CholeskyOptions``), one Cholesky of ``H + S^-1(C_l)`` and three triangular solves;
on the CG path (``CGOptions``), CG warm-started at the previous draw with a
preconditioner updated in O(n k^2): a rank-k Nystrom approximation ``H ~ G G^T`` built
once, and per step ``M = S^-1(C_l) + G G^T`` inverted by Woodbury (a k x k Cholesky).
A stale approximation of H only costs iterations: the draw is exact to the CG
tolerance for the current ``C_l``.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import check_float64
from ..model.operator import adjoint
from ..model.prior import prior_from_cl
from ..model.system import LinearSystem, data_apply, fluctuation_rhs, precision_matrix, wiener_rhs
from ..solvers.cg import cg_solve, freq_slice, resolve_cg_options, solve_cg
from ..solvers.info import SolveInfo, direct_info
from ..solvers.options import CGOptions, CholeskyOptions
from ..solvers.preconditioners import make_preconditioner, nystrom_preconditioner
from ..sphere.modes import lmax_from_nparams, mode_table
from .cl import sample_cl, sample_power_law

__all__ = [
    "GCRState",
    "GibbsFixed",
    "GibbsInfo",
    "GibbsState",
    "gcr_init",
    "gcr_step",
    "gibbs_init",
    "gibbs_setup",
    "gibbs_step",
]

#: The step's default: matrix-free CG (a dense P would be rebuilt every step).
STEP_OPTIONS = CGOptions(dense=False)


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
    tol: float | None = None,
    options: CGOptions | None = None,
    pc=None,
) -> tuple[GCRState, SolveInfo]:
    """One exact conditional draw ``a ~ p(a | d, S, N, a0)`` (pure; jit/scan it yourself).

    Solves the full GCR equation by preconditioned CG warm-started at the previous
    position (which is typically within a few posterior sigma of the new draw).

    Args:
        key: PRNG key of this step.
        state: the chain's :class:`GCRState`.
        system: the current linear system.
        tol: CG tolerance in posterior-sigma units (overrides ``options.tol``).
        options: :class:`~gcrsky.solvers.CGOptions`; default matrix-free
            (``dense=False``).  Its preconditioner (``"auto"`` means Nystrom under
            a trace, which needs ``S^-1 > 0`` in every mode; pass ``"mblock"`` for a
            flat prior) is rebuilt each step from ``system`` unless a prebuilt ``pc``
            is passed.  A stale ``pc`` (built for an earlier S) only costs
            iterations: the draw stays exact because convergence is checked
            against the current system.
        pc: optional prebuilt preconditioner (:mod:`gcrsky.solvers.preconditioners`).

    Returns:
        (GCRState, SolveInfo with (Nf,) fields).
    """
    options = STEP_OPTIONS if options is None else options
    if tol is not None:
        options = dataclasses.replace(options, tol=float(tol))
    options = resolve_cg_options(system, options)
    precision = precision_matrix(system) if options.dense else None
    if pc is None:
        pc = make_preconditioner(system, options.preconditioner, precision, options.rank, options.pc_dtype)
    b = wiener_rhs(system) + fluctuation_rhs(key, system)
    x, info = solve_cg(system, precision, pc, b, state.position, options)
    return GCRState(x), info


# ---------------------------------------------------------------- the hierarchical (a, C_l) kernel


class GibbsFixed(eqx.Module):
    """What the hierarchical a-step reuses every step (built once by :func:`gibbs_setup`; a PyTree).

    Attributes:
        system: the linear system (its prior's mean is kept; its variance is replaced by
            ``C_l`` each step).
        data_rhs: ``X^T N^-1 d`` (Nf, n).
        data_term: dense ``H = X^T N^-1 X`` (Nf, n, n), or None (matrix-free CG).
        data_sqrt: ``F`` (Nf, n, n) with ``F F^T = H`` (dense CG: the data part of the
            GCR right-hand side is then ``F z``, exactly ``N(0, H)``), or None.
        lowrank: ``G`` (Nf, n, k) with ``H ~ G G^T`` (CG preconditioner), or None.
        lowrank_blocks: ``B_l = G^T diag(v_l) G`` (Nf, lmax+1, k, k) with ``v_l`` the
            prior variance pattern of degree l (``S(C_l) = sum_l C_l diag(v_l)``), so the
            preconditioner's k x k core ``I + G^T S G = I + sum_l C_l B_l`` costs
            O(lmax k^2) per step; or None.
        options: the a-step's solver options (``CholeskyOptions`` or ``CGOptions``).
    """

    system: LinearSystem
    data_rhs: jax.Array
    data_term: jax.Array | None
    data_sqrt: jax.Array | None
    lowrank: jax.Array | None
    lowrank_blocks: jax.Array | None
    options: CholeskyOptions | CGOptions = eqx.field(static=True)


class GibbsState(NamedTuple):
    """State of the hierarchical chain.

    Attributes:
        position: a (Nf, n), the current sky coefficients.
        cl: (Nf, lmax+1) the current angular power spectrum, K^2.
        amplitude, alpha: (Nf,) the power-law parameters (``family="power_law"``;
            ``nan`` for free C_l).
    """

    position: jax.Array
    cl: jax.Array
    amplitude: jax.Array
    alpha: jax.Array


class GibbsInfo(NamedTuple):
    """Per step: the a-step's :class:`~gcrsky.solvers.SolveInfo` ((Nf,) fields)."""

    solve: SolveInfo


def gibbs_setup(system: LinearSystem, *, options=None, rank: int = 128, key=None) -> GibbsFixed:
    """Build the a-step's fixed data term once (pure).

    Args:
        system: the linear system (data, noise, response and prior mean; the prior's
            inverse variance sets the scale of the CG preconditioner's sketch only).
        options: ``CholeskyOptions()`` (default: dense ``H``, one Cholesky per step) or
            ``CGOptions(...)`` (its ``dense``, tolerance and iteration cap are used; the
            preconditioner is the Woodbury update of a rank-``rank`` sketch of H).
        rank: sketch size k of the CG path's approximation ``H ~ G G^T``.
        key: PRNG key of that sketch (default PRNGKey(0)).
    """
    options = CholeskyOptions() if options is None else options
    if not isinstance(options, (CholeskyOptions, CGOptions)):
        raise TypeError(f"gibbs_setup takes CholeskyOptions or CGOptions, got {type(options).__name__}")
    check_float64(system.op.response, system.inv_noise)
    data_rhs = adjoint(system.op, system.inv_noise * system.data)
    dense = isinstance(options, CholeskyOptions) or options.dense
    diag = jax.vmap(jnp.diag)(system.prior.inv_var)
    H = precision_matrix(system) - diag if dense else None
    F = G = B = None
    if isinstance(options, CGOptions):
        if dense:
            lam, V = jnp.linalg.eigh(H)
            F = V * jnp.sqrt(jnp.maximum(lam, 0.0))[:, None, :]  # H is PSD: negative lam are rounding
        pc = nystrom_preconditioner(system, rank, key, None if H is None else H + diag)
        G = pc.U * (jnp.sqrt(pc.lam)[:, None, :] / pc.scale[..., None])  # H ~ S^-1/2 U lam U^T S^-1/2
        n = G.shape[1]
        lmax = lmax_from_nparams(n)
        tab = mode_table(lmax)
        pattern = np.zeros((lmax + 1, n))
        pattern[tab.ell, np.arange(n)] = np.where(tab.m == 0, 1.0, 0.5)  # Var(a_i) = C_l(i) * pattern
        B = jnp.einsum("fik,li,fij->flkj", G, jnp.asarray(pattern), G)
    return GibbsFixed(system, data_rhs, H, F, G, B, options)


def gibbs_init(fixed: GibbsFixed, cl, *, position=None, alpha=None) -> GibbsState:
    """Start a chain at spectrum ``cl`` ((lmax+1,) or (Nf, lmax+1), K^2).

    ``position`` defaults to the prior mean; ``alpha`` (scalar or (Nf,)) starts the
    power-law family's slope (its amplitude is drawn at the first step).
    """
    mean = fixed.system.prior.mean
    cl = jnp.broadcast_to(jnp.asarray(cl, mean.dtype), (mean.shape[0], jnp.shape(cl)[-1]))
    pos = mean if position is None else jnp.broadcast_to(jnp.asarray(position, mean.dtype), mean.shape)
    nan = jnp.full(mean.shape[:1], jnp.nan, mean.dtype)
    al = nan if alpha is None else jnp.broadcast_to(jnp.asarray(alpha, mean.dtype), nan.shape)
    return GibbsState(pos, cl, nan, al)


def _woodbury_precond(var, G, blocks, cl):
    """``r -> (S^-1 + G G^T)^-1 r`` by Woodbury, with ``S = diag(var)`` (n,), G (n, k) and the
    k x k core ``I + G^T S G = I + sum_l C_l B_l`` from the precomputed blocks (lmax+1, k, k)."""
    K = jnp.eye(G.shape[1], dtype=G.dtype) + jnp.einsum("l,lkj->kj", cl, blocks)
    L = jnp.linalg.cholesky(K)

    def apply(r):
        t = jax.scipy.linalg.cho_solve((L, True), G.T @ (var * r))
        return var * (r - G @ t)

    return apply


def _fluctuation(key, fixed: GibbsFixed, inv_var):
    """The random part of the GCR right-hand side, ``~ N(0, H + S^-1)`` (Nf, n)."""
    if fixed.data_sqrt is None:
        sys_c = fixed.system._replace(prior=fixed.system.prior._replace(inv_var=inv_var))
        return fluctuation_rhs(key, sys_c)
    kd, ka = jax.random.split(key)
    shape = inv_var.shape
    zd = jax.random.normal(kd, shape, inv_var.dtype)
    return jnp.einsum("fij,fj->fi", fixed.data_sqrt, zd) + jnp.sqrt(inv_var) * jax.random.normal(ka, shape, inv_var.dtype)


def _a_step(key, fixed: GibbsFixed, cl, x0):
    """Exact draw of a | C_l, d for spectra ``cl`` (Nf, lmax+1): (Nf, n) and SolveInfo."""
    system, opts = fixed.system, fixed.options
    mean = system.prior.mean
    var = jnp.broadcast_to(1.0 / prior_from_cl(cl).inv_var, mean.shape)
    inv_var = 1.0 / var
    rhs0 = fixed.data_rhs + inv_var * mean
    if isinstance(opts, CholeskyOptions):
        P = fixed.data_term + jax.vmap(jnp.diag)(inv_var)
        L = jnp.linalg.cholesky(P)
        z = jax.random.normal(key, mean.shape, mean.dtype)

        def one(Lf, bf, zf):
            m = jax.scipy.linalg.cho_solve((Lf, True), bf)
            return m + jax.scipy.linalg.solve_triangular(Lf.T, zf, lower=False)

        a = jax.vmap(one)(L, rhs0, z)
        finite = jnp.all(jnp.isfinite(a), axis=1)
        zeros = jnp.zeros(mean.shape[0])
        return a, direct_info(zeros, zeros, finite)
    b = rhs0 + _fluctuation(key, fixed, inv_var)
    sys_c = system._replace(prior=system.prior._replace(inv_var=inv_var))

    def one(f, bf, xf):
        if fixed.data_term is not None:
            mv = lambda x: fixed.data_term[f] @ x + inv_var[f] * x  # noqa: E731
        else:
            sys_f = freq_slice(sys_c, f)
            mv = lambda x: data_apply(sys_f, x[None])[0] + inv_var[f] * x  # noqa: E731
        prec = _woodbury_precond(var[f], fixed.lowrank[f], fixed.lowrank_blocks[f], cl[f])
        return cg_solve(mv, prec, bf, xf, opts)

    return jax.vmap(one)(jnp.arange(mean.shape[0]), b, x0)


def gibbs_step(
    key: jax.Array,
    state: GibbsState,
    fixed: GibbsFixed,
    *,
    family: str = "free",
    cl_prior: str = "jeffreys",
    monopole=None,
    hyper=None,
    lmin: int = 1,
    alpha_range: tuple[float, float] = (-2.0, 8.0),
) -> tuple[GibbsState, GibbsInfo]:
    """One sweep ``a | C_l, d`` then ``C_l | a`` (pure; jit / ``lax.scan`` it yourself).

    Args:
        key: PRNG key of this step.
        state: the chain's :class:`GibbsState`.
        fixed: :func:`gibbs_setup`'s data term.
        family: ``"free"`` (every C_l drawn, :func:`~gcrsky.inference.cl.sample_cl`) or
            ``"power_law"`` (``C_l = A (l+1)^-alpha`` for ``l >= lmin``,
            :func:`~gcrsky.inference.cl.sample_power_law`; lower l keep ``state.cl``).
        cl_prior: ``"jeffreys"``, ``"uniform"`` or ``"inverse_gamma"`` with ``hyper``
            (free family; :func:`~gcrsky.inference.cl.sample_cl`).
        monopole: ``C_0`` to keep fixed (required by ``"uniform"``; scalar or (Nf,)).
        lmin, alpha_range: the power law's range in l and the slope's uniform prior.

    Returns:
        (GibbsState, GibbsInfo).
    """
    if family not in ("free", "power_law"):
        raise ValueError(f"family must be 'free' or 'power_law', got {family!r}")
    k_a, k_c = jax.random.split(key)
    mean = fixed.system.prior.mean
    a, info = _a_step(k_a, fixed, state.cl, state.position)
    if family == "free":
        cl = sample_cl(k_c, a, prior=cl_prior, monopole=monopole, mean=mean, hyper=hyper)
        return GibbsState(a, cl, state.amplitude, state.alpha), GibbsInfo(info)
    alpha0 = jnp.where(jnp.isnan(state.alpha), 0.5 * (alpha_range[0] + alpha_range[1]), state.alpha)
    amp, alpha = sample_power_law(k_c, a, alpha0, lmin=lmin, alpha_range=alpha_range, mean=mean)
    ell1 = jnp.arange(1, state.cl.shape[-1] + 1, dtype=mean.dtype)
    law = amp[:, None] * ell1[None, :] ** (-alpha[:, None])
    cl = jnp.where(jnp.arange(state.cl.shape[-1]) >= lmin, law, state.cl)
    return GibbsState(a, cl, amp, alpha), GibbsInfo(info)
