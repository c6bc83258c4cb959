"""Top-level conveniences on a :class:`~gcrsky.problem.Problem`."""

from __future__ import annotations

from typing import Literal

import jax

from .problem import Problem
from .sampler import DEFAULT_TOL, EIGH_RCOND, PreparedSampler, prepare_sampler, resolve_preconditioner, sample_system, wiener_filter_system

__all__ = ["wiener_filter", "sample", "prepare"]


def wiener_filter(
    problem: Problem,
    *,
    tol: float = DEFAULT_TOL,
    maxiter: int = 5000,
    preconditioner: str = "auto",
    return_info: bool = False,
):
    """Posterior mean (Wiener filter) of the realified coefficients, (Nf, n).

    Solved by m-block-preconditioned CG to ``tol`` posterior sigma (P-norm of the
    error).  With ``return_info`` also returns the :class:`~gcrsky.sampler.SolveInfo`.
    A solve that did not converge logs a warning and is flagged in the info.
    """
    system = problem.system()
    pc = resolve_preconditioner(system, preconditioner)
    a, info = wiener_filter_system(system, tol=tol, maxiter=maxiter, preconditioner=pc)
    _warn_unconverged(info, "Wiener filter")
    return (a, info) if return_info else a


def sample(
    key: jax.Array,
    problem: Problem,
    ndraws: int,
    method: Literal["cg", "cholesky", "eigh"] = "cg",
    *,
    tol: float = DEFAULT_TOL,
    maxiter: int = 5000,
    dense: bool = True,
    preconditioner: str = "auto",
):
    """Draw ``ndraws`` exact posterior samples (GCR).

    Args:
        key: JAX PRNG key; a fixed key reproduces the draws.
        problem: the :class:`~gcrsky.problem.Problem`.
        ndraws: number of draws (static).
        method: ``"cg"`` (preconditioned CG, vmapped), ``"cholesky"`` (exact
            factorisation of the dense P) or ``"eigh"`` (eigen-decomposition of the
            dense P; exact too, and the only one that handles a singular P, e.g. a
            flat prior, by sampling the directions the data constrain and pinning the
            others at 0: see :func:`gcrsky.sampler.prepare_sampler`).
        tol: CG tolerance in posterior-sigma units (P-norm of the error).
        dense: CG with a dense P (fast for n up to a few thousand) or matrix-free.
        preconditioner: ``"auto"`` (Nystrom for a proper prior, m-blocks otherwise),
            ``"nystrom"`` or ``"mblock"``.

    Returns:
        draws (Nf, ndraws, n) realified, Kelvin; info dict with ``"wiener"`` and
        ``"draws"`` :class:`~gcrsky.sampler.SolveInfo` and ``"a_wf"``.
    """
    if int(ndraws) != ndraws or ndraws < 1:
        raise ValueError(f"ndraws must be a positive integer, got {ndraws}")
    system = problem.system()
    pc = resolve_preconditioner(system, preconditioner)
    draws, info = sample_system(
        key, system, int(ndraws), method=method, tol=tol, maxiter=maxiter, dense=dense, preconditioner=pc
    )
    _warn_unconverged(info["wiener"], "Wiener filter")
    _warn_unconverged(info["draws"], "GCR draws")
    return draws, info


def prepare(
    problem: Problem,
    method: Literal["cg", "cholesky", "eigh"] = "cg",
    *,
    tol: float = DEFAULT_TOL,
    maxiter: int = 5000,
    dense: bool = True,
    preconditioner: str = "auto",
    rcond: float = EIGH_RCOND,
) -> PreparedSampler:
    """Set up once for many draws: P, its factor or preconditioner, and the Wiener filter.

    Then ``gcrsky.draw(key, prepared, ndraws)`` as often as needed (each call costs only
    the draws).  Arguments as for :func:`sample`; ``rcond``: the eigen sampler's
    cut, eigenvalues below ``rcond * max`` are treated as zero.
    """
    system = problem.system()
    pc = resolve_preconditioner(system, preconditioner) if method == "cg" else "nystrom"
    prepared = prepare_sampler(
        system, method=method, tol=tol, maxiter=maxiter, dense=dense, preconditioner=pc, rcond=rcond
    )
    _warn_unconverged(prepared.wiener, "Wiener filter")
    return prepared


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
