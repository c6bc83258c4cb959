"""Rotations of the sky: about the Earth's axis (diagonal phases) and full Wigner-D.

A rotation of the sky by ``dphi`` in right ascension is diagonal in (l, m):
``a_lm -> a_lm exp(i m dphi)``.  With the co-rotating frame of
:mod:`gcrsky.instrument.response`, the visibility at local sidereal angle ``t`` is
``R(t_ref) . rotate(a, t - t_ref)``: ``rotate(a, d)`` is the map ``I(RA + d)``, i.e.
the sky shifted to *smaller* RA by ``d``, so that the direction that saw RA ``alpha``
at the reference angle sees RA ``alpha + d`` (pinned against matvis in
``tests/test_matvis.py`` and by ``tests/test_operator.py``).

On the realified vector this is a 2x2 rotation of each (Re a_lm, Im a_lm) pair by
``m dphi``; ``m = 0`` entries are unchanged.  The angle is a traced value (vmap
over times, differentiate in it); only the vector length is static.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .modes import lmax_from_nparams, mode_table, n_alm, realify, unrealify

__all__ = [
    "rotate",
    "rotate_complex_alm",
    "WignerBlocks",
    "wigner_band_edges",
    "wigner_band_shapes",
    "wigner_blocks",
    "wigner_lmax",
    "wigner_nbytes",
    "rotate_euler",
    "rotate_euler_transpose",
    "rotate_matrix",
    "rotation_matrix_zyz",
    "euler_zyz",
    "to_lm_grid",
    "from_lm_grid",
]


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


# ----------------------------------------------------------------------------------
# Full rotations: Wigner-D matrices of realified coefficients.
#
# Convention (healpy's rotate_alm, active): the rotation R = Rz(alpha) Ry(beta)
# Rz(gamma) acting on directions takes the sky I to I'(n) = I(R^-1 n), and
#     a'_lm = sum_m' D^l_mm'(alpha, beta, gamma) a_lm',
#     D = exp(-i alpha Jz) exp(-i beta Jy) exp(-i gamma Jz).
# exp(-i beta Jy) = exp(-i pi/2 Jz) U diag(exp(-i k beta)) U^T exp(+i pi/2 Jz),
# with U the real orthogonal eigenvectors of the real symmetric tridiagonal Jx
# (eigenvalues k = -l..l).  U depends only on l: it is computed once (numpy /
# LAPACK's tridiagonal eigensolver, accurate to ~l * 1e-16) and the angles enter
# only through phases, so one compiled function serves every angle: traced,
# vmappable and differentiable.
# ----------------------------------------------------------------------------------

#: Refuse Wigner tables above this size (bytes) with a clear error.
_MAX_WIGNER_BYTES = 4 * 2**30
#: Degree bands of :class:`WignerBlocks`: at most this many, of equal width in l.
WIGNER_BANDS = 16


def wigner_band_edges(lmax: int) -> list[int]:
    """Edges ``0 = l_0 < l_1 < ... = lmax + 1`` of the degree bands of :class:`WignerBlocks` up to ``lmax``."""
    lmax = int(lmax)
    return sorted(set(np.linspace(0, lmax + 1, min(WIGNER_BANDS, lmax + 1) + 1).round().astype(int).tolist()))


def wigner_band_shapes(lmax: int) -> list[tuple[int, int, int]]:
    """Shapes ``(l_1 - l_0, 2 t + 1, 2 t + 1)`` of the bands of :class:`WignerBlocks` up to ``lmax``
    (``t = l_1 - 1``, the band's widest degree)."""
    e = wigner_band_edges(lmax)
    return [(l1 - l0, 2 * l1 - 1, 2 * l1 - 1) for l0, l1 in zip(e[:-1], e[1:])]


class WignerBlocks(NamedTuple):
    """Per-degree eigenvector blocks of ``J_x`` for Wigner-D rotations up to ``lmax``, by degree band.

    The degrees ``0..lmax`` are split into :func:`wigner_band_edges` (at most :data:`WIGNER_BANDS`
    bands of equal width); the blocks of a band are stored at the width of its widest degree ``t``.

    Attributes:
        bands: tuple of (l_1 - l_0, 2 t + 1, 2 t + 1) float arrays; ``bands[b][l - l_0, t + m, t + k]``
            is the component ``m`` of the ``J_x`` eigenvector of eigenvalue ``k`` at degree l (zero for
            ``|m| > l`` or ``|k| > l``).  Memory ~``8 x 1.46 lmax^3`` bytes (0.37 of every degree padded
            to ``2 lmax + 1``): 12 MB at lmax 100, 94 MB at lmax 200, 0.83 GB at lmax 413.
    """

    bands: tuple


def wigner_lmax(blocks: WignerBlocks) -> int:
    """The largest degree ``blocks`` holds (static: from the array shapes)."""
    return (blocks.bands[-1].shape[1] - 1) // 2


def wigner_nbytes(blocks) -> float:
    """Bytes of ``blocks`` as float64 (from shapes only: a stand-in with shaped ``bands`` works too)."""
    return 8.0 * float(sum(np.prod(b.shape) for b in blocks.bands))


def wigner_blocks(lmax: int) -> WignerBlocks:
    """Precompute :class:`WignerBlocks` for degrees ``0..lmax`` (float64, NumPy/LAPACK)."""
    from scipy.linalg import eigh_tridiagonal

    lmax = int(lmax)
    if lmax < 0:
        raise ValueError(f"lmax must be non-negative, got {lmax}")
    size = 8 * sum(int(np.prod(sh)) for sh in wigner_band_shapes(lmax))
    if size > _MAX_WIGNER_BYTES:
        raise MemoryError(
            f"Wigner blocks for lmax={lmax} need {size / 2**30:.1f} GiB (limit "
            f"{_MAX_WIGNER_BYTES / 2**30:.0f} GiB); rotate in pixel space or with a lower lmax"
        )
    edges = wigner_band_edges(lmax)
    bands = []
    for l0, l1 in zip(edges[:-1], edges[1:]):
        t = l1 - 1
        u = np.zeros((l1 - l0, 2 * t + 1, 2 * t + 1))
        for l in range(l0, l1):
            if l == 0:
                u[0, t, t] = 1.0
                continue
            m = np.arange(-l, l)
            off = 0.5 * np.sqrt(l * (l + 1) - m * (m + 1.0))  # <m+1| Jx |m>
            w, v = eigh_tridiagonal(np.zeros(2 * l + 1), off)
            k = np.arange(-l, l + 1)
            if np.max(np.abs(w - k)) > 1e-8 * max(l, 1):
                raise RuntimeError(f"J_x eigenvalues at l={l} are not -l..l (max error {np.max(np.abs(w - k)):.2e})")
            u[l - l0, t - l : t + l + 1, t - l : t + l + 1] = v
        bands.append(jnp.asarray(u))
    return WignerBlocks(tuple(bands))


def _grid_index(lmax: int):
    """Healpy index of (l, m) on an (l, m >= 0) grid, and the validity mask."""
    l, m = np.meshgrid(np.arange(lmax + 1), np.arange(lmax + 1), indexing="ij")
    idx = np.where(m <= l, m * (2 * lmax + 1 - m) // 2 + l, 0)
    return idx, m <= l


def to_lm_grid(a: jax.Array) -> jax.Array:
    """Realified ``(..., (L+1)^2)`` -> complex ``a_lm`` on a grid ``(..., L+1 [l], L+1 [m >= 0])``."""
    lmax = lmax_from_nparams(a.shape[-1])
    alm = unrealify(a, lmax)
    idx, ok = _grid_index(lmax)
    return jnp.where(jnp.asarray(ok), alm[..., idx], 0.0)


def from_lm_grid(g: jax.Array) -> jax.Array:
    """Inverse of :func:`to_lm_grid` (entries with ``m > l`` are ignored)."""
    lmax = g.shape[-1] - 1
    mt = mode_table(lmax)
    nalm = n_alm(lmax)
    alm = g[..., mt.ell[:nalm], mt.m[:nalm]]
    return realify(alm, lmax)


def _lm_to_full(g: jax.Array) -> jax.Array:
    """(l, m >= 0) grid -> (l, m = -L..L) grid using ``a_{l,-m} = (-1)^m conj(a_lm)``."""
    lmax = g.shape[-1] - 1
    sign = (-1.0) ** np.arange(lmax, 0, -1)  # m = -L..-1
    neg = jnp.conj(g[..., :0:-1]) * sign
    return jnp.concatenate([neg, g], axis=-1)


def rotate_euler(a: jax.Array, alpha, beta, gamma, blocks: WignerBlocks) -> jax.Array:
    """Rotate realified coefficients by the Euler angles (ZYZ, active; radians).

    The result is the coefficient vector of ``I'(n) = I(R^-1 n)`` with
    ``R = Rz(alpha) Ry(beta) Rz(gamma)`` (healpy's ``rotate_alm(alm, psi=gamma,
    theta=beta, phi=alpha)``).  Angles are traced values.

    Args:
        a: (..., (lmax+1)^2) realified coefficients.
        alpha, beta, gamma: scalar angles.
        blocks: :func:`wigner_blocks` for at least ``lmax``.

    Returns:
        (..., (lmax+1)^2) rotated coefficients.  Cost ``O(lmax^3)``.
    """
    lmax = lmax_from_nparams(a.shape[-1])
    lb = wigner_lmax(blocks)
    if lb < lmax:
        raise ValueError(f"Wigner blocks go to lmax={lb}, coefficients need {lmax}")
    m = jnp.arange(-lmax, lmax + 1)
    f = _lm_to_full(to_lm_grid(a)) * jnp.exp(-1j * m * (gamma - jnp.pi / 2))
    y = _per_degree(blocks, f, "lmk,...lm->...lk") * jnp.exp(-1j * m * beta)
    z = _per_degree(blocks, y, "lmk,...lk->...lm") * jnp.exp(-1j * m * (alpha + jnp.pi / 2))
    return from_lm_grid(z[..., lmax:]).astype(a.dtype)


def _per_degree(blocks: WignerBlocks, g: jax.Array, spec: str) -> jax.Array:
    """The per-degree products ``sum_m u_l[m, k] g[..., l, m]`` (``spec`` ``"lmk,...lm->...lk"``) or their
    transposes (``"lmk,...lk->...lm"``) on a full-m grid ``g`` (..., L+1, 2L+1) complex, ``L <= `` the
    blocks' lmax.

    In real arithmetic (the blocks are real: the real and imaginary parts of ``g`` are two right-hand
    sides, half the flops of a complex product and no complex copy of the blocks), one batched dot per
    degree band of :class:`WignerBlocks` at the band's own width (the blocks of degree ``l`` are zero
    beyond ``|m|, |k| <= l``, so this is exact): ~2.7x fewer flops than every degree padded to ``2L+1``,
    and the dots' transient packing buffers (which XLA's CPU runtime allocates outside its buffer
    assignment, for every block of a batched dot at once) are those of real, band-sized blocks.
    """
    lmax = g.shape[-2] - 1
    parts = jnp.stack([g.real, g.imag])  # (2, ..., L+1, 2L+1)
    out, l0 = [], 0
    for band in blocks.bands:
        if l0 > lmax:
            break
        t = band.shape[1] // 2  # the band's widest degree
        l1 = min(l0 + band.shape[0], lmax + 1)
        w = min(t, lmax)  # orders beyond lmax are zero in g: drop them (a band cut by a smaller lmax)
        u = band[: l1 - l0, t - w : t + w + 1, t - w : t + w + 1] if (l1 - l0 < band.shape[0] or w < t) else band
        y = jnp.einsum(spec, u.astype(parts.dtype), parts[..., l0:l1, lmax - w : lmax + w + 1])
        out.append(jnp.pad(y, [(0, 0)] * (y.ndim - 1) + [(lmax - w, lmax - w)]))
        l0 += band.shape[0]
    y = jnp.concatenate(out, axis=-2)
    return jax.lax.complex(y[0], y[1])


def _realified_weight(n: int, dtype) -> jax.Array:
    """``W``: 1 on m = 0 entries, 2 on m > 0 ones (``sum_m |a_lm|^2 = a . W a``)."""
    return jnp.asarray(np.where(mode_table(lmax_from_nparams(n)).m == 0, 1.0, 2.0), dtype)


def rotate_euler_transpose(b: jax.Array, alpha, beta, gamma, blocks: WignerBlocks) -> jax.Array:
    """Plain transpose of :func:`rotate_euler` on realified vectors.

    D is unitary in the complex ``a_lm``, so the realified map ``Q`` satisfies
    ``Q^T W Q = W``: ``Q^T = W Q^-1 W^-1`` with ``Q^-1`` the rotation by
    ``(-gamma, -beta, -alpha)``.
    """
    w = _realified_weight(b.shape[-1], b.dtype)
    return w * rotate_euler(b / w, -gamma, -beta, -alpha, blocks)


def rotation_matrix_zyz(alpha, beta, gamma) -> np.ndarray:
    """``Rz(alpha) Ry(beta) Rz(gamma)`` (3, 3), right-handed, active."""

    def rz(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    c, s = np.cos(beta), np.sin(beta)
    ry = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return rz(alpha) @ ry @ rz(gamma)


def euler_zyz(rot) -> tuple[float, float, float]:
    """ZYZ Euler angles ``(alpha, beta, gamma)`` of a rotation matrix (inverse of
    :func:`rotation_matrix_zyz`).  Raises if ``rot`` is not a proper rotation."""
    r = np.asarray(rot, np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"rotation matrix must be 3x3, got shape {r.shape}")
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-9 or np.linalg.det(r) < 0:
        raise ValueError("matrix is not a proper rotation (R R^T != 1 or det < 0)")
    beta = float(np.arctan2(np.hypot(r[0, 2], r[1, 2]), r[2, 2]))
    if np.hypot(r[0, 2], r[1, 2]) < 1e-12:  # beta = 0 or pi: only alpha +- gamma is defined
        alpha = float(np.arctan2(r[1, 0], r[0, 0])) if r[2, 2] > 0 else float(np.arctan2(-r[1, 0], -r[0, 0]))
        return alpha, beta, 0.0
    return float(np.arctan2(r[1, 2], r[0, 2])), beta, float(np.arctan2(r[2, 1], -r[2, 0]))


def rotate_matrix(a: jax.Array, rot, blocks: WignerBlocks) -> jax.Array:
    """:func:`rotate_euler` for a 3x3 active rotation matrix ``rot`` (``I'(n) = I(rot^-1 n)``)."""
    return rotate_euler(a, *euler_zyz(rot), blocks)
