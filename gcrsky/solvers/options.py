"""One options object per exact solver path.

Each path's knobs live in one frozen, hashable dataclass, so they travel through
``jax.jit`` as a single static argument, are validated once (a bad value is a
``ValueError`` naming it) and cannot drift apart between modules:

- ``"cg"``: :class:`CGOptions`: ``tol``, ``maxiter``, ``dense``, ``preconditioner``, ``bandwidth``, ``rank``, ``pc_dtype``,
  ``engine``, ``throw``
- ``"cholesky"``: :class:`CholeskyOptions`: ``throw`` (the factorisation is exact)
- ``"eigh"``: :class:`EighOptions`: ``rcond``, ``throw``
- ``"mmode"``: :class:`MModeOptions`: ``atol``, ``rtol`` of the structural check, ``throw``
- ``"dataspace"``: :class:`DataSpaceOptions`: ``time_chunk``, ``stationary``, ``materialize``, ``throw``

Every direct path's options carry ``tol``: the accuracy (posterior sigma, measured from
the true residual) its solve must reach to be reported converged.  ``throw=True`` makes a
failed solve an error inside ``jit`` (``equinox.error_if``; reliable on CPU, where the
check runs in the host callback before results are returned) instead of a flag in
:class:`~gcrsky.solvers.SolveInfo`.

:func:`gcrsky.solvers.registry.options_for` (in :mod:`gcrsky.solvers.registry`, which knows every
path) gives the default options of a path name and checks that options handed in belong
to it.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Literal

__all__ = [
    "DEFAULT_TOL",
    "EIGH_RCOND",
    "CGOptions",
    "CholeskyOptions",
    "DataSpaceOptions",
    "EighOptions",
    "MModeOptions",
    "SLQOptions",
]

#: CG tolerance in posterior-sigma units (the P-norm of the error; a rigorous bound
#: with the Nystrom preconditioner).
DEFAULT_TOL = 1e-6

#: Eigen sampler: eigenvalues below ``EIGH_RCOND * max eigenvalue`` count as zero.  Just
#: above the eigensolver's rounding floor (~n * 1e-16 relative for n ~ 500): every
#: direction the data inform, however weakly, is sampled.
EIGH_RCOND = 1e-12


def _positive(name: str, value, *, integer: bool = False) -> None:
    ok = isinstance(value, int) and not isinstance(value, bool) if integer else isinstance(value, (int, float))
    if not ok or not (value > 0) or (not integer and not math.isfinite(value)):
        kind = "a positive integer" if integer else "a positive finite number"
        raise ValueError(f"{name} must be {kind}, got {value!r}")


def _check_direct(options) -> None:
    """Validate the fields every direct path's options share (``throw``, ``tol``)."""
    if not isinstance(options.throw, bool):
        raise ValueError(f"throw must be True or False, got {options.throw!r}")
    _positive("tol", options.tol)


