"""Frequency-coupled Gaussian priors on the realified coefficients (DESIGN section 13).

A *separable* prior couples the channels only through a frequency covariance ``R``:

    Cov(a_k(nu), a_k'(nu')) = delta_kk' c_k R(nu, nu'),

with ``c_k`` the variance of realified entry k at the reference frequency ``nu0``
(``c_k = C_l(nu0)`` at m = 0, ``C_l(nu0) / 2`` for the real and imaginary parts at m > 0,
the convention of :func:`gcrsky.model.isotropic_prior`) and ``R`` an (Nf, Nf) symmetric
positive-definite matrix.  On the (Nf n) vector ``vec(a)`` (channel-major: index ``f n + k``)
the prior covariance is ``S = R (x) diag(c)`` and its precision ``R^-1 (x) diag(c)^-1``.

Two ways to build ``R``, both differentiable in their hyperparameters (``jax.grad``):

* :func:`log_frequency_kernel`: a smooth squared-exponential kernel in ``log nu`` times a
  power law, ``R = A (nu nu' / nu0^2)^beta exp(-(log nu - log nu')^2 / (2 xi^2))``;
* :func:`spectral_basis_cov`: a spectral basis ``a(nu) = sum_k f_k(nu) c^k`` with
  log-polynomial ``f_k(nu) = (nu/nu0)^beta (log(nu/nu0))^k`` (k = 0: power law, k = 1: a
  running index, k = 2: curvature) and independent ``c^k ~ N(0, p_k C)``:
  ``R = F diag(p) F^T``.

The nugget.  Both add ``nugget * diag(diag(R))`` (a relative jitter: every channel's own
variance grows by the factor ``1 + nugget``; the off-diagonal correlations shrink by it).
For the kernel it only bounds the condition number of ``R`` (the squared exponential's
spectrum decays like a Gaussian, so closely spaced channels make it numerically singular:
``cond(R) <~ (1 + nugget) Nf / nugget``).  For the spectral basis, ``F diag(p) F^T`` has rank
``K < Nf`` and is no proper prior; we *choose the nugget* rather than sampling in the K n
dimensional c-space, so that one joint sampler (:mod:`gcrsky.solvers.joint`) serves both
priors and flagged channels keep a proper prior: the nugget is the variance the basis does
not explain, per channel, as a fraction of the modelled one.  A nugget of 0 is allowed where
``R`` is already positive definite (e.g. the kernel with ``xi`` much below the channels'
log spacing); the samplers only need the Cholesky factor of ``R``, never ``R^-1``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..sphere.modes import lmax_from_nparams, mode_table

__all__ = [
    "FrequencyPrior",
    "frequency_prior",
    "log_frequency_kernel",
    "log_polynomial_basis",
    "mode_variance",
    "spectral_basis_cov",
]


class FrequencyPrior(NamedTuple):
    """A separable frequency-coupled Gaussian prior ``a ~ N(mean, R (x) diag(mode_var))``.

    Attributes:
        mean: (Nf, n) prior mean a0, Kelvin.
        mode_var: (n,) variance ``c_k`` of each realified entry at the reference frequency,
            K^2 (positive).
        freq_cov: (Nf, Nf) symmetric positive-definite frequency covariance ``R``
            (dimensionless; the channel variances are ``c_k R_ff``).
    """

    mean: jax.Array
    mode_var: jax.Array
    freq_cov: jax.Array


def mode_variance(cl) -> jax.Array:
    """Per-entry variances (n,) of the realified vector from ``C_l`` (lmax+1,), K^2, in JAX.

    ``Var(a_l0) = C_l``; ``Var(Re a_lm) = Var(Im a_lm) = C_l / 2`` for m > 0 (as
    :func:`gcrsky.model.prior_from_cl`).  Differentiable in ``cl``.
    """
    cl = jnp.asarray(cl)
    if cl.ndim != 1:
        raise ValueError(f"cl must be 1-d (lmax+1,), got shape {cl.shape}")
    tab = mode_table(cl.shape[0] - 1)
    return cl[tab.ell] * jnp.asarray(np.where(tab.m == 0, 1.0, 0.5))


def _with_nugget(R: jax.Array, nugget) -> jax.Array:
    R = 0.5 * (R + R.T)
    return R + nugget * jnp.diag(jnp.diag(R))


def log_frequency_kernel(freqs_hz, nu0_hz, amplitude, beta, xi, *, nugget=1e-6) -> jax.Array:
    """The smooth frequency covariance ``R`` (Nf, Nf) of a power law with a log-frequency kernel.

    ``R(nu, nu') = A (nu nu' / nu0^2)^beta exp(-(log nu - log nu')^2 / (2 xi^2))`` plus the
    relative nugget ``nugget * R(nu, nu)`` on the diagonal (module docstring).

    Args:
        freqs_hz: (Nf,) channel frequencies, Hz (positive).
        nu0_hz: reference frequency, Hz (``R(nu0, nu0) = A``).
        amplitude: A > 0 (dimensionless; multiplies ``C_l(nu0)``).
        beta: spectral index of the standard deviation (the variance scales as ``nu^(2 beta)``).
        xi: correlation length in ``log nu`` (> 0, natural log; ``xi -> 0`` decouples the
            channels, ``xi -> inf`` makes them one power law).
        nugget: relative jitter (>= 0), keyword.

    Returns:
        (Nf, Nf) float64, differentiable in ``amplitude``, ``beta``, ``xi``, ``nugget``.
    """
    x = jnp.log(jnp.asarray(freqs_hz, jnp.result_type(float)) / nu0_hz)
    d = x[:, None] - x[None, :]
    R = amplitude * jnp.exp(beta * (x[:, None] + x[None, :]) - 0.5 * (d / xi) ** 2)
    return _with_nugget(R, nugget)


def log_polynomial_basis(freqs_hz, nu0_hz, beta, nbasis: int) -> jax.Array:
    """The spectral basis ``F`` (Nf, K): ``f_k(nu) = (nu/nu0)^beta (log(nu/nu0))^k``, k < K.

    k = 0 is a power law of index ``beta``, k = 1 a change of index (running), k = 2 the
    curvature; ``nbasis`` (static) is K.  Differentiable in ``beta``.
    """
    x = jnp.log(jnp.asarray(freqs_hz, jnp.result_type(float)) / nu0_hz)
    return jnp.exp(beta * x)[:, None] * x[:, None] ** jnp.arange(nbasis)[None, :]


def spectral_basis_cov(freqs_hz, nu0_hz, beta, basis_var, *, nugget=1e-3) -> jax.Array:
    """The frequency covariance ``R = F diag(p) F^T + nugget diag(F diag(p) F^T)`` of a spectral basis.

    ``a(nu) = sum_k f_k(nu) c^k`` with ``c^k ~ N(0, p_k C)`` independent
    (:func:`log_polynomial_basis`); ``F diag(p) F^T`` has rank K, and the nugget (> 0 when
    K < Nf) makes it a proper prior (module docstring).

    Args:
        freqs_hz: (Nf,) channel frequencies, Hz.
        nu0_hz: reference frequency, Hz.
        beta: the power law's index.
        basis_var: (K,) variances ``p_k`` of the basis coefficients (relative to ``C_l(nu0)``).
        nugget: relative jitter, keyword.

    Returns:
        (Nf, Nf), differentiable in ``beta``, ``basis_var`` and ``nugget``.
    """
    p = jnp.asarray(basis_var)
    F = log_polynomial_basis(freqs_hz, nu0_hz, beta, p.shape[0])
    return _with_nugget((F * p[None, :]) @ F.T, nugget)


def frequency_prior(cl, freq_cov, mean=None) -> FrequencyPrior:
    """A :class:`FrequencyPrior` from ``C_l(nu0)`` (lmax+1,) K^2 and ``R`` (Nf, Nf).

    Args:
        cl: (lmax+1,) angular power spectrum at the reference frequency, K^2.
        freq_cov: (Nf, Nf) frequency covariance (:func:`log_frequency_kernel`,
            :func:`spectral_basis_cov`).
        mean: (Nf, n) prior mean, Kelvin, or None (zero).

    Differentiable in ``cl`` and ``freq_cov`` (usable under ``jit``).
    """
    var = mode_variance(cl)
    R = jnp.asarray(freq_cov)
    nf, n = R.shape[0], var.shape[0]
    lmax_from_nparams(n)
    m = jnp.zeros((nf, n), var.dtype) if mean is None else jnp.broadcast_to(jnp.asarray(mean, var.dtype), (nf, n))
    return FrequencyPrior(mean=m, mode_var=var, freq_cov=R)
