"""What every solve reports: :class:`SolveInfo` (its codes and constructors are in :mod:`gcrsky.solvers.info`).

The type lives here, below every layer, so that the files that store it (:mod:`gcrsky.io.results`)
need nothing of the solvers: its field names are the datasets of ``results.h5``'s ``draw_info`` /
``wiener_info`` groups.
"""

from __future__ import annotations

from typing import Any, NamedTuple

__all__ = ["SolveInfo"]


class SolveInfo(NamedTuple):
    """How a solve went (arrays have the batch shape of the solve, e.g. (Nf,) or (Nf, ndraws)).

    Attributes:
        iterations: CG iterations taken (0 for the direct paths; -1 where the engine
            does not report them, ``CGOptions(engine="jax")``).
        err_sigma: ``sqrt(r^T M^-1 r)`` from the *true* final residual ``b - P x``, in
            posterior-sigma units: an upper bound on the error's P-norm with the
            Nystrom preconditioner, an estimate with m-blocks; with the window
            preconditioner ``sqrt(r^T S r)`` instead (a bound: ``P >= S^-1``); for the direct paths
            the same quantity with their exact factor (rounding only).
        rel_residual: ``||b - P x|| / ||b||``.
        converged: ``result == Result.SUCCESS``.
        result: the :class:`Result` code (int).
    """

    iterations: Any
    err_sigma: Any
    rel_residual: Any
    converged: Any
    result: Any
