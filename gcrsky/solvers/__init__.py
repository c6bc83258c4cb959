"""Exact solver paths for the GCR system, one module each, and the planner that picks one.

- ``options``: one frozen options object per path (:class:`CGOptions`, ...)
- ``info``: :class:`SolveInfo`, what every solve reports
- ``preconditioners``: prior-whitened Nystrom and m-block preconditioners for CG
- ``window``: the window preconditioner (block-banded in m, Fejer-tapered window kernel)
- ``cg``: preconditioned CG (matrix-free or dense P): :func:`prepare_cg`, :func:`draw_cg`, :func:`wiener_cg`
- ``dense``: dense Cholesky and eigen-decomposition
- ``mmode``: block-by-block solves for uniform full-day coverage
- ``dataspace``: everything through the ``N_d x N_d`` matrix ``I + W^1/2 X S X^T W^1/2``
  (fewer data than parameters): :func:`prepare_dataspace`, :func:`draw_dataspace`
- ``slq``: stochastic Lanczos quadrature of the whitened log-determinant (CG's evidence)
- ``path``: :class:`SolverPath`, what every path answers (applicability, memory and cost,
  prepare / draw / condition on new data, the evidence's pieces)
- ``registry``: :data:`PATHS`, every path by name, and :func:`path_of`
- ``plan``: :func:`plan_sampler` / :func:`choose_path`: the cheapest exact path that fits in memory

Every path is one :class:`SolverPath` object in :data:`PATHS` (:class:`CGPath`,
:class:`CholeskyPath`, :class:`EighPath`, :class:`MModePath`, :class:`DataSpacePath`),
with its options (:class:`CGOptions`, ...) and its typed state (:class:`CGState`,
:class:`CholeskyState`, :class:`EighState`, :class:`MModeState`,
:class:`DataSpaceState`, each an equinox Module whose ``method`` names the path).
:mod:`gcrsky.inference`, :mod:`gcrsky.parallel` and the planner find a path with
:func:`path_of` and ask it; nothing else tests path names.
"""

from .cg import CGPath, CGState, cg_solve, draw_cg, pcg, prepare_cg, resolve_cg_options, solve_cg, wiener_cg
from .dataspace import (
    DATASPACE_MAX_ND,
    DataSpacePath,
    DataSpaceState,
    data_size,
    dataspace_evidence_parts,
    dataspace_matrix,
    dataspace_memory_bytes,
    draw_dataspace,
    prepare_dataspace,
)
from .dense import (
    DENSE_MAX_N,
    CholeskyPath,
    CholeskyState,
    EighPath,
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
from .mmode import MModePath, MModeState, draw_mmode, mmode_blocks, mmode_check, prepare_mmode
from .options import (
    DEFAULT_TOL,
    EIGH_RCOND,
    CGOptions,
    CholeskyOptions,
    DataSpaceOptions,
    EighOptions,
    MModeOptions,
    SLQOptions,
)
from .path import EvidenceParts, SolverPath
from .plan import (
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
    stop_norm,
)
from .registry import METHODS, PATHS, SolverOptions, method_of, options_for, path_of
from .window import WindowPreconditioner, auto_bandwidth, window_preconditioner

__all__ = [
    "DATASPACE_MAX_ND",
    "DEFAULT_TOL",
    "DENSE_MAX_N",
    "DENSE_MEMORY_FRACTION",
    "EIGH_RCOND",
    "METHODS",
    "PATHS",
    "PLAN_DRAWS",
    "WindowPreconditioner",
    "CGOptions",
    "CGPath",
    "CGState",
    "CholeskyOptions",
    "CholeskyPath",
    "CholeskyState",
    "DataSpaceOptions",
    "DataSpacePath",
    "DataSpaceState",
    "DrawInfo",
    "EighOptions",
    "EighPath",
    "EighState",
    "EvidenceParts",
    "MBlockPreconditioner",
    "MModeOptions",
    "MModePath",
    "MModeState",
    "NystromPreconditioner",
    "Result",
    "SLQOptions",
    "SamplerPlan",
    "SolveInfo",
    "SolverOptions",
    "SolverPath",
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
    "path_of",
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
    "stop_norm",
    "auto_bandwidth",
    "window_preconditioner",
    "wiener_cg",
]
