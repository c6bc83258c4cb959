"""Posterior mean and exact draws of a :class:`~gcrsky.model.LinearSystem`, on any exact path.

The system tier: pure functions of a system, usable inside a user's ``jit`` and ``vmap``
(pick the path yourself; :mod:`gcrsky.inference.api` chooses it by size for a
:class:`~gcrsky.model.Problem`).  Every path is found in :mod:`gcrsky.solvers.registry`.

* :func:`prepare_system` sets a path up once (factor / preconditioner and the Wiener
  filter) and returns its typed state (:class:`~gcrsky.solvers.CGState`,
  :class:`~gcrsky.solvers.CholeskyState`, :class:`~gcrsky.solvers.EighState`,
  :class:`~gcrsky.solvers.MModeState`, :class:`~gcrsky.solvers.DataSpaceState`);
  :func:`draw` takes any of them, and new data (``data=``) reuse its factor;
  :func:`condition` gives the state for new data.
* :func:`sample_system` is both in one call; :func:`wiener_filter_system` the mean.

Every path returns ``a_wf + delta`` with ``Cov(delta) = P^-1`` exactly.

**Draw layout** (the one convention, everywhere in gcrsky): draws are ``(Nf, ndraws, n)``,
channel first, then draw, then the realified coefficients (:mod:`gcrsky.sphere.modes`);
a chain of :func:`gcrsky.gcr_step` stacked by ``lax.scan`` is ``(nsteps, Nf, n)``.

**Keys.** :func:`draw` draws in batches of a fixed, bucketed size ``B`` (the smallest
power of two ``>= ndraws``, at most :data:`DRAW_BATCH`), batch ``b`` keyed
``jax.random.fold_in(key, b)`` and truncated to ``ndraws``: a fixed key reproduces the
draws, a new ``ndraws`` in the same bucket does not recompile (300 and 301 draws are both
two batches of 256), and within one bucket draw ``i`` does not depend on ``ndraws``.
Inside a batch, draw ``i`` of a CG, Cholesky or data-space batch uses
``jax.random.split(batch_key, B)[i]`` (the eigen and m-mode paths draw their normals as
one array).  Different paths give different (equally exact) draws.
"""

from __future__ import annotations

import warnings
from typing import Union

import jax
import jax.numpy as jnp

from ..model.system import LinearSystem
from ..solvers.info import DrawInfo, SolveInfo
from ..solvers.registry import PATHS, SolverOptions, options_for, path_of

__all__ = ["DRAW_BATCH", "SamplerState", "condition", "draw", "draw_bucket", "draw_exactly", "prepare_sampler", "prepare_system",
           "sample_system", "wiener_filter_system"]

#: The state of any prepared exact path (its ``method`` attribute names the path).
SamplerState = Union[tuple(p.state_type for p in PATHS.values())]

#: Largest batch :func:`draw` draws at once (more draws are several batches of this size).
DRAW_BATCH = 256


def _options(method: str | None, options: SolverOptions | None, tol: float | None) -> SolverOptions:
    if method is None:
        return options_for(path_of(options).name if options is not None else "cg", options, tol=tol)
    return options_for(method, options, tol=tol)


def prepare_system(
    system: LinearSystem,
    *,
    method: str | None = None,
    options: SolverOptions | None = None,
    tol: float | None = None,
):
    """Set up one exact path once: factor / precondition P and solve for the Wiener filter.

    Args:
        system: the linear system.
        method: ``"cg"`` (the default when neither ``method`` nor ``options`` is
            given), ``"cholesky"``, ``"eigh"``, ``"mmode"`` or ``"dataspace"``.  ``"mmode"``
            is exact only when :func:`gcrsky.solvers.mmode_check` passes; it is checked on
            concrete arrays, and under a trace its solve is judged against the true P
            (reported ``INACCURATE``, never converged, where the check would have failed).
            ``"dataspace"`` needs a proper prior (refused on concrete arrays otherwise).
        options: the path's options (:mod:`gcrsky.solvers.options`); implies the path.
        tol: CG tolerance in posterior-sigma units (overrides ``options.tol``).

    Returns:
        the path's state; pass it to :func:`draw` as often as needed.
    """
    opts = _options(method, options, tol)
    path = path_of(opts)
    return path.prepare(system, path.resolve(system, opts))


def prepare_sampler(system: LinearSystem, **kw):
    """Deprecated name of :func:`prepare_system` (to be removed in the next release)."""
    warnings.warn("gcrsky.prepare_sampler is deprecated: use gcrsky.prepare_system", DeprecationWarning, stacklevel=2)
    return prepare_system(system, **kw)