@dataclasses.dataclass(frozen=True)
class CGOptions:
    """Preconditioned conjugate gradients (:mod:`gcrsky.solvers.cg`).

    Attributes:
        tol: stop when ``sqrt(r^T M^-1 r) <= tol``, posterior-sigma units (with the
            Nystrom preconditioner a rigorous bound on the error's P-norm, hence on
            every mode's error in units of its posterior std; with m-blocks an
            estimate, so pass a smaller ``tol`` there).  With ``"window"`` (no
            ``M <= P``) the stop is ``sqrt(r^T S r) <= tol`` instead, S the prior
            covariance: rigorous since ``P >= S^-1``, and never looser than the error's
            P-norm.
        maxiter: cap on iterations per solve (both passes of the residual restart).
        dense: form the dense P once (fast for n up to a few thousand) or stay
            matrix-free (O(Nf Nt Nbl n) per product, no n^2 memory).
        preconditioner: ``"auto"`` (Nystrom when every mode has a proper prior, else
            m-blocks; decided on concrete arrays by
            :func:`gcrsky.solvers.preconditioners.resolve_preconditioner`, and
            ``"nystrom"`` inside a trace), ``"nystrom"``, ``"mblock"`` or ``"window"``
            (:mod:`gcrsky.solvers.window`: P's data term with a Fejer-tapered window
            kernel, block-banded in m; proper prior and no frame map needed; helps only
            at large coverage fractions of the day, ``benchmarks/window_pc.py``; never
            chosen by ``"auto"``).
        bandwidth: the window preconditioner's bandwidth B in m (an integer >= 0), or
            ``"auto"`` (:func:`gcrsky.solvers.window.auto_bandwidth`, from the decay of
            the window kernel ``|K(D)| / K(0)``; 8 under a trace).  Ignored by the others.
        sketch_size: Nystrom sketch size, the number of directions sketched (clipped to n).
            ``rank=`` is accepted as its old name, with a DeprecationWarning.
        pc_dtype: ``"float64"`` or ``"float32"`` storage of the preconditioner (CG
            itself stays float64; float32 only costs iterations,
            ``benchmarks/float32.py``).
        engine: ``"gcrsky"`` (this package's CG: iteration counts, the posterior-sigma
            stopping rule, a residual restart) or ``"jax"``
            (``jax.scipy.sparse.linalg.cg`` with the same preconditioner; its 2-norm
            stopping rule is set so that it implies ``tol``, and the
            :class:`~gcrsky.solvers.SolveInfo` is computed from the true residual of its
            answer, ``iterations = -1``).  Both differentiate implicitly.
        throw: raise (through ``equinox.error_if``) when a solve does not converge.
    """

    tol: float = DEFAULT_TOL
    maxiter: int = 5000
    dense: bool = True
    preconditioner: Literal["auto", "nystrom", "mblock", "window"] = "auto"
    sketch_size: int = 128
    pc_dtype: Literal["float64", "float32"] = "float64"
    engine: Literal["gcrsky", "jax"] = "gcrsky"
    throw: bool = False
    bandwidth: int | Literal["auto"] = "auto"

    method = "cg"

    def __post_init__(self):
        if self.engine not in ("gcrsky", "jax"):
            raise ValueError(f"engine must be 'gcrsky' or 'jax', got {self.engine!r}")
        if not isinstance(self.throw, bool):
            raise ValueError(f"throw must be True or False, got {self.throw!r}")
        _positive("tol", self.tol)
        _positive("maxiter", self.maxiter, integer=True)
        _positive("sketch_size", self.sketch_size, integer=True)
        if not isinstance(self.dense, bool):
            raise ValueError(f"dense must be True or False, got {self.dense!r}")
        if self.preconditioner not in ("auto", "nystrom", "mblock", "window"):
            raise ValueError(f"preconditioner must be 'auto', 'nystrom', 'mblock' or 'window', got {self.preconditioner!r}")
        bw = self.bandwidth
        if bw != "auto" and (isinstance(bw, bool) or not isinstance(bw, int) or bw < 0):
            raise ValueError(f"bandwidth must be 'auto' or an integer >= 0, got {bw!r}")
        if self.pc_dtype not in ("float64", "float32"):
            raise ValueError(f"pc_dtype must be 'float64' or 'float32', got {self.pc_dtype!r}")


def _cg_rank(self) -> int:
    warnings.warn("CGOptions.rank is deprecated: use CGOptions.sketch_size", DeprecationWarning, stacklevel=2)
    return self.sketch_size


_cg_init = CGOptions.__init__


def _cg_init_rank(self, *args, rank: int | None = None, **kw):
    if rank is not None:  # the old name, for one release
        warnings.warn("CGOptions(rank=...) is deprecated: the Nystrom sketch size is CGOptions(sketch_size=...)",
                      DeprecationWarning, stacklevel=2)
        kw.setdefault("sketch_size", rank)
    _cg_init(self, *args, **kw)


_cg_init_rank.__doc__ = _cg_init.__doc__
CGOptions.__init__ = _cg_init_rank
CGOptions.rank = property(_cg_rank, doc="Deprecated name of :attr:`sketch_size`.")


