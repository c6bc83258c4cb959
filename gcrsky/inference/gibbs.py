"""Gibbs kernels (blackjax style): the GCR step, and the hierarchical ``(a, C_l)`` sampler.

``gcr_init(position) -> GCRState`` and ``gcr_step(key, state, system) -> (state, info)``
are pure and jittable, usable inside ``lax.scan``; the library does not jit for
you.  ``system`` may change between steps (e.g. a Gibbs update of the prior), so
each step draws exactly from the current conditional ``a | d, S, N, a0``, on any
registered path (``options``: CG by default, warm-started, its preconditioner rebuilt from
``system`` each call; any other path sets itself up and draws once).  Where only a noise
scale and a prior amplitude change, :mod:`gcrsky.inference.scalar_gibbs` factors once.

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
tolerance for the current ``C_l``.  Any other registered path's options set that path up
per step (its own factorisation) and draw through it.
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import check_float64
from ..base.memory import check_memory
from ..model.operator import adjoint
from ..model.prior import prior_from_cl
from ..model.system import LinearSystem, data_apply, fluctuation_rhs, precision_matrix, wiener_rhs
from ..solvers.cg import cg_solve, freq_slice, resolve_cg_options, solve_cg
from ..solvers.info import SolveInfo, direct_info
from ..solvers.options import CGOptions, CholeskyOptions
from ..solvers.preconditioners import make_preconditioner, nystrom_preconditioner
from ..solvers.registry import options_for, path_of
from ..sphere.modes import lmax_from_nparams, mode_table
from .cl import sample_cl, sample_power_law

__all__ = [
    "GCRState",
    "GibbsFixed",
    "GibbsInfo",
    "GibbsState",
    "JointInfo",
    "gcr_init",
    "gcr_step",
    "gibbs_init",
    "gibbs_setup",
    "gibbs_setup_bytes",
    "gibbs_step",
    "joint_step",
    "sky_step",
]

log = logging.getLogger(__name__)

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
    options=None,
    pc=None,
) -> tuple[GCRState, SolveInfo]:
    """One exact conditional draw ``a ~ p(a | d, S, N, a0)`` (pure; jit/scan it yourself).

    Any exact path: ``options`` are the options of a path in the registry
    (:func:`gcrsky.solvers.path_of`: ``CGOptions``, ``CholeskyOptions``, ``EighOptions``,
    ``MModeOptions``, ``DataSpaceOptions``, or a path added there later).  The CG path
    (the default) solves the GCR equation by preconditioned CG warm-started at the
    previous position (typically within a few posterior sigma of the new draw); every
    other path sets itself up for ``system`` (``path.prepare``) and draws once
    (``path.draw``), so a step costs that path's factorisation.  Where only the noise
    scale and the prior amplitude change between steps, :func:`gcrsky.inference.prepare_scalar`
    factors once and each draw costs O(n^2).

    Args:
        key: PRNG key of this step.
        state: the chain's :class:`GCRState`.
        system: the current linear system.
        tol: CG tolerance in posterior-sigma units (overrides ``options.tol`` on the CG path;
            a direct path keeps its own ``tol``, the accuracy its factor must reach).
        options: a path's options; default ``CGOptions(dense=False)`` (matrix-free).  CG's
            preconditioner (``"auto"`` means Nystrom under a trace, which needs ``S^-1 > 0``
            in every mode; pass ``"mblock"`` for a flat prior) is rebuilt each step from
            ``system`` unless a prebuilt ``pc`` is passed.  A stale ``pc`` (built for an
            earlier S) only costs iterations: the draw stays exact because convergence is
            checked against the current system.
        pc: optional prebuilt preconditioner (:mod:`gcrsky.solvers.preconditioners`; CG only).

    Returns:
        (GCRState with position (Nf, n), SolveInfo with (Nf,) fields: the draw's, or on a direct
        path the factor's measured accuracy).
    """
    options = STEP_OPTIONS if options is None else options
    if not isinstance(options, CGOptions):
        return _path_step(key, system, options, tol, pc)
    if tol is not None:
        options = dataclasses.replace(options, tol=float(tol))
    options = resolve_cg_options(system, options)
    precision = precision_matrix(system) if options.dense else None
    if pc is None:
        pc = make_preconditioner(system, options.preconditioner, precision, options.sketch_size, options.pc_dtype,
                                 options.bandwidth)
    b = wiener_rhs(system) + fluctuation_rhs(key, system)
    x, info = solve_cg(system, precision, pc, b, state.position, options)
    return GCRState(x), info


def _path_step(key, system: LinearSystem, options, tol, pc) -> tuple[GCRState, SolveInfo]:
    """:func:`gcr_step` on a path other than CG: its own set-up and one draw, through the registry."""
    if pc is not None:
        raise ValueError(f"pc= is a CG preconditioner; {type(options).__name__} takes none")
    path = path_of(options)
    options = path.resolve(system, options_for(path.name, options, tol=tol))
    draws, info = path.draw(key, path.prepare(system, options), 1)
    return GCRState(draws[:, 0]), jax.tree_util.tree_map(lambda x: x[:, 0], info.draws)


# ---------------------------------------------------------------- the hierarchical (a, C_l) kernel


class GibbsFixed(eqx.Module):
    """What the hierarchical a-step reuses every step (built once by :func:`gibbs_setup`; a PyTree).

    Attributes:
        system: the linear system (its prior's mean is kept; its variance is replaced by
            ``C_l`` each step, or kept where :func:`sky_step` is called without one).
        data_rhs: ``X^T N^-1 d`` (Nf, n).
        data_term: dense ``H = X^T N^-1 X`` (Nf, n, n), or None (matrix-free CG).
        data_sqrt: ``F`` (Nf, n, n) with ``F F^T = H`` (dense CG: the data part of the
            GCR right-hand side is then ``F z``, exactly ``N(0, H)``), or None.
        lowrank: ``G`` (Nf, n, k) with ``H ~ G G^T`` (CG preconditioner), or None.
        lowrank_blocks: ``B_l = G^T diag(v_l) G`` (Nf, lmax+1, k, k) with ``v_l`` the
            prior variance pattern of degree l (``S(C_l) = sum_l C_l diag(v_l)``), so the
            preconditioner's k x k core ``I + G^T S G = I + sum_l C_l B_l`` costs
            O(lmax k^2) per step; or None.
        factor: the system's own prior, factorised once: the lower Cholesky factor of
            ``H + S^-1`` (Nf, n, n) on the dense path, of the Woodbury core
            ``I + G^T S G`` (Nf, k, k) on the CG path, the path's prepared state on any
            other path.
        options: the a-step's solver options (any registered path's).
    """

    system: LinearSystem
    data_rhs: jax.Array
    data_term: jax.Array | None
    data_sqrt: jax.Array | None
    lowrank: jax.Array | None
    lowrank_blocks: jax.Array | None
    factor: jax.Array | eqx.Module
    options: object = eqx.field(static=True)


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


#: ``sketch_size="auto"``: the sketch's size, and the share of the posterior precision (in the system's
#: own prior-whitened frame) below which a direction is left to CG.
AUTO_SKETCH, AUTO_THRESHOLD = 512, 1e-2


def _auto_rank(lam) -> int:
    """The CG path's sketch size for ``sketch_size="auto"`` from the Nystrom eigenvalues (Nf, k0) (host-side)."""
    try:
        lam = np.asarray(lam)
    except jax.errors.ConcretizationTypeError:
        raise ValueError("gibbs_setup(sketch_size='auto') reads the sketch's eigenvalues on the host: call it "
                         "outside jit, or pass an integer sketch_size") from None
    k0 = lam.shape[-1]
    count = int(np.max(np.sum(lam >= AUTO_THRESHOLD, axis=-1)))
    if count >= k0:
        log.warning("gibbs_setup: all %d sketched directions of the data term are above %g: pass a larger sketch_size "
                    "if CG needs many iterations", k0, AUTO_THRESHOLD)
    return min(k0, max(32, 16 * int(np.ceil(1.25 * count / 16))))


