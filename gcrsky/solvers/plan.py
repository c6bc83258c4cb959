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
  ``O(Nf Nbl lmax^3)`` to build and ``~(32/3) Nf lmax^3`` bytes, built and factorised by
  buckets of orders (:func:`gcrsky.solvers.mmode.mmode_memory`).
* ``"cholesky"``: dense ``P`` built once by m-blocks (``~8 Nf Nbl n^2`` flop whatever
  Nt, :func:`gcrsky.model.system.precision_matrix`; ``8 Nf n^2`` bytes, three times that with
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
:func:`gcrsky.sample`), over the paths of :mod:`gcrsky.solvers.registry`: of the direct
paths that are exact for the system (:meth:`~gcrsky.solvers.path.SolverPath.check`) and
within the planner's limits (:meth:`~gcrsky.solvers.path.SolverPath.auto_limits`: m-mode
and Cholesky need a proper prior; dense paths ``n <= DENSE_MAX_N`` and their set-up
within :data:`DENSE_MEMORY_FRACTION` of the available memory; data space ``N_d < n``,
``N_d <= DATASPACE_MAX_ND`` and D within the same fraction), the one with the smallest
estimated cost of set-up plus :data:`PLAN_DRAWS` draws
(:meth:`~gcrsky.solvers.path.SolverPath.cost_flop`); else matrix-free CG.  So m-mode
wins wherever it is exact, Cholesky over the eigen sampler for a proper prior, the eigen
sampler for a flat one.  The crossovers are measured in ``benchmarks/scale.py``: at lmax 50
(n = 2601) Cholesky set-up is 2-9 s and a draw 2-3 ms against 40-600 ms per draw for
matrix-free CG, so dense wins wherever it fits; ``DENSE_MAX_N`` = 24000 keeps the
``n^3 / 3`` factorisation under ~2.5 min (n = 22801: P 94 s, factor 127 s on one
OpenBLAS thread, which n > :data:`~gcrsky.solvers.dense.OPENBLAS_SAFE_N` needs: the
dense path is only chosen there when ``OPENBLAS_NUM_THREADS=1``).
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np

from ..base.memory import available_memory_bytes, check_memory
from ..model.operator import n_in
from ..model.system import LinearSystem
from .cg import CGOptions
from .dataspace import DATASPACE_MAX_ND
from .dense import DENSE_MAX_N
from .joint import JointSystem, data_system
from .mmode import mmode_check
from .path import AUTO_MEMORY_FRACTION, SolverPath, has_flat_prior
from .registry import PATHS, SolverOptions, joint_methods, method_of, options_for, path_of

__all__ = [
    "DATASPACE_MAX_ND",
    "DENSE_MAX_N",
    "PLAN_DRAWS",
    "DENSE_MEMORY_FRACTION",
    "JointPlan",
    "SamplerPlan",
    "choose_joint_path",
    "choose_path",
    "path_cost_flop",
    "path_memory_bytes",
    "plan_sampler",
]

log = logging.getLogger(__name__)

#: Fraction of the available memory a direct path's set-up peak may take under "auto".
DENSE_MEMORY_FRACTION = AUTO_MEMORY_FRACTION
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


def path_memory_bytes(system: LinearSystem, method: str, *, dense: bool = True, ndraws: int = 1,
                      sketch_size: int | None = None, rank: int | None = None) -> float:
    """Estimated peak bytes of a path's large arrays (float64), beyond the system
    (:meth:`gcrsky.solvers.path.SolverPath.memory_bytes` with the path's default options).

    ``dense`` and ``sketch_size`` describe the CG path (:class:`~gcrsky.solvers.CGOptions`;
    ``rank`` is the deprecated name of ``sketch_size``).
    """
    path = path_of(method)
    options = path.options_type()
    if not path.direct:
        size = sketch_size if sketch_size is not None else (rank if rank is not None else options.sketch_size)
        options = CGOptions(dense=dense, sketch_size=size)
    return path.memory_bytes(system, options, ndraws)


