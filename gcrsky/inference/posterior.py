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

**Inputs.** The system is checked as the user tier checks it: on concrete arrays
:func:`gcrsky.model.check_system` raises a ``ValueError`` naming a bad input (a non-finite
datum, flagged or not; ``inv_noise`` non-finite or negative; a non-finite prior mean; a prior
``inv_var`` non-finite or negative; dtypes, shapes), before any set-up (``check=False``
skips it, for a system already checked; host NumPy on the data, noise and prior, no copy of
the response).  Under a trace (a user's ``jit`` / ``vmap`` / ``grad``) it cannot raise, so
the same value checks (:func:`gcrsky.model.input_faults`, a few elementwise reductions, no
host callback) are folded into the result: every channel with a bad input reports
:data:`~gcrsky.solvers.Result.BAD_INPUT` (never converged), in ``wiener`` and ``draws``, on
every path, whatever the solve measured (it can look converged); the values themselves are
left as the path computed them.  With the path's ``throw=True`` a bad input is an error
(``equinox.error_if``) naming it.  This happens here, once, for every path; a state
prepared by a path directly (:class:`~gcrsky.solvers.SolverPath`) still gets the fold in
:func:`draw` and :func:`draw_exactly`.

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

import functools
import warnings
from typing import Union

import equinox as eqx
import jax
import jax.numpy as jnp

from ..model.system import INPUT_FAULTS, LinearSystem, check_system, input_faults
from ..solvers.info import DrawInfo, SolveInfo, fold_bad_input
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


def guard_inputs(system: LinearSystem, options) -> tuple[LinearSystem, jax.Array]:
    """``(system, bad)``: ``bad`` (Nf,) True where a channel's inputs are bad (:func:`~gcrsky.model.input_faults`).

    With ``options.throw`` the returned system's data carry one ``equinox.error_if`` per input,
    "gcrsky: bad input: <what>", so a bad input raises before (and instead of) the path's own
    error.  Otherwise the system is returned as it is.
    """
    faults = input_faults(system)
    if getattr(options, "throw", False):
        data = system.data
        for name, bad in faults.items():
            data = eqx.error_if(data, bad, f"gcrsky: bad input: {INPUT_FAULTS[name]}")
        system = system._replace(data=data)
    return system, functools.reduce(jnp.logical_or, faults.values())


def bad_channels(system: LinearSystem) -> jax.Array:
    """(Nf,) True where a channel's inputs are bad (any of :func:`~gcrsky.model.input_faults`; traceable)."""
    return functools.reduce(jnp.logical_or, input_faults(system).values())


def _fold_state(state, bad: jax.Array):
    return eqx.tree_at(lambda s: s.wiener, state, fold_bad_input(state.wiener, bad))


def prepare_system(
    system: LinearSystem,
    *,
    method: str | None = None,
    options: SolverOptions | None = None,
    tol: float | None = None,
    check: bool = True,
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
        check: check concrete inputs with :func:`gcrsky.model.check_system` first (the
            module's **Inputs**; under a trace bad inputs are reported ``BAD_INPUT``).

    Returns:
        the path's state; pass it to :func:`draw` as often as needed.

    Raises:
        ValueError: a bad concrete input (``check``), naming it; or a path that does not apply.
    """
    if check:
        check_system(system)
    opts = _options(method, options, tol)
    path = path_of(opts)
    opts = path.resolve(system, opts)
    system, bad = guard_inputs(system, opts)
    return _fold_state(path.prepare(system, opts), bad)


def prepare_sampler(system: LinearSystem, **kw):
    """Deprecated name of :func:`prepare_system` (to be removed in the next release)."""
    warnings.warn("gcrsky.prepare_sampler is deprecated: use gcrsky.prepare_system", DeprecationWarning, stacklevel=2)
    return prepare_system(system, **kw)


def condition(prepared, data: jax.Array, *, check: bool = True):
    """The prepared state for new visibilities ``data`` (Nf, Nt, Nbl), with the same noise and prior.

    The Wiener filter is solved again with the existing factor (direct paths) or preconditioner
    (CG); nothing is refactorised.  Equal to a fresh :func:`prepare_system` on the system with
    ``data`` (to rounding on the direct paths, to the tolerance on CG), and pure: vmap it over
    data sets.  Concrete ``data`` are checked (``check``: :func:`gcrsky.model.check_system` on
    the new system, a ``ValueError`` naming a non-finite sample); traced ones that are not
    finite make the channel's ``wiener`` :data:`~gcrsky.solvers.Result.BAD_INPUT` (the module's
    **Inputs**).
    """
    path = path_of(prepared)
    data = jnp.asarray(data, prepared.system.data.dtype)
    system = prepared.system._replace(data=data)
    if check:
        check_system(system)
    system, bad = guard_inputs(system, getattr(prepared, "options", None))  # a state need not keep its options
    return _fold_state(path.condition(prepared, system.data), bad)


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
    ``ndraws``.  Returns as :func:`draw` (bad inputs reported ``BAD_INPUT``, as there).
    """
    draws, info = path_of(prepared).draw(key, prepared, int(ndraws))
    bad = bad_channels(prepared.system)
    return draws, info._replace(wiener=fold_bad_input(info.wiener, bad), draws=fold_bad_input(info.draws, bad))


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
        over (Nf,), ``draws``: SolveInfo over (Nf, ndraws), ``a_wf`` (Nf, n)); a channel whose
        inputs are bad (the module's **Inputs**) reports ``BAD_INPUT`` in both.
    """
    path = path_of(prepared)
    if data is not None:
        prepared = condition(prepared, data)
    size = draw_bucket(ndraws)
    nbatch = -(-int(ndraws) // size)
    parts = [path.draw(jax.random.fold_in(key, b), prepared, size) for b in range(nbatch)]
    draws = jnp.concatenate([p[0] for p in parts], axis=1)[:, :ndraws]
    dinfo = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a, axis=1)[:, :ndraws], *[p[1].draws for p in parts])
    bad = bad_channels(prepared.system)
    return draws, DrawInfo(fold_bad_input(prepared.wiener, bad), fold_bad_input(dinfo, bad), prepared.a_wf)


def sample_system(
    key: jax.Array,
    system: LinearSystem,
    ndraws: int,
    *,
    method: str | None = None,
    options: SolverOptions | None = None,
    tol: float | None = None,
    check: bool = True,
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

    Concrete inputs are checked (``check``; a ``ValueError`` naming a bad one), traced ones
    reported ``BAD_INPUT`` (the module's **Inputs**).

    Returns:
        as :func:`draw`.
    """
    return draw(key, prepare_system(system, method=method, options=options, tol=tol, check=check), ndraws)


def wiener_filter_system(
    system: LinearSystem,
    *,
    method: str | None = None,
    options: SolverOptions | None = None,
    tol: float | None = None,
    check: bool = True,
) -> tuple[jax.Array, SolveInfo]:
    """Wiener filter (posterior mean) ``P^-1 (X^T W d + S^-1 a0)`` on one exact path.

    CG (the default) starts at the prior mean and never forms the factors the draws
    need; the direct paths solve with their factor.

    Concrete inputs are checked (``check``; a ``ValueError`` naming a bad one), traced ones
    reported ``BAD_INPUT`` (the module's **Inputs**).

    Returns:
        (a_wf (Nf, n), SolveInfo with (Nf,) fields).
    """
    if check:
        check_system(system)
    opts = _options(method, options, tol)
    path = path_of(opts)
    opts = path.resolve(system, opts)
    system, bad = guard_inputs(system, opts)
    a_wf, info = path.wiener(system, opts)
    return a_wf, fold_bad_input(info, bad)
