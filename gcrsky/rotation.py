"""Rotation of the sky about the Earth's rotation axis (Wigner-D with beta=gamma=0).

A rotation of the sky by ``dphi`` in right ascension is diagonal in (l, m):
``a_lm -> a_lm exp(i m dphi)``.  With the co-rotating frame of
:mod:`gcrsky.response`, the visibility at local sidereal angle ``t`` is
``R(t_ref) . rotate(a, t - t_ref)``: ``rotate(a, d)`` is the map ``I(RA + d)``, i.e.
the sky shifted to *smaller* RA by ``d``, so that the direction that saw RA ``alpha``
at the reference angle sees RA ``alpha + d`` (pinned against matvis in
``tests/test_matvis.py`` and by ``tests/test_operator.py``).

On the realified vector this is a 2x2 rotation of each (Re a_lm, Im a_lm) pair by
``m dphi``; ``m = 0`` entries are unchanged.  The angle is a traced value (vmap
over times, differentiate in it); only the vector length is static.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .layout import lmax_from_nparams, mode_table, n_alm

__all__ = ["rotate", "rotate_complex_alm"]


def rotate(a: jax.Array, dphi) -> jax.Array:
    """Rotate realified coefficients ``a`` (..., n) by angle ``dphi`` (radians, scalar).

    Orthogonal: ``rotate(rotate(a, x), -x) == a`` and its transpose is ``rotate(., -dphi)``.
    Works on real arrays; apply to real and imaginary parts separately for complex input.
    """
    n = a.shape[-1]
    lmax = lmax_from_nparams(n)
    nalm = n_alm(lmax)
    m_alm = jnp.asarray(mode_table(lmax).m[:nalm], a.dtype)
    c = jnp.cos(m_alm * dphi)
    s = jnp.sin(m_alm * dphi)
    re = a[..., :nalm]
    im = jnp.concatenate([jnp.zeros(a.shape[:-1] + (lmax + 1,), a.dtype), a[..., nalm:]], axis=-1)
    re2 = re * c - im * s
    im2 = re * s + im * c
    return jnp.concatenate([re2, im2[..., lmax + 1 :]], axis=-1)


def rotate_complex_alm(alm: jax.Array, dphi, lmax: int) -> jax.Array:
    """Same rotation on complex healpy-ordered alm (..., nalm): ``a_lm exp(i m dphi)``."""
    m_alm = jnp.asarray(mode_table(lmax).m[: n_alm(lmax)])
    return alm * jnp.exp(1j * m_alm * dphi)