@dataclasses.dataclass(frozen=True)
class CholeskyOptions:
    """Dense Cholesky factorisation of P (:mod:`gcrsky.solvers.dense`); exact.

    Attributes:
        throw: raise (through ``equinox.error_if``) when the factor is not finite
            (P not positive definite) or the solve misses ``tol``.
        inverse: form ``L^-T`` once so that a batch of draws is one matrix product
            (``n^3`` flop and ``8 n^2`` bytes more); ``False`` draws by a triangular
            solve per batch instead.  ``None``: only for ``n <=``
            :data:`gcrsky.solvers.dense.CHOLESKY_INVERSE_MAX_N`.
        tol: the accuracy the solve must reach to count as converged, in posterior
            sigma: the error estimate ``sqrt(r^T P^-1 r)`` of the Wiener filter from its
            true residual (rounding only: ~1e-9 on the standard case, 3e-8 at n = 22801).
    """

    throw: bool = False
    inverse: bool | None = None
    tol: float = DEFAULT_TOL

    method = "cholesky"

    def __post_init__(self):
        _check_direct(self)


@dataclasses.dataclass(frozen=True)
class EighOptions:
    """Eigen-decomposition of the dense P (:mod:`gcrsky.solvers.dense`).

    Attributes:
        rcond: eigenvalues below ``rcond * max`` are treated as zero (a singular P,
            e.g. a flat prior: those directions are pinned at 0).
        throw: raise (through ``equinox.error_if``) on a non-finite or inaccurate
            decomposition.
        tol: the accuracy the solve must reach to count as converged (posterior sigma,
            within the sampled subspace).
    """

    rcond: float = EIGH_RCOND
    throw: bool = False
    tol: float = DEFAULT_TOL

    method = "eigh"

    def __post_init__(self):
        _check_direct(self)
        if not isinstance(self.rcond, (int, float)) or not (0 <= self.rcond < 1):
            raise ValueError(f"rcond must be in [0, 1), got {self.rcond!r}")


@dataclasses.dataclass(frozen=True)
class MModeOptions:
    """Exact m-mode block solves (:mod:`gcrsky.solvers.mmode`).

    Attributes:
        atol: tolerance of ``|mean_t exp(i k t)|`` for uniform full-day coverage.
        rtol: tolerance on the time variation of the inverse noise, relative to its
            maximum.
        throw: raise (through ``equinox.error_if``) when a block factor is not finite or
            the solve misses ``tol`` (e.g. coverage that is not block-diagonal in m under a
            trace, where the structural check cannot run).
        tol: the accuracy the Wiener solve must reach, in posterior sigma, measured from its
            *true* (matrix-free) residual: any part of P off the m-blocks shows here.
        bucket: the blocks' padded half-size is a multiple of this (at most lmax+1); the
            orders sharing one padded size form a bucket, built and factorised together
            (:func:`gcrsky.solvers.mmode.mmode_buckets`).  Changes only speed and memory:
            32 pads the factors by 7 % at lmax 650 (21 buckets, 21 compiled shapes).
    """

    atol: float = 1e-10
    rtol: float = 1e-12
    throw: bool = False
    tol: float = DEFAULT_TOL
    bucket: int = 32

    method = "mmode"

    def __post_init__(self):
        _check_direct(self)
        _positive("atol", self.atol)
        _positive("rtol", self.rtol)
        _positive("bucket", self.bucket, integer=True)