def gibbs_setup_bytes(n_freqs: int, n: int, options=None, sketch_size: int | str = "auto") -> float:
    """Estimated peak bytes of :func:`gibbs_setup`'s fixed data term (float64), beyond the system.

    Cholesky path (the default): ``H``, its factor and the precision they are formed from, ``3 x 8 Nf n^2``.
    CG path: the sketch, its eigenvectors and ``G`` (``4 x 8 Nf n k``, ``k = min(n, 512)`` for ``"auto"``)
    and the per-degree blocks ``B`` (``8 Nf (lmax + 1) k^2``), plus ``H`` and its eigendecomposition
    (``3 x 8 Nf n^2``) where ``options.dense``.  Other paths: 0 (their own set-up checks its memory).
    """
    options = CholeskyOptions() if options is None else options
    nf, n = int(n_freqs), int(n)
    if isinstance(options, CholeskyOptions):
        return 3 * 8.0 * nf * n * n
    if isinstance(options, CGOptions):
        k = min(n, AUTO_SKETCH) if isinstance(sketch_size, str) else int(sketch_size)
        lmax = lmax_from_nparams(n)
        dense = 3 * 8.0 * nf * n * n if options.dense else 0.0
        return dense + 4 * 8.0 * nf * n * k + 8.0 * nf * (lmax + 1) * k * k
    return 0.0


