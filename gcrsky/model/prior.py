"""Gaussian priors on the realified coefficients: ``a ~ N(a0, S)``, S diagonal.

A prior is stored by its mean and *inverse* variance so that a flat prior
(``S^-1 = 0``, paper cases B5/B6) is representable exactly.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..sphere.modes import lmax_from_nparams, mode_table

__all__ = ["Prior", "flat_prior", "isotropic_prior", "paper_prior", "power_law_cl", "prior_from_cl"]


class Prior(NamedTuple):
    """Diagonal Gaussian prior.

    Attributes:
        mean: (Nf, n) prior mean a0, Kelvin.
        inv_var: (Nf, n) diagonal of S^-1, K^-2 (0 = flat in that direction).
    """

    mean: jax.Array
    inv_var: jax.Array


def paper_prior(
    a_true,
    key: jax.Array,
    *,
    frac: float = 0.1,
    floor_std: float = 0.5,
    prior_scale: float = 1.0,
    zero_mean: bool = False,
    keep_true_monopole: bool = True,
) -> Prior:
    """The paper's prior: ``S = diag(max(frac |a_true|, floor)^2) * prior_scale``.

    The mean is drawn ``a0 ~ N(a_true, S_unscaled)`` (the paper's standard draw,
    independent of ``prior_scale`` so that cases B3/B4 widen S around the same a0),
    with the monopole kept at its true value as the reference code does
    (``keep_true_monopole``); ``zero_mean`` sets ``a0 = 0`` (case B1/B2).

    Args:
        a_true: (Nf, n) true realified coefficients, Kelvin.
        key: PRNG key for the draw of a0.
    """
    a_true = np.asarray(a_true, np.float64)
    if not (frac > 0 and floor_std >= 0 and prior_scale > 0):
        raise ValueError("need frac > 0, floor_std >= 0, prior_scale > 0")
    std = np.maximum(frac * np.abs(a_true), floor_std)
    if np.any(std <= 0):
        raise ValueError("prior std is zero for some mode: give floor_std > 0")
    if zero_mean:
        mean = np.zeros_like(a_true)
    else:
        z = np.asarray(jax.random.normal(key, a_true.shape, np.float64))
        mean = a_true + std * z
        if keep_true_monopole:
            mean[..., 0] = a_true[..., 0]
    return Prior(mean=mean, inv_var=1.0 / (prior_scale * std**2))


def flat_prior(nfreq: int, n: int, mean=None) -> Prior:
    """``S^-1 = 0``: the posterior is the likelihood; P may be singular (then no sampler can
    succeed for the unconstrained directions, and the solvers report it)."""
    m = np.zeros((nfreq, n)) if mean is None else np.asarray(mean, np.float64)
    return Prior(mean=m, inv_var=np.zeros((nfreq, n)))


def isotropic_prior(cl, n: int, mean=None) -> Prior:
    """Prior from angular power spectra ``C_l`` (Nf, lmax+1), K^2.

    ``Var(a_l0) = C_l``; ``Var(Re a_lm) = Var(Im a_lm) = C_l / 2`` for m > 0.
    """
    cl = np.atleast_2d(np.asarray(cl, np.float64))
    lmax = lmax_from_nparams(n)
    if cl.shape[-1] != lmax + 1:
        raise ValueError(f"cl has {cl.shape[-1]} degrees, expected lmax+1 = {lmax + 1}")
    if np.any(cl <= 0):
        raise ValueError("C_l must be positive (use flat_prior for an improper prior)")
    tab = mode_table(lmax)
    var = cl[:, tab.ell] * np.where(tab.m == 0, 1.0, 0.5)[None, :]
    m = np.zeros_like(var) if mean is None else np.asarray(mean, np.float64)
    return Prior(mean=m, inv_var=1.0 / var)


def prior_from_cl(cl, mean=None) -> Prior:
    """The isotropic prior of angular power spectra ``C_l``, in JAX (jittable, differentiable).

    The twin of :func:`isotropic_prior` for traced spectra (hyperparameters):
    ``Var(a_l0) = C_l``, ``Var(Re a_lm) = Var(Im a_lm) = C_l / 2`` for m > 0.

    Args:
        cl: (lmax+1,) or (Nf, lmax+1) power spectra, K^2 (positive; not checked under
            a trace).
        mean: prior mean (Nf, n) or None (zero).

    Returns:
        a :class:`Prior` with (Nf, n) arrays (Nf = 1 for a 1-D ``cl``).
    """
    cl = jnp.atleast_2d(jnp.asarray(cl))
    lmax = cl.shape[-1] - 1
    tab = mode_table(lmax)
    half = jnp.asarray(np.where(tab.m == 0, 1.0, 0.5))
    var = cl[:, tab.ell] * half[None, :]
    m = jnp.zeros_like(var) if mean is None else jnp.broadcast_to(jnp.asarray(mean, var.dtype), var.shape)
    return Prior(mean=m, inv_var=1.0 / var)


def power_law_cl(amplitude, alpha, lmax: int):
    """The power-law spectrum ``C_l = A (l + 1)^-alpha``, K^2, in JAX.

    Args:
        amplitude: A (scalar or (Nf,)), K^2.
        alpha: the slope (scalar or (Nf,)).
        lmax: maximum degree (static).

    Returns:
        (lmax+1,) or (Nf, lmax+1).
    """
    ell1 = jnp.arange(1, lmax + 2, dtype=jnp.result_type(float))
    amplitude, alpha = jnp.asarray(amplitude), jnp.asarray(alpha)
    return amplitude[..., None] * ell1 ** (-alpha[..., None])
