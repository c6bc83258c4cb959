"""The dense exact paths: Cholesky and eigen-decomposition of P.

* Cholesky: ``P = L L^T``; ``a = a_wf + L^-T z`` with ``z ~ N(0, I)``.  The exact
  reference, and the fast path when n^2 fits in memory.  ``L^-T`` is formed once by
  :func:`prepare_cholesky` (to ~cond(L) eps relative), so a batch of draws is one
  matrix product.  Draw ``i`` of a batch uses ``jax.random.split(key, ndraws)[i]``,
  as CG does.
* Eigen: ``P = V diag(lam) V^T``; ``a = a_wf + (P^+)^1/2 z`` with the symmetric
  square root ``(P^+)^1/2 = V_r lam_r^-1/2 V_r^T``.  Exact like Cholesky for a proper
  prior, and the only path that handles a singular P (a flat prior, ``S^-1 = 0``,
  leaves directions the data do not see): it samples the posterior restricted to the
  directions with eigenvalue ``> rcond * max``; the others have no information and
  are pinned at 0 (the minimum-norm solution), and ``EighState.kept`` says how many
  were kept.

Differentiation.  The Cholesky Wiener filter differentiates implicitly
(:func:`cholesky_solve`: ``lax.custom_linear_solve`` with the factor as the exact
solve, so a gradient costs one more pair of triangular solves rather than the
factor's own derivative, ~4x its cost); its log determinant by
:func:`cholesky_logdet` (``d log det P = tr(P^-1 dP)``); the draws' ``L^-T``
natively (JAX's rules for the factor and the triangular solve).  The eigen path's matrix functions ``P^+`` and ``(P^+)^1/2``
carry their own JVP (:func:`eigh_functions`, the Daleckii-Krein formula), which stays
finite where eigenvalues are degenerate (e.g. every prior-dominated mode with the same
floor variance): differentiating ``eigh``'s eigenvectors there gives NaN.  The
symmetric square root is the one factor that is a smooth function of P, which is why
the eigen draws use it.  The cut at ``rcond`` is held fixed under differentiation.
"""

from __future__ import annotations

import os
from functools import partial
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import check_float64
from ..base.memory import format_bytes
from ..model.operator import n_in
from ..model.system import LinearSystem, precision_matrix, wiener_rhs
from .info import DrawInfo, Result, SolveInfo, direct_info, exact_info
from .options import CholeskyOptions, EighOptions
from .path import AUTO_MEMORY_FRACTION, EvidenceParts, SolverPath, has_flat_prior, quadratic_from_state

__all__ = [
    "CHOLESKY_INVERSE_MAX_N",
    "DENSE_MAX_N",
    "CholeskyPath",
    "EighPath",
    "OPENBLAS_SAFE_N",
    "CholeskyState",
    "EighState",
    "cholesky_logdet",
    "cholesky_solve",
    "draw_cholesky",
    "draw_eigh",
    "eigh_functions",
    "prepare_cholesky",
    "prepare_eigh",
    "solve_accuracy",
    "upper_triangular_product",
]


class CholeskyState(eqx.Module):
    """The Cholesky path set up for many draws (a PyTree).

    Attributes:
        system: the linear system.
        a_wf: (Nf, n) Wiener filter.
        wiener: SolveInfo of the Wiener solve, (Nf,) fields.
        precision: dense P (Nf, n, n).
        chol: lower Cholesky factor L of P (Nf, n, n).
        chol_inv_t: ``L^-T`` (Nf, n, n): draws are then one matrix product (~3x faster
            than a triangular solve per batch); None where it was not formed
            (``CholeskyOptions.inverse``), and draws solve with ``L^T``.
        options: the :class:`CholeskyOptions` (static).
    """

    system: LinearSystem
    a_wf: jax.Array
    wiener: SolveInfo
    precision: jax.Array
    chol: jax.Array
    chol_inv_t: jax.Array | None
    options: CholeskyOptions = eqx.field(static=True, default=CholeskyOptions())

    method: ClassVar[str] = "cholesky"