def gibbs_setup(system: LinearSystem, *, options=None, sketch_size: int | str = "auto", key=None,
                rank: int | str | None = None) -> GibbsFixed:
    """Build the a-step's fixed data term once (pure for an integer ``sketch_size``).

    Args:
        system: the linear system (data, noise, response and prior; the prior's mean is
            the hierarchical prior's mean, its inverse variance the one :func:`sky_step`
            uses when given no ``C_l``, and the scale of the CG preconditioner's sketch).
        options: ``CholeskyOptions()`` (default: dense ``H``, one Cholesky per step),
            ``CGOptions(...)`` (its ``dense``, tolerance and iteration cap are used; the
            preconditioner is the Woodbury update of a rank-``sketch_size`` sketch of H), or
            any other registered path's options (``EighOptions``, ``MModeOptions``,
            ``DataSpaceOptions``, ...): that path set up once for the system's own prior and
            once per step for a new one (its own factorisation each step), then one draw.
        sketch_size: sketch size k of the CG path's approximation ``H ~ G G^T``, or ``"auto"``
            (host-side, not under ``jit``): sketch ``min(n, 512)`` directions, then keep
            1.25 x the number whose eigenvalue in the system's prior-whitened frame is
            ``>= 0.01`` (at least 32): measured, 112 at the standard case (2 CG iterations a
            step) and 240 at lmax 50 with 8 h of data (2 iterations, where a fixed 128 needed
            80).  Per step the preconditioner costs ``O(lmax k^2 + k^3)``.
        key: PRNG key of that sketch (default PRNGKey(0)).
        rank: deprecated name of ``sketch_size``.

    Raises:
        gcrsky.base.InsufficientMemoryError: the set-up (:func:`gibbs_setup_bytes`) would not fit in the
            memory available, before anything is allocated; the message names the sizes.
    """
    if rank is not None:
        warnings.warn("gibbs_setup(rank=...) is deprecated: use sketch_size=", DeprecationWarning, stacklevel=2)
        sketch_size = rank
    options = CholeskyOptions() if options is None else options
    sky = _sky_solver(options)
    check_float64(system.op.response, system.inv_noise)
    nf, n = (int(x) for x in system.prior.mean.shape)
    check_memory(gibbs_setup_bytes(nf, n, options, sketch_size),
                 f"gibbs_setup ({type(options).__name__}, Nf = {nf}, n = {n})",
                 "use a lower lmax or fewer channels" + ("" if isinstance(options, CGOptions) and not options.dense
                                                         else ", or the matrix-free CG path (CGOptions(dense=False))")
                 + ("" if isinstance(options, CholeskyOptions) else ", or a smaller sketch_size"))
    data_rhs = adjoint(system.op, system.inv_noise * system.data)
    return GibbsFixed(system, data_rhs, *sky.setup(system, options, sketch_size, key), options)


class _DenseSky:
    """The a-step on the Cholesky path: dense ``H``, one Cholesky of ``H + S^-1`` per prior."""

    def setup(self, system, options, size, key):
        diag = jax.vmap(jnp.diag)(system.prior.inv_var)
        H = precision_matrix(system) - diag
        return H, None, None, None, jnp.linalg.cholesky(H + diag)

    def factor(self, fixed, cl, inv_var):
        return jnp.linalg.cholesky(fixed.data_term + jax.vmap(jnp.diag)(inv_var))

    def mean(self, fixed, cond, rhs):
        m = _dense_mean(cond, rhs)
        zeros = jnp.zeros(m.shape[0])
        return m, direct_info(zeros, zeros, jnp.all(jnp.isfinite(m), axis=1), fixed.options.tol)

    def draw(self, key, fixed, cond, rhs0, x0, data=None):
        mean = fixed.system.prior.mean
        z = jax.random.normal(key, mean.shape, mean.dtype)

        def one(Lf, bf, zf):
            m = jax.scipy.linalg.cho_solve((Lf, True), bf)
            return m + jax.scipy.linalg.solve_triangular(Lf.T, zf, lower=False)

        a = jax.vmap(one)(cond.factor, rhs0, z)
        zeros = jnp.zeros(mean.shape[0])
        return a, direct_info(zeros, zeros, jnp.all(jnp.isfinite(a), axis=1), fixed.options.tol)


