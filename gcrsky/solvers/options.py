"""One options object per exact solver path.

Each path's knobs live in one frozen, hashable dataclass, so they travel through
``jax.jit`` as a single static argument, are validated once (a bad value is a
``ValueError`` naming it) and cannot drift apart between modules:

- ``"cg"``: :class:`CGOptions`: ``tol``, ``maxiter``, ``dense``, ``preconditioner``, ``rank``, ``pc_dtype``
- ``"cholesky"``: :class:`CholeskyOptions` (no knobs: the factorisation is exact)
- ``"eigh"``: :class:`EighOptions`: ``rcond``
- ``"mmode"``: :class:`MModeOptions`: ``atol``, ``rtol`` of the structural check

:func:`options_for` gives the default options of a path name and checks that
options handed in belong to it.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal, Union

__all__ = [
    "DEFAULT_TOL",
    "EIGH_RCOND",
    "METHODS",
    "CGOptions",
    "CholeskyOptions",
    "EighOptions",
    "MModeOptions",
    "SolverOptions",
    "method_of",
    "options_for",
]

#: CG tolerance in posterior-sigma units (the P-norm of the error; a rigorous bound
#: with the Nystrom preconditioner).
DEFAULT_TOL = 1e-6

#: Eigen sampler: eigenvalues below ``EIGH_RCOND * max eigenvalue`` count as zero.  Just
#: above the eigensolver's rounding floor (~n * 1e-16 relative for n ~ 500): every
#: direction the data inform, however weakly, is sampled.
EIGH_RCOND = 1e-12

#: The exact paths, by name.
METHODS = ("cg", "cholesky", "eigh", "mmode")


def _positive(name: str, value, *, integer: bool = False) -> None:
    ok = isinstance(value, int) and not isinstance(value, bool) if integer else isinstance(value, (int, float))
    if not ok or not (value > 0) or (not integer and not math.isfinite(value)):
        kind = "a positive integer" if integer else "a positive finite number"
        raise ValueError(f"{name} must be {kind}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class CGOptions:
    """Preconditioned conjugate gradients (:mod:`gcrsky.solvers.cg`).

    Attributes:
        tol: stop when ``sqrt(r^T M^-1 r) <= tol``, posterior-sigma units (with the
            Nystrom preconditioner a rigorous bound on the error's P-norm, hence on
            every mode's error in units of its posterior std; with m-blocks an
            estimate, so pass a smaller ``tol`` there).
        maxiter: cap on iterations per solve (both passes of the residual restart).
        dense: form the dense P once (fast for n up to a few thousand) or stay
            matrix-free (O(Nf Nt Nbl n) per product, no n^2 memory).
        preconditioner: ``"auto"`` (Nystrom when every mode has a proper prior, else
            m-blocks; decided on concrete arrays by
            :func:`gcrsky.solvers.preconditioners.resolve_preconditioner`, and
            ``"nystrom"`` inside a trace), ``"nystrom"`` or ``"mblock"``.
        rank: Nystrom sketch size (clipped to n).
        pc_dtype: ``"float64"`` or ``"float32"`` storage of the preconditioner (CG
            itself stays float64; float32 only costs iterations,
            ``benchmarks/float32.py``).
    """

    tol: float = DEFAULT_TOL
    maxiter: int = 5000
    dense: bool = True
    preconditioner: Literal["auto", "nystrom", "mblock"] = "auto"
    rank: int = 128
    pc_dtype: Literal["float64", "float32"] = "float64"

    method = "cg"

    def __post_init__(self):
        _positive("tol", self.tol)
        _positive("maxiter", self.maxiter, integer=True)
        _positive("rank", self.rank, integer=True)
        if not isinstance(self.dense, bool):
            raise ValueError(f"dense must be True or False, got {self.dense!r}")
        if self.preconditioner not in ("auto", "nystrom", "mblock"):
            raise ValueError(f"preconditioner must be 'auto', 'nystrom' or 'mblock', got {self.preconditioner!r}")
        if self.pc_dtype not in ("float64", "float32"):
            raise ValueError(f"pc_dtype must be 'float64' or 'float32', got {self.pc_dtype!r}")


@dataclasses.dataclass(frozen=True)
class CholeskyOptions:
    """Dense Cholesky factorisation of P (:mod:`gcrsky.solvers.dense`); exact, no knobs."""

    method = "cholesky"


@dataclasses.dataclass(frozen=True)
class EighOptions:
    """Eigen-decomposition of the dense P (:mod:`gcrsky.solvers.dense`).

    Attributes:
        rcond: eigenvalues below ``rcond * max`` are treated as zero (a singular P,
            e.g. a flat prior: those directions are pinned at 0).
    """

    rcond: float = EIGH_RCOND

    method = "eigh"

    def __post_init__(self):
        if not isinstance(self.rcond, (int, float)) or not (0 <= self.rcond < 1):
            raise ValueError(f"rcond must be in [0, 1), got {self.rcond!r}")


@dataclasses.dataclass(frozen=True)
class MModeOptions:
    """Exact m-mode block solves (:mod:`gcrsky.solvers.mmode`).

    Attributes:
        atol: tolerance of ``|mean_t exp(i k t)|`` for uniform full-day coverage.
        rtol: tolerance on the time variation of the inverse noise, relative to its
            maximum.
    """

    atol: float = 1e-10
    rtol: float = 1e-12

    method = "mmode"

    def __post_init__(self):
        _positive("atol", self.atol)
        _positive("rtol", self.rtol)


SolverOptions = Union[CGOptions, CholeskyOptions, EighOptions, MModeOptions]

_BY_METHOD = {"cg": CGOptions, "cholesky": CholeskyOptions, "eigh": EighOptions, "mmode": MModeOptions}


def method_of(options: SolverOptions) -> str:
    """The path name (``"cg"``, ``"cholesky"``, ``"eigh"``, ``"mmode"``) of an options object."""
    if type(options) not in _BY_METHOD.values():
        raise TypeError(
            f"options must be CGOptions, CholeskyOptions, EighOptions or MModeOptions, got {type(options).__name__}"
        )
    return options.method


def options_for(method: str, options: SolverOptions | None = None, *, tol: float | None = None) -> SolverOptions:
    """The options of path ``method``: ``options`` checked against it, or the defaults.

    Args:
        method: ``"cg"``, ``"cholesky"``, ``"eigh"`` or ``"mmode"``.
        options: options for that path, or None for its defaults.
        tol: if given, the CG tolerance (replaces ``options.tol``); ignored by the
            direct paths, which are exact.

    Raises:
        ValueError: unknown method, or options of another path.
    """
    if method not in _BY_METHOD:
        raise ValueError(f"method must be one of {', '.join(map(repr, METHODS))}, got {method!r}")
    if options is None:
        options = _BY_METHOD[method]()
    elif method_of(options) != method:
        raise ValueError(f"method={method!r} was given {type(options).__name__} (options of method={options.method!r})")
    if tol is not None and isinstance(options, CGOptions) and tol != options.tol:
        options = dataclasses.replace(options, tol=float(tol))
    return options
