"""The user tier: posterior mean and draws of a :class:`~gcrsky.model.Problem`, path chosen by size.

``wiener_filter``, ``sample`` and ``prepare`` accept a Problem or its
:class:`~gcrsky.model.LinearSystem` (e.g. from :func:`gcrsky.model.compress_system`).
On concrete arrays the system is checked first (:func:`gcrsky.model.check_system`
names what is wrong with a hand-edited one), ``method="auto"`` (the default) picks
the cheapest exact path that fits in memory (:func:`gcrsky.solvers.choose_path`), an
explicit ``method`` is checked against the memory first, and unconverged solves are
logged as warnings.  ``tol`` is the CG tolerance in posterior-sigma units; every other
knob of a path lives in its options object (:mod:`gcrsky.solvers.options`), passed as
``options=`` (which also selects the path).

Under ``jax.jit`` / ``jax.vmap`` / ``jax.grad`` (a traced system) the same functions work
once the path is fixed: choose it on concrete inputs (``opts = gcrsky.choose_path(problem)``)
and pass ``options=opts``, or pass ``method=``; ``method="auto"`` alone is refused with
that advice.  The host-side checks are skipped there (the paths judge their own accuracy:
see :class:`~gcrsky.solvers.SolveInfo`; bad inputs are reported
:data:`~gcrsky.solvers.Result.BAD_INPUT`, :mod:`gcrsky.inference.posterior`), and unconverged
solves are logged from inside the computation (``jax.debug.callback``).
"""

from __future__ import annotations

import logging

import jax
import numpy as np

from ..model.problem import Problem
from ..model.system import LinearSystem, check_system
from ..solvers.info import Result, SolveInfo
from ..solvers.path import is_traced
from ..solvers.plan import choose_path
from ..solvers.registry import SolverOptions, options_for, path_of
from .posterior import SamplerState, draw, prepare_system, wiener_filter_system

__all__ = ["Method", "fixed_path", "prepare", "sample", "wiener_filter"]

#: ``method=`` of the user tier: ``"auto"`` or the name of a path in :data:`gcrsky.solvers.METHODS`
#: (``"cg"``, ``"cholesky"``, ``"eigh"``, ``"mmode"``, ``"dataspace"``; the registry is the list).
Method = str


def wiener_filter(
    problem: Problem | LinearSystem,
    *,
    method: Method = "auto",
    tol: float | None = None,
    options: SolverOptions | None = None,
    memory_budget: float | None = None,
    return_info: bool = False,
):
    """Posterior mean (Wiener filter) of the realified coefficients, (Nf, n), kelvin.

    Solved on the path ``method`` chooses (as for :func:`prepare`: exact m-mode or
    dense factorisation where they apply, else preconditioned CG to ``tol`` posterior
    sigma, the P-norm of the error).  With ``return_info`` also returns the
    :class:`~gcrsky.solvers.SolveInfo`.  A solve that did not converge logs a warning
    and is flagged in the info; a non-finite answer on concrete arrays is a ``ValueError``
    (never a silent NaN map; under a trace the info's ``NONFINITE`` says it, and a path's
    ``throw=True`` raises).
    """
    system = as_system(problem)
    opts = fixed_path(system, method, options=options, tol=tol, memory_budget=memory_budget)
    a, info = wiener_filter_system(system, options=opts, check=False)  # as_system checked it
    warn_unconverged(info, "Wiener filter")
    refuse_nonfinite(a, info, "Wiener filter")
    return (a, info) if return_info else a