class _CGSky:
    """The a-step on the CG path: a rank-k sketch ``H ~ G G^T`` built once, a Woodbury
    preconditioner per prior, CG warm-started at the previous draw."""

    def setup(self, system, options, size, key):
        diag = jax.vmap(jnp.diag)(system.prior.inv_var)
        H = precision_matrix(system) - diag if options.dense else None
        F = None
        if options.dense:
            lam, V = jnp.linalg.eigh(H)
            F = V * jnp.sqrt(jnp.maximum(lam, 0.0))[:, None, :]  # H is PSD: negative lam are rounding
        auto = isinstance(size, str)
        if auto and size != "auto":
            raise ValueError(f"sketch_size must be an integer or 'auto', got {size!r}")
        n = system.prior.mean.shape[1]
        pc = nystrom_preconditioner(system, min(n, AUTO_SKETCH) if auto else size, key,
                                    None if H is None else H + diag)
        U, lam = pc.U, pc.lam
        if auto:  # the sketch's eigenpairs come sorted, largest first: keep the leading ones
            k = _auto_rank(lam)
            U, lam = U[..., :k], lam[..., :k]
            log.info("gibbs_setup: rank-%d sketch of the data term (of %d sketched)", k, pc.lam.shape[-1])
        G = U * (jnp.sqrt(lam)[:, None, :] / pc.scale[..., None])  # H ~ S^-1/2 U lam U^T S^-1/2
        tab = mode_table(lmax_from_nparams(n))
        pattern = np.zeros((tab.ell.max() + 1, n))
        pattern[tab.ell, np.arange(n)] = np.where(tab.m == 0, 1.0, 0.5)  # Var(a_i) = C_l(i) * pattern
        B = jnp.einsum("fik,li,fij->flkj", G, jnp.asarray(pattern), G)
        return H, F, G, B, jax.vmap(_core_factor)(G, 1.0 / system.prior.inv_var)

    def factor(self, fixed, cl, inv_var):
        if cl is None:
            return jax.vmap(_core_factor)(fixed.lowrank, 1.0 / inv_var)
        mean = fixed.system.prior.mean  # Woodbury core from the per-l blocks: O(lmax k^2 + k^3)
        k = fixed.lowrank.shape[-1]
        cls = jnp.broadcast_to(cl, (mean.shape[0], cl.shape[-1]))
        return jnp.linalg.cholesky(jnp.eye(k, dtype=mean.dtype) + jnp.einsum("fl,flkj->fkj", cls,
                                                                            fixed.lowrank_blocks))

    def mean(self, fixed, cond, rhs):
        return _cg_solve(fixed, cond, rhs, fixed.system.prior.mean)

    def draw(self, key, fixed, cond, rhs0, x0, data=None):
        return _cg_solve(fixed, cond, rhs0 + _fluctuation(key, fixed, cond.inv_var), x0)


class _PathSky:
    """The a-step on any other registered path (:func:`gcrsky.solvers.path_of`): the path set up for the
    system's own prior once, and for each new prior per step (``path.prepare``, its own factorisation),
    then one draw (``path.draw``); new data by ``path.condition`` (the factor reused)."""

    def setup(self, system, options, size, key):
        return None, None, None, None, path_of(options).prepare(system, options)

    def factor(self, fixed, cl, inv_var):
        system = fixed.system
        return path_of(fixed.options).prepare(system._replace(prior=system.prior._replace(inv_var=inv_var)),
                                              fixed.options)

    def mean(self, fixed, cond, rhs):
        return cond.factor.a_wf, cond.factor.wiener

    def draw(self, key, fixed, cond, rhs0, x0, data=None):
        path = path_of(fixed.options)
        state = cond.factor if data is None else path.condition(cond.factor, data)
        draws, info = path.draw(key, state, 1)
        return draws[:, 0], jax.tree_util.tree_map(lambda x: x[:, 0], info.draws)


#: The a-steps specialised to reuse the data term (by options type); every other path: :class:`_PathSky`.
_SKY_SOLVERS = {CholeskyOptions: _DenseSky(), CGOptions: _CGSky()}


def _sky_solver(options):
    """The a-step of ``options``' path: a specialised one, or the path's own prepare and draw."""
    path_of(options)  # a TypeError for what is not a registered path's options
    return _SKY_SOLVERS.get(type(options), _PathSky())


