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

from .cg import CGPath, CGState
from .dataspace import DataSpacePath, DataSpaceState
from .dense import CholeskyPath, CholeskyState, EighPath, EighState
from .info import DrawInfo, SolveInfo
from .mmode import MModePath, MModeState, mmode_check
from .options import CGOptions, CholeskyOptions, DataSpaceOptions, EighOptions, MModeOptions, SLQOptions
from .path import EvidenceParts, SolverPath
from .plan import SamplerPlan, choose_path, path_cost_flop, path_memory_bytes, plan_sampler
from .registry import METHODS, PATHS, SolverOptions, path_of

__all__ = [
    "METHODS",
    "PATHS",
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
    "MModeOptions",
    "MModePath",
    "MModeState",
    "SLQOptions",
    "SamplerPlan",
    "SolveInfo",
    "SolverOptions",
    "SolverPath",
    "choose_path",
    "mmode_check",
    "path_of",
    "path_cost_flop",
    "path_memory_bytes",
    "plan_sampler",
]