class EighState(eqx.Module):
    """The eigen path set up for many draws (a PyTree).

    Attributes:
        system: the linear system.
        a_wf: (Nf, n) Wiener filter (minimum-norm for a singular P).
        wiener: SolveInfo of the Wiener solve, (Nf,) fields.
        precision: dense P (Nf, n, n).
        sqrt_cov: (Nf, n, n) the symmetric ``T = (P^+)^1/2``, ``T T = P^+`` (``delta = T z``).
        kept: (Nf,) number of directions sampled (n unless P is singular: those with
            eigenvalue above ``rcond`` times the largest).
        eigenvalues: (Nf, n) the eigenvalues of P, ascending (the evidence's ``log det P``).
        options: the :class:`EighOptions` (static).
    """

    system: LinearSystem
    a_wf: jax.Array
    wiener: SolveInfo
    precision: jax.Array
    sqrt_cov: jax.Array
    kept: jax.Array
    eigenvalues: jax.Array
    options: EighOptions = eqx.field(static=True)

    @property
    def rank(self) -> jax.Array:
        """Deprecated name of :attr:`kept` (the number of directions sampled)."""
        import warnings

        warnings.warn("EighState.rank is deprecated: use EighState.kept (directions sampled)", DeprecationWarning,
                      stacklevel=2)
        return self.kept

    method: ClassVar[str] = "eigh"


def cholesky_solve(P: jax.Array, L: jax.Array, b: jax.Array) -> jax.Array:
    """``P^-1 b`` for SPD P (..., n, n) with its lower Cholesky factor L, b (..., n).

    Differentiated implicitly, as ``lax.custom_linear_solve`` does: ``dx = P^-1 (db - dP x)``
    with the same factor (held fixed), to every order; no derivative of the factor.
    """
    if P.ndim > 2:
        return jax.vmap(cholesky_solve)(P, L, b)
    Lc = jax.lax.stop_gradient(L)

    def solve(_, r):
        return jax.scipy.linalg.cho_solve((Lc, True), r)

    return jax.lax.custom_linear_solve(lambda x: P @ x, b, solve, symmetric=True)


@jax.custom_jvp
def _logdet_factor(P, L):
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), axis=-1)


@_logdet_factor.defjvp
def _logdet_factor_jvp(primals, tangents):
    P, L = primals
    dP, _ = tangents  # L is a function of P: all of the dependence is in dP
    eye = jnp.broadcast_to(jnp.eye(L.shape[-1], dtype=L.dtype), L.shape)
    # P^-1 by two triangular solves (2 n^3; 25% faster than L^-T @ L^-1), from the factor
    # with its own derivative, so second orders are right
    p_inv = jax.scipy.linalg.cho_solve((L, True), eye)
    return _logdet_factor(P, L), jnp.sum(p_inv * dP, axis=(-2, -1))


def cholesky_logdet(P: jax.Array, L: jax.Array) -> jax.Array:
    """``log det P`` (...,) of SPD P (..., n, n) from its lower Cholesky factor L.

    ``2 sum log diag L``; the JVP is ``tr(P^-1 dP)`` with ``P^-1 = L^-T L^-1``, and
    higher orders differentiate that (pass the factor with its derivative, as
    ``jnp.linalg.cholesky(P)`` gives it, for Hessians). Measured at n = 2601: a gradient
    1.15 s against 2.25 s through the factor's own rule.
    """
    return _logdet_factor(P, L)


#: ``CholeskyOptions(inverse=None)`` forms ``L^-T`` up to this n (n^3 flop, 8 n^2 bytes more).
CHOLESKY_INVERSE_MAX_N = 12000

#: Above this n, a multi-threaded OpenBLAS ``dpotrf`` crashed (segmentation fault) on the
#: development host (scipy-openblas 0.3.30, the LAPACK jaxlib calls: n = 14000 ran, n =
#: 16000 crashed, in scipy as in JAX); with ``OPENBLAS_NUM_THREADS=1`` set before start-up
#: it ran (n = 22801 in 127 s).  :func:`prepare_cholesky` refuses larger n without it where XLA factorises
#: (under a trace, or off the CPU backend); on concrete CPU arrays it factorises on the host instead
#: (:func:`host_cholesky`, whose ``potrf`` calls stay below this size).
OPENBLAS_SAFE_N = 14000


@partial(jax.jit, static_argnames=("options", "inverse"))
def _prepare_cholesky(system: LinearSystem, options: CholeskyOptions, inverse: bool = True) -> CholeskyState:
    check_float64(system.op.response, system.inv_noise)
    return _factor_cholesky(system, precision_matrix(system), options, inverse)


