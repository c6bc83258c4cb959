"""Index layout of spherical-harmonic modes (the realified vector): the one module that owns it.

Conventions (see README, "Conventions"):

* Complex coefficients ``a_lm`` for ``m >= 0`` are stored in healpy order
  (m-major: for m in 0..lmax, for l in m..lmax), length
  ``nalm = (lmax+1)(lmax+2)/2``.  Negative m follow from reality:
  ``a_{l,-m} = (-1)^m conj(a_lm)``.
* The *realified* parameter vector, length ``n = (lmax+1)**2``, is
  ``[Re a_lm for all (l, m>=0) in healpy order] ++ [Im a_lm for m>=1 in healpy order]``.
* The real basis map multiplying each realified entry:
  ``m = 0 -> Y_l0``; real part, ``m > 0 -> 2 Re Y_lm``; imaginary part,
  ``m > 0 -> -2 Im Y_lm``.  So ``I(n) = sum_k a_k f_k(n)`` exactly equals
  healpy's ``alm2map`` of the complex coefficients.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

__all__ = [
    "order_slots",
    "ModeTable",
    "n_alm",
    "n_params",
    "mode_table",
    "realify",
    "unrealify",
    "lmax_from_nparams",
]


def n_alm(lmax: int) -> int:
    """Number of complex coefficients with m >= 0 up to ``lmax`` (healpy's Alm.getsize)."""
    _check_lmax(lmax)
    return (lmax + 1) * (lmax + 2) // 2


def n_params(lmax: int) -> int:
    """Length of the realified parameter vector, ``(lmax+1)**2``."""
    _check_lmax(lmax)
    return (lmax + 1) ** 2


def lmax_from_nparams(n: int) -> int:
    """Invert :func:`n_params`; raises ``ValueError`` if ``n`` is not a square."""
    lmax = int(round(np.sqrt(n))) - 1
    if lmax < 0 or (lmax + 1) ** 2 != n:
        raise ValueError(f"{n} is not (lmax+1)**2 for any integer lmax >= 0")
    return lmax


def _check_lmax(lmax: int) -> None:
    if int(lmax) != lmax or lmax < 0:
        raise ValueError(f"lmax must be a non-negative integer, got {lmax!r}")


class ModeTable(NamedTuple):
    """Per-entry description of the realified vector (all arrays length n).

    Attributes:
        ell: degree l of each entry.
        m: order m >= 0 of each entry.
        is_imag: True for entries holding Im a_lm (only m >= 1).
        alm_index: index of the entry's complex coefficient in healpy order.
    """

    ell: np.ndarray
    m: np.ndarray
    is_imag: np.ndarray
    alm_index: np.ndarray


def mode_table(lmax: int) -> ModeTable:
    """The (l, m, re/im) meaning of every entry of the realified vector."""
    nalm = n_alm(lmax)
    m = np.concatenate([np.full(lmax + 1 - mm, mm) for mm in range(lmax + 1)])  # healpy's m-major order
    ell = np.concatenate([np.arange(mm, lmax + 1) for mm in range(lmax + 1)])
    pos = m > 0
    idx = np.concatenate([np.arange(nalm), np.flatnonzero(pos)])
    return ModeTable(
        ell=np.concatenate([ell, ell[pos]]).astype(np.int64),
        m=np.concatenate([m, m[pos]]).astype(np.int64),
        is_imag=np.concatenate([np.zeros(nalm, bool), np.ones(pos.sum(), bool)]),
        alm_index=idx.astype(np.int64),
    )


def realify(alm, lmax: int):
    """Complex healpy-ordered alm ``(..., nalm)`` -> realified ``(..., (lmax+1)**2)``.

    Works on NumPy and JAX arrays (returns the same kind).  ``Im a_l0`` is
    dropped; it must be zero for a real sky (not checked here).
    """
    nalm = n_alm(lmax)
    if alm.shape[-1] != nalm:
        raise ValueError(f"alm has last axis {alm.shape[-1]}, expected {nalm} for lmax={lmax}")
    xp = jnp if not isinstance(alm, np.ndarray) else np
    return xp.concatenate([alm.real, alm.imag[..., lmax + 1 :]], axis=-1)


def unrealify(a, lmax: int):
    """Realified ``(..., (lmax+1)**2)`` -> complex healpy-ordered alm ``(..., nalm)``."""
    nalm = n_alm(lmax)
    if a.shape[-1] != n_params(lmax):
        raise ValueError(
            f"realified vector has last axis {a.shape[-1]}, expected {n_params(lmax)} for lmax={lmax}"
        )
    xp = jnp if not isinstance(a, np.ndarray) else np
    re = a[..., :nalm]
    im = xp.concatenate([xp.zeros(a.shape[:-1] + (lmax + 1,), a.dtype), a[..., nalm:]], axis=-1)
    return re + 1j * im


@lru_cache(maxsize=32)
def order_slots(lmax: int) -> tuple[np.ndarray, np.ndarray]:
    """The realified entries of each order m: ``(lmax+1, B)`` indices and a mask, padded to the largest B.

    Row m holds the indices of ``Re a_lm`` (l = m..lmax) then ``Im a_lm`` (m > 0); ``B = 2 lmax + 1``
    (order 1's size; order 0 has ``lmax + 1``).  Host-side, cached: do not modify the arrays.
    """
    tab = mode_table(lmax)
    blocks = [np.flatnonzero(tab.m == m) for m in range(lmax + 1)]
    width = max(len(b) for b in blocks)
    idx = np.zeros((lmax + 1, width), np.int64)
    mask = np.zeros((lmax + 1, width), bool)
    for m, b in enumerate(blocks):
        idx[m, : len(b)] = b
        mask[m, : len(b)] = True
    return idx, mask