def gibbs_init(fixed: GibbsFixed, cl, *, position=None, alpha=None, amplitude=None) -> GibbsState:
    """Start a chain at spectrum ``cl`` ((lmax+1,) or (Nf, lmax+1), K^2).

    ``position`` defaults to the prior mean; ``alpha`` (scalar or (Nf,)) starts the
    power-law family's slope; ``amplitude`` (K^2) its amplitude (default unset: drawn at
    the first :func:`gibbs_step`; :func:`joint_step` needs it set).
    """
    mean = fixed.system.prior.mean
    cl = jnp.broadcast_to(jnp.asarray(cl, mean.dtype), (mean.shape[0], jnp.shape(cl)[-1]))
    pos = mean if position is None else jnp.broadcast_to(jnp.asarray(position, mean.dtype), mean.shape)
    nan = jnp.full(mean.shape[:1], jnp.nan, mean.dtype)
    al = nan if alpha is None else jnp.broadcast_to(jnp.asarray(alpha, mean.dtype), nan.shape)
    amp = nan if amplitude is None else jnp.broadcast_to(jnp.asarray(amplitude, mean.dtype), nan.shape)
    return GibbsState(pos, cl, amp, al)


def _core_factor(G, var):
    """Lower Cholesky factor of the Woodbury core ``I + G^T diag(var) G`` (k, k), O(n k^2)."""
    return jnp.linalg.cholesky(jnp.eye(G.shape[1], dtype=G.dtype) + G.T @ (var[:, None] * G))


def _woodbury_precond(var, G, Lk):
    """``r -> (S^-1 + G G^T)^-1 r`` by Woodbury, with ``S = diag(var)`` (n,), G (n, k) and the
    lower Cholesky factor ``Lk`` of the k x k core ``I + G^T S G``."""

    def apply(r):
        t = jax.scipy.linalg.cho_solve((Lk, True), G.T @ (var * r))
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


class _Conditional(NamedTuple):
    """The prior of one a-step: inverse variance (Nf, n), and the factor of the dense P (Cholesky
    path) or of the Woodbury core (CG path)."""

    inv_var: jax.Array
    factor: jax.Array


def _conditional(fixed: GibbsFixed, cl=None, inv_var=None) -> _Conditional:
    """The a-step's prior from ``cl`` (isotropic), ``inv_var``, or the system's own (factor reused)."""
    if cl is not None and inv_var is not None:
        raise ValueError("pass cl or inv_var, not both")
    mean = fixed.system.prior.mean
    if cl is None and inv_var is None:
        return _Conditional(fixed.system.prior.inv_var, fixed.factor)
    if cl is not None:
        cl = jnp.asarray(cl, mean.dtype)
        inv_var = jnp.broadcast_to(prior_from_cl(cl).inv_var, mean.shape)
    inv_var = jnp.broadcast_to(jnp.asarray(inv_var, mean.dtype), mean.shape)
    return _Conditional(inv_var, _sky_solver(fixed.options).factor(fixed, cl, inv_var))


def _data_rhs(fixed: GibbsFixed, data):
    if data is None:
        return fixed.data_rhs
    system = fixed.system
    data = jnp.asarray(data, system.data.dtype)
    if data.shape != system.data.shape:
        raise ValueError(f"data must have the system's shape {system.data.shape}, got {data.shape}")
    return adjoint(system.op, system.inv_noise * data)


def _dense_mean(cond: _Conditional, rhs):
    return jax.vmap(lambda L, b: jax.scipy.linalg.cho_solve((L, True), b))(cond.factor, rhs)


def _cg_solve(fixed: GibbsFixed, cond: _Conditional, b, x0):
    """``(H + S^-1)^-1 b`` per frequency by CG from ``x0``, Woodbury-preconditioned: (x, SolveInfo)."""
    system, inv_var = fixed.system, cond.inv_var
    sys_c = system._replace(prior=system.prior._replace(inv_var=inv_var))

    def one(f, bf, xf):
        if fixed.data_term is not None:
            mv = lambda x: fixed.data_term[f] @ x + inv_var[f] * x  # noqa: E731
        else:
            sys_f = freq_slice(sys_c, f)
            mv = lambda x: data_apply(sys_f, x[None])[0] + inv_var[f] * x  # noqa: E731
        prec = _woodbury_precond(1.0 / inv_var[f], fixed.lowrank[f], jax.lax.stop_gradient(cond.factor[f]))
        return cg_solve(mv, prec, bf, xf, fixed.options)

    return jax.vmap(one)(jnp.arange(b.shape[0]), b, x0)