@partial(jax.jit, static_argnames=("options",))
def _factor_cholesky_jit(system: LinearSystem, P: jax.Array, options: CholeskyOptions):
    """The factor and the Wiener filter of a given P, without L^-T; returns only what is new
    (an input passed through a jit's outputs would be copied: 8 n^2 bytes more)."""
    st = _factor_cholesky(system, P, options, False)
    return st.a_wf, st.wiener, st.chol


@partial(jax.jit, static_argnames=("options",))
def _wiener_of_factor(system: LinearSystem, P: jax.Array, L: jax.Array, options: CholeskyOptions):
    """The Wiener filter of a given P and its factor L (the host-factor route)."""
    return _cholesky_wiener(system, P, L, wiener_rhs(system), options)


def host_factor_applies(P: jax.Array) -> bool:
    """Whether :func:`prepare_cholesky` (without ``L^-T``) factorises P on the host: P concrete and held by
    the CPU backend.  There :func:`gcrsky.solvers.blocked.blocked_cholesky` runs its BLAS calls on every
    core the process may use (``potrf`` only on panels of at most ``BLOCK`` columns, so the threaded-``dpotrf``
    crash above :data:`OPENBLAS_SAFE_N` is out of reach) while XLA's own factor runs on one thread.  Measured
    at n = 22801 on 2 cores (``benchmarks/scale.py`` row C''): set-up 205 -> 138 s, the same peak."""
    if isinstance(P, jax.core.Tracer) or not P.is_fully_addressable:  # traced, or spread over processes
        return False
    return all(d.platform == "cpu" for d in P.devices())


def host_cholesky(P: jax.Array) -> jax.Array:
    """Lower Cholesky factors (Nf, n, n) of a concrete P (Nf, n, n) on the CPU backend, factorised on the
    host (:func:`host_factor_applies`) into one aligned buffer that XLA then uses without a copy.

    A channel whose P is not positive definite gets a NaN factor (as XLA's factor does), which the
    Wiener filter's info reports as not converged.
    """
    from .blocked import blocked_cholesky
    from .dataspace_large import aligned_empty

    host = np.asarray(P)  # the CPU buffer itself (read-only view), no copy
    out = aligned_empty(host.shape)
    for f in range(host.shape[0]):
        np.copyto(out[f], host[f])
        try:
            blocked_cholesky(out[f])
        except ValueError:
            out[f] = np.nan
    return jax.device_put(out)


def _cholesky_wiener(system: LinearSystem, P, L, b, options: CholeskyOptions):
    """``a_wf = P^-1 b`` through the factor, with its info from the true residual ``b - P a_wf``."""
    cho = jax.vmap(lambda l, v: jax.scipy.linalg.cho_solve((l, True), v))
    a_wf = cholesky_solve(P, L, b)
    r = jax.lax.stop_gradient(b - jnp.einsum("fij,fj->fi", P, a_wf))
    err = jnp.sqrt(jnp.abs(jnp.einsum("fi,fi->f", r, cho(jax.lax.stop_gradient(L), r))))
    finite = jnp.all(jnp.isfinite(jax.lax.stop_gradient(L)), axis=(1, 2))
    winfo = direct_info(err, jnp.linalg.norm(r, axis=1) / jnp.linalg.norm(jax.lax.stop_gradient(b), axis=1), finite,
                        options.tol)
    if options.throw:
        a_wf = eqx.error_if(a_wf, ~winfo.converged, "gcrsky Cholesky: P is not positive definite (non-finite "
                            "factor) or the solve missed CholeskyOptions.tol")
    return a_wf, winfo


def _factor_cholesky(system: LinearSystem, P: jax.Array, options: CholeskyOptions, inverse: bool) -> CholeskyState:
    b = wiener_rhs(system)
    # the large-n path factors P's lower triangle as it is (P is symmetric to rounding):
    # no symmetrised copy, 8 n^2 bytes less at the peak
    L = jnp.linalg.cholesky(P) if inverse else jax.lax.linalg.cholesky(P, symmetrize_input=False)
    a_wf, winfo = _cholesky_wiener(system, P, L, b, options)
    if not inverse:
        return CholeskyState(system, a_wf, winfo, P, L, None, options)
    eye = jnp.eye(L.shape[-1], dtype=L.dtype)
    linv = jax.vmap(lambda l: jax.scipy.linalg.solve_triangular(l, eye, lower=True))(L)
    return CholeskyState(system, a_wf, winfo, P, L, jnp.swapaxes(linv, -1, -2), options)


