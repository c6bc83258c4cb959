"""The GCR step as a kernel for a user's JAX Gibbs loop (blackjax style).

``gcr_init(position) -> GCRState`` and ``gcr_step(key, state, system) -> (state, info)``
are pure and jittable, usable inside ``lax.scan``; the library does not jit for
you.  ``system`` may change between steps (e.g. a Gibbs update of the prior), so
each step draws exactly from the current conditional ``a | d, S, N, a0``.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..model.system import LinearSystem, fluctuation_rhs, precision_matrix, wiener_rhs
from ..solvers.cg import resolve_cg_options, solve_cg
from ..solvers.info import SolveInfo
from ..solvers.options import CGOptions
from ..solvers.preconditioners import make_preconditioner

__all__ = ["GCRState", "gcr_init", "gcr_step"]

#: The step's default: matrix-free CG (a dense P would be rebuilt every step).
STEP_OPTIONS = CGOptions(dense=False)


class GCRState(NamedTuple):
    """State of the GCR kernel: the current coefficients (Nf, n)."""

    position: jax.Array


def gcr_init(position: jax.Array) -> GCRState:
    """Start a chain at ``position`` (Nf, n), e.g. the prior mean."""
    return GCRState(jnp.asarray(position))


def gcr_step(
    key: jax.Array,
    state: GCRState,
    system: LinearSystem,
    *,
    tol: float | None = None,
    options: CGOptions | None = None,
    pc=None,
) -> tuple[GCRState, SolveInfo]:
    """One exact conditional draw ``a ~ p(a | d, S, N, a0)`` (pure; jit/scan it yourself).

    Solves the full GCR equation by preconditioned CG warm-started at the previous
    position (which is typically within a few posterior sigma of the new draw).

    Args:
        key: PRNG key of this step.
        state: the chain's :class:`GCRState`.
        system: the current linear system.
        tol: CG tolerance in posterior-sigma units (overrides ``options.tol``).
        options: :class:`~gcrsky.solvers.CGOptions`; default matrix-free
            (``dense=False``).  Its preconditioner (``"auto"`` means Nystrom under
            a trace, which needs ``S^-1 > 0`` in every mode; pass ``"mblock"`` for a
            flat prior) is rebuilt each step from ``system`` unless a prebuilt ``pc``
            is passed.  A stale ``pc`` (built for an earlier S) only costs
            iterations: the draw stays exact because convergence is checked
            against the current system.
        pc: optional prebuilt preconditioner (:mod:`gcrsky.solvers.preconditioners`).

    Returns:
        (GCRState, SolveInfo with (Nf,) fields).
    """
    options = STEP_OPTIONS if options is None else options
    if tol is not None:
        options = dataclasses.replace(options, tol=float(tol))
    options = resolve_cg_options(system, options)
    precision = precision_matrix(system) if options.dense else None
    if pc is None:
        pc = make_preconditioner(system, options.preconditioner, precision, options.rank, options.pc_dtype)
    b = wiener_rhs(system) + fluctuation_rhs(key, system)
    x, info = solve_cg(system, precision, pc, b, state.position, options)
    return GCRState(x), info
