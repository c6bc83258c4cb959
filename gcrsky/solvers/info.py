"""How a solve went: the result type every solver path returns, with a result code.

Codes (:class:`Result`): ``SUCCESS`` (0), ``MAX_ITERATIONS`` (1: CG hit ``maxiter``
before reaching ``tol``), ``BREAKDOWN`` (2: non-positive curvature ``p^T P p <= 0``,
i.e. a singular or indefinite P, e.g. a flat prior), ``NONFINITE`` (3: NaN or Inf in
the residual, the factor or the answer), ``INACCURATE`` (4: a direct path's factor is
finite but its solve misses the tolerance, measured by the true residual: e.g. the
m-mode path on coverage that is not block-diagonal in m, which a trace cannot check
beforehand, or a factor that lost its accuracy to rounding).  ``SolveInfo.converged``
is ``result == 0``: on every path it is *measured* (CG's error bound, the direct paths'
true residual against their ``tol``), never assumed.  ``BAD_INPUT`` (5: the system's
inputs are not valid: a non-finite datum, a non-finite or negative ``inv_noise``, a
non-finite prior mean, a non-finite or negative prior ``inv_var``, non-finite angles;
see :func:`gcrsky.model.input_faults`) is set by the system tier
(:mod:`gcrsky.inference.posterior`, :func:`gcrsky.inference.log_evidence_system`) under a
trace, where :func:`gcrsky.model.check_system` cannot raise: it overrides whatever the
path measured (a solve of bad inputs can look converged), in every channel with a bad
input, and with a path's ``throw=True`` it is an error naming the input.
:func:`result_names` turns codes into words for messages.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.solveinfo import SolveInfo

__all__ = ["DrawInfo", "Result", "SolveInfo", "direct_info", "exact_info", "fold_bad_input", "result_code",
           "result_names"]


class Result:
    """The result codes of :class:`SolveInfo` (plain ints, usable inside ``jit``)."""

    SUCCESS = 0
    MAX_ITERATIONS = 1
    BREAKDOWN = 2
    NONFINITE = 3
    INACCURATE = 4
    BAD_INPUT = 5

    NAMES = ("success", "max_iterations", "breakdown", "nonfinite", "inaccurate", "bad_input")


class DrawInfo(NamedTuple):
    """What a batch of draws reports, on every path (:func:`gcrsky.draw`, :func:`gcrsky.sample`).

    Attributes:
        wiener: :class:`SolveInfo` of the set-up's Wiener solve, (Nf,) fields.
        draws: :class:`SolveInfo` of the draws, (Nf, ndraws) fields.
        a_wf: (Nf, n) the Wiener filter (exact posterior mean) the draws scatter about.

    ``info["draws"]``-style access by field name still works (it was a dict before 0.2)
    but is deprecated: use the attributes.
    """

    wiener: SolveInfo
    draws: SolveInfo
    a_wf: jax.Array

    def __getitem__(self, key):
        if isinstance(key, str):
            import warnings

            warnings.warn(f"info[{key!r}] is deprecated: DrawInfo is a NamedTuple, use info.{key}",
                          DeprecationWarning, stacklevel=2)
            return getattr(self, key)
        return tuple.__getitem__(self, key)


def result_code(ok, *, finite, broke=None) -> jax.Array:
    """The :class:`Result` code from ``ok`` (tolerance met), ``finite`` and ``broke`` (breakdown)."""
    code = jnp.where(ok, Result.SUCCESS, Result.MAX_ITERATIONS)
    if broke is not None:
        code = jnp.where(broke, Result.BREAKDOWN, code)
    return jnp.where(finite, code, Result.NONFINITE)


def direct_info(err, rel, finite, tol) -> SolveInfo:
    """Info of a direct (factorised) solve, judged by its achieved accuracy.

    Args:
        err: (...) the error estimate ``sqrt(r^T P^-1 r)`` from the *true* residual
            ``r = b - P x`` (posterior-sigma units), P^-1 applied with the path's factor.
        rel: (...) ``||r|| / ||b||``.
        finite: (...) the factor and the answer are finite.
        tol: the path's tolerance (posterior sigma): ``err <= tol`` is success, a finite
            answer above it :data:`Result.INACCURATE`.
    """
    code = jnp.where(err <= tol, Result.SUCCESS, Result.INACCURATE)
    code = jnp.where(finite & jnp.isfinite(err), code, Result.NONFINITE)
    return SolveInfo(jnp.zeros(jnp.shape(err), int), err, rel, code == Result.SUCCESS, code)


def exact_info(wiener: SolveInfo, finite: jax.Array, shape: tuple[int, ...]) -> SolveInfo:
    """Info of draws by an exact factor: no iterations; the factor's measured accuracy.

    A direct path's draws use the factor its Wiener solve used, so they carry that solve's
    error estimate and result code (broadcast over the draws), and ``NONFINITE`` where a
    draw is not finite.

    Args:
        wiener: the set-up's :class:`SolveInfo`, (Nf,) fields.
        finite: boolean (Nf, ndraws), each draw finite.
        shape: batch shape (Nf, ndraws).
    """
    expand = lambda x: jnp.broadcast_to(jnp.asarray(x)[:, None], shape)  # noqa: E731
    code = jnp.where(jnp.broadcast_to(finite, shape), expand(wiener.result), Result.NONFINITE)
    return SolveInfo(jnp.zeros(shape, int), expand(wiener.err_sigma), expand(wiener.rel_residual),
                     code == Result.SUCCESS, code)


def fold_bad_input(info: SolveInfo, bad: jax.Array) -> SolveInfo:
    """``info`` with :data:`Result.BAD_INPUT` (never converged) wherever ``bad`` is True.

    Args:
        info: a :class:`SolveInfo` with fields of shape (Nf, ...).
        bad: (Nf,) booleans, a channel's inputs are bad (:func:`gcrsky.model.input_faults`);
            broadcast over the trailing batch axes (e.g. the draws).
    """
    bad = jnp.asarray(bad)
    bad = jnp.reshape(bad, bad.shape + (1,) * (jnp.ndim(info.result) - bad.ndim))
    code = jnp.where(bad, Result.BAD_INPUT, info.result).astype(jnp.asarray(info.result).dtype)
    return info._replace(converged=code == Result.SUCCESS, result=code)


def result_names(info: SolveInfo) -> dict[str, int]:
    """How many solves ended with each result, e.g. ``{"success": 8, "max_iterations": 2}`` (host-side)."""
    codes = np.asarray(info.result).ravel()
    return {Result.NAMES[c]: int(np.sum(codes == c)) for c in np.unique(codes)}