def prepare_cholesky(system: LinearSystem, options: CholeskyOptions | None = None) -> CholeskyState:
    """Form the dense P, factorise it, solve for the Wiener filter and form ``L^-T``, once.

    A P that is not positive definite (e.g. a flat prior with unconstrained
    directions) gives a non-finite factor, reported as ``wiener.converged = False``;
    use the eigen path there.
    """
    options = CholeskyOptions() if options is None else options
    if not isinstance(options, CholeskyOptions):
        raise TypeError(f"the Cholesky path takes CholeskyOptions, got {type(options).__name__}")
    n = n_in(system.op)
    inverse = n <= CHOLESKY_INVERSE_MAX_N if options.inverse is None else bool(options.inverse)
    if not inverse:
        # two programs: P, then its factor -- one program holds the P being built, its copy
        # for LAPACK and the factor at once (5.25 n^2 doubles at the peak against 3 n^2;
        # measured with ``memory_analysis``).  Inside a caller's jit they fuse again.
        check_float64(system.op.response, system.inv_noise)
        P = precision_matrix(system)
        if host_factor_applies(P):
            L = host_cholesky(P)
            a_wf, winfo = _wiener_of_factor(system, P, L, options)
            return CholeskyState(system, a_wf, winfo, P, L, None, options)
        _check_openblas_threads(n)
        a_wf, winfo, L = _factor_cholesky_jit(system, P, options)
        return CholeskyState(system, a_wf, winfo, P, L, None, options)
    _check_openblas_threads(n)
    return _prepare_cholesky(system, options, inverse)


def _check_openblas_threads(n: int) -> None:
    """Refuse XLA's dense factor of n > :data:`OPENBLAS_SAFE_N` unless OpenBLAS runs single-threaded."""
    if n > OPENBLAS_SAFE_N and os.environ.get("OPENBLAS_NUM_THREADS") != "1":
        raise RuntimeError(
            f"the dense Cholesky of n = {n} > {OPENBLAS_SAFE_N} parameters needs OPENBLAS_NUM_THREADS=1 "
            "in the environment before Python starts (multi-threaded OpenBLAS dpotrf crashed at this "
            "size); the gcrsky CLI sets it, as does gcrsky.parallel.use_safe_cpu_threading() when "
            "called before numpy/scipy/jax are imported")


def _eigh_fns(lam, rcond):
    keep = lam > rcond * lam[-1]
    safe = jnp.where(keep, lam, 1.0)
    f1, d1 = jnp.where(keep, 1.0 / safe, 0.0), jnp.where(keep, -1.0 / safe**2, 0.0)
    f2, d2 = jnp.where(keep, safe**-0.5, 0.0), jnp.where(keep, -0.5 * safe**-1.5, 0.0)
    return (f1, d1), (f2, d2)


def eigh_functions(P: jax.Array, b: jax.Array, rcond: float):
    """``(P^+ b, (P^+)^1/2, lam)`` of a symmetric (n, n) P and b (n,); eigenvalues ``<= rcond * max`` cut.

    ``P^+ b`` is formed as ``V (f(lam) * (V^T b))`` (accurate across the spectrum, which
    spans ~1e13 for a flat prior), ``(P^+)^1/2`` as ``V diag(lam^-1/2) V^T``.
    Differentiable everywhere the cut does not move, degenerate eigenvalues included:
    the JVP is the Daleckii-Krein formula ``d f(P) = V (F o (V^T dP V)) V^T`` with
    ``F_ij = (f(lam_i) - f(lam_j)) / (lam_i - lam_j)``, and ``f'(lam_i)`` where the two
    are equal to ~1e-10 of the spectrum's scale.
    """
    return _eigh_parts(P, b, rcond)[:3]


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def _eigh_parts(P, b, rcond):
    """:func:`eigh_functions` and the eigenvectors V, for diagnostics only (V's tangent is set to 0)."""
    lam, V = jnp.linalg.eigh(P)
    (f1, _), (f2, _) = _eigh_fns(lam, rcond)
    return V @ (f1 * (V.T @ b)), (V * f2) @ V.T, lam, V


