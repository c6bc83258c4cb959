"""Response matrix by spherical-harmonic transforms of each baseline's kernel map.

:func:`response_matrix_sht` computes exactly the quantity of
:func:`gcrsky.instrument.response_matrix`,

``R[f, b, k] = sum_p  w_p A_i(p) A_j(p) exp(+2 pi i b_ij . s_p nu_f / c) f_k(p)``,

over the same HEALPix pixels (RING order, strictly above the horizon, Up > 0, at
``lst_ref_rad``; :func:`gcrsky.instrument.sky_grid`), the same weight
``w_p = 4 pi / Npix`` (steradians), the same ENU conversion
(:func:`gcrsky.instrument.equatorial_to_enu`), the same beam kernels
(:func:`gcrsky.instrument.baseline_kernels`: ``A_i A_j`` with ``A = sqrt(P_xx)`` by
default, or the polarisation products ``pols`` as in ``response_matrix``; azimuth North of
East), the same baseline sign (``b_ij = x_j - x_i``, fringe ``exp(+2 pi i b.s/lambda)``)
and the same realified basis ``f_k`` (:mod:`gcrsky.sphere.modes`: ``m = 0 -> Y_l0``,
Re part ``m > 0 -> 2 Re Y_lm``, Im part ``m > 0 -> -2 Im Y_lm``).  Only the
order of the sums differs, so the two agree to floating-point rounding (tested to
~1e-12 relative in ``tests/test_response_sht.py``).

Method.  For each frequency and baseline the kernel map
``M_p = K_b(p) exp(+2 pi i b.s_p / lambda)`` (zero below the horizon; ``K_b = A_i A_j`` or
the row's complex cross power beam ``K_r + i K_i``) is
split into the real maps ``Re M`` and ``Im M``, each transformed with
``healpy.map2alm(iter=0, use_weights=False, use_pixel_weights=False)``, which is
the plain pixel sum ``a_lm = (4 pi / Npix) sum_p M_p conj(Y_lm(p))``.  For a real
map ``sum_p M_p Y_lm(p) = conj(sum_p M_p conj(Y_lm(p)))``, hence the realified
projection ``P_k = sum_p w_p M_p f_k(p)`` is

* ``m = 0``:           ``P = Re a_l0``  (``Im a_l0 = 0``),
* Re entry, ``m > 0``: ``P = 2 Re a_lm``,
* Im entry, ``m > 0``: ``P = -2 Im conj(a_lm) = +2 Im a_lm``,

i.e. ``P = realify(a) * (1 if m == 0 else 2)``, and ``R = P[Re M] + i P[Im M]``.
The healpy weight ``4 pi / Npix`` is the response's ``w_p``, so no further scaling.

Cost.  The direct quadrature evaluates all ``(lmax+1)^2`` basis maps on the
``~Npix/2`` visible pixels (``O(Npix lmax^2)``, shared by all baselines) and
contracts them with the kernels: ``O(Nf Nbl Npix lmax^2)``.  Here each of the
``2 Nf Nbl`` real maps costs one ring-based SHT, ``O(Npix^{1/2} lmax^2 + Npix log Npix)``,
i.e. ``O(Npix^{3/2})`` when ``lmax ~ nside``: ``O(Nf Nbl Npix^{3/2})`` in all (the
full-sky maps are transformed whatever the horizon).  Measured on 2 shared CPU
cores, nside 128, 2 frequencies, 45 baselines (direct timings include JIT):
lmax 20: 1.8 s direct vs 1.2 s here; lmax 50: 7.0 s vs 1.0 s; lmax 100: 38.5 s vs
4.0 s (10 baselines: 34 s vs 0.9 s).  Since then the default
``response_matrix(method="rings")`` factors the same sum through the HEALPix rings
in JAX and skips pixels below the beam floor; side by side it was faster (nside 128,
2 channels: lmax 50, 10 antennas 0.39 s vs 4.1 s; lmax 100, 37 antennas 21 s vs 89 s,
on a loaded 2-core box, where healpy's OpenMP threads suffer most), but on a quiet box
this route's threaded transforms can win at lmax >= 100 (13.7 s for that case measured
here earlier, against ~30 s for the rings under load: not a side-by-side number).  Side by
side at HERA-core scale (630 unique rows of the 331-antenna hexagon, nside 256, one
channel, load ~1-2; ``benchmarks/scale.py`` section (B')): lmax 300, rings 115.6 s vs
41.5 s here; lmax 150, 27.0 s vs 24.6 s; equal to 3.3e-14 of the largest entry.  So
``response_matrix(method="auto")`` (the default) uses this route from
:data:`gcrsky.instrument.response.RESPONSE_SHT_MIN_LMAX` = 200 on, and it remains the
independent cross-check of the rings below that (healpy's transforms, not gcrsky's
Legendre recursion).  Since then :mod:`gcrsky.instrument.response_ducc` transforms the same
maps with ducc0 over only the rings that hold beam pixels, faster at every lmax measured
(lmax 650, nside 512: 2.9x per row under load; see that module), so ``"auto"`` uses this
route only where ducc0 is not installed.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..base.units import SPEED_OF_LIGHT
from ..sphere.modes import mode_table, n_params, realify
from .antennas import AntennaArray, baseline_vectors
from .polarization import baseline_kernels, normalise_pols
from .skygrid import sky_grid

__all__ = ["realified_projection", "response_matrix_sht"]


def realified_projection(alm: np.ndarray, lmax: int) -> np.ndarray:
    """``sum_p w_p M_p f_k(p)`` from healpy's ``a_lm`` of a *real* map ``M``.

    Args:
        alm: (..., nalm) complex, healpy order, ``a_lm = w sum_p M_p conj(Y_lm(p))``.
        lmax: maximum degree.

    Returns:
        (..., (lmax+1)**2) real projections onto the realified basis ``f_k``.
    """
    factor = np.where(mode_table(lmax).m == 0, 1.0, 2.0)
    return realify(np.asarray(alm), lmax) * factor


def response_matrix_sht(
    array: AntennaArray,
    pairs: np.ndarray,
    freqs_hz,
    lmax: int,
    nside: int,
    lst_ref_rad: float = 0.0,
    *,
    chunk: int = 16,
    pols=None,
) -> jax.Array:
    """Same response as :func:`gcrsky.instrument.response_matrix`, built with healpy SHTs.

    Args:
        array: the :class:`~gcrsky.instrument.AntennaArray` (positions, latitude, beams).
        pairs: (Nbl, 2) antenna index pairs (i, j); autos (i, i) allowed.
        freqs_hz: (Nf,) frequencies, Hz.
        lmax: maximum degree; must satisfy ``lmax <= 3 nside - 1`` (beyond that the
            pixel quadrature cannot resolve the modes and healpy's transform is
            not meaningful).
        nside: HEALPix nside of the quadrature grid (as accepted by ``healpy.isnsideok``).
        lst_ref_rad: local sidereal angle of the reference grid, radians.
        chunk: baselines transformed per batch; memory is
            ``~2 * chunk * 12 nside^2 * 8`` bytes for the maps (50 MB at nside 128,
            chunk 16) plus the output.
        pols: the visibility product of each row (``None``: the unpolarised ``A_i A_j``), as
            for :func:`gcrsky.instrument.response_matrix`.

    Returns:
        (Nf, Nbl, (lmax+1)**2) complex response in K sr per unit coefficient (K),
        as a JAX array (complex128 when x64 is enabled, as for ``response_matrix``).
    """
    import healpy as hp

    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    if freqs.ndim != 1 or not np.all(freqs > 0):
        raise ValueError("freqs_hz must be a 1-D array of positive frequencies")
    if int(lmax) != lmax or lmax < 0:
        raise ValueError(f"lmax must be a non-negative integer, got {lmax!r}")
    lmax = int(lmax)
    if not hp.isnsideok(nside):
        raise ValueError(f"nside must be a valid HEALPix nside, got {nside}")
    nside = int(nside)
    if lmax > 3 * nside - 1:
        raise ValueError(
            f"lmax={lmax} exceeds 3*nside-1={3 * nside - 1} for nside={nside}: "
            "the HEALPix quadrature cannot resolve these modes; raise nside"
        )
    if int(chunk) != chunk or chunk < 1:
        raise ValueError(f"chunk must be a positive integer, got {chunk!r}")
    chunk = int(chunk)
    pairs = np.asarray(pairs, np.int64)
    nant = array.positions_enu_m.shape[0]
    if pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.min() < 0 or pairs.max() >= nant:
        raise ValueError(f"pairs must be (Nbl, 2) antenna indices in [0, {nant}), got shape {pairs.shape}")
    pols = normalise_pols(pols, pairs.shape[0])

    grid = sky_grid(nside, array.latitude_rad, lst_ref_rad)
    npix_full = hp.nside2npix(nside)
    if not np.isclose(grid.weight_sr, 4 * np.pi / npix_full):  # healpy's implicit weight
        raise AssertionError("sky_grid weight is not 4 pi / Npix; the SHT scaling would be wrong")

    kern = baseline_kernels(array.beams, pairs, grid.az_uvbeam, grid.za, freqs, pols)  # (Nf, Nk, Np)
    K, kidx = kern.kernels, kern.index
    bvec = baseline_vectors(np.asarray(array.positions_enu_m, np.float64), pairs)  # (Nbl, 3) m

    nbl = pairs.shape[0]
    out = np.empty((freqs.size, nbl, n_params(lmax)), np.complex128)
    maps = np.zeros((2 * min(chunk, nbl), npix_full), np.float64)
    for f, nu in enumerate(freqs):
        for b0 in range(0, nbl, chunk):
            sl = slice(b0, min(b0 + chunk, nbl))
            nb = sl.stop - sl.start
            beam = K[f, kidx[sl]]  # (nb, Np)
            phase = (2 * np.pi * nu / SPEED_OF_LIGHT) * (bvec[sl] @ grid.enu.T)  # +: matvis/pyuvdata sign
            m = maps[: 2 * nb]
            if np.isrealobj(beam):
                m[:nb, grid.pix] = beam * np.cos(phase)
                m[nb:, grid.pix] = beam * np.sin(phase)
            else:
                m[:nb, grid.pix] = beam.real * np.cos(phase) - beam.imag * np.sin(phase)
                m[nb:, grid.pix] = beam.real * np.sin(phase) + beam.imag * np.cos(phase)
            alm = np.atleast_2d(
                hp.map2alm(m, lmax=lmax, mmax=lmax, iter=0, pol=False, use_weights=False, use_pixel_weights=False)
            )
            proj = realified_projection(alm, lmax)  # (2 nb, n)
            out[f, sl] = proj[:nb] + 1j * proj[nb:]
    return jnp.asarray(out)