def sample(
    key: jax.Array,
    problem: Problem | LinearSystem,
    ndraws: int,
    method: Method = "auto",
    *,
    tol: float | None = None,
    options: SolverOptions | None = None,
    memory_budget: float | None = None,
):
    """Draw ``ndraws`` exact posterior samples (GCR).

    Args:
        key: JAX PRNG key; a fixed key reproduces the draws (for a given path).
        problem: the :class:`~gcrsky.model.Problem`, or its
            :class:`~gcrsky.model.LinearSystem`.
        ndraws: number of draws (static).
        method: ``"auto"`` (default: chosen by problem size, see
            :func:`gcrsky.solvers.plan_sampler`), ``"mmode"`` (exact block solves;
            uniform full-day coverage and time-stationary noise only), ``"cholesky"``
            (exact factorisation of the dense P), ``"eigh"`` (eigen-decomposition of the
            dense P; exact too, and the only one that handles a singular P, e.g. a
            flat prior, by sampling the directions the data constrain and pinning the
            others at 0), ``"dataspace"`` (exact, through the ``N_d x N_d`` matrix
            ``I + W^1/2 X S X^T W^1/2``: the cheap direct path when there are fewer real
            data values than parameters; a proper prior only) or ``"cg"``
            (preconditioned CG, vmapped over draws).
        tol: CG tolerance in posterior-sigma units (P-norm of the error); default
            :data:`gcrsky.solvers.options.DEFAULT_TOL`.
        options: a path's options (:class:`~gcrsky.solvers.CGOptions`, ...: dense or
            matrix-free CG, preconditioner, iteration cap, eigen cut, ...); selects
            that path when ``method="auto"``.
        memory_budget: bytes the path may use (default: what is free on the device,
            :func:`gcrsky.base.available_memory_bytes`).

    Returns:
        draws (Nf, ndraws, n) realified, Kelvin (the draw layout and key scheme of
        :mod:`gcrsky.inference.posterior`: batches of a bucketed size, so a new ``ndraws``
        in the same bucket does not recompile); a :class:`~gcrsky.solvers.DrawInfo`
        (``wiener``, ``draws``: :class:`~gcrsky.solvers.SolveInfo`, ``a_wf``).
    """
    if int(ndraws) != ndraws or ndraws < 1:
        raise ValueError(f"ndraws must be a positive integer, got {ndraws}")
    prepared = prepare(problem, method, tol=tol, options=options, ndraws=int(ndraws), memory_budget=memory_budget)
    draws, info = draw(key, prepared, int(ndraws))
    warn_unconverged(info.draws, "GCR draws")
    return draws, info


def prepare(
    problem: Problem | LinearSystem,
    method: Method = "auto",
    *,
    tol: float | None = None,
    options: SolverOptions | None = None,
    ndraws: int = 1,
    memory_budget: float | None = None,
) -> SamplerState:
    """Set up once for many draws: P, its factor or preconditioner, and the Wiener filter.

    Then ``gcrsky.draw(key, prepared, ndraws)`` as often as needed (each call costs only
    the draws); ``prepared.method`` says which path ``"auto"`` chose.  Arguments as for
    :func:`sample`; ``ndraws``: the batch size you will draw (sizes the memory check).

    Returns:
        the path's state (:class:`~gcrsky.solvers.CGState`,
        :class:`~gcrsky.solvers.CholeskyState`, :class:`~gcrsky.solvers.EighState`,
        :class:`~gcrsky.solvers.MModeState` or :class:`~gcrsky.solvers.DataSpaceState`).
    """
    system = as_system(problem)
    opts = fixed_path(system, method, options=options, tol=tol, ndraws=int(ndraws), memory_budget=memory_budget)
    prepared = prepare_system(system, options=opts, check=False)  # as_system checked it
    warn_unconverged(prepared.wiener, "Wiener filter")
    refuse_nonfinite(prepared.a_wf, prepared.wiener, "Wiener filter (prepare)")
    return prepared