@_eigh_parts.defjvp
def _eigh_parts_jvp(rcond, primals, tangents):
    (P, b), (dP, db) = primals, tangents
    lam, V = jnp.linalg.eigh(P)
    dPv = V.T @ ((dP + dP.T) / 2) @ V
    diff = lam[:, None] - lam[None, :]
    close = jnp.abs(diff) <= 1e-10 * jnp.max(jnp.abs(lam))
    (f1, d1), (f2, d2) = _eigh_fns(lam, rcond)

    def dk(f, fp):  # Daleckii-Krein divided differences
        return jnp.where(close, 0.5 * (fp[:, None] + fp[None, :]), (f[:, None] - f[None, :]) / jnp.where(close, 1.0, diff))

    vb, vdb = V.T @ b, V.T @ db
    x, dx = V @ (f1 * vb), V @ ((dk(f1, d1) * dPv) @ vb + f1 * vdb)
    T, dT = (V * f2) @ V.T, V @ (dk(f2, d2) * dPv) @ V.T
    return (x, T, lam, V), (dx, dT, jnp.diagonal(dPv), jnp.zeros_like(V))


@partial(jax.jit, static_argnames=("options",))
def _prepare_eigh(system: LinearSystem, options: EighOptions) -> EighState:
    check_float64(system.op.response, system.inv_noise)
    b = wiener_rhs(system)
    P = precision_matrix(system)
    a_wf, sqrt_cov, lam, V = jax.vmap(lambda p, bb: _eigh_parts(p, bb, options.rcond))(P, b)
    # residual within the sampled subspace, in posterior-sigma units (P^+ norm)
    lam, V = jax.lax.stop_gradient(lam), jax.lax.stop_gradient(V)
    keep = lam > options.rcond * lam[:, -1:]
    inv = jnp.where(keep, 1.0 / jnp.where(keep, lam, 1.0), 0.0)
    r = jax.lax.stop_gradient(b - jnp.einsum("fij,fj->fi", P, a_wf))
    r_coef = jnp.where(keep, jnp.einsum("fji,fj->fi", V, r), 0.0)  # V^T r within range(P)
    err = jnp.sqrt(jnp.sum(inv * r_coef**2, axis=1))
    finite = jnp.all(jnp.isfinite(jax.lax.stop_gradient(sqrt_cov)), axis=(1, 2)) & jnp.isfinite(err)
    winfo = direct_info(err, jnp.linalg.norm(r_coef, axis=1) / jnp.linalg.norm(jax.lax.stop_gradient(b), axis=1),
                        finite, options.tol)
    if options.throw:
        a_wf = eqx.error_if(a_wf, ~winfo.converged, "gcrsky eigh: non-finite eigen-decomposition of P, or the solve "
                            "missed EighOptions.tol")
    return EighState(system, a_wf, winfo, P, sqrt_cov, jnp.sum(keep, axis=1), lam, options)


def prepare_eigh(system: LinearSystem, options: EighOptions | None = None) -> EighState:
    """Eigen-decompose the dense P and solve for the (minimum-norm) Wiener filter, once."""
    options = EighOptions() if options is None else options
    if not isinstance(options, EighOptions):
        raise TypeError(f"the eigen path takes EighOptions, got {type(options).__name__}")
    return _prepare_eigh(system, options)


def upper_triangular_product(U: jax.Array, z: jax.Array) -> jax.Array:
    """``U z`` for upper-triangular U (Nf, n, n) and z (ndraws, Nf, n) -> (Nf, ndraws, n).

    In 4 block rows that skip U's zero lower-left blocks: 5/8 of the dense product's
    flops (measured 2.8 vs 4.1 ms for n = 441, 2 channels, 200 draws); the same sums.
    """
    n = U.shape[-1]
    k = 4 if n >= 256 else 1
    edges = [round(i * n / k) for i in range(k + 1)]
    parts = [jnp.einsum("fij,dfj->fdi", U[:, a:b, a:], z[:, :, a:]) for a, b in zip(edges[:-1], edges[1:])]
    return jnp.concatenate(parts, axis=-1)


@partial(jax.jit, static_argnames=("ndraws",))
def draw_cholesky(key: jax.Array, state: CholeskyState, ndraws: int):
    """``ndraws`` exact draws ``a_wf + L^-T z``; draw ``i`` uses ``split(key, ndraws)[i]``.

    Returns:
        draws (Nf, ndraws, n); a :class:`~gcrsky.solvers.DrawInfo` (``wiener``, ``draws`` a SolveInfo over
        (Nf, ndraws), ``a_wf``).
    """
    a_wf = state.a_wf
    nf, n = a_wf.shape
    keys = jax.random.split(key, ndraws)
    z = jax.vmap(lambda k: jax.random.normal(k, (nf, n), a_wf.dtype))(keys)  # (ndraws, Nf, n)
    if state.chol_inv_t is None:  # L^T delta = z, one triangular solve per channel
        solve = jax.vmap(lambda l, zf: jax.scipy.linalg.solve_triangular(l, zf.T, lower=True, trans="T").T,
                         in_axes=(0, 1))
        delta = solve(state.chol, z)
    else:
        delta = upper_triangular_product(state.chol_inv_t, z)
    finite = jnp.all(jnp.isfinite(delta), axis=-1)
    return a_wf[:, None, :] + delta, DrawInfo(state.wiener, exact_info(state.wiener, finite, (nf, ndraws)), a_wf)


