"""The matrix-free exact path: preconditioned conjugate gradients, vmapped over draws.

Convergence is judged in *posterior-sigma units*: iterate until
``sqrt(r^T M^-1 r) <= tol``.  With the default prior-whitened Nystrom preconditioner
``M <= P`` in the Loewner order (a Nystrom sketch never exceeds the matrix it
approximates), so ``r^T M^-1 r >= r^T P^-1 r = ||x - x*||_P^2``: a rigorous bound on
the error's P-norm, which itself bounds every mode's error in units of its posterior
std.  With the m-block preconditioner (flat priors) the same number is only an
estimate (measured 100x optimistic on the standard case), so pass a smaller ``tol``
there.  The window preconditioner (:mod:`gcrsky.solvers.window`, block-banded in m)
has no ``M <= P``, so ``r^T M^-1 r`` bounds nothing; CG preconditions with it but
stops on the prior norm, ``sqrt(r^T S r) <= tol``, rigorous because ``P >= S^-1``
gives ``r^T P^-1 r <= r^T S r`` (the stop quantity is chosen per preconditioner by
:func:`gcrsky.solvers.preconditioners.stop_norm`; it costs one more n-vector product
per iteration, and more iterations than the M-norm would need, the price of rigour).
``jax.scipy.sparse.linalg.cg`` implements the same recurrence but reports
neither iterations nor residual, so it is written out here with ``lax.while_loop``
(tests check the two agree; ``CGOptions(engine="jax")`` selects JAX's).

Differentiation: every solve goes through ``jax.lax.custom_linear_solve``
(:func:`cg_solve`), as ``jax.scipy.sparse.linalg.cg`` does, so ``jax.grad``,
``jax.jvp`` and ``jax.vmap`` work through the Wiener filter, the draws and the Gibbs
step with the implicit rule ``dx = P^-1 (db - dP x)``, without differentiating the
iterations.

Set up once (:func:`prepare_cg`: the preconditioner, optionally the dense P, the
Wiener filter), then draw as often as needed (:func:`draw_cg`): draw ``i`` of a
batch solves ``P delta = `` (GCR fluctuation right-hand side of
``jax.random.split(key, ndraws)[i]``) from 0, so a fixed key reproduces the draws.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import check_float64
from ..model.system import LinearSystem, fluctuation_rhs, precision_apply, precision_matrix, wiener_rhs
from .info import DrawInfo, Result, SolveInfo, result_code
from .options import CGOptions, SLQOptions
from .path import EvidenceParts, SolverPath
from .preconditioners import (
    NystromPreconditioner,
    inverse_bound,
    make_preconditioner,
    precondition_one,
    resolve_preconditioner,
    stop_norm,
)
from .slq import whitened_logdet_slq
from .window import WINDOW_AUTO_MAX, resolve_bandwidth, window_memory_bytes

__all__ = ["CGPath", "CGState", "cg_solve", "draw_cg", "freq_slice", "pcg", "prepare_cg", "resolve_cg_options", "solve_cg",
           "wiener_cg"]


def pcg(matvec, precond, b, x0, *, tol: float = CGOptions.tol, maxiter: int = CGOptions.maxiter, rtol: float = 0.0,
        stop=None):
    """Preconditioned CG for one right-hand side (vectors of any shape); not differentiable itself.

    Stops when ``sqrt(r . M^-1 r) <= max(tol, rtol * sqrt(b . M^-1 b))`` (with ``stop``
    given: ``sqrt(stop(r)) <= max(tol, rtol * sqrt(stop(b)))``): ``tol`` is
    absolute, in posterior-sigma units for the GCR system; ``rtol`` relative to the
    right-hand side (used for the cotangent solves of :func:`cg_solve`).  The
    recurrence residual drifts from the true one ``b - P x`` in floating point; when
    the loop stops, CG is restarted once from the true residual ("residual
    replacement"), so the reported error is that of the returned ``x`` and meets the
    threshold whenever the iteration budget allows.  Use :func:`cg_solve` for a solve
    that differentiates.

    Args:
        matvec: x -> P x (symmetric positive definite).
        precond: r -> M^-1 r (symmetric positive definite).
        b, x0: right-hand side and initial guess.
        tol: absolute threshold on ``sqrt(r . M^-1 r)``.
        maxiter: hard cap on iterations (both passes together).
        rtol: relative threshold (0: absolute only).
        stop: None (stop on ``r . M^-1 r``) or ``r -> r . N r`` for another SPD N, e.g. the
            prior covariance S when ``M <= P`` does not hold
            (:func:`gcrsky.solvers.preconditioners.stop_norm`).

    Returns:
        (x, SolveInfo) with scalar info fields.
    """
    sq = (lambda r, z: jnp.vdot(r, z).real) if stop is None else (lambda r, z: stop(r))  # noqa: E731
    thresh = jnp.maximum(tol, rtol * jnp.sqrt(jnp.abs(sq(b, precond(b)))))

    def cond(s):
        k, *_, bad, e2 = s
        return (k < maxiter) & (jnp.sqrt(jnp.abs(e2)) > thresh) & (~bad)

    def body(s):
        k, x, r, z, p, rz, bad, _ = s
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
        return k + 1, x, r, z, p, rz_new, bad, sq(r, z)

    def run(k0, x):
        r = b - matvec(x)
        z = precond(r)
        rz = jnp.vdot(r, z).real
        init = (k0, x, r, z, z, rz, jnp.asarray(False), sq(r, z))
        k, x, *_, bad, _ = jax.lax.while_loop(cond, body, init)
        return k, x, bad

    k, x, bad1 = run(jnp.asarray(0), x0)
    k, x, bad2 = run(k, x)  # restart from the true residual (exits at once if converged)
    return x, _residual_info(matvec, precond, b, x, k, thresh, bad1 | bad2, stop)


def _residual_info(matvec, precond, b, x, k, thresh, broke, stop=None) -> SolveInfo:
    r = b - matvec(x)
    err = jnp.sqrt(jnp.abs(jnp.vdot(r, precond(r)).real if stop is None else stop(r)))
    rel = jnp.linalg.norm(r) / jnp.maximum(jnp.linalg.norm(b), jnp.finfo(b.dtype).tiny)
    finite = jnp.isfinite(err) & jnp.all(jnp.isfinite(x))
    code = result_code(err <= thresh, finite=finite, broke=broke)
    return SolveInfo(k, err, rel, code == Result.SUCCESS, code)


def cg_solve(matvec, precond, b, x0, options: CGOptions, *, inverse_bound=None, stop=None):
    """``P^-1 b`` by preconditioned CG that differentiates implicitly (``jax.lax.custom_linear_solve``).

    The forward solve starts at ``x0`` and stops at ``options.tol`` (absolute,
    posterior sigma).  Derivatives follow the implicit rule ``dx = P^-1 (db - dP x)``:
    ``jax.grad`` solves once more with P (from 0, to ``options.tol`` relative to the
    cotangent), ``jax.jvp`` solves for the tangent with the forward settings; neither
    differentiates through the iterations, and the preconditioner (``precond``'s
    closure) is held constant (``stop_gradient``): it changes the path, not the answer.
    ``P`` may depend on anything ``matvec`` closes over; those leaves get gradients.

    ``inverse_bound``: an upper bound on ``lambda_max(M^-1)``, needed by
    ``engine="jax"`` (:func:`gcrsky.solvers.preconditioners.inverse_bound`).
    ``stop``: the stopping quantity (:func:`pcg`; None: ``r^T M^-1 r``).  With
    ``engine="jax"`` and a ``stop`` of weight N, ``inverse_bound`` must bound
    ``lambda_max(N)`` as well.

    Returns:
        (x, SolveInfo) of the forward solve (scalar fields; not differentiated).
    """
    if options.engine == "jax":
        if inverse_bound is None:
            raise ValueError("engine='jax' needs inverse_bound, an upper bound on lambda_max(M^-1)")
        return _jax_cg(matvec, precond, b, x0, options, inverse_bound, stop)

    def solve(mv, rhs):
        return pcg(mv, precond, rhs, x0, tol=options.tol, maxiter=options.maxiter, stop=stop)

    def transpose_solve(mv, rhs):
        return pcg(mv, precond, rhs, jnp.zeros_like(rhs), tol=0.0, maxiter=options.maxiter, rtol=options.tol,
                   stop=stop)

    return jax.lax.custom_linear_solve(matvec, b, solve, transpose_solve, symmetric=True, has_aux=True)


def _jax_cg(matvec, precond, b, x0, options: CGOptions, inverse_bound, stop=None):
    """``jax.scipy.sparse.linalg.cg`` with our preconditioner; SolveInfo from the true residual.

    JAX stops on the 2-norm, ``||r|| <= atol``.  Since ``r^T M^-1 r <= ||r||^2
    lambda_max(M^-1)``, ``atol = tol / sqrt(inverse_bound)`` makes its stop imply ours
    (conservatively: it may iterate longer).  JAX reports no iteration count.
    """
    atol = options.tol / jnp.sqrt(jax.lax.stop_gradient(inverse_bound))
    x, _ = jax.scipy.sparse.linalg.cg(matvec, b, x0, tol=0.0, atol=atol, maxiter=options.maxiter, M=precond)
    info = _residual_info(matvec, precond, jax.lax.stop_gradient(b), jax.lax.stop_gradient(x), jnp.asarray(-1),
                          options.tol, jnp.asarray(False), stop)
    return x, jax.tree_util.tree_map(jax.lax.stop_gradient, info)


def freq_slice(system: LinearSystem, f) -> LinearSystem:
    """The one-frequency system ``f`` (traced index allowed), leading axis of length 1."""
    sl = lambda a: jax.lax.dynamic_slice_in_dim(a, f, 1, axis=0)  # noqa: E731
    return LinearSystem(
        op=system.op._replace(response=sl(system.op.response)),
        data=sl(system.data),
        inv_noise=sl(system.inv_noise),
        prior=system.prior._replace(mean=sl(system.prior.mean), inv_var=sl(system.prior.inv_var)),
    )


def solve_cg(system: LinearSystem, precision, pc, b, x0, options: CGOptions):
    """Solve ``P x = b`` for b (Nf, n) or (Nf, k, n) batches by preconditioned CG.

    vmapped over frequencies (and over the k right-hand sides); every solve keeps its
    own iteration count and differentiates implicitly (:func:`cg_solve`).
    ``precision``: the dense P (Nf, n, n) or None (matrix-free).  With
    ``options.throw`` a solve that did not converge raises.

    Returns:
        (x like b, SolveInfo with b's batch shape).
    """

    pc = jax.lax.stop_gradient(pc)  # the preconditioner changes the path, not the answer

    def one_freq(f, bf, x0f):
        if precision is not None:
            mv = lambda x: precision[f] @ x  # noqa: E731
        else:
            sys_f = freq_slice(system, f)
            mv = lambda x: precision_apply(sys_f, x[None])[0]  # noqa: E731
        prec = lambda r: precondition_one(pc, f, r)  # noqa: E731
        bound = inverse_bound(pc, f) if options.engine == "jax" else None
        stop = stop_norm(pc, f)
        solve1 = lambda bb, xx: cg_solve(mv, prec, bb, xx, options, inverse_bound=bound, stop=stop)  # noqa: E731
        if bf.ndim == 1:
            return solve1(bf, x0f)
        return jax.vmap(solve1)(bf, x0f)

    x, info = jax.vmap(one_freq)(jnp.arange(b.shape[0]), b, x0)
    if options.throw:
        x = eqx.error_if(x, ~info.converged, "gcrsky CG: a solve did not converge (CGOptions(throw=True))")
    return x, info


def resolve_cg_options(system: LinearSystem, options: CGOptions | None = None) -> CGOptions:
    """``options`` with ``preconditioner="auto"`` (and the window's ``bandwidth="auto"``) made concrete.

    See :func:`gcrsky.solvers.preconditioners.resolve_preconditioner` (host-side on
    concrete arrays; ``"nystrom"`` under a trace) and
    :func:`gcrsky.solvers.window.resolve_bandwidth`.
    """
    options = CGOptions() if options is None else options
    if not isinstance(options, CGOptions):
        raise TypeError(f"the CG path takes CGOptions, got {type(options).__name__}")
    kind = resolve_preconditioner(system, options.preconditioner, warn=options.preconditioner == "auto")
    if kind == "window" and options.bandwidth == "auto":
        options = dataclasses.replace(options, bandwidth=resolve_bandwidth(system, "auto"))
    return options if kind == options.preconditioner else dataclasses.replace(options, preconditioner=kind)


def _setup(system: LinearSystem, options: CGOptions):
    check_float64(system.op.response, system.inv_noise)
    if options.preconditioner == "auto":
        raise ValueError("resolve preconditioner='auto' first (resolve_cg_options)")
    precision = precision_matrix(system) if options.dense else None
    pc = make_preconditioner(system, options.preconditioner, precision, options.sketch_size, options.pc_dtype,
                             options.bandwidth)
    return precision, pc


@partial(jax.jit, static_argnames=("options",))
def _wiener_cg(system: LinearSystem, options: CGOptions):
    precision, pc = _setup(system, options)
    return solve_cg(system, precision, pc, wiener_rhs(system), system.prior.mean, options)


def wiener_cg(system: LinearSystem, options: CGOptions | None = None):
    """Wiener filter (posterior mean) by preconditioned CG, started at the prior mean.

    Returns:
        (a_wf (Nf, n), SolveInfo with (Nf,) fields).
    """
    return _wiener_cg(system, resolve_cg_options(system, options))


class CGState(eqx.Module):
    """The CG path set up for many draws (a PyTree; pass it through jit).

    Attributes:
        system: the linear system.
        a_wf: (Nf, n) Wiener filter (posterior mean).
        wiener: SolveInfo of the Wiener-filter solve, (Nf,) fields.
        precision: dense P (Nf, n, n), or None (matrix-free).
        pc: the preconditioner (:mod:`gcrsky.solvers.preconditioners`).
        options: the :class:`CGOptions` (static), ``preconditioner`` resolved.
    """

    system: LinearSystem
    a_wf: jax.Array
    wiener: SolveInfo
    precision: jax.Array | None
    pc: object
    options: CGOptions = eqx.field(static=True)

    method: ClassVar[str] = "cg"


@partial(jax.jit, static_argnames=("options",))
def _prepare_cg(system: LinearSystem, options: CGOptions) -> CGState:
    precision, pc = _setup(system, options)
    a_wf, winfo = solve_cg(system, precision, pc, wiener_rhs(system), system.prior.mean, options)
    return CGState(system, a_wf, winfo, precision, pc, options)


def prepare_cg(system: LinearSystem, options: CGOptions | None = None) -> CGState:
    """Build the preconditioner (and the dense P if ``options.dense``) and solve for the Wiener filter."""
    return _prepare_cg(system, resolve_cg_options(system, options))


@partial(jax.jit, static_argnames=("ndraws",))
def draw_cg(key: jax.Array, state: CGState, ndraws: int):
    """``ndraws`` exact draws ``a_wf + delta``, ``P delta`` = the GCR fluctuation right-hand side.

    Draw ``i`` uses ``jax.random.split(key, ndraws)[i]``.

    Returns:
        draws (Nf, ndraws, n); a :class:`~gcrsky.solvers.DrawInfo` (``wiener``, ``draws`` a SolveInfo over
        (Nf, ndraws), ``a_wf``).
    """
    system, a_wf = state.system, state.a_wf
    keys = jax.random.split(key, ndraws)
    fl = jax.vmap(lambda k: fluctuation_rhs(k, system), out_axes=1)(keys)  # (Nf, ndraws, n)
    delta, dinfo = solve_cg(system, state.precision, state.pc, fl, jnp.zeros_like(fl), state.options)
    return a_wf[:, None, :] + delta, DrawInfo(state.wiener, dinfo, a_wf)


# ---------------------------------------------------------------- new data, same preconditioner


@jax.jit
def _condition_cg(state: CGState, data: jax.Array) -> CGState:
    """The Wiener filter for new data, by CG from the old one with the state's P and preconditioner."""
    system = state.system._replace(data=jnp.asarray(data, state.system.data.dtype))
    a_wf, winfo = solve_cg(system, state.precision, state.pc, wiener_rhs(system), state.a_wf, state.options)
    return CGState(system, a_wf, winfo, state.precision, state.pc, state.options)


# ---------------------------------------------------------------- the path


def _slq_parts(state: CGState, terms, slq: SLQOptions | None, key) -> EvidenceParts:
    slq = SLQOptions() if slq is None else slq
    key = jax.random.PRNGKey(slq.seed) if key is None else key
    pc = state.pc
    if not isinstance(pc, NystromPreconditioner):
        raise ValueError("the matrix-free evidence needs the Nystrom preconditioner (a proper prior)")
    logdet, sem = whitened_logdet_slq(state.system, pc, slq, key, freq_slice)
    chi2 = terms["rWr"] - jnp.sum(terms["b_res"] * (state.a_wf - state.system.prior.mean), axis=-1)
    return EvidenceParts(chi2, logdet, 0.5 * sem, state.wiener)  # log p carries -1/2 log det: so does its error


class CGPath(SolverPath):
    """Preconditioned CG, matrix-free or on a dense P (:func:`prepare_cg`): the iterative fallback."""

    name = "cg"
    options_type = CGOptions
    state_type = CGState
    direct = False

    def resolve(self, system, options):
        return resolve_cg_options(system, options)

    def resolve_channels(self, system, options, requested):
        """The preconditioner chosen on all channels' priors from what the user asked for."""
        asked = requested.preconditioner if isinstance(requested, CGOptions) else "auto"
        kind = resolve_preconditioner(system, asked, warn=False)
        return options if kind == options.preconditioner else dataclasses.replace(options, preconditioner=kind)

    def memory_bytes(self, system, options, ndraws=1):
        nf, n = int(system.data.shape[0]), int(system.prior.mean.shape[-1])
        lmax = int(round(np.sqrt(n))) - 1
        vec = 6.0 * 8 * nf * max(1, ndraws) * n  # CG state per draw
        sketch = max(3.0 * 8 * nf * n * min(n, options.sketch_size), 8.0 * nf * (lmax + 1) * (2 * lmax + 2) ** 2)
        if options.preconditioner == "window":
            bw = options.bandwidth if options.bandwidth != "auto" else WINDOW_AUTO_MAX
            nbl = int(system.op.response.shape[1])
            sketch = max(sketch, window_memory_bytes(lmax, bw, nbl, nf)["peak"])
        return (8.0 * nf * n * n if options.dense else 0.0) + sketch + vec

    def describe(self, system, options, memory):
        return f"matrix-free CG, {options.preconditioner} preconditioner" if not options.dense else \
            f"CG on the dense P, {options.preconditioner} preconditioner"

    def prepare(self, system, options):
        return prepare_cg(system, options)

    def draw(self, key, state, ndraws):
        return draw_cg(key, state, ndraws)

    def condition(self, state, data):
        return _condition_cg(state, data)

    def wiener(self, system, options):
        return wiener_cg(system, options)

    def evidence_parts(self, system, options, terms, *, slq=None, key=None):
        if options.preconditioner not in ("auto", "nystrom"):
            raise ValueError("the matrix-free evidence needs the Nystrom preconditioner (a proper prior)")
        state = prepare_cg(system, dataclasses.replace(options, preconditioner="nystrom"))
        return _slq_parts(state, terms, slq, key)

    def state_evidence_parts(self, state, terms, *, slq=None, key=None):
        return _slq_parts(state, terms, slq, key)