def path_cost_flop(system: LinearSystem, method: str, *, ndraws: int = PLAN_DRAWS) -> float:
    """Estimated floating-point operations of a direct path's set-up plus ``ndraws`` draws (all channels)
    (:meth:`gcrsky.solvers.path.SolverPath.cost_flop` with the path's default options).

    Rough but of the right order (the planner compares them): ``"cholesky"`` / ``"eigh"``:
    P by m-blocks (``8 Nf Nbl n^2``, :func:`gcrsky.model.system.precision_matrix`) and its factor
    (``Nf n^3 / 3``; ``9 Nf n^3`` for the eigen-decomposition), then ``2 n^2`` per draw;
    ``"dataspace"``: :meth:`gcrsky.solvers.dataspace.DataSpacePath.cost_flop`; ``"mmode"``: the
    blocks and their factors.
    """
    path = path_of(method)
    return path.cost_flop(system, path.options_type(), ndraws)


def _candidates(system: LinearSystem, ndraws: int, avail: float):
    """The direct paths ``method="auto"`` may choose, ``(cost, path, options, memory)``, and why not the others."""
    chosen, notes = [], []
    for path in PATHS.values():
        if not path.direct:
            continue
        opts = path.options_type()
        why = path.check(system, opts) or path.auto_limits(system, opts, avail, ndraws)
        if why:
            notes.append(f"not {path.name}: {why}")
            continue
        chosen.append((path.cost_flop(system, opts, PLAN_DRAWS), path, opts, path.memory_bytes(system, opts, ndraws)))
    return chosen, notes


def _fallback(system: LinearSystem, ndraws: int, avail: float, notes) -> SamplerPlan:
    """Matrix-free CG (m-blocks for a flat prior), memory checked."""
    nf, n = int(system.data.shape[0]), n_in(system.op)
    path: SolverPath = next(p for p in PATHS.values() if not p.direct)
    opts = path.options_type(dense=False, preconditioner="mblock" if has_flat_prior(system) else "nystrom")
    mem = path.memory_bytes(system, opts, ndraws)
    check_memory(mem, f"matrix-free CG ({ndraws} draws per batch, n = {n}, Nf = {nf})",
                 "draw in smaller batches (ndraws) or shard the baselines (gcrsky.parallel)", budget=avail)
    return SamplerPlan(opts, mem, "; ".join([path.describe(system, opts, mem), *notes]))