@partial(jax.jit, static_argnames=("ndraws",))
def draw_eigh(key: jax.Array, state: EighState, ndraws: int):
    """``ndraws`` exact draws ``a_wf + (P^+)^1/2 z``, z drawn as one (Nf, n, ndraws) array.

    Returns:
        as :func:`draw_cholesky`.
    """
    a_wf = state.a_wf
    nf, n = a_wf.shape
    z = jax.random.normal(key, (nf, n, ndraws), a_wf.dtype)
    delta = jnp.einsum("fij,fjd->fdi", state.sqrt_cov, z)  # (Nf, ndraws, n)
    finite = jnp.all(jnp.isfinite(delta), axis=-1)
    return a_wf[:, None, :] + delta, DrawInfo(state.wiener, exact_info(state.wiener, finite, (nf, ndraws)), a_wf)


# ---------------------------------------------------------------- new data, same factor


@jax.jit
def _condition_cholesky(state: CholeskyState, data: jax.Array) -> CholeskyState:
    system = state.system._replace(data=jnp.asarray(data, state.system.data.dtype))
    a_wf, winfo = _cholesky_wiener(system, state.precision, state.chol, wiener_rhs(system), state.options)
    return CholeskyState(system, a_wf, winfo, state.precision, state.chol, state.chol_inv_t, state.options)


@jax.jit
def _condition_eigh(state: EighState, data: jax.Array) -> EighState:
    system = state.system._replace(data=jnp.asarray(data, state.system.data.dtype))
    b = wiener_rhs(system)
    T = state.sqrt_cov
    a_wf = jnp.einsum("fij,fj->fi", T, jnp.einsum("fij,fj->fi", T, b))  # P^+ b = T T b
    r = jax.lax.stop_gradient(b - jnp.einsum("fij,fj->fi", state.precision, a_wf))
    tr = jnp.einsum("fij,fj->fi", jax.lax.stop_gradient(T), r)  # ||T r||^2 = r^T P^+ r: the sampled subspace
    err = jnp.linalg.norm(tr, axis=1)
    finite = jnp.all(jnp.isfinite(a_wf), axis=1) & jnp.isfinite(err)
    winfo = direct_info(err, jnp.linalg.norm(r, axis=1) / jnp.linalg.norm(b, axis=1), finite, state.options.tol)
    if state.options.throw:
        a_wf = eqx.error_if(a_wf, ~winfo.converged, "gcrsky eigh: the solve missed EighOptions.tol")
    return EighState(system, a_wf, winfo, state.precision, T, state.kept, state.eigenvalues, state.options)


# ---------------------------------------------------------------- the evidence's pieces


def _whitened_precision(system: LinearSystem):
    sh = 1.0 / jnp.sqrt(system.prior.inv_var)  # S^1/2
    return sh[:, :, None] * precision_matrix(system) * sh[:, None, :], sh


def solve_accuracy(A, solve, rhs, x, finite, tol) -> SolveInfo:
    """Info of the solve ``x = A^-1 rhs`` (A (Nf, k, k) SPD, rhs and x (Nf, k)) from its *true* residual.

    ``err_sigma = sqrt(r^T A^-1 r)`` with ``r = rhs - A x``, ``A^-1`` applied by ``solve`` (the same factor):
    the error of ``x`` in the A-norm (posterior sigma for the whitened precision, whose norm is P's), so that
    ``rhs^T x``, e.g. the evidence's quadratic term, is within ``sqrt(rhs^T x) * err_sigma`` of its exact
    value.  Judged against ``tol`` as every direct solve (:func:`gcrsky.solvers.info.direct_info`); no
    gradient flows through it.
    """
    A, rhs, x = (jax.lax.stop_gradient(v) for v in (A, rhs, x))
    r = rhs - jnp.einsum("fij,fj->fi", A, x)
    err = jnp.sqrt(jnp.abs(jnp.sum(r * solve(r), axis=-1)))
    rel = jnp.linalg.norm(r, axis=-1) / jnp.where(jnp.linalg.norm(rhs, axis=-1) > 0, jnp.linalg.norm(rhs, axis=-1), 1.0)
    return direct_info(err, rel, finite & jnp.all(jnp.isfinite(x), axis=-1), tol)