@dataclasses.dataclass(frozen=True)
class DataSpaceOptions:
    """The exact data-space path (:mod:`gcrsky.solvers.dataspace`): everything through the
    ``N_d x N_d`` matrix ``D = I + W^1/2 X S X^T W^1/2``, for ``N_d < n`` (partial coverage
    at high lmax).  Needs a proper prior (``S^-1 > 0`` everywhere).

    Attributes:
        time_chunk: times whose rows are formed at once when D (or Y) is built; None:
            chosen from the free memory on concrete arrays
            (:func:`gcrsky.solvers.dataspace.choose_time_chunk`: 1 where Y is materialised,
            else the largest that fits, at most 8), under a trace as many as keep a chunk's
            rows under 512 MiB.  Changes only speed and memory (each time of a chunk holds
            ~40 copies of one channel-set of the response while it is formed).
        throw: raise (through ``equinox.error_if``) when the factor of ``D`` or the
            Wiener filter is not finite (e.g. a flat prior direction under a trace).
        stationary: build D by the stationary shortcut (one block per distinct lag
            between times; :func:`gcrsky.solvers.dataspace.lag_structure`) where it is
            exact, checked on concrete arrays; False: always the general construction.
        materialize: keep ``Y = W^1/2 X`` (``8 Nf N_d n`` bytes), formed once time by time,
            D then built from it and the draws' products with Y and ``Y^T`` matrix products
            over the batch; None: when it takes at most
            ``gcrsky.solvers.dataspace.ROWS_MAX_BYTES`` (4 GiB) and the set-up with it fits
            the free memory.  Changes only speed and memory.
        tol: the accuracy the Wiener solve must reach (posterior sigma, from its true
            primal residual) to count as converged.
        in_place: build D by per-order Grams and factorise it in its own (host) buffer, keeping
            only the factor (:mod:`gcrsky.solvers.dataspace_large`: ``8 Nf N_d^2`` bytes instead of
            ``~4x`` that; needs the stationary shortcut and concrete arrays); None: where the
            standard set-up does not fit the free memory and this one does.  Changes only speed
            and memory, and that ``log det D`` from such a state has no derivative.
        proxy: with a frame map (a file's ICRS coefficients), factorise the *stationary proxy*'s
            ``D0`` (the frame map's rotations without aberration: exact stationary structure for an
            isotropic prior) and solve with the true D by CG preconditioned with ``D0^-1``
            (:mod:`gcrsky.solvers.dataspace_proxy`: no rows, no exact D; stops on the rigorous bound
            ``||r||_2 <= tol``); None: wherever it applies (a frame map, an isotropic prior,
            concrete arrays); False: never (the general construction); True: required (``ValueError``
            naming why where it does not apply).  The evidence needs ``log det D``, which such a
            state does not have.
        maxiter: iterations a proxy CG solve may take (both passes together) before it is reported
            as not converged.
    """

    time_chunk: int | None = None
    throw: bool = False
    stationary: bool = True
    materialize: bool | None = None
    tol: float = DEFAULT_TOL
    in_place: bool | None = None
    proxy: bool | None = None
    maxiter: int = 200

    method = "dataspace"

    def __post_init__(self):
        _check_direct(self)
        if not isinstance(self.stationary, bool):
            raise ValueError(f"stationary must be True or False, got {self.stationary!r}")
        if self.materialize is not None and not isinstance(self.materialize, bool):
            raise ValueError(f"materialize must be None, True or False, got {self.materialize!r}")
        if self.in_place is not None and not isinstance(self.in_place, bool):
            raise ValueError(f"in_place must be None, True or False, got {self.in_place!r}")
        if self.proxy is not None and not isinstance(self.proxy, bool):
            raise ValueError(f"proxy must be None, True or False, got {self.proxy!r}")
        _positive("maxiter", self.maxiter, integer=True)
        if self.time_chunk is not None:
            _positive("time_chunk", self.time_chunk, integer=True)


@dataclasses.dataclass(frozen=True)
class SLQOptions:
    """Stochastic Lanczos quadrature of ``log det P`` on the matrix-free path (matfree).

    ``log det P = sum log S^-1 + log det(M) + log det(M^-1/2 (I + H) M^-1/2)`` with
    ``I + H`` the prior-whitened precision and ``M`` its rank-k Nystrom approximation
    (whose log-determinant is exact); only the last, nearly-identity term is
    estimated, with ``probes`` Rademacher probes and ``lanczos`` Lanczos steps each.

    Attributes:
        probes: number of random probes (the standard error falls as ``probes^-1/2``).
        lanczos: Lanczos steps per probe (the quadrature's bias falls exponentially).
        seed: the probes' PRNG seed (used when no key is passed).
    """

    probes: int = 32
    lanczos: int = 24
    seed: int = 0

    def __post_init__(self):
        _positive("probes", self.probes, integer=True)
        _positive("lanczos", self.lanczos, integer=True)
        if not isinstance(self.seed, int) or isinstance(self.seed, bool):
            raise ValueError(f"seed must be an integer, got {self.seed!r}")
