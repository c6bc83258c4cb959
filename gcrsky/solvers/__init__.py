"""Exact solver paths for the GCR system, one module each, and the planner that picks one.

- ``options``: one frozen options object per path (:class:`CGOptions`, ...)
- ``info``: :class:`SolveInfo`, what every solve reports
- ``preconditioners``: prior-whitened Nystrom and m-block preconditioners for CG
- ``cg``: preconditioned CG (matrix-free or dense P): :func:`prepare_cg`, :func:`draw_cg`, :func:`wiener_cg`
- ``dense``: dense Cholesky and eigen-decomposition
- ``mmode``: block-by-block solves for uniform full-day coverage
- ``dataspace``: everything through the ``N_d x N_d`` matrix ``I + W^1/2 X S X^T W^1/2``
  (fewer data than parameters): :func:`prepare_dataspace`, :func:`draw_dataspace`
- ``plan``: :func:`plan_sampler` / :func:`choose_path`: the cheapest exact path that fits in memory

Every path is a pair ``prepare_*(system, options) -> State`` (set up once: factor or
preconditioner and the Wiener filter) and ``draw_*(key, state, ndraws)`` (exact
posterior draws), with one typed state per path (:class:`CGState`,
:class:`CholeskyState`, :class:`EighState`, :class:`MModeState`,
:class:`DataSpaceState`, each an equinox
Module whose ``method`` names the path).  :mod:`gcrsky.inference` dispatches on them.
"""

from .cg import CGState, cg_solve, draw_cg, pcg, prepare_cg, resolve_cg_options, solve_cg, wiener_cg
from .dataspace import (
    DataSpaceState,
    data_size,
    dataspace_evidence_parts,
    dataspace_matrix,
    dataspace_memory_bytes,
    draw_dataspace,
    prepare_dataspace,
)
from .dense import (
    CholeskyState,
    EighState,
    cholesky_logdet,
    cholesky_solve,
    draw_cholesky,
    draw_eigh,
    eigh_functions,
    prepare_cholesky,
    prepare_eigh,
)
from .info import DrawInfo, Result, SolveInfo, result_names
from .mmode import MModeState, draw_mmode, mmode_blocks, mmode_check, prepare_mmode
from .options import (
    DEFAULT_TOL,
    EIGH_RCOND,
    METHODS,
    CGOptions,
    CholeskyOptions,
    DataSpaceOptions,
    EighOptions,
    MModeOptions,
    SLQOptions,
    SolverOptions,
    method_of,
    options_for,
)
from .plan import (
    DATASPACE_MAX_ND,
    DENSE_MAX_N,
    DENSE_MEMORY_FRACTION,
    PLAN_DRAWS,
    SamplerPlan,
    choose_path,
    path_cost_flop,
    path_memory_bytes,
    plan_sampler,
)
from .preconditioners import (
    MBlockPreconditioner,
    NystromPreconditioner,
    apply_preconditioner,
    inverse_bound,
    m_block_preconditioner,
    make_preconditioner,
    nystrom_preconditioner,
    resolve_preconditioner,
)

__all__ = [
    "DATASPACE_MAX_ND",
    "DEFAULT_TOL",
    "DENSE_MAX_N",
    "DENSE_MEMORY_FRACTION",
    "EIGH_RCOND",
    "METHODS",
    "PLAN_DRAWS",
    "CGOptions",
    "CGState",
    "CholeskyOptions",
    "CholeskyState",
    "DataSpaceOptions",
    "DataSpaceState",
    "DrawInfo",
    "EighOptions",
    "EighState",
    "MBlockPreconditioner",
    "MModeOptions",
    "MModeState",
    "NystromPreconditioner",
    "Result",
    "SLQOptions",
    "SamplerPlan",
    "SolveInfo",
    "SolverOptions",
    "apply_preconditioner",
    "cg_solve",
    "cholesky_logdet",
    "cholesky_solve",
    "choose_path",
    "data_size",
    "dataspace_evidence_parts",
    "dataspace_matrix",
    "dataspace_memory_bytes",
    "draw_cg",
    "draw_cholesky",
    "draw_dataspace",
    "draw_eigh",
    "draw_mmode",
    "eigh_functions",
    "inverse_bound",
    "m_block_preconditioner",
    "make_preconditioner",
    "method_of",
    "mmode_blocks",
    "mmode_check",
    "nystrom_preconditioner",
    "options_for",
    "path_cost_flop",
    "path_memory_bytes",
    "pcg",
    "plan_sampler",
    "prepare_cg",
    "prepare_cholesky",
    "prepare_dataspace",
    "prepare_eigh",
    "prepare_mmode",
    "resolve_cg_options",
    "resolve_preconditioner",
    "result_names",
    "solve_cg",
    "wiener_cg",
]
