"""Top-level conveniences on a :class:`~gcrsky.problem.Problem`."""

from __future__ import annotations

import logging
from typing import Literal

import jax

from .normal import LinearSystem
from .plan import check_memory, path_memory_bytes, plan_sampler
from .problem import Problem
from .sampler import DEFAULT_TOL, EIGH_RCOND, PreparedSampler, prepare_sampler, resolve_preconditioner, sample_system, wiener_filter_system

__all__ = ["wiener_filter", "sample", "prepare", "choose_path"]


def wiener_filter(
    problem: Problem,
    *,
    method: str = "auto",
    tol: float = DEFAULT_TOL,
    maxiter: int = 5000,
    dense: bool = True,
    preconditioner: str = "auto",
    memory_budget: float | None = None,
    return_info: bool = False,
):
    """Posterior mean (Wiener filter) of the realified coefficients, (Nf, n).

    Solved on the path ``method`` chooses (as for :func:`prepare`: exact m-mode or
    dense factorisation where they apply, else preconditioned CG to ``tol`` posterior
    sigma, the P-norm of the error).  With ``return_info`` also returns the
    :class:`~gcrsky.sampler.SolveInfo`.  A solve that did not converge logs a warning
    and is flagged in the info.
    """
    system = _system(problem)
    method, dense, pc = choose_path(system, method, dense=dense, preconditioner=preconditioner,
                                    memory_budget=memory_budget)
    if method == "cg":
        a, info = wiener_filter_system(system, tol=tol, maxiter=maxiter, dense=dense, preconditioner=pc)
    else:
        prepared = prepare_sampler(system, method=method)
        a, info = prepared.a_wf, prepared.wiener
    _warn_unconverged(info, "Wiener filter")
    return (a, info) if return_info else a


Method = Literal["auto", "cg", "cholesky", "eigh", "mmode"]


def choose_path(
    system,
    method: str = "auto",
    *,
    dense: bool = True,
    preconditioner: str = "auto",
    ndraws: int = 1,
    memory_budget: float | None = None,
) -> tuple[str, bool, str]:
    """Resolve ``method="auto"`` and check the memory of an explicit choice (host-side).

    Returns ``(method, dense, preconditioner)`` for :func:`gcrsky.sampler.prepare_sampler`.
    ``"auto"`` follows :func:`gcrsky.plan.plan_sampler` (m-mode, else dense
    Cholesky/eigen where P fits, else matrix-free CG) and logs its choice at INFO;
    naming a ``preconditioner`` with ``method="auto"`` selects CG.
    An explicit method is used as given, after checking that its large arrays fit
    (:class:`gcrsky.plan.InsufficientMemoryError` otherwise, naming the alternative);
    ``"mmode"`` raises ``ValueError`` with the reason when P is not block-diagonal in m.
    """
    from .mmode import mmode_check

    if method == "auto" and preconditioner != "auto":
        method = "cg"  # naming a preconditioner asks for CG
    if method == "auto":
        plan = plan_sampler(system, ndraws=ndraws, budget=memory_budget)
        logging.getLogger("gcrsky").info("sampler path: %s (%s)", plan.method, plan.reason)
        if plan.method == "cg":  # validates the choice and warns about a flat prior
            return plan.method, plan.dense, resolve_preconditioner(system, plan.preconditioner)
        return plan.method, plan.dense, "nystrom"  # unused by the direct paths
    if method not in ("cg", "cholesky", "eigh", "mmode"):
        raise ValueError(f"method must be 'auto', 'cg', 'cholesky', 'eigh' or 'mmode', got {method!r}")
    if method == "mmode":
        chk = mmode_check(system)
        if not chk.ok:
            raise ValueError(f"method='mmode' needs P block-diagonal in m, but {chk.reason}; use method='auto'")
    need = path_memory_bytes(system, method, dense=dense, ndraws=ndraws)
    alt = ("use method='cg' with dense=False (matrix-free) or method='auto'"
           if (method != "cg" or dense) else "draw in smaller batches or shard the baselines (gcrsky.sharding)")
    check_memory(need, f"method={method!r}" + (" (dense P)" if method == "cg" and dense else ""), alt,
                 budget=memory_budget)
    pc = resolve_preconditioner(system, preconditioner) if method == "cg" else "nystrom"
    return method, dense, pc


