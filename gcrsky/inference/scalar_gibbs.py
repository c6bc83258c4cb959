"""The sky and the evidence for any noise scale and prior amplitude, factored once.

A Gibbs loop over ``(a, s, A)``, where only the noise scale ``s`` (``N -> s N``) and the
prior amplitude ``A`` (``S -> A S``) change between steps, need not refactorise the
posterior precision each step.  With ``H = X^T N^-1 X`` the data term and ``S`` the prior
covariance, one generalised eigendecomposition per channel,

    S^1/2 H S^1/2 = U diag(lam) U^T,

diagonalises the posterior precision of every ``(s, A)`` at once:

    P(s, A) = H / s + S^-1 / A = S^-1/2 U diag(lam / s + 1 / A) U^T S^-1/2.

With ``r = d - X a0`` and the one-time projection ``beta = U^T S^1/2 X^T N^-1 r``:

- a draw of ``a | d, s, A`` is ``a0 + S^1/2 U (beta / (lam + s/A) + z / sqrt(lam/s + 1/A))``,
  ``z ~ N(0, I)``: two matrix-vector products, O(n^2), nothing refactorised;
- the exact log evidence ``log p(d | s, A) = -1/2 [chi2 + sum log(1 + A lam / s) + log det N
  + N_d log s + N_d log 2 pi]`` with ``chi2 = r^T N^-1 r / s - sum beta^2 / (s (lam + s/A))``
  costs O(n) per ``(s, A)``;
- the quadratic forms of the inverse-gamma conditionals of ``s`` and ``A`` given a sky
  (:func:`scalar_quadratics`) cost O(n^2).

Conditions: the noise covariance is diagonal (a :class:`~gcrsky.model.LinearSystem`'s
``inv_noise``; flagged data, ``inv_noise = 0``, drop out) and the prior covariance ``S`` is
diagonal and positive (every ``inv_var > 0``): a flat prior direction has no ``S^1/2`` and
is refused with a ``ValueError``.  The set-up forms the dense ``H`` (n x n per channel) and
its eigendecomposition, O(n^3) once.  Every function after :func:`prepare_scalar` is pure,
jit-able, vmap-able and differentiable in the scales; channels (Nf) are independent and a
scale may be a scalar or (Nf,).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import check_float64
from ..model.system import LinearSystem, precision_matrix
from ..solvers.path import is_traced
from .evidence import evidence_terms

__all__ = ["ScalarQuadratics", "ScalarState", "prepare_scalar", "scalar_draw", "scalar_log_evidence",
           "scalar_quadratics"]

LOG_2PI = float(np.log(2.0 * np.pi))


class ScalarState(NamedTuple):
    """The one-time factorisation of :func:`prepare_scalar` (a PyTree; per channel, Nf first).

    Attributes:
        prior_mean: ``a0`` (Nf, n), K.
        prior_std: ``S^1/2`` (Nf, n), the prior standard deviations at ``A = 1``, K.
        vectors: ``U`` (Nf, n, n), eigenvectors of ``S^1/2 H S^1/2`` (columns).
        lam: (Nf, n) its eigenvalues (the signal-to-noise of each direction at ``s = A = 1``).
        beta: (Nf, n) the projected residual ``U^T S^1/2 X^T N^-1 (d - X a0)``.
        rwr: (Nf,) ``r^T N^-1 r`` with ``r = d - X a0`` at ``s = 1``.
        logdet_noise: (Nf,) ``log det N`` at ``s = 1``.
        n_data: (Nf,) ``N_d``, the number of real data (twice the unflagged visibilities).
    """

    prior_mean: jax.Array
    prior_std: jax.Array
    vectors: jax.Array
    lam: jax.Array
    beta: jax.Array
    rwr: jax.Array
    logdet_noise: jax.Array
    n_data: jax.Array


class ScalarQuadratics(NamedTuple):
    """The quadratic forms of a sky ``a`` that the conditionals of ``s`` and ``A`` need, (Nf,) each.

    Attributes:
        data: ``(d - X a)^T N^-1 (d - X a)`` at ``s = 1``: ``s | a, d`` is inverse-gamma with shape
            ``N_d / 2`` and scale ``data / 2`` under the Jeffreys prior ``1/s``.
        prior: ``(a - a0)^T S^-1 (a - a0)`` at ``A = 1``: ``A | a`` is inverse-gamma with shape
            ``n / 2`` and scale ``prior / 2`` under the Jeffreys prior ``1/A``.
    """

    data: jax.Array
    prior: jax.Array


def prepare_scalar(system: LinearSystem) -> ScalarState:
    """Factor ``system`` once for every noise scale and prior amplitude (the module's docstring).

    Args:
        system: the linear system at ``s = A = 1`` (diagonal noise ``inv_noise`` (Nf, Nt, Nbl),
            K^-2 sr^-2; a diagonal prior with every ``inv_var > 0``, K^-2).

    Returns:
        :class:`ScalarState`.  Cost: the dense ``H`` and one ``eigh`` per channel, O(Nf n^3).

    Raises:
        ValueError: a flat or non-positive prior direction (``inv_var <= 0``; checked on concrete
            arrays), for which ``S^1/2`` does not exist.
    """
    check_float64(system.op.response, system.inv_noise)
    if not is_traced(system.prior.inv_var) and bool(np.any(np.asarray(system.prior.inv_var) <= 0)):
        raise ValueError("prepare_scalar needs a proper prior (every inv_var > 0): a flat direction has no "
                         "prior amplitude to scale; use gcr_step with a path's options for a flat prior")
    inv_var = system.prior.inv_var
    std = 1.0 / jnp.sqrt(inv_var)
    H = precision_matrix(system) - jax.vmap(jnp.diag)(inv_var)
    lam, U = jnp.linalg.eigh(std[:, :, None] * H * std[:, None, :])
    lam = jnp.maximum(lam, 0.0)  # H is positive semi-definite: a negative eigenvalue is rounding
    terms = evidence_terms(system)
    beta = jnp.einsum("fij,fi->fj", U, std * terms["b_res"])
    return ScalarState(system.prior.mean, std, U, lam, beta, terms["rWr"], terms["logdet_n"], terms["n_data"])


def _scales(state: ScalarState, noise_scale, prior_scale):
    nf = state.lam.shape[0]
    dtype = state.lam.dtype
    s = jnp.broadcast_to(jnp.asarray(noise_scale, dtype), (nf,))
    A = jnp.broadcast_to(jnp.asarray(prior_scale, dtype), (nf,))
    return s, A


def scalar_draw(key: jax.Array, state: ScalarState, noise_scale, prior_scale, ndraws: int = 1) -> jax.Array:
    """Exact draws of ``a | d, s, A``: the noise variance times ``noise_scale``, the prior's times ``prior_scale``.

    Args:
        key: PRNG key (``z = jax.random.normal(key, (Nf, ndraws, n))``).
        state: :func:`prepare_scalar`'s factorisation.
        noise_scale: ``s`` > 0, scalar or (Nf,).
        prior_scale: ``A`` > 0, scalar or (Nf,).
        ndraws: draws per channel (static).

    Returns:
        (Nf, ndraws, n) draws, K; O(Nf ndraws n^2).
    """
    s, A = _scales(state, noise_scale, prior_scale)
    z = jax.random.normal(key, (state.lam.shape[0], ndraws, state.lam.shape[1]), state.lam.dtype)
    prec = state.lam / s[:, None] + 1.0 / A[:, None]  # (Nf, n): the posterior precision's eigenvalues
    mean = state.beta / (state.lam + (s / A)[:, None])
    y = mean[:, None, :] + z / jnp.sqrt(prec)[:, None, :]
    return state.prior_mean[:, None, :] + state.prior_std[:, None, :] * jnp.einsum("fij,fdj->fdi", state.vectors, y)


def scalar_log_evidence(state: ScalarState, noise_scale, prior_scale) -> jax.Array:
    """The exact log evidence ``log p(d | s, A)`` (Nf,), O(Nf n) per call (the module's docstring).

    Equals :func:`gcrsky.log_evidence` of the system with its noise variance times ``noise_scale``
    and its prior variance times ``prior_scale``; differentiable in both.

    Args:
        state: :func:`prepare_scalar`'s factorisation.
        noise_scale, prior_scale: ``s`` and ``A`` > 0, scalars or (Nf,).
    """
    s, A = _scales(state, noise_scale, prior_scale)
    quad = jnp.sum(state.beta**2 / (state.lam + (s / A)[:, None]), axis=-1) / s
    chi2 = state.rwr / s - quad
    logdet = jnp.sum(jnp.log1p(state.lam * (A / s)[:, None]), axis=-1)
    return -0.5 * (chi2 + logdet + state.logdet_noise + state.n_data * (jnp.log(s) + LOG_2PI))


def scalar_quadratics(state: ScalarState, position: jax.Array) -> ScalarQuadratics:
    """The data and prior quadratic forms of a sky ``position`` (Nf, n) at ``s = A = 1``, O(Nf n^2).

    From the factorisation alone: with ``y = U^T S^-1/2 (a - a0)``, the data term is
    ``r^T N^-1 r - 2 y.beta + sum lam y^2`` and the prior term ``sum y^2``.
    """
    x = jnp.asarray(position, state.prior_mean.dtype) - state.prior_mean
    y = jnp.einsum("fij,fi->fj", state.vectors, x / state.prior_std)
    data = state.rwr - 2.0 * jnp.sum(y * state.beta, axis=-1) + jnp.sum(state.lam * y**2, axis=-1)
    return ScalarQuadratics(data, jnp.sum((x / state.prior_std) ** 2, axis=-1))
