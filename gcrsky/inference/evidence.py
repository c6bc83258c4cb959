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
  subtraction (:func:`gcrsky.solvers.dataspace.dataspace_evidence_parts`);
- ``"cg"``: stochastic Lanczos quadrature (matfree) of the Nystrom-preconditioned
  whitened precision (:class:`~gcrsky.solvers.SLQOptions`), with a standard error from
  the probes; ``a_wf`` by CG.

Every term differentiates, to second order on the exact paths (the fit's Laplace
Hessian): the solves implicitly, the Cholesky log determinants by
``tr(P^-1 dP)`` / ``tr(D^-1 dD)`` (:func:`~gcrsky.solvers.dense.cholesky_logdet`), the eigen and m-mode ones
through their factorisations, SLQ through matfree's Lanczos adjoint (the
preconditioner held fixed), so
``jax.grad(lambda t: log_evidence(make_system(t)).sum())`` works on every path.  A
flat or non-positive prior direction makes the evidence improper: that is an error.

Each path's pieces come from its :class:`~gcrsky.solvers.SolverPath`
(:meth:`~gcrsky.solvers.SolverPath.evidence_parts`), and from a prepared state without
refactorising (``log_evidence(gcrsky.prepare(...))``,
:meth:`~gcrsky.solvers.SolverPath.state_evidence_parts`).

Never a silent NaN.  Where the factorisation fails in float64 (e.g. a prior variance so
large that ``I + H`` has a condition number beyond ``1 / eps``: measured on the standard
case at lmax 10 with the prior variances times 1e12), the value is NaN and the
:class:`EvidenceInfo` says why (``solve.result`` is ``NONFINITE``); on concrete arrays
:func:`log_evidence` raises a ``ValueError`` naming the channels and the cause instead.
Under a trace (``jit``, ``grad``, an optimiser) it cannot raise: check ``solve.converged``
(with ``options.throw`` an error is raised from inside the computation).

