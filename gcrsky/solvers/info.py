"""How a solve went: the result type every solver path returns."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["SolveInfo", "exact_info"]


class SolveInfo(NamedTuple):
    """How a solve went (arrays have the batch shape of the solve, e.g. (Nf,) or (Nf, ndraws)).

    Attributes:
        iterations: CG iterations taken (0 for the direct paths).
        err_sigma: ``sqrt(r^T M^-1 r)`` from the *true* final residual ``b - P x``, in
            posterior-sigma units: an upper bound on the error's P-norm with the
            Nystrom preconditioner, an estimate with m-blocks; for the direct paths
            the same quantity with their exact factor (rounding only).
        rel_residual: ``||b - P x|| / ||b||``.
        converged: ``err_sigma <= tol`` and no breakdown (non-positive curvature,
            which signals a singular or indefinite P, e.g. a flat prior); for the
            direct paths: the factor is finite.
    """

    iterations: jax.Array
    err_sigma: jax.Array
    rel_residual: jax.Array
    converged: jax.Array


def exact_info(ok: jax.Array, shape: tuple[int, ...]) -> SolveInfo:
    """Info of draws by an exact factor: no iterations, no residual, ``converged = ok``.

    Args:
        ok: boolean array broadcastable to ``shape`` (e.g. the Wiener solve's status
            per frequency combined with the draws' finiteness).
        shape: batch shape, e.g. (Nf, ndraws).
    """
    zeros = jnp.zeros(shape)
    return SolveInfo(jnp.zeros(shape, int), zeros, zeros, jnp.broadcast_to(ok, shape))
