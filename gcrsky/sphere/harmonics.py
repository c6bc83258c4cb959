"""Real spherical-harmonic basis maps, evaluated in JAX.

``real_basis(lmax, theta, phi)`` returns the basis map ``f_k`` of every entry of
the realified vector (see :mod:`gcrsky.sphere.modes`) at arbitrary directions, using the
orthonormal associated-Legendre recursion with the Condon-Shortley phase (healpy's
convention; pinned by ``tests/test_harmonics.py`` against ``healpy.alm2map``).
``lmax`` is static; directions are traced.  Stable for lmax up to a few hundred in
float64 (the sectoral seed ``sin^m theta`` underflows only within ~1e-300 of the poles).
"""

from __future__ import annotations

from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np

from .modes import mode_table

__all__ = ["real_basis", "legendre_table"]


@lru_cache(maxsize=32)
def _recursion_constants(lmax: int):
    L = lmax + 1
    ell = np.arange(L)[:, None].astype(np.float64)
    m = np.arange(L)[None, :].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.sqrt((4 * ell**2 - 1) / (ell**2 - m**2))  # a_lm, valid for m < l
        a_prev = np.sqrt((4 * (ell - 1) ** 2 - 1) / ((ell - 1) ** 2 - m**2))  # a_{l-1,m}, valid m < l-1
    valid2 = m <= ell - 2
    A = np.where(m <= ell - 1, a, 0.0)
    Binv = np.where(valid2, 1.0 / np.where(valid2, a_prev, 1.0), 0.0)
    # sectoral constants sqrt((2m+1)/(4 pi) prod_{k<=m} (2k-1)/(2k)) with (-1)^m
    mm = np.arange(L)
    logc = 0.5 * (np.log((2 * mm + 1) / (4 * np.pi)) + np.concatenate([[0.0], np.cumsum(np.log((2 * mm[1:] - 1) / (2 * mm[1:])))]))
    diag_c = ((-1.0) ** mm) * np.exp(logc)
    sub_c = np.sqrt(2 * mm + 3.0)
    return A, Binv, diag_c, sub_c


def legendre_table(lmax: int, x, sin_theta=None):
    """Orthonormal associated Legendre functions ``Pbar_lm(x)`` for 0 <= m <= l <= lmax.

    ``Y_lm(theta, phi) = Pbar_lm(cos theta) exp(i m phi)`` (Condon-Shortley phase
    included, as in healpy).

    Args:
        lmax: static maximum degree.
        x: (Npix,) cos(theta).
        sin_theta: optional (Npix,) sin(theta) (>= 0 for theta in [0, pi]).  Pass it
            when theta is known: ``sqrt(1 - x^2)`` loses all accuracy within ~1e-8 rad
            of the poles, and its derivative in theta is NaN on them.

    Returns:
        (lmax+1, Npix, lmax+1) array indexed [l, pixel, m]; zero where m > l.
    """
    A, Binv, diag_c, sub_c = (jnp.asarray(c) for c in _recursion_constants(lmax))
    x = jnp.asarray(x)
    if sin_theta is None:
        s = jnp.sqrt(jnp.clip(1.0 - x * x, 0.0, None))
    else:
        s = jnp.asarray(sin_theta)
    mvec = jnp.arange(lmax + 1)
    # sin^m theta, computed by cumulative products to stay exact for integer powers
    spow = jnp.cumprod(jnp.concatenate([jnp.ones_like(s)[:, None], jnp.repeat(s[:, None], lmax, axis=1)], axis=1), axis=1)
    diag = spow * diag_c[None, :]  # Pbar_mm, (Npix, L)
    xs = x[:, None]

    def step(carry, l):
        p1, p2 = carry  # Pbar_{l-1, m}, Pbar_{l-2, m}
        rec = A[l][None, :] * (xs * p1 - Binv[l][None, :] * p2)
        sub = xs * sub_c[None, :] * p1  # Pbar_{m+1, m} from Pbar_{m, m}
        pl = jnp.where(mvec[None, :] <= l - 2, rec, jnp.where(mvec[None, :] == l - 1, sub, 0.0))
        pl = jnp.where(mvec[None, :] == l, diag, pl)
        return (pl, p1), pl

    zero = jnp.zeros_like(diag)
    _, table = jax.lax.scan(step, (zero, zero), jnp.arange(lmax + 1))
    return table


@partial(jax.jit, static_argnums=0)
def real_basis(lmax: int, theta, phi):
    """Basis maps of the realified vector at the given directions.

    Args:
        lmax: static maximum degree.
        theta: (Npix,) colatitude in radians (equatorial: pi/2 - dec).
        phi: (Npix,) longitude in radians (equatorial: RA).

    Returns:
        (Npix, (lmax+1)**2) real array ``F`` with ``I(p) = F[p] @ a`` for realified ``a``:
        ``Y_l0``; ``2 Pbar_lm cos(m phi)`` for Re parts; ``-2 Pbar_lm sin(m phi)`` for Im parts.
    """
    tab = mode_table(lmax)
    table = legendre_table(lmax, jnp.cos(theta), jnp.sin(theta))  # [l, p, m]
    p_lm = table[tab.ell, :, tab.m].T  # (Npix, n)
    mphi = jnp.asarray(tab.m)[None, :] * phi[:, None]
    factor = jnp.where(jnp.asarray(tab.m) == 0, 1.0, 2.0)[None, :]
    trig = jnp.where(jnp.asarray(tab.is_imag)[None, :], -jnp.sin(mphi), jnp.cos(mphi))
    return p_lm * factor * trig