Bad inputs, as in :mod:`gcrsky.inference.posterior`: on concrete arrays
:func:`log_evidence_system` (and :func:`log_evidence`) raise a ``ValueError`` naming them
(:func:`gcrsky.model.check_system`; ``check=False`` skips it); under a trace a channel with a
non-finite datum, a non-finite or negative ``inv_noise``, a non-finite prior mean or a
non-finite or negative prior ``inv_var`` has the value NaN (its gradient stays finite in the
other channels) and ``solve.result`` :data:`~gcrsky.solvers.Result.BAD_INPUT`, and with
``options.throw`` it is an error naming the input.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.operator import adjoint, apply
from ..model.system import LinearSystem, check_system
from ..solvers.info import SolveInfo, fold_bad_input
from ..solvers.options import EighOptions, SLQOptions
from ..solvers.path import EvidenceParts, is_traced
from ..solvers.registry import SolverOptions, path_of
from .api import as_system, fixed_path
from .posterior import bad_channels, guard_inputs

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
        solve: :class:`~gcrsky.solvers.SolveInfo` of the solve the value rests on (the
            Wiener solve; ``D^-1 r~`` on the data-space path), its ``err_sigma`` measured from
            the true residual: ``NONFINITE`` where the factorisation failed and the value is
            NaN, ``INACCURATE`` where the solve misses the path's ``tol`` (the quadratic term
            is then off by up to ``sqrt(quadratic) * err_sigma``).
        chi2: ``(d - X a0)^T C^-1 (d - X a0)`` with ``C = N + X S X^T``: exactly
            chi-square with ``n_data`` degrees of freedom under the model (a goodness of fit).
        n_data: the number of real data values (twice the unflagged samples).
    """

    stderr: jax.Array
    logdet_whitened: jax.Array
    quadratic: jax.Array
    solve: SolveInfo
    chi2: jax.Array
    n_data: jax.Array


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


def _assemble(terms: dict, parts: EvidenceParts):
    value = -0.5 * (parts.chi2 + parts.logdet_whitened + terms["logdet_n"] + terms["n_data"] * LOG_2PI)
    info = EvidenceInfo(parts.stderr, parts.logdet_whitened, terms["rWr"] - parts.chi2, parts.solve, parts.chi2,
                        terms["n_data"])
    return value, info


def _fold_bad_input(value, info: EvidenceInfo, bad):
    """NaN and ``BAD_INPUT`` in the channels whose inputs are bad (the module's docstring)."""
    return jnp.where(bad, jnp.nan, value), info._replace(solve=fold_bad_input(info.solve, bad))


def _throw_unless_converged(value, info: EvidenceInfo, options, method: str):
    """With ``options.throw``: an error from inside the computation (works under ``jit`` and ``grad``)
    wherever the solve the value rests on did not converge (``NONFINITE``: the value is NaN;
    ``INACCURATE``: its quadratic term misses the path's ``tol``; ``BAD_INPUT`` is raised earlier, naming
    the input).  Without it, the value is returned and ``info.solve`` says so."""
    if not getattr(options, "throw", False):
        return value
    return eqx.error_if(value, ~info.solve.converged,
                        f"gcrsky log_evidence ({method}): the solve it rests on failed (a non-finite factor: the "
                        "value is NaN) or missed the path's tol (INACCURATE): the whitened precision I + H is too "
                        "ill-conditioned for float64; rescale the prior or the noise")


def log_evidence_system(
    system: LinearSystem,
    *,
    options: SolverOptions,
    slq: SLQOptions | None = None,
    key: jax.Array | None = None,
    check: bool = True,
):
    """``(log p(d) (Nf,), EvidenceInfo)`` on the path of ``options`` (pure; usable inside ``jit``).

    Args:
        system: the linear system (every prior direction proper, ``inv_var > 0``).
        options: the path's options (:mod:`gcrsky.solvers.options`); ``CGOptions``
            means SLQ for ``log det P``, ``DataSpaceOptions`` the exact data-space form.
        slq: SLQ settings (``"cg"`` only); default :class:`~gcrsky.solvers.SLQOptions`.
        key: PRNG key of the SLQ probes (default ``PRNGKey(slq.seed)``): a fixed key
            makes the estimate a deterministic, differentiable function of the system.
        check: check concrete inputs with :func:`gcrsky.model.check_system` first.

    Returns:
        the value, NaN where the factorisation failed or an input is bad (``info.solve.result``
        then says which: ``NONFINITE`` or ``BAD_INPUT``).

    Raises:
        ValueError: a bad concrete input (``check``), naming it.
    """
    if check:
        check_system(system)
    system, bad = guard_inputs(system, options)
    terms = evidence_terms(system)
    path = path_of(options)
    parts = path.evidence_parts(system, options, terms, slq=slq, key=key)
    value, info = _fold_bad_input(*_assemble(terms, parts), bad)
    return _throw_unless_converged(value, info, options, path.name), info


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


def _refuse_nonfinite(value, info: EvidenceInfo, method: str) -> None:
    """On concrete results: a ``ValueError`` instead of a silent NaN (module docstring)."""
    if is_traced(value):
        return
    bad = ~np.isfinite(np.asarray(value))
    if bad.any():
        chans = np.flatnonzero(bad).tolist()
        raise ValueError(
            f"log_evidence ({method}) is not finite in channels {chans}: the factorisation of the whitened "
            "precision I + H failed in float64 (it is positive definite in exact arithmetic). This happens when "
            "the prior's variances are so large, or the noise so small, that I + H has a condition number beyond "
            "~1e16; rescale the prior (prior_scale) or the noise, or use method='eigh' to see its spectrum")


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
    """The log evidence ``log p(d | theta)`` of a problem, system or prepared state, per frequency (Nf,).

    The normalised log density of the real and imaginary parts of every unflagged
    sample under ``d ~ N(X a0, X S X^T + N)``, constants included (module docstring).

    Args:
        problem: a :class:`~gcrsky.model.Problem`, a :class:`~gcrsky.model.LinearSystem`, or
            a prepared state (:func:`gcrsky.prepare`): then its factor is reused (no new
            factorisation; ``method`` and ``options`` are ignored).
        method: ``"auto"`` (on concrete arrays: as :func:`gcrsky.solvers.choose_path`, the
            cheapest exact path, else matrix-free SLQ; under a trace: Cholesky),
            ``"cholesky"``, ``"eigh"``, ``"mmode"``, ``"dataspace"`` or ``"cg"`` (SLQ).
        options: the path's options (select the path when ``method="auto"``).
        slq: SLQ settings for ``"cg"``.
        key: PRNG key of the SLQ probes.
        memory_budget: bytes the path may use (``"auto"`` and explicit paths are
            checked against it).
        return_info: also return the :class:`EvidenceInfo` (standard error, terms,
            solve info, the chi-square of the data).

    Raises:
        ValueError: a flat or non-positive prior direction (the evidence is improper), or,
            on concrete arrays, a factorisation that failed in float64 (never a silent NaN).
    """
    if hasattr(problem, "a_wf") and hasattr(problem, "wiener"):  # a prepared state
        path = path_of(problem)
        _check_proper(problem.system)
        terms = evidence_terms(problem.system)
        value, info = _assemble(terms, path.state_evidence_parts(problem, terms, slq=slq, key=key))
        value, info = _fold_bad_input(value, info, bad_channels(problem.system))
        value = _throw_unless_converged(value, info, getattr(problem, "options", None), path.name)
        _refuse_nonfinite(value, info, path.name)
        return (value, info) if return_info else value
    system = as_system(problem)
    _check_proper(system)
    if is_traced(system) and method == "auto" and options is None:
        method = "cholesky"
    opts = fixed_path(system, method, options=options, memory_budget=memory_budget)
    if isinstance(opts, EighOptions) and opts.rcond > 0:
        opts = EighOptions(rcond=0.0, throw=opts.throw, tol=opts.tol)  # every direction is proper here
    value, info = log_evidence_system(system, options=opts, slq=slq, key=key, check=False)  # as_system checked it
    _refuse_nonfinite(value, info, path_of(opts).name)
    return (value, info) if return_info else value