def condition(prepared, data: jax.Array):
    """The prepared state for new visibilities ``data`` (Nf, Nt, Nbl), with the same noise and prior.

    The Wiener filter is solved again with the existing factor (direct paths) or preconditioner
    (CG); nothing is refactorised.  Equal to a fresh :func:`prepare_system` on the system with
    ``data`` (to rounding on the direct paths, to the tolerance on CG), and pure: vmap it over
    data sets.
    """
    return path_of(prepared).condition(prepared, data)


def draw_bucket(ndraws: int) -> int:
    """The batch size :func:`draw` uses for ``ndraws``: the smallest power of two ``>= ndraws``,
    at most :data:`DRAW_BATCH`."""
    if int(ndraws) != ndraws or ndraws < 1:
        raise ValueError(f"ndraws must be a positive integer, got {ndraws!r}")
    return min(DRAW_BATCH, 1 << (int(ndraws) - 1).bit_length())


def draw_exactly(key: jax.Array, prepared, ndraws: int) -> tuple[jax.Array, DrawInfo]:
    """One batch of exactly ``ndraws`` draws, keyed by the path's own scheme (draw ``i`` of a CG,
    Cholesky or data-space batch: ``jax.random.split(key, ndraws)[i]``).

    What :func:`draw` calls per batch, and what fixed-batch loops (:mod:`gcrsky.inference.batches`,
    ``gcrsky run``, :mod:`gcrsky.parallel.channels`) use directly: one compiled program per
    ``ndraws``.  Returns as :func:`draw`.
    """
    return path_of(prepared).draw(key, prepared, int(ndraws))


def draw(key: jax.Array, prepared, ndraws: int, *, data: jax.Array | None = None) -> tuple[jax.Array, DrawInfo]:
    """``ndraws`` exact posterior draws from a prepared path (any state of :func:`prepare_system`).

    Args:
        key: PRNG key (the module doc's key scheme: batches of :func:`draw_bucket` draws).
        prepared: the state of :func:`prepare_system` / :func:`gcrsky.prepare`.
        ndraws: number of draws (static).
        data: optional new visibilities (Nf, Nt, Nbl), K sr, with the same noise and prior:
            the factor is reused (:func:`condition`) and the draws scatter about the new Wiener
            filter.  vmap over it to sample many data sets with one factorisation.

    Returns:
        draws (Nf, ndraws, n) and a :class:`~gcrsky.solvers.DrawInfo` (``wiener``: SolveInfo
        over (Nf,), ``draws``: SolveInfo over (Nf, ndraws), ``a_wf`` (Nf, n)).
    """
    path = path_of(prepared)
    if data is not None:
        prepared = path.condition(prepared, data)
    size = draw_bucket(ndraws)
    nbatch = -(-int(ndraws) // size)
    parts = [path.draw(jax.random.fold_in(key, b), prepared, size) for b in range(nbatch)]
    draws = jnp.concatenate([p[0] for p in parts], axis=1)[:, :ndraws]
    dinfo = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a, axis=1)[:, :ndraws], *[p[1].draws for p in parts])
    return draws, DrawInfo(prepared.wiener, dinfo, prepared.a_wf)


def sample_system(
    key: jax.Array,
    system: LinearSystem,
    ndraws: int,
    *,
    method: str | None = None,
    options: SolverOptions | None = None,
    tol: float | None = None,
) -> tuple[jax.Array, DrawInfo]:
    """GCR draws from the exact posterior ``N(a_wf, P^-1)``: :func:`prepare_system` then :func:`draw`.

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

    For many batches, call :func:`prepare_system` once and :func:`draw` per batch.

    Returns:
        as :func:`draw`.
    """
    return draw(key, prepare_system(system, method=method, options=options, tol=tol), ndraws)


def wiener_filter_system(
    system: LinearSystem,
    *,
    method: str | None = None,
    options: SolverOptions | None = None,
    tol: float | None = None,
) -> tuple[jax.Array, SolveInfo]:
    """Wiener filter (posterior mean) ``P^-1 (X^T W d + S^-1 a0)`` on one exact path.

    CG (the default) starts at the prior mean and never forms the factors the draws
    need; the direct paths solve with their factor.

    Returns:
        (a_wf (Nf, n), SolveInfo with (Nf,) fields).
    """
    opts = _options(method, options, tol)
    path = path_of(opts)
    return path.wiener(system, path.resolve(system, opts))