def _cholesky_evidence(system: LinearSystem, options: CholeskyOptions, terms) -> EvidenceParts:
    """``log det(I + H)`` and ``b'^T P^-1 b'`` from the Cholesky factor of the whitened precision; the
    solve's accuracy from its true residual (:func:`solve_accuracy`)."""
    b_res = terms["b_res"]
    Pw, sh = _whitened_precision(system)
    L = jnp.linalg.cholesky(Pw)
    x = cholesky_solve(Pw, L, sh * b_res)  # S^-1/2 (a_wf - a0)
    finite = jnp.all(jnp.isfinite(jax.lax.stop_gradient(L)), axis=(1, 2))
    chi2 = terms["rWr"] - jnp.sum(sh * b_res * x, axis=1)
    Lc = jax.lax.stop_gradient(L)
    info = solve_accuracy(Pw, lambda r: jax.vmap(lambda l, v: jax.scipy.linalg.cho_solve((l, True), v))(Lc, r),
                          sh * b_res, x, finite, options.tol)
    return EvidenceParts(chi2, cholesky_logdet(Pw, L), jnp.zeros(finite.shape), info)


def _eigh_evidence(system: LinearSystem, options: EighOptions, terms) -> EvidenceParts:
    """The same pieces from the eigen-decomposition (finite gradients at degenerate eigenvalues)."""
    b_res = terms["b_res"]
    Pw, sh = _whitened_precision(system)
    x, _, lam, V = jax.vmap(lambda p, bb: _eigh_parts(p, bb, 0.0))(Pw, sh * b_res)  # every direction is proper
    finite = jnp.all(jax.lax.stop_gradient(lam) > 0, axis=1)
    logdet = jnp.sum(jnp.log(jnp.where(lam > 0, lam, 1.0)), axis=1)
    chi2 = terms["rWr"] - jnp.sum(sh * b_res * x, axis=1)
    lc, Vc = jax.lax.stop_gradient(lam), jax.lax.stop_gradient(V)
    inv = jnp.where(lc > 0, 1.0 / jnp.where(lc > 0, lc, 1.0), 0.0)
    info = solve_accuracy(Pw, lambda r: jnp.einsum("fij,fj->fi", Vc, inv * jnp.einsum("fji,fj->fi", Vc, r)),
                          sh * b_res, x, finite, options.tol)
    return EvidenceParts(chi2, logdet, jnp.zeros(finite.shape), info)


def _state_evidence(state, terms, logdet_p, finite) -> EvidenceParts:
    """Pieces from a prepared dense state: ``log det(I + H) = log det P - sum log S^-1``."""
    logdet = logdet_p - jnp.sum(jnp.log(state.system.prior.inv_var), axis=-1)
    chi2 = terms["rWr"] - quadratic_from_state(state, terms["b_res"])
    ok = finite & state.wiener.converged
    info = state.wiener._replace(converged=ok, result=jnp.where(finite, state.wiener.result, Result.NONFINITE))
    return EvidenceParts(chi2, logdet, jnp.zeros(logdet.shape), info)


# ---------------------------------------------------------------- the two dense paths

#: Largest n for which ``method="auto"`` forms and factorises the dense P.
DENSE_MAX_N = 24000


def _dense_limits(system: LinearSystem, memory: float, budget: float) -> str:
    n = n_in(system.op)
    if n > DENSE_MAX_N:
        return f"n = {n} > {DENSE_MAX_N} (DENSE_MAX_N)"
    if memory > AUTO_MEMORY_FRACTION * budget:
        return (f"the dense P + factor would need {format_bytes(memory)} (n = {n}), more than "
                f"{AUTO_MEMORY_FRACTION:.0%} of {format_bytes(budget)}")
    if n > OPENBLAS_SAFE_N and os.environ.get("OPENBLAS_NUM_THREADS") != "1":
        return f"n = {n} > {OPENBLAS_SAFE_N} needs OPENBLAS_NUM_THREADS=1 (threaded dpotrf crashed)"
    return ""