def _draw(key, fixed: GibbsFixed, cond: _Conditional, data_rhs, x0, data=None):
    """Exact draw of ``a | d, S`` for the prior ``cond``: (Nf, n) and SolveInfo (``data``: the
    visibilities behind ``data_rhs`` where they are not the system's)."""
    rhs0 = data_rhs + cond.inv_var * fixed.system.prior.mean
    return _sky_solver(fixed.options).draw(key, fixed, cond, rhs0, x0, data)


def sky_step(
    key: jax.Array, fixed: GibbsFixed, position=None, *, cl=None, inv_var=None, data=None
) -> tuple[jax.Array, SolveInfo]:
    """One exact draw of the sky ``a | d, S`` reusing :func:`gibbs_setup`'s data term (pure).

    The sky block of a Gibbs sampler: the prior is the isotropic one of ``cl``, a
    diagonal one given by ``inv_var``, or (neither) the system's own, whose factor
    :func:`gibbs_setup` built once, so that step costs two triangular solves (dense) or
    a warm-started CG (no factorisation at all).  ``data`` replaces the system's
    visibilities for this draw, e.g. the data minus the model visibilities of another
    block (point sources, a foreground model): the data term ``H`` does not depend on
    them, only ``X^T N^-1 d`` is recomputed (one adjoint of the operator).

    Args:
        key: PRNG key.
        fixed: :func:`gibbs_setup`'s data term.
        position: (Nf, n) the CG path's warm start (the previous draw; default the
            prior mean); unused by the Cholesky path.
        cl: (Nf, lmax+1) or (lmax+1,) angular power spectrum (K^2) of an isotropic prior
            about the system's prior mean (:func:`gcrsky.prior_from_cl`).
        inv_var: (Nf, n) a diagonal prior's inverse variance (K^-2), instead of ``cl``.
        data: (Nf, Nt, Nbl) complex visibilities (K sr) replacing the system's data.

    Returns:
        ``(a (Nf, n), SolveInfo with (Nf,) fields)``; exact for the Cholesky path, to the
        CG tolerance (posterior sigma) for the CG path.
    """
    mean = fixed.system.prior.mean
    x0 = mean if position is None else jnp.broadcast_to(jnp.asarray(position, mean.dtype), mean.shape)
    if data is not None:
        data = jnp.asarray(data, fixed.system.data.dtype)
    return _draw(key, fixed, _conditional(fixed, cl, inv_var), _data_rhs(fixed, data), x0, data)


def _a_step(key, fixed: GibbsFixed, cl, x0):
    """Exact draw of a | C_l, d for spectra ``cl`` (Nf, lmax+1): (Nf, n) and SolveInfo."""
    return sky_step(key, fixed, x0, cl=cl)


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


# ---------------------------------------------------------------- the joint (C_l, a) move (Racine et al. 2016)


class JointInfo(NamedTuple):
    """Per joint move, (Nf,) fields.

    Attributes:
        accepted: the proposal was accepted.
        log_ratio: log of the Metropolis-Hastings ratio (``-inf`` outside the prior's support).
        solve: SolveInfo of the proposed spectrum's Wiener solve (CG), or a direct solve's.
    """

    accepted: jax.Array
    log_ratio: jax.Array
    solve: SolveInfo


RESCALINGS = ("prior", "posterior")


def _log_target(fixed: GibbsFixed, cond: _Conditional, a):
    """``log p(d | a) + log N(a; a0, S)`` up to a constant, (Nf,): ``-1/2 a.Ha + a.b_d``
    ``- 1/2 sum (a - a0)^2 / var - 1/2 sum log var``."""
    system = fixed.system
    if fixed.data_term is not None:
        Ha = jnp.einsum("fij,fj->fi", fixed.data_term, a)
    else:
        Ha = data_apply(system, a)
    r = a - system.prior.mean
    return (jnp.sum(-0.5 * a * Ha + a * fixed.data_rhs, axis=-1)
            - 0.5 * jnp.sum(cond.inv_var * r**2, axis=-1) + 0.5 * jnp.sum(jnp.log(cond.inv_var), axis=-1))