def plan_sampler(system: LinearSystem, *, ndraws: int = 1, budget: float | None = None) -> SamplerPlan:
    """The cheapest exact path for ``system`` (host-side; call outside ``jit``).

    Args:
        system: the linear system (concrete arrays).
        ndraws: draws per batch (sizes the CG work vectors).
        budget: bytes available; default :func:`available_memory_bytes`.

    Returns:
        a :class:`SamplerPlan` whose reason names the chosen path's sizes, its estimated cost
        against the other candidates, and why each other direct path was not chosen; raises
        :class:`~gcrsky.base.InsufficientMemoryError` if even the matrix-free path does not fit.
    """
    avail = available_memory_bytes() if budget is None else float(budget)
    candidates, notes = _candidates(system, ndraws, avail)
    if not candidates:
        return _fallback(system, ndraws, avail, notes)
    candidates.sort(key=lambda c: c[0])
    cost, path, opts, mem = candidates[0]
    others = [f"{p.name} ({c:.2g})" for c, p, _, _ in candidates[1:]]
    why = f"{path.describe(system, opts, mem)}; est. {cost:.2g} flop for set-up + {PLAN_DRAWS} draws"
    if others:
        why += f", cheaper than {', '.join(others)}"
    return SamplerPlan(opts, mem, "; ".join([why, *notes]))


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

    * ``method="auto"`` without options follows :func:`plan_sampler` (the cheapest exact
      path that fits, else matrix-free CG) and logs its choice and the reason at INFO.
    * Options alone (``method="auto"``) select their path; ``method`` and options of
      another path are an error.
    * An explicit path is used as given, after checking that it applies
      (:meth:`~gcrsky.solvers.path.SolverPath.resolve`: e.g. ``"mmode"`` raises
      ``ValueError`` with the reason when P is not block-diagonal in m, ``"dataspace"`` for a
      flat prior) and that its large arrays fit
      (:class:`~gcrsky.base.InsufficientMemoryError` otherwise, naming the alternative).
    * ``tol`` sets the CG tolerance (the direct paths keep their options' ``tol``).

    CG options come back with ``preconditioner`` resolved (Nystrom for a proper
    prior, m-blocks for a flat one; a warning is logged for a flat prior).

    Args:
        system: the linear system (concrete arrays).
        method: ``"auto"`` or a path name (:data:`gcrsky.solvers.METHODS`).
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
        path = path_of(chosen)
        chosen = path.resolve(system, chosen)
        need = path.memory_bytes(system, chosen, ndraws)
        dense = getattr(chosen, "dense", True)
        alt = ("use method='cg' with options=CGOptions(dense=False) (matrix-free) or method='auto'"
               if (path.direct or dense) else "draw in smaller batches or shard the baselines (gcrsky.parallel)")
        check_memory(need, f"method={method!r}" + (" (dense P)" if not path.direct and dense else ""), alt,
                     budget=memory_budget)
        return chosen
    return path_of(chosen).resolve(system, chosen)


class JointPlan(NamedTuple):
    """What :func:`choose_joint_path` chose: the path's name (:data:`~gcrsky.solvers.registry.PATHS`),
    the form of its joint flavour (``"dense"``, ``"mmode"``, ``"cg"``, ...) and its estimated memory
    (bytes; NaN for the iterative path)."""

    method: str
    variant: str
    memory_bytes: float


def choose_joint_path(joint: JointSystem, method: str = "auto") -> JointPlan:
    """The exact joint path of ``method`` for a frequency-coupled system, its memory checked.

    ``auto``: with uniform full-day coverage (:func:`gcrsky.solvers.mmode_check`) the per-order forms,
    else the dense ones; of the direct paths' forms (:meth:`~gcrsky.solvers.path.SolverPath.joint_variants`:
    a-space ``mmode`` / ``cholesky``, data space ``dataspace``) the narrower factor that fits in memory;
    where none fits, the iterative path (CG, :mod:`gcrsky.solvers.joint_cg`: matrix-free, its error
    bounded by its stop).  A named path: its own forms (``cholesky``: dense a-space, ``mmode``: per order,
    checked; ``dataspace``: per order where the coverage allows), or the iterative path as asked.

    Args:
        joint: the :class:`~gcrsky.solvers.joint.JointSystem` (concrete arrays).
        method: ``"auto"`` or the name of a path with a joint flavour
            (:func:`gcrsky.solvers.registry.joint_methods`, read at call time).

    Raises:
        ValueError: a method no joint path serves, or one that does not apply (``mmode`` off full day).
        InsufficientMemoryError: the form asked for does not fit.
    """
    names = joint_methods()
    if method not in ("auto", *names):
        raise ValueError(f"a frequency prior samples all channels jointly by {', '.join(names)} (or auto), "
                         f"not --method {method}")
    ok = mmode_check(data_system(joint))
    full_day = bool(ok)
    if method != "auto":
        path = PATHS[method]
        why = path.joint_check(joint, ok)
        if why:
            raise ValueError(why)
        if not path.direct:
            return JointPlan(method, method, float("nan"))
        paths = [path]
    else:
        paths = [p for p in PATHS.values() if p.joint and p.direct]
    # the narrower factor first; equal widths keep the registry's order (a-space before data space)
    cands = sorted(((p.name, v) for p in paths for v in p.joint_variants(joint, full_day, method != "auto")),
                   key=lambda c: c[1].width)
    budget = available_memory_bytes()
    for name, v in cands:
        if v.memory <= budget:
            return JointPlan(name, v.variant, v.memory)
    if method == "auto":
        iterative = next(name for name, p in PATHS.items() if p.joint and not p.direct)
        log.info("no direct joint path fits in %.3g GB: %s", budget / 2**30, iterative)
        return JointPlan(iterative, iterative, float("nan"))
    name, v = cands[0]
    check_memory(v.memory, f"the joint path {name} ({v.variant}) over {np.shape(joint.data)[0]} channels",
                 "use fewer channels (--freq-range, --chans), a lower --lmax, or fewer times or baselines",
                 budget=budget)
    return JointPlan(name, v.variant, v.memory)
