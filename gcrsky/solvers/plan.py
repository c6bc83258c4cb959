"""Choosing a sampler path by problem size, and memory estimates before large allocations.

Given a :class:`~gcrsky.model.LinearSystem`, :func:`plan_sampler` picks the
cheapest *exact* path and says why, and :func:`choose_path` turns a user's
``method=`` / ``options=`` into the options of one path (``"auto"`` through the plan;
an explicit choice after checking that its large arrays fit, with
:func:`gcrsky.base.check_memory`, which raises
:class:`~gcrsky.base.InsufficientMemoryError` naming the size and the path that would
fit).

Paths (all exact; they differ only in cost):

* ``"mmode"``: uniform full-day coverage with time-stationary noise and no frame map
  (:func:`gcrsky.solvers.mmode.mmode_check`): P is block-diagonal in m; blocks cost
  ``O(Nf Nbl lmax^3)`` to build and ``8 Nf (lmax+1) (2 lmax+2)^2`` bytes.
* ``"cholesky"``: dense ``P`` built once by m-blocks (``~8 Nf Nbl n^2`` flop whatever
  Nt, :func:`gcrsky.model.precision_matrix`; ``8 Nf n^2`` bytes, three times that with
  its factor and ``L^-T``, twice for ``n >`` :data:`~gcrsky.solvers.dense.CHOLESKY_INVERSE_MAX_N`
  where draws solve with ``L^T``), then each draw is a product with ``L^-T`` (``2 n^2`` flop).
* ``"eigh"``: like Cholesky, for a singular P (a flat prior, ``S^-1 = 0`` somewhere).
* ``"dataspace"``: through the ``N_d x N_d`` matrix ``D = I + W^1/2 X S X^T W^1/2``
  (:mod:`gcrsky.solvers.dataspace`; ``N_d = 2 Nt Nbl`` real data values per channel):
  ``~4 Nf N_d^2 n`` flop to build D (products of per-time response blocks), ``Nf N_d^3 / 3`` to
  factorise it, ``8 Nf N_d^2`` bytes for D and again for its factor; each draw is one
  matrix-free product with X and one with ``X^T`` plus two triangular solves.  A proper
  prior only.
* ``"cg"`` matrix-free: never forms P; ``16 Nf Nt Nbl n`` flop per product, a rank-128
  Nystrom preconditioner (``8 Nf n 128`` bytes) for a proper prior, m-blocks for a
  flat one.

Rule of :func:`plan_sampler` (``method="auto"`` in :func:`gcrsky.prepare` /
:func:`gcrsky.sample`): m-mode when its check passes; else, of the direct paths that
apply and fit -- dense (Cholesky, or the eigen sampler for a flat prior) when the dense
P and its factor fit in :data:`DENSE_MEMORY_FRACTION` of the available memory and
``n <= DENSE_MAX_N``; data space for a proper prior when ``N_d < n``,
``N_d <= DATASPACE_MAX_ND`` and D and its factor fit in the same fraction -- the one
with the smaller estimated cost of set-up plus :data:`PLAN_DRAWS` draws
(:func:`path_cost_flop`); else matrix-free CG.  The crossovers are measured in ``benchmarks/scale.py``: at lmax 50
(n = 2601) Cholesky set-up is 2-9 s and a draw 2-3 ms against 40-600 ms per draw for
matrix-free CG, so dense wins wherever it fits; ``DENSE_MAX_N`` = 24000 keeps the
``n^3 / 3`` factorisation under ~2.5 min (n = 22801: P 94 s, factor 127 s on one
OpenBLAS thread, which n > :data:`~gcrsky.solvers.dense.OPENBLAS_SAFE_N` needs: the
dense path is only chosen there when ``OPENBLAS_NUM_THREADS=1``).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from typing import NamedTuple

import numpy as np

from ..base.memory import available_memory_bytes, check_memory, format_bytes
from ..model.operator import n_in
from ..model.system import LinearSystem
from .dataspace import check_proper_prior, dataspace_memory_bytes, lag_structure, materialize_rows
from .dense import CHOLESKY_INVERSE_MAX_N, OPENBLAS_SAFE_N
from .mmode import mmode_check
from .options import (
    CGOptions,
    CholeskyOptions,
    DataSpaceOptions,
    EighOptions,
    MModeOptions,
    SolverOptions,
    method_of,
    options_for,
)
from .preconditioners import resolve_preconditioner

__all__ = [
    "DATASPACE_MAX_ND",
    "DENSE_MAX_N",
    "PLAN_DRAWS",
    "DENSE_MEMORY_FRACTION",
    "SamplerPlan",
    "choose_path",
    "path_cost_flop",
    "path_memory_bytes",
    "plan_sampler",
]

log = logging.getLogger(__name__)

#: Largest n for which ``method="auto"`` forms and factorises the dense P.
DENSE_MAX_N = 24000
#: Fraction of the available memory the dense path's set-up peak may take under "auto".
DENSE_MEMORY_FRACTION = 0.75
#: Largest number of real data values per channel for which ``method="auto"`` forms and
#: factorises the data-space matrix D (the same ~1 min factorisation bound as ``DENSE_MAX_N``).
DATASPACE_MAX_ND = 12000
#: Draws the planner's cost comparison assumes (set-up plus this many draws).
PLAN_DRAWS = 200


class SamplerPlan(NamedTuple):
    """What :func:`plan_sampler` chose.

    Attributes:
        options: the chosen path's options (:mod:`gcrsky.solvers.options`); for CG
            with ``dense`` and ``preconditioner`` set.
        memory_bytes: estimated peak of the path's large arrays.
        reason: one line saying why.
    """

    options: SolverOptions
    memory_bytes: float
    reason: str

    @property
    def method(self) -> str:
        """``"mmode"``, ``"cholesky"``, ``"eigh"``, ``"dataspace"`` or ``"cg"``."""
        return method_of(self.options)


def _sizes(system: LinearSystem) -> tuple[int, int, int, int]:
    nf, nbl, _ = system.op.response.shape
    return int(nf), int(system.data.shape[1]), int(nbl), int(n_in(system.op))


def path_memory_bytes(
    system: LinearSystem, method: str, *, dense: bool = True, ndraws: int = 1, rank: int = CGOptions.rank
) -> float:
    """Estimated peak bytes of a path's large arrays (float64), beyond the system itself.

    ``dense`` and ``rank`` describe the CG path (:class:`~gcrsky.solvers.CGOptions`).
    Counts the dense P, its factor and inverse factor / eigenvectors (``8 Nf n^2`` each; for
    Cholesky the set-up's measured peak with LAPACK's copies, 7.5 or 3.5 of them), the m-blocks,
    the Nystrom sketch and the per-draw CG work vectors (``~6 x 8 Nf ndraws n``).
    """
    nf, nt, nbl, n = _sizes(system)
    lmax = int(round(np.sqrt(n))) - 1
    vec = 6.0 * 8 * nf * max(1, ndraws) * n  # CG state per draw
    if method == "mmode":
        return 2.0 * 8 * nf * (lmax + 1) * (2 * lmax + 2) ** 2 + vec
    if method == "cholesky":  # the peak of the set-up (XLA memory_analysis, in n^2 doubles): one program
        # holding P, its factor, L^-T and their transients (7.25); for n > CHOLESKY_INVERSE_MAX_N two
        # programs, the factor's holding P, L and LAPACK's working copy (3.4)
        copies = 3.5 if n > CHOLESKY_INVERSE_MAX_N else 7.5
        return copies * 8 * nf * n * n + 8.0 * nf * max(1, ndraws) * n
    if method == "eigh":  # P, eigenvectors, sqrt_cov
        return 3.0 * 8 * nf * n * n + 8.0 * nf * max(1, ndraws) * n
    if method == "dataspace":  # D, its factor, the assembly's transients, per-time responses, per-draw vectors
        return dataspace_memory_bytes(system, ndraws, materialize_rows(system, DataSpaceOptions()))
    if method == "cg":
        sketch = max(3.0 * 8 * nf * n * min(n, rank), 8.0 * nf * (lmax + 1) * (2 * lmax + 2) ** 2)
        return (8.0 * nf * n * n if dense else 0.0) + sketch + vec
    raise ValueError(f"unknown method {method!r}")


def path_cost_flop(system: LinearSystem, method: str, *, ndraws: int = PLAN_DRAWS) -> float:
    """Estimated floating-point operations of a direct path's set-up plus ``ndraws`` draws (all channels).

    Rough but of the right order (the planner compares them): ``"cholesky"`` / ``"eigh"``:
    P by m-blocks (``8 Nf Nbl n^2``, :func:`gcrsky.model.precision_matrix`) and its factor (``Nf n^3 / 3``), then
    ``2 n^2`` per draw; ``"dataspace"``: D (``4 Nf N_d^2 n`` with ``N_d = 2 Nt Nbl``, or
    ``8 Nf k (2 Nbl)^2 n`` for ``k`` distinct lags on the stationary shortcut,
    :func:`gcrsky.solvers.dataspace.lag_structure`) and its
    factor (``Nf N_d^3 / 3``), then per draw the products with X and ``X^T``
    (``16 Nf Nt Nbl n`` plus ``~8 Nf Nt (lmax+1)^3`` for the rotations; ``4 Nf N_d n`` with
    ``Y = W^1/2 X`` materialised) and two triangular solves (``2 Nf N_d^2``).
    """
    nf, nt, nbl, n = _sizes(system)
    if method in ("cholesky", "eigh"):
        return 8.0 * nf * min(1.0, nt / 2.0) * nbl * n * n + nf * n**3 / 3.0 + ndraws * 2.0 * nf * n * n
    if method == "dataspace":
        nd = 2.0 * nt * nbl
        rot = 8.0 * nf * nt * (np.sqrt(n)) ** 3
        lags = lag_structure(system)
        build = 4.0 * nf * nd * nd * n if lags is None else 8.0 * nf * lags.lags.shape[0] * (2.0 * nbl) ** 2 * n
        per_draw = (4.0 * nf * nd * n if materialize_rows(system, DataSpaceOptions()) else
                    16.0 * nf * nt * nbl * n + rot)
        return build + nf * nd**3 / 3.0 + ndraws * (per_draw + 2.0 * nf * nd * nd)
    raise ValueError(f"no cost model for method {method!r} (direct paths only: 'cholesky', 'eigh', 'dataspace')")


def plan_sampler(system: LinearSystem, *, ndraws: int = 1, budget: float | None = None) -> SamplerPlan:
    """The cheapest exact path for ``system`` (host-side; call outside ``jit``).

    Args:
        system: the linear system (concrete arrays).
        ndraws: draws per batch (sizes the CG work vectors).
        budget: bytes available; default :func:`available_memory_bytes`.

    Returns:
        a :class:`SamplerPlan`; raises :class:`~gcrsky.base.InsufficientMemoryError` if
        even the matrix-free path does not fit.
    """
    avail = available_memory_bytes() if budget is None else float(budget)
    nf, nt, nbl, n = _sizes(system)
    flat = bool(np.any(np.asarray(system.prior.inv_var) <= 0))
    chk = mmode_check(system)
    if chk.ok and not flat:
        mem = path_memory_bytes(system, "mmode", ndraws=ndraws)
        if mem <= avail:
            return SamplerPlan(MModeOptions(), mem, "uniform full-day coverage, stationary noise: P is block-diagonal in m")
    dense_mem = path_memory_bytes(system, "cholesky", ndraws=ndraws)
    ds_mem = path_memory_bytes(system, "dataspace", ndraws=ndraws)
    nd = 2 * nt * nbl
    dense_ok = (n <= DENSE_MAX_N and dense_mem <= DENSE_MEMORY_FRACTION * avail
                and (n <= OPENBLAS_SAFE_N or os.environ.get("OPENBLAS_NUM_THREADS") == "1"))
    ds_ok = (not flat) and nd < n and nd <= DATASPACE_MAX_ND and ds_mem <= DENSE_MEMORY_FRACTION * avail
    if ds_ok and (not dense_ok or path_cost_flop(system, "dataspace") < path_cost_flop(system, "cholesky")):
        why = (f"N_d = {nd} real data values per channel < n = {n}: data space (D + factor "
               f"{format_bytes(ds_mem)}; est. {path_cost_flop(system, 'dataspace'):.2g} flop for set-up + "
               f"{PLAN_DRAWS} draws")
        why += (f" against {path_cost_flop(system, 'cholesky'):.2g} dense)" if dense_ok else
                f"; the dense P + factor would need {format_bytes(dense_mem)} (n = {n}))")
        if not chk.ok:
            why += f"; not m-mode: {chk.reason}"
        return SamplerPlan(DataSpaceOptions(), ds_mem, why)
    if dense_ok:
        why = (f"n = {n} <= {DENSE_MAX_N} and the dense P + factor ({format_bytes(dense_mem)}) fit in "
               f"{DENSE_MEMORY_FRACTION:.0%} of {format_bytes(avail)}")
        if flat:
            why += "; flat prior: eigen sampler (P may be singular)"
        elif ds_ok:
            why += (f"; cheaper than data space (N_d = {nd}: est. {path_cost_flop(system, 'cholesky'):.2g} against "
                    f"{path_cost_flop(system, 'dataspace'):.2g} flop for set-up + {PLAN_DRAWS} draws)")
        if not chk.ok:
            why += f"; not m-mode: {chk.reason}"
        return SamplerPlan(EighOptions() if flat else CholeskyOptions(), dense_mem, why)
    pc = "mblock" if flat else "nystrom"
    mem = path_memory_bytes(system, "cg", dense=False, ndraws=ndraws)
    check_memory(mem, f"matrix-free CG ({ndraws} draws per batch, n = {n}, Nf = {nf})",
                 "draw in smaller batches (ndraws) or shard the baselines (gcrsky.parallel)", budget=avail)
    why = (f"dense P + factor would need {format_bytes(dense_mem)} (n = {n}); "
           + ("flat prior (no data space)" if flat else f"data space N_d = {nd} (D + factor {format_bytes(ds_mem)})")
           + f"; matrix-free CG, {pc} preconditioner")
    return SamplerPlan(CGOptions(dense=False, preconditioner=pc), mem, why)


def choose_path(
    system: LinearSystem,
    method: str = "auto",
    *,
    options: SolverOptions | None = None,
    tol: float | None = None,
    ndraws: int = 1,
    memory_budget: float | None = None,
) -> SolverOptions:
    """Resolve a user's ``method`` / ``options`` / ``tol`` into one path's options (host-side).

    * ``method="auto"`` without options follows :func:`plan_sampler` (m-mode, else
      the cheaper of dense Cholesky/eigen and data space where they fit, else
      matrix-free CG) and logs its choice and the reason at INFO.
    * Options alone (``method="auto"``) select their path; ``method`` and options of
      another path are an error.
    * An explicit path is used as given, after checking that its large arrays fit
      (:class:`~gcrsky.base.InsufficientMemoryError` otherwise, naming the
      alternative); ``"mmode"`` raises ``ValueError`` with the reason when P is not
      block-diagonal in m.
    * ``tol`` sets the CG tolerance (the direct paths are exact and ignore it).

    CG options come back with ``preconditioner`` resolved (Nystrom for a proper
    prior, m-blocks for a flat one; a warning is logged for a flat prior).

    Args:
        system: the linear system (concrete arrays).
        method: ``"auto"``, ``"cg"``, ``"cholesky"``, ``"eigh"``, ``"mmode"`` or ``"dataspace"``.
        options: options of one path (:mod:`gcrsky.solvers.options`).
        tol: CG tolerance in posterior-sigma units.
        ndraws: draws per batch (sizes the memory check).
        memory_budget: bytes the path may use (default: what is free on the device).
    """
    if method == "auto" and options is not None:
        method = method_of(options)
    if method == "auto":
        plan = plan_sampler(system, ndraws=ndraws, budget=memory_budget)
        logging.getLogger("gcrsky").info("sampler path: %s (%s)", plan.method, plan.reason)
        chosen = options_for(plan.method, plan.options, tol=tol)
    else:
        chosen = options_for(method, options, tol=tol)
        if method == "mmode":
            chk = mmode_check(system, atol=chosen.atol, rtol=chosen.rtol)
            if not chk.ok:
                raise ValueError(f"method='mmode' needs P block-diagonal in m, but {chk.reason}; use method='auto'")
        if method == "dataspace":
            check_proper_prior(system)
        dense = chosen.dense if isinstance(chosen, CGOptions) else True
        rank = chosen.rank if isinstance(chosen, CGOptions) else CGOptions.rank
        need = path_memory_bytes(system, method, dense=dense, ndraws=ndraws, rank=rank)
        alt = ("use method='cg' with options=CGOptions(dense=False) (matrix-free) or method='auto'"
               if (method != "cg" or dense) else "draw in smaller batches or shard the baselines (gcrsky.parallel)")
        check_memory(need, f"method={method!r}" + (" (dense P)" if method == "cg" and dense else ""), alt,
                     budget=memory_budget)
    if isinstance(chosen, CGOptions):  # validates the choice and warns about a flat prior
        pc = resolve_preconditioner(system, chosen.preconditioner)
        chosen = dataclasses.replace(chosen, preconditioner=pc)
    return chosen