def _rescale(rescale, cond, cond_new, mean, mean_new, a):
    """The deterministic map ``a -> a'`` about the Wiener means and ``log |det da'/da|``, (Nf,)."""
    if rescale == "prior":  # a' = m' + (S'/S)^1/2 (a - m)   (Jewell et al. 2009; Racine et al. 2016)
        ratio = jnp.sqrt(cond.inv_var / cond_new.inv_var)
        return mean_new + ratio * (a - mean), jnp.sum(jnp.log(ratio), axis=-1)

    # "posterior": whitened by the posterior's own square roots, z = L^T (a - m), a' = m' + L'^-T z
    def one(L, Ln, d):
        z = L.T @ d
        return jax.scipy.linalg.solve_triangular(Ln.T, z, lower=False)

    moved = jax.vmap(one)(cond.factor, cond_new.factor, a - mean)
    logdet = lambda L: jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), axis=-1)  # noqa: E731
    return mean_new + moved, logdet(cond.factor) - logdet(cond_new.factor)


def _wiener_mean(fixed: GibbsFixed, cond: _Conditional):
    """The Wiener filter for the prior ``cond``: (Nf, n) and SolveInfo (CG from the prior mean, so a
    deterministic function of the spectrum and the move exactly reversible)."""
    rhs = fixed.data_rhs + cond.inv_var * fixed.system.prior.mean
    return _sky_solver(fixed.options).mean(fixed, cond, rhs)


def _proposal(key, state: GibbsState, family, proposal, lmin, alpha_range, cl_prior, hyper, dtype):
    """The proposed spectrum (Nf, lmax+1), amplitude and slope, and the log prior ratio (Nf,) in the
    proposal's coordinates ((log A, alpha), or log C_l), in which the random walk is symmetric."""
    nf, nl = state.cl.shape
    prop = jnp.asarray(proposal, dtype)
    if family == "power_law":
        chol = jnp.linalg.cholesky(prop) if prop.ndim == 2 else jnp.diag(jnp.broadcast_to(prop, (2,)))
        step = jax.random.normal(key, (nf, 2), dtype) @ chol.T
        amp = state.amplitude * jnp.exp(step[:, 0])
        alpha = state.alpha + step[:, 1]
        ell1 = jnp.arange(1, nl + 1, dtype=dtype)
        law = amp[:, None] * ell1[None, :] ** (-alpha[:, None])
        cl = jnp.where(jnp.arange(nl) >= lmin, law, state.cl)
        inside = (alpha >= alpha_range[0]) & (alpha <= alpha_range[1])  # prior: 1/A, alpha uniform
        return cl, amp, alpha, jnp.where(inside, 0.0, -jnp.inf)
    scale = jnp.broadcast_to(prop, (nl,))
    logc = jnp.log(state.cl) + scale * jax.random.normal(key, (nf, nl), dtype)
    cl = jnp.exp(logc)
    moved = scale > 0

    def log_prior(c):  # density of log C_l (the prior on C_l times the Jacobian C_l)
        if cl_prior == "jeffreys":
            return jnp.zeros_like(c)
        if cl_prior == "uniform":
            return jnp.log(c)
        k, s = (jnp.broadcast_to(jnp.asarray(x, dtype), (nl,)) for x in hyper)
        return -k * jnp.log(c) - s / c

    dprior = jnp.sum(jnp.where(moved, log_prior(cl) - log_prior(state.cl), 0.0), axis=-1)
    return cl, state.amplitude, state.alpha, dprior