def fixed_path(
    system: LinearSystem,
    method: Method = "auto",
    *,
    options: SolverOptions | None = None,
    tol: float | None = None,
    ndraws: int = 1,
    memory_budget: float | None = None,
) -> SolverOptions:
    """The options of the path the user tier will run.

    On concrete arrays: :func:`gcrsky.solvers.choose_path` (planned for ``"auto"``, checked
    against the system and the memory otherwise).  Under a trace: the path given by
    ``method`` or ``options`` (resolved as far as shapes allow); ``"auto"`` without options
    is a ``ValueError`` that says how to fix the path outside the transformation.
    """
    if not is_traced(system):
        return choose_path(system, method, options=options, tol=tol, ndraws=ndraws, memory_budget=memory_budget)
    if method == "auto" and options is None:
        raise ValueError(
            "method='auto' chooses a path from the values of the system, but they are traced here (inside "
            "jax.jit, jax.vmap or jax.grad): choose it on concrete inputs, e.g. opts = gcrsky.choose_path(problem) "
            "outside the transformation, and pass options=opts (or pass method='cholesky', 'cg', ...)")
    opts = options_for(path_of(options).name if method == "auto" else method, options, tol=tol)
    return path_of(opts).resolve(system, opts)


def as_system(problem: Problem | LinearSystem, *, check: bool = True) -> LinearSystem:
    """A :class:`Problem`'s linear system, or the system itself, checked by
    :func:`gcrsky.model.check_system` (host-side; traced systems pass unchecked).  A prepared
    state (:func:`prepare`) gives its own system."""
    if hasattr(problem, "a_wf") and isinstance(getattr(problem, "system", None), LinearSystem):
        problem = problem.system
    if isinstance(problem, Problem):
        problem = problem.system()
    if not isinstance(problem, LinearSystem):
        raise TypeError(f"expected a gcrsky Problem or LinearSystem, got {type(problem).__name__}")
    return check_system(problem) if check else problem


def warn_unconverged(info: SolveInfo, what: str) -> None:
    """Log a warning naming how many solves in ``info`` did not converge, and the worst error.

    Host-side on concrete arrays; under a trace the check runs inside the computation
    (``jax.debug.callback``), so ``jit``-ed and ``vmap``-ed calls warn too.
    """
    if is_traced(info):
        jax.debug.callback(lambda c, e: _log_unconverged(np.asarray(c), np.asarray(e), what), info.converged,
                           info.err_sigma)
    else:
        _log_unconverged(np.asarray(info.converged), np.asarray(info.err_sigma), what)


def refuse_nonfinite(a: jax.Array, info: SolveInfo, what: str) -> None:
    """On concrete arrays: a ``ValueError`` naming the channels where ``a`` (Nf, ...) is not finite.

    The inputs were checked before (:func:`gcrsky.model.check_system`), so a non-finite answer
    means the factorisation or the iteration broke down in float64; under a trace nothing is
    raised (``info.result`` is ``NONFINITE``; ``throw=True`` raises from inside).
    """
    if is_traced(a):
        return
    arr = np.asarray(a)
    bad = ~np.all(np.isfinite(arr.reshape(arr.shape[0], -1)), axis=1)
    if bad.any():
        codes = sorted({Result.NAMES[int(c)] for c in np.asarray(info.result)[bad].ravel()})
        raise ValueError(
            f"{what} is not finite in channels {np.flatnonzero(bad).tolist()} (result: {', '.join(codes)}): the "
            "solve broke down in float64 although the inputs are finite. Usually the prior's variances are so large, "
            "or the noise so small, that the posterior precision's condition number is beyond ~1e16: rescale the "
            "prior (prior_scale) or the noise, or use method='eigh' to see its spectrum")


def _log_unconverged(converged: np.ndarray, err: np.ndarray, what: str) -> None:
    bad = ~converged
    if bad.any():
        worst = float(np.max(np.where(np.isfinite(err), err, np.inf)))
        logging.getLogger("gcrsky").warning(
            "%s: %d of %d solves did not converge (worst error estimate %.3g posterior sigma; "
            "inf/NaN means a singular or indefinite precision matrix)",
            what,
            int(bad.sum()),
            bad.size,
            worst,
        )
