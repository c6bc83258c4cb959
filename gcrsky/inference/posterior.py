"""Posterior mean and exact draws of a :class:`~gcrsky.model.LinearSystem`, on any exact path.

The system tier: pure functions of a system, usable inside a user's ``jit`` (pick the
path yourself; :mod:`gcrsky.inference.api` chooses it by size for a
:class:`~gcrsky.model.Problem`).

* :func:`prepare_sampler` sets a path up once (factor / preconditioner and the
  Wiener filter) and returns its typed state (:class:`~gcrsky.solvers.CGState`,
  :class:`~gcrsky.solvers.CholeskyState`, :class:`~gcrsky.solvers.EighState`,
  :class:`~gcrsky.solvers.MModeState`, :class:`~gcrsky.solvers.DataSpaceState`);
  :func:`draw` takes any of them.
* :func:`sample_system` is both in one call; :func:`wiener_filter_system` the mean.

Every path returns ``a_wf + delta`` with ``Cov(delta) = P^-1`` exactly.  Draw ``i``
of a CG, Cholesky or data-space batch uses ``jax.random.split(key, ndraws)[i]`` (the eigen and
m-mode paths draw their normals as one array from ``key``): a fixed key
reproduces the draws, and different paths give different (equally exact) draws.
"""

from __future__ import annotations

from typing import Union

import jax

from ..model.system import LinearSystem
from ..solvers.cg import CGState, draw_cg, prepare_cg, wiener_cg
from ..solvers.dataspace import DataSpaceState, draw_dataspace, prepare_dataspace
from ..solvers.dense import CholeskyState, EighState, draw_cholesky, draw_eigh, prepare_cholesky, prepare_eigh
from ..solvers.mmode import MModeState, draw_mmode, prepare_mmode
from ..solvers.options import CGOptions, SolverOptions, method_of, options_for

__all__ = ["SamplerState", "draw", "prepare_sampler", "sample_system", "wiener_filter_system"]

#: The state of any prepared exact path (its ``method`` attribute names the path).
SamplerState = Union[CGState, CholeskyState, EighState, MModeState, DataSpaceState]

_PREPARE = {"cg": prepare_cg, "cholesky": prepare_cholesky, "eigh": prepare_eigh, "mmode": prepare_mmode,
            "dataspace": prepare_dataspace}
_DRAW = {CGState: draw_cg, CholeskyState: draw_cholesky, EighState: draw_eigh, MModeState: draw_mmode,
         DataSpaceState: draw_dataspace}


def _options(method: str | None, options: SolverOptions | None, tol: float | None) -> SolverOptions:
    if method is None:
        method = method_of(options) if options is not None else "cg"
    return options_for(method, options, tol=tol)


def prepare_sampler(
    system: LinearSystem,
    *,
    method: str | None = None,
    options: SolverOptions | None = None,
    tol: float | None = None,
) -> SamplerState:
    """Set up one exact path once: factor / precondition P and solve for the Wiener filter.

    Args:
        system: the linear system.
        method: ``"cg"`` (the default when neither ``method`` nor ``options`` is
            given), ``"cholesky"``, ``"eigh"``, ``"mmode"`` or ``"dataspace"``.  ``"mmode"``
            is exact only when :func:`gcrsky.solvers.mmode_check` passes; it is checked on
            concrete arrays (under a trace, check beforehand).  ``"dataspace"`` needs a
            proper prior (refused on concrete arrays otherwise).
        options: the path's options (:mod:`gcrsky.solvers.options`); implies the path.
        tol: CG tolerance in posterior-sigma units (overrides ``options.tol``).

    Returns:
        the path's state; pass it to :func:`draw` as often as needed.
    """
    opts = _options(method, options, tol)
    return _PREPARE[method_of(opts)](system, opts)


def draw(key: jax.Array, prepared: SamplerState, ndraws: int):
    """``ndraws`` exact posterior draws from a prepared path (any :data:`SamplerState`).

    Returns:
        draws (Nf, ndraws, n); info dict: ``"wiener"`` (SolveInfo over (Nf,)),
        ``"draws"`` (SolveInfo over (Nf, ndraws)) and ``"a_wf"`` (Nf, n).
    """
    fn = _DRAW.get(type(prepared))
    if fn is None:
        raise TypeError(f"draw() needs a state from prepare_sampler / gcrsky.prepare, got {type(prepared).__name__}")
    return fn(key, prepared, int(ndraws))


def sample_system(
    key: jax.Array,
    system: LinearSystem,
    ndraws: int,
    *,
    method: str | None = None,
    options: SolverOptions | None = None,
    tol: float | None = None,
):
    """GCR draws from the exact posterior ``N(a_wf, P^-1)``: :func:`prepare_sampler` then :func:`draw`.

    * cg: ``delta`` solves ``P delta = (GCR fluctuation rhs)`` (mean zero, O(1 sigma)
      in every direction, so ``tol`` is directly a fraction of a posterior sigma);
      ``a_wf`` by CG too.  ``CGOptions(dense=True)`` forms P once (O(n^2) per
      matvec); ``dense=False`` is matrix-free (O(Nt Nbl n) per matvec).
    * cholesky: ``delta = L^-T z``.
    * eigh: ``delta = V_r Lambda_r^-1/2 z``; for a singular P see
      :mod:`gcrsky.solvers.dense`.
    * mmode: ``delta = L_m^-T z`` block by block.
    * dataspace: ``delta = delta_u - S X^T W^1/2 D^-1 (W^1/2 X delta_u + z)`` with
      ``delta_u ~ N(0, S)``, ``z ~ N(0, I)`` and ``D = I + W^1/2 X S X^T W^1/2``
      (Hoffman & Ribak; :mod:`gcrsky.solvers.dataspace`).

    For many batches, call :func:`prepare_sampler` once and :func:`draw` per batch.

    Returns:
        as :func:`draw`.
    """
    return draw(key, prepare_sampler(system, method=method, options=options, tol=tol), ndraws)


def wiener_filter_system(
    system: LinearSystem,
    *,
    method: str | None = None,
    options: SolverOptions | None = None,
    tol: float | None = None,
):
    """Wiener filter (posterior mean) ``P^-1 (X^T W d + S^-1 a0)`` on one exact path.

    CG (the default) starts at the prior mean and never forms the factors the draws
    need; the direct paths solve with their factor.

    Returns:
        (a_wf (Nf, n), SolveInfo with (Nf,) fields).
    """
    opts = _options(method, options, tol)
    if isinstance(opts, CGOptions):
        return wiener_cg(system, opts)
    state = _PREPARE[method_of(opts)](system, opts)
    return state.a_wf, state.wiener