def joint_step(
    key: jax.Array,
    state: GibbsState,
    fixed: GibbsFixed,
    *,
    proposal,
    family: str = "power_law",
    rescale: str = "prior",
    cl_prior: str = "jeffreys",
    hyper=None,
    lmin: int = 1,
    alpha_range: tuple[float, float] = (-2.0, 8.0),
    refresh: bool = False,
) -> tuple[GibbsState, JointInfo]:
    """One joint Metropolis-Hastings move of ``(C_l, a)``: a new spectrum and the sky rescaled with it.

    Gibbs sampling of ``(a, C_l)`` mixes slowly where the data barely constrain a degree:
    ``C_l | a`` is then pinned by ``a`` and ``a | C_l`` by ``C_l``.  This move (Jewell et
    al. 2009; Racine et al. 2016) proposes ``C'`` by a symmetric random walk and moves the
    sky with it deterministically, keeping its fluctuation about the Wiener mean ``m(C)``
    in step with the prior:

    - ``rescale="prior"`` (Racine et al.; every path): ``a' = m(C') + (S'/S)^1/2 (a - m(C))``;
    - ``rescale="posterior"`` (Cholesky path): ``a' = m(C') + L'^-T L^T (a - m(C))`` with
      ``L L^T = P(C)``, the posterior's own square roots.  Its acceptance ratio is then
      exactly ``p(d | C') p(C') / p(d | C) p(C)`` whatever ``a``: a Metropolis move on the
      collapsed marginal of the spectrum, carrying the sky along.

    Both maps are bijections whose inverse is the reverse proposal's map, so the move
    leaves ``p(a, C_l | d)`` invariant with the ratio
    ``pi(a', C') |det da'/da| / pi(a, C)`` (``pi`` the joint density).  Alternate it with
    :func:`gibbs_step`.  Cost: two Wiener solves (one Cholesky or CG solve per spectrum);
    each frequency accepts or rejects on its own.

    Args:
        key: PRNG key.
        state: the chain's :class:`GibbsState` (for ``family="power_law"`` its amplitude
            must be set: run one :func:`gibbs_step` first).
        fixed: :func:`gibbs_setup`'s data term.
        proposal: the random walk's scale: ``family="power_law"``: (2,) standard deviations
            of ``(log A, alpha)`` or their (2, 2) covariance (e.g. from a pilot chain);
            ``family="free"``: scalar or (lmax+1,) standard deviations of ``log C_l`` (0: that
            degree is not moved; keep it 0 where ``C_l`` is fixed, e.g. the monopole).
        family, cl_prior, hyper, lmin, alpha_range: as for :func:`gibbs_step`, whose
            hyperpriors this move targets (power law: ``1/A`` and alpha uniform on
            ``alpha_range``).
        rescale: ``"prior"`` or ``"posterior"`` (above).
        refresh: then draw the sky afresh, ``a | C_l, d`` at the accepted spectrum, reusing
            the move's factorisation (Cholesky path: no extra factorisation; CG: one more
            solve).  With ``rescale="posterior"`` the move's acceptance does not depend on
            ``a``, so ``joint_step(..., refresh=True)`` alone is a complete sampler:
            Metropolis on the exact collapsed marginal of the spectrum plus an exact sky,
            at two factorisations per step.

    Returns:
        (GibbsState, JointInfo); with ``refresh`` the SolveInfo is the sky draw's.
    """
    if family not in ("free", "power_law"):
        raise ValueError(f"family must be 'free' or 'power_law', got {family!r}")
    if rescale not in RESCALINGS:
        raise ValueError(f"rescale must be one of {RESCALINGS}, got {rescale!r}")
    if refresh and isinstance(_sky_solver(fixed.options), _PathSky):
        raise ValueError("joint_step(refresh=True) needs gibbs_setup with CholeskyOptions or CGOptions")
    if rescale == "posterior" and not isinstance(_sky_solver(fixed.options), _DenseSky):
        raise ValueError("rescale='posterior' needs the Cholesky path (gibbs_setup(..., options=CholeskyOptions()))")
    if family == "free" and cl_prior not in ("jeffreys", "uniform", "inverse_gamma"):
        raise ValueError(f"cl_prior must be 'jeffreys', 'uniform' or 'inverse_gamma', got {cl_prior!r}")
    if (cl_prior == "inverse_gamma") != (hyper is not None) and family == "free":
        raise ValueError("hyper=(shape, scale) goes with cl_prior='inverse_gamma' and only with it")
    k_p, k_u = jax.random.split(key)
    a = state.position
    dtype = a.dtype
    cl_new, amp_new, alpha_new, dprior = _proposal(k_p, state, family, proposal, lmin, alpha_range, cl_prior,
                                                   hyper, dtype)
    cond, cond_new = _conditional(fixed, state.cl), _conditional(fixed, cl_new)
    m, _ = _wiener_mean(fixed, cond)
    m_new, info = _wiener_mean(fixed, cond_new)
    a_new, log_jac = _rescale(rescale, cond, cond_new, m, m_new, a)
    log_ratio = _log_target(fixed, cond_new, a_new) - _log_target(fixed, cond, a) + log_jac + dprior
    log_ratio = jnp.where(jnp.isnan(log_ratio), -jnp.inf, log_ratio)
    accept = jnp.log(jax.random.uniform(k_u, log_ratio.shape, dtype)) < log_ratio
    pick = lambda new, old: jnp.where(accept.reshape(accept.shape + (1,) * (new.ndim - 1)), new, old)  # noqa: E731
    new_state = GibbsState(pick(a_new, a), pick(cl_new, state.cl), pick(amp_new, state.amplitude),
                           pick(alpha_new, state.alpha))
    if refresh:
        k_a = jax.random.fold_in(key, 1)
        cond_acc = jax.tree_util.tree_map(pick, cond_new, cond)
        a_fresh, info = _draw(k_a, fixed, cond_acc, fixed.data_rhs, new_state.position)
        new_state = new_state._replace(position=a_fresh)
    return new_state, JointInfo(accept, log_ratio, info)
