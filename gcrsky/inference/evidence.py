"""The exact log evidence (marginal likelihood) of the linear-Gaussian model, and its gradient.

With ``d = X a + n``, ``a ~ N(a0, S)`` and ``n ~ N(0, N)`` over the real and imaginary
parts of every unflagged sample, ``d ~ N(X a0, X S X^T + N)``.  By the determinant
lemma and Woodbury (DESIGN section 6), per frequency,

    log p(d) = -1/2 [ d^T W d + a0^T S^-1 a0 - b^T P^-1 b
                      + log det N + log det S + log det P + N_d log 2 pi ],

with ``W = N^-1`` (the system's ``inv_noise``, per component), ``b`` the Wiener
right-hand side, ``P`` the posterior precision and ``N_d`` twice the number of
unflagged samples (``inv_noise > 0``; a fractional weight ``w`` means variance
``sigma^2 / w``).  Constants are included: it is the normalised density.

It is evaluated in the equivalent, better-conditioned form

    log p(d) = -1/2 [ r^T W r - b'^T (a_wf - a0) + log det N + log det(I + H) + N_d log 2 pi ],

with the residual ``r = d - X a0``, ``b' = X^T W r`` (so ``P^-1 b' = a_wf - a0``) and
the prior-whitened precision ``I + H = S^1/2 P S^1/2`` (``log det S + log det P``).
Written as above, the terms ``a0^T S^-1 a0`` and ``b^T P^-1 b`` grow without bound as
the prior tightens and cancel catastrophically (measured: a prior-variance scale of
1e-76 gave an evidence 1700 above the true maximum); in this form nothing does.

``log det(I + H)`` comes from the path (:func:`log_evidence`'s ``method``):

- ``"cholesky"``: ``2 sum log diag L`` of the whitened dense precision;
- ``"eigh"``: ``sum log lam`` of it (gradients stay finite at degenerate eigenvalues);
- ``"mmode"``: ``log det P`` over the m-blocks (uniform full-day coverage) plus
  ``log det S``;
- ``"dataspace"``: in data space, exactly: ``log p(d) = -1/2 [r~^T D^-1 r~ + log det D
  + log det N + N_d log 2 pi]`` with ``r~ = W^1/2 r`` and ``D = I + W^1/2 X S X^T W^1/2``
  over the unflagged samples (``r~^T D^-1 r~ = r^T W r - b'^T (a_wf - a0)`` by Woodbury,
  ``log det D = log det(I + H)`` by Sylvester), evaluated as written, without the
  subtraction (:func:`gcrsky.solvers.dataspace_evidence_parts`);
- ``"cg"``: stochastic Lanczos quadrature (matfree) of the Nystrom-preconditioned
  whitened precision (:class:`~gcrsky.solvers.SLQOptions`), with a standard error from
  the probes; ``a_wf`` by CG.

Every term differentiates, to second order on the exact paths (the fit's Laplace
Hessian): the solves implicitly, the Cholesky log determinants by
``tr(P^-1 dP)`` / ``tr(D^-1 dD)`` (:func:`~gcrsky.solvers.cholesky_logdet`), the eigen and m-mode ones
through their factorisations, SLQ through matfree's Lanczos adjoint (the
preconditioner held fixed), so
``jax.grad(lambda t: log_evidence(make_system(t)).sum())`` works on every path.  A
flat or non-positive prior direction makes the evidence improper: that is an error.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.operator import adjoint, apply
from ..model.system import LinearSystem, data_apply, precision_matrix
from ..solvers.cg import freq_slice, prepare_cg
from ..solvers.dataspace import dataspace_evidence_parts, lag_structure
from ..solvers.dense import _eigh_parts, cholesky_logdet, cholesky_solve
from ..solvers.info import SolveInfo, direct_info
from ..solvers.mmode import prepare_mmode
from ..solvers.options import (
    CGOptions,
    EighOptions,
    MModeOptions,
    SLQOptions,
    SolverOptions,
    method_of,
    options_for,
)
from ..solvers.plan import choose_path
from ..solvers.preconditioners import NystromPreconditioner, nystrom_preconditioner
from .api import as_system

__all__ = ["EvidenceInfo", "evidence_terms", "log_evidence", "log_evidence_system"]

LOG_2PI = float(np.log(2 * np.pi))


class EvidenceInfo(NamedTuple):
    """How :func:`log_evidence` was computed (arrays are (Nf,)).

    Attributes:
        stderr: standard error of ``log p(d)`` (0 on the exact paths; the SLQ probes'
            standard error on ``"cg"``).
        logdet_whitened: ``log det(I + H) = log det S + log det P`` (``= log det D`` on
            the data-space path).
        quadratic: ``b'^T P^-1 b'`` with ``b' = X^T W (d - X a0)`` (on the data-space
            path ``r^T W r - r~^T D^-1 r~``, for information: the value does not use it).
        solve: :class:`~gcrsky.solvers.SolveInfo` of the Wiener solve (of the
            factorisation of D on the data-space path: no Wiener filter is formed).
    """

    stderr: jax.Array
    logdet_whitened: jax.Array
    quadratic: jax.Array
    solve: SolveInfo


def evidence_terms(system: LinearSystem) -> dict:
    """The terms of ``log p(d)`` that need no solve, per frequency (Nf,) each.

    Returns:
        ``{"rWr": r^T W r with r = d - X a0, "b_res": b' = X^T W r (Nf, n),
        "logdet_n": log det N, "n_data": N_d}`` (``N_d`` counts real numbers).
    """
    w = system.inv_noise
    kept = w > 0
    safe = jnp.where(kept, w, 1.0)
    r = jnp.where(kept, system.data - apply(system.op, system.prior.mean), 0.0)
    return {
        "rWr": jnp.sum(w * (r.real**2 + r.imag**2), axis=(1, 2)),
        "b_res": adjoint(system.op, w * r),
        "logdet_n": -2.0 * jnp.sum(jnp.where(kept, jnp.log(safe), 0.0), axis=(1, 2)),
        "n_data": 2.0 * jnp.sum(kept, axis=(1, 2)),
    }


def _combine(terms: dict, quad, logdet_w):
    return -0.5 * (terms["rWr"] - quad + terms["logdet_n"] + logdet_w + terms["n_data"] * LOG_2PI)


def _whitened_precision(system: LinearSystem):
    sh = 1.0 / jnp.sqrt(system.prior.inv_var)  # S^1/2
    return sh[:, :, None] * precision_matrix(system) * sh[:, None, :], sh


def _dense_cholesky(system: LinearSystem, b_res):
    Pw, sh = _whitened_precision(system)
    L = jnp.linalg.cholesky(Pw)
    x = cholesky_solve(Pw, L, sh * b_res)  # S^-1/2 (a_wf - a0)
    logdet = cholesky_logdet(Pw, L)
    finite = jnp.all(jnp.isfinite(jax.lax.stop_gradient(L)), axis=(1, 2))
    zeros = jnp.zeros(b_res.shape[0])
    return jnp.sum(sh * b_res * x, axis=1), logdet, zeros, direct_info(zeros, zeros, finite)


def _dense_eigh(system: LinearSystem, b_res):
    Pw, sh = _whitened_precision(system)
    x, _, lam, _ = jax.vmap(lambda p, bb: _eigh_parts(p, bb, 0.0))(Pw, sh * b_res)
    finite = jnp.all(jax.lax.stop_gradient(lam) > 0, axis=1)
    logdet = jnp.sum(jnp.log(jnp.where(lam > 0, lam, 1.0)), axis=1)
    zeros = jnp.zeros(b_res.shape[0])
    return jnp.sum(sh * b_res * x, axis=1), logdet, zeros, direct_info(zeros, zeros, finite)


def _mmode(system: LinearSystem, options: MModeOptions, b_res):
    state = prepare_mmode(system, options)
    diag = jnp.diagonal(state.chol, axis1=-2, axis2=-1)  # padding rows are identity: log 1 = 0
    logdet = 2.0 * jnp.sum(jnp.log(diag), axis=(1, 2)) - jnp.sum(jnp.log(system.prior.inv_var), axis=1)
    quad = jnp.sum(b_res * (state.a_wf - system.prior.mean), axis=1)
    return quad, logdet, jnp.zeros(b_res.shape[0]), state.wiener


def _whitened_logdet_slq(system_f: LinearSystem, pc: NystromPreconditioner, f, slq: SLQOptions, key):
    """SLQ of ``log det(M^-1/2 (I + H) M^-1/2)`` for one frequency (leading axis 1)."""
    from matfree import decomp, funm, stochtrace

    U, lam = pc.U[f], pc.lam[f]
    shrink = 1.0 / jnp.sqrt(1.0 + lam) - 1.0  # M^-1/2 = I + U diag((1+lam)^-1/2 - 1) U^T

    def matvec(v, sys_f, U, shrink):  # everything as parameters: matfree's adjoint sees no closures
        def mhalf(x):
            return x + U @ (shrink * (U.T @ x))

        s = 1.0 / jnp.sqrt(sys_f.prior.inv_var[0])  # S^1/2, differentiable in the prior
        u = mhalf(v)
        hu = u + s * data_apply(sys_f, (s * u)[None])[0]
        return mhalf(hu)

    n = system_f.prior.mean.shape[1]
    integrand = funm.monte_carlo_funm_sym_logdet(decomp.tridiag_sym(min(slq.lanczos, n)))
    sampler = stochtrace.sampler_signs(jnp.zeros(n), num=slq.probes)
    estimate = stochtrace.estimator_monte_carlo_mean_and_sem(integrand, sampler)
    mean, sem = estimate(matvec, key, system_f, U, shrink)
    return mean + jnp.sum(jnp.log1p(lam)), sem


def _cg_slq(system: LinearSystem, options: CGOptions, slq: SLQOptions, key, b_res):
    if options.preconditioner not in ("auto", "nystrom"):
        raise ValueError("the matrix-free evidence needs the Nystrom preconditioner (a proper prior)")
    options = dataclasses.replace(options, preconditioner="nystrom")
    state = prepare_cg(system, options)
    pc = state.pc if isinstance(state.pc, NystromPreconditioner) else nystrom_preconditioner(system, options.rank)
    pc = jax.lax.stop_gradient(pc)
    nf = b_res.shape[0]
    keys = jax.random.split(key, nf)
    logdet_w, sem = jax.vmap(lambda f, k: _whitened_logdet_slq(freq_slice(system, f), pc, f, slq, k))(
        jnp.arange(nf), keys
    )
    quad = jnp.sum(b_res * (state.a_wf - system.prior.mean), axis=1)
    return quad, logdet_w, 0.5 * sem, state.wiener  # log p carries -1/2 log det: so does its error


def log_evidence_system(
    system: LinearSystem,
    *,
    options: SolverOptions,
    slq: SLQOptions | None = None,
    key: jax.Array | None = None,
):
    """``(log p(d) (Nf,), EvidenceInfo)`` on the path of ``options`` (pure; usable inside ``jit``).

    Args:
        system: the linear system (every prior direction proper, ``inv_var > 0``).
        options: the path's options (:mod:`gcrsky.solvers.options`); ``CGOptions``
            means SLQ for ``log det P``, ``DataSpaceOptions`` the exact data-space form.
        slq: SLQ settings (``"cg"`` only); default :class:`~gcrsky.solvers.SLQOptions`.
        key: PRNG key of the SLQ probes (default ``PRNGKey(slq.seed)``): a fixed key
            makes the estimate a deterministic, differentiable function of the system.
    """
    terms = evidence_terms(system)
    b_res = terms["b_res"]
    method = method_of(options)
    if method == "dataspace":
        lags = lag_structure(system) if options.stationary else None  # None under a trace
        q, logdet, finite = dataspace_evidence_parts(system, options.time_chunk, lags)
        zeros = jnp.zeros(q.shape)
        info = direct_info(zeros, zeros, finite)
        if options.throw:
            q = eqx.error_if(q, ~finite, "gcrsky data space: D is not positive definite (a flat prior direction?)")
        value = -0.5 * (q + logdet + terms["logdet_n"] + terms["n_data"] * LOG_2PI)
        return value, EvidenceInfo(zeros, logdet, terms["rWr"] - q, info)
    if method == "cholesky":
        quad, logdet, sem, info = _dense_cholesky(system, b_res)
    elif method == "eigh":
        quad, logdet, sem, info = _dense_eigh(system, b_res)
    elif method == "mmode":
        quad, logdet, sem, info = _mmode(system, options, b_res)
    else:
        slq = SLQOptions() if slq is None else slq
        key = jax.random.PRNGKey(slq.seed) if key is None else key
        quad, logdet, sem, info = _cg_slq(system, options, slq, key, b_res)
    return _combine(terms, quad, logdet), EvidenceInfo(sem, logdet, quad, info)


def _check_proper(system: LinearSystem) -> None:
    iv = system.prior.inv_var
    if isinstance(iv, jax.core.Tracer):
        return
    bad = np.asarray(iv) <= 0
    if bad.any():
        f, k = np.argwhere(bad)[0]
        raise ValueError(
            f"the evidence is improper: the prior is flat or non-positive in {int(bad.sum())} directions "
            f"(first: frequency {f}, parameter {k}, inv_var = {float(np.asarray(iv)[f, k])!r}); "
            "give every mode a proper prior (e.g. gcrsky.isotropic_prior)"
        )


def log_evidence(
    problem,
    *,
    method: str = "auto",
    options: SolverOptions | None = None,
    slq: SLQOptions | None = None,
    key: jax.Array | None = None,
    memory_budget: float | None = None,
    return_info: bool = False,
):
    """The log evidence ``log p(d | theta)`` of a problem or system, per frequency (Nf,).

    The normalised log density of the real and imaginary parts of every unflagged
    sample under ``d ~ N(X a0, X S X^T + N)``, constants included (module docstring).

    Args:
        problem: a :class:`~gcrsky.model.Problem` or :class:`~gcrsky.model.LinearSystem`.
        method: ``"auto"`` (on concrete arrays: m-mode where P is block-diagonal in m,
            else dense Cholesky where P fits, else matrix-free SLQ, as
            :func:`gcrsky.solvers.choose_path`, which also picks ``"dataspace"`` where
            there are fewer data than parameters and it is cheaper; under a trace:
            Cholesky), ``"cholesky"``, ``"eigh"``, ``"mmode"``, ``"dataspace"`` or
            ``"cg"`` (SLQ).
        options: the path's options (select the path when ``method="auto"``).
        slq: SLQ settings for ``"cg"``.
        key: PRNG key of the SLQ probes.
        memory_budget: bytes the path may use (``"auto"`` and explicit paths are
            checked against it).
        return_info: also return the :class:`EvidenceInfo` (standard error, terms,
            solve info).

    Raises:
        ValueError: a flat or non-positive prior direction (the evidence is improper).
    """
    system = as_system(problem)
    _check_proper(system)
    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(system))
    if traced:
        if method == "auto":
            method = method_of(options) if options is not None else "cholesky"
        opts = options_for(method, options)
    else:
        opts = choose_path(system, method, options=options, memory_budget=memory_budget)
    if isinstance(opts, EighOptions) and opts.rcond > 0:
        opts = EighOptions(rcond=0.0, throw=opts.throw)  # every direction is proper here
    value, info = log_evidence_system(system, options=opts, slq=slq, key=key)
    return (value, info) if return_info else value