def _dense_build_flop(system: LinearSystem) -> float:
    nf, nt, nbl = (int(x) for x in system.data.shape)
    n = n_in(system.op)
    return 8.0 * nf * min(1.0, nt / 2.0) * nbl * n * n  # P by m-blocks, whatever Nt


class CholeskyPath(SolverPath):
    """Dense Cholesky of P (:func:`prepare_cholesky`): the exact reference, fast where n^2 fits."""

    name = "cholesky"
    options_type = CholeskyOptions
    state_type = CholeskyState

    def memory_bytes(self, system, options, ndraws=1):
        # the set-up's peak (XLA memory_analysis, in n^2 doubles): one program holding P, its factor,
        # L^-T and their transients (7.25); for n > CHOLESKY_INVERSE_MAX_N two programs, the
        # factor's holding P, L and LAPACK's working copy (3.4)
        nf, n = int(system.data.shape[0]), n_in(system.op)
        copies = 3.5 if n > CHOLESKY_INVERSE_MAX_N else 7.5
        return copies * 8 * nf * n * n + 8.0 * nf * max(1, ndraws) * n

    def cost_flop(self, system, options, ndraws):
        nf, n = int(system.data.shape[0]), n_in(system.op)
        return _dense_build_flop(system) + nf * n**3 / 3.0 + ndraws * 2.0 * nf * n * n

    def auto_limits(self, system, options, budget, ndraws):
        if has_flat_prior(system):
            return "a flat prior direction: P may be singular"
        return _dense_limits(system, self.memory_bytes(system, options, ndraws), budget)

    def describe(self, system, options, memory):
        return f"n = {n_in(system.op)}: dense P + Cholesky factor ({format_bytes(memory)})"

    def prepare(self, system, options):
        return prepare_cholesky(system, options)

    def draw(self, key, state, ndraws):
        return draw_cholesky(key, state, ndraws)

    def condition(self, state, data):
        return _condition_cholesky(state, data)

    def evidence_parts(self, system, options, terms, *, slq=None, key=None):
        return _cholesky_evidence(system, options, terms)

    def state_evidence_parts(self, state, terms, *, slq=None, key=None):
        L = jax.lax.stop_gradient(state.chol)
        finite = jnp.all(jnp.isfinite(L), axis=(1, 2))
        return _state_evidence(state, terms, 2.0 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), -1), finite)


class EighPath(SolverPath):
    """Eigen-decomposition of the dense P (:func:`prepare_eigh`): exact, and the path for a singular P."""

    name = "eigh"
    options_type = EighOptions
    state_type = EighState

    def memory_bytes(self, system, options, ndraws=1):  # P, eigenvectors, sqrt_cov
        nf, n = int(system.data.shape[0]), n_in(system.op)
        return 3.0 * 8 * nf * n * n + 8.0 * nf * max(1, ndraws) * n

    def cost_flop(self, system, options, ndraws):  # a symmetric eigensolver with vectors: ~9 n^3
        nf, n = int(system.data.shape[0]), n_in(system.op)
        return _dense_build_flop(system) + 9.0 * nf * n**3 + ndraws * 2.0 * nf * n * n

    def auto_limits(self, system, options, budget, ndraws):
        if not has_flat_prior(system):
            return "a proper prior: the Cholesky path is as exact and ~27x cheaper"
        return _dense_limits(system, self.memory_bytes(system, options, ndraws), budget)

    def describe(self, system, options, memory):
        flat = "; flat prior: P may be singular" if has_flat_prior(system) else ""
        return f"n = {n_in(system.op)}: dense P + eigen-decomposition ({format_bytes(memory)}){flat}"

    def prepare(self, system, options):
        return prepare_eigh(system, options)

    def draw(self, key, state, ndraws):
        return draw_eigh(key, state, ndraws)

    def condition(self, state, data):
        return _condition_eigh(state, data)

    def evidence_parts(self, system, options, terms, *, slq=None, key=None):
        return _eigh_evidence(system, options, terms)

    def state_evidence_parts(self, state, terms, *, slq=None, key=None):
        lam = jax.lax.stop_gradient(state.eigenvalues)
        finite = jnp.all(lam > 0, axis=1)
        return _state_evidence(state, terms, jnp.sum(jnp.log(jnp.where(lam > 0, lam, 1.0)), axis=1), finite)
