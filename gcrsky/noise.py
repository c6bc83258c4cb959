"""Noise model: radiometer noise from auto-visibilities, flags as weights.

Convention: complex noise ``n = n_re + i n_im`` with ``n_re, n_im ~ N(0, sigma^2)``
independent, so ``E|n|^2 = 2 sigma^2``.  Everywhere in gcrsky ``sigma`` means the
*per-component* standard deviation.  The radiometer equation gives
``E|n|^2 = V_ii V_jj / (dt dnu)``, hence ``sigma^2 = V_ii V_jj / (2 dt dnu)``.

Weights ``w`` (0 = flagged, 1 = kept, fractional allowed) multiply the inverse
noise variance: ``W = w / sigma^2`` per component.  Flagged samples contribute
nothing; NaN data are allowed only where ``w == 0``.
"""

from __future__ import annotations

from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "radiometer_sigma",
    "inverse_variance",
    "draw_noise",
    "clean_data",
]


def radiometer_sigma(
    auto_i, auto_j, dt_s: float, dnu_hz: float, *, convention: Literal["per_component", "total"] = "per_component"
) -> np.ndarray:
    """Noise standard deviation from the radiometer equation.

    Args:
        auto_i, auto_j: real auto-visibilities ``V_ii``, ``V_jj`` (any broadcastable shape).
        dt_s: integration time, seconds.  dnu_hz: channel width, Hz.
        convention: ``"per_component"`` (default) returns ``sigma`` with
            ``sigma^2 = V_ii V_jj / (2 dt dnu)`` (each of Re, Im);
            ``"total"`` returns ``sqrt(E|n|^2) = sqrt(V_ii V_jj / (dt dnu))``.
    """
    if not (dt_s > 0 and dnu_hz > 0):
        raise ValueError(f"dt_s and dnu_hz must be positive, got {dt_s}, {dnu_hz}")
    ai, aj = np.asarray(auto_i, np.float64), np.asarray(auto_j, np.float64)
    if np.any(ai <= 0) or np.any(aj <= 0):
        raise ValueError("auto-visibilities must be positive to define radiometer noise")
    total = ai * aj / (dt_s * dnu_hz)
    if convention == "per_component":
        return np.sqrt(total / 2.0)
    if convention == "total":
        return np.sqrt(total)
    raise ValueError(f"convention must be 'per_component' or 'total', got {convention!r}")


def inverse_variance(sigma, weights=None) -> np.ndarray:
    """Per-component inverse variance ``w / sigma^2`` (flagged -> exactly 0).

    Args:
        sigma: per-component noise std, (Nf, Nt, Nbl), positive.
        weights: same shape, in [0, 1]; None means all ones.
    """
    sigma = np.asarray(sigma, np.float64)
    if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise ValueError("noise sigma must be finite and positive everywhere (flag with weights instead)")
    if weights is None:
        return 1.0 / sigma**2
    w = np.broadcast_to(np.asarray(weights, np.float64), sigma.shape)
    if not np.all(np.isfinite(w)) or np.any(w < 0) or np.any(w > 1):
        raise ValueError("weights must be finite and within [0, 1]")
    return w / sigma**2


def clean_data(data, inv_var) -> np.ndarray:
    """Replace NaN/inf in flagged samples by 0; error on any non-finite unflagged sample."""
    d = np.asarray(data)
    iv = np.asarray(inv_var)
    bad = ~np.isfinite(d)
    if np.any(bad & (iv > 0)):
        idx = np.argwhere(bad & (iv > 0))[0]
        raise ValueError(
            f"data contain {int(np.sum(bad & (iv > 0)))} non-finite unflagged samples "
            f"(first at (freq, time, baseline) = {tuple(int(i) for i in idx)}); flag them with weight 0"
        )
    return np.where(bad, 0.0, d)


def draw_noise(key: jax.Array, sigma) -> jax.Array:
    """Complex Gaussian noise, each component ``N(0, sigma^2)`` (sigma per component)."""
    sigma = jnp.asarray(sigma)
    kr, ki = jax.random.split(key)
    return sigma * jax.random.normal(kr, sigma.shape, sigma.dtype) + 1j * sigma * jax.random.normal(
        ki, sigma.shape, sigma.dtype
    )