def sample(
    key: jax.Array,
    problem: Problem,
    ndraws: int,
    method: Method = "auto",
    *,
    tol: float = DEFAULT_TOL,
    maxiter: int = 5000,
    dense: bool = True,
    preconditioner: str = "auto",
    memory_budget: float | None = None,
):
    """Draw ``ndraws`` exact posterior samples (GCR).

    Args:
        key: JAX PRNG key; a fixed key reproduces the draws.
        problem: the :class:`~gcrsky.problem.Problem`, or its
            :class:`~gcrsky.normal.LinearSystem` (e.g. from :func:`gcrsky.compress_system`).
        ndraws: number of draws (static).
        method: ``"auto"`` (default: chosen by problem size, see
            :func:`gcrsky.plan.plan_sampler`), ``"mmode"`` (exact block solves; uniform
            full-day coverage and time-stationary noise only), ``"cholesky"`` (exact
            factorisation of the dense P), ``"eigh"`` (eigen-decomposition of the
            dense P; exact too, and the only one that handles a singular P, e.g. a
            flat prior, by sampling the directions the data constrain and pinning the
            others at 0: see :func:`gcrsky.sampler.prepare_sampler`) or ``"cg"``
            (preconditioned CG, vmapped over draws).
        tol: CG tolerance in posterior-sigma units (P-norm of the error).
        dense: CG with a dense P (fast for n up to a few thousand) or matrix-free.
        preconditioner: ``"auto"`` (Nystrom for a proper prior, m-blocks otherwise),
            ``"nystrom"`` or ``"mblock"``.
        memory_budget: bytes the path may use (default: what is free on the device,
            :func:`gcrsky.plan.available_memory_bytes`).

    Returns:
        draws (Nf, ndraws, n) realified, Kelvin; info dict with ``"wiener"`` and
        ``"draws"`` :class:`~gcrsky.sampler.SolveInfo` and ``"a_wf"``.
    """
    if int(ndraws) != ndraws or ndraws < 1:
        raise ValueError(f"ndraws must be a positive integer, got {ndraws}")
    system = _system(problem)
    method, dense, pc = choose_path(system, method, dense=dense, preconditioner=preconditioner,
                                    ndraws=int(ndraws), memory_budget=memory_budget)
    draws, info = sample_system(
        key, system, int(ndraws), method=method, tol=tol, maxiter=maxiter, dense=dense, preconditioner=pc
    )
    _warn_unconverged(info["wiener"], "Wiener filter")
    _warn_unconverged(info["draws"], "GCR draws")
    return draws, info


def prepare(
    problem: Problem,
    method: Method = "auto",
    *,
    tol: float = DEFAULT_TOL,
    maxiter: int = 5000,
    dense: bool = True,
    preconditioner: str = "auto",
    rcond: float = EIGH_RCOND,
    ndraws: int = 1,
    memory_budget: float | None = None,
) -> PreparedSampler:
    """Set up once for many draws: P, its factor or preconditioner, and the Wiener filter.

    Then ``gcrsky.draw(key, prepared, ndraws)`` as often as needed (each call costs only
    the draws); ``prepared.method`` says which path ``"auto"`` chose.  Arguments as for
    :func:`sample`; ``rcond``: the eigen sampler's cut, eigenvalues below
    ``rcond * max`` are treated as zero; ``ndraws``: the batch size you will draw
    (sizes the memory check).
    """
    system = _system(problem)
    method, dense, pc = choose_path(system, method, dense=dense, preconditioner=preconditioner,
                                    ndraws=int(ndraws), memory_budget=memory_budget)
    prepared = prepare_sampler(
        system, method=method, tol=tol, maxiter=maxiter, dense=dense, preconditioner=pc, rcond=rcond
    )
    _warn_unconverged(prepared.wiener, "Wiener filter")
    return prepared


def _system(problem) -> LinearSystem:
    """A :class:`Problem`'s linear system, or the system itself (e.g. from ``compress_system``)."""
    return problem if isinstance(problem, LinearSystem) else problem.system()


def _warn_unconverged(info, what: str) -> None:
    import logging

    import numpy as np

    bad = ~np.asarray(info.converged)
    if bad.any():
        err = np.asarray(info.err_sigma)
        worst = float(np.max(np.where(np.isfinite(err), err, np.inf)))
        logging.getLogger("gcrsky").warning(
            "%s: %d of %d solves did not converge (worst error estimate %.3g posterior sigma; "
            "inf/NaN means a singular or indefinite precision matrix)",
            what,
            int(bad.sum()),
            bad.size,
            worst,
        )
