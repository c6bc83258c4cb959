"""Response matrix by ducc0's adjoint spherical-harmonic synthesis over the beam's rings only.

:func:`response_matrix_ducc` computes the sum of
:func:`gcrsky.instrument.response_sht.response_matrix_sht` (and of
:func:`gcrsky.instrument.response_matrix`),

``R[f, b, k] = sum_p  w_p K_b(p) exp(+2 pi i b_ij . s_p nu_f / c) f_k(p)``,

with the same pixels (HEALPix RING order, strictly above the horizon, Up > 0, at
``lst_ref_rad``; :func:`gcrsky.instrument.sky_grid`; less the ``beam_floor`` cut of
``response_matrix``, see below), the same weight ``w_p = 4 pi / Npix``
(steradians), the same kernels ``K_b`` (:func:`gcrsky.instrument.baseline_kernels`:
``A_i A_j`` or the polarisation products ``pols``), the same baseline sign
(``b_ij = x_j - x_i``) and the same realified basis ``f_k`` (:mod:`gcrsky.sphere.modes`).

Method.  For each frequency and row the real maps ``Re M`` and ``Im M`` of
``M_p = K_b(p) exp(+2 pi i b.s_p / lambda)`` (zero below the horizon) go through
``ducc0.sht.experimental.adjoint_synthesis`` (spin 0), which returns
``a_lm = sum_p M_p conj(Y_lm(p))`` in healpy's m-major order; times ``w = 4 pi / Npix`` that
is healpy's ``map2alm(iter=0, use_weights=False)``, and the realified projection is the
one of :func:`gcrsky.instrument.response_sht.realified_projection` (``Re a`` for ``m = 0``,
``2 Re a`` and ``2 Im a`` for ``m > 0``; see that module for the derivation), written
straight into the result.

Pixels and rings.  The summed pixels are those of ``response_matrix``'s ring quadrature:
above the horizon and, with ``beam_floor > 0``, with some kernel above ``beam_floor`` times
the peak (the dropped terms are each at most ``beam_floor x peak``: below float64 rounding of
the result at the default 1e-16; with ``beam_floor=0`` every pixel above the horizon, the
healpy route's sum term for term).  The maps are zero on every other pixel, so the transform
runs on the HEALPix ring geometry restricted to the rings that hold a summed pixel (on the
other rings the pixel sum is zero: skipping them is exact), and only the summed pixels'
fringes are evaluated.  The transform costs ``O(Nrings_kept lmax^2)`` per map and the fill
``O(Nsummed)``: a zenith-pointing 14 m dish at 100 MHz at HERA's latitude (nside 512)
keeps 1052 of 2047 rings and 456101 of the 1572864 pixels above the horizon.

Measured 2026-12-03 05:31-05:41 UTC, ``python benchmarks/response_routes.py --hera650`` (one run;
2 shared cores under heavy load from other jobs: ``/proc/loadavg`` 12.75 8.61 4.77 at the start,
16-22 throughout, so every time is inflated, the ratios less so; the 331-antenna HERA core,
630 unique rows, one channel at 100 MHz, 14 m Gaussian dish)::

    lmax 650, nside 512, all 630 rows, ducc: 135.0 s (0.214 s/row); result (630, 423801)
        complex128 = 4.27 GB, process peak (ru_maxrss) 5.10 GB
    lmax 650, nside 512, 32 rows: ducc 0.248 s/row, sht 0.834 s/row, rings 4.917 s/row
        (sht/ducc 3.4x, rings/ducc 19.8x); max |diff| / max |R|: ducc-sht 1.6e-14,
        ducc-rings 4.5e-14, sht-rings 4.3e-14
    lmax 300, nside 256, 32 rows: ducc 0.020 s/row, sht 0.051 s/row, rings 0.141 s/row
        (2.6x, 7.1x); ducc-sht 1.1e-14, ducc-rings 2.9e-14
    lmax 300, nside 256, all 630 rows, ducc: 13.0 s (healpy: 41.5 s, rings 115.6 s on
        2026-12-02 at load 0.4-2, ``benchmarks/scale.py`` (B'))

A second run (06:01-06:12 UTC, load 8.85 9.35 10.17 at the start, 10-12 throughout): 630 rows at
lmax 650 by ducc 178.7 s (0.284 s/row), peak 5.10 GB; 32 rows at lmax 650: ducc 0.258, sht 0.856,
rings 6.155 s/row (3.3x, 23.9x); at lmax 300: 0.051, 0.156, 0.500 s/row (3.1x, 9.8x); 630 rows
at lmax 300 by ducc 31.7 s; the same agreement.  The absolute times follow the other jobs'
load (135 s vs 179 s for the same build); the per-row ratios hold at ~3x healpy, 16-24x rings.

An earlier run (load 2.2 at the start, 6.3 after the build; before the fill was restricted to the pixels above the floor) gave
108.7 s for the 630 rows at lmax 650 (peak 5.20 GB) and 2.9x / 16.1x per row.  Smaller cases
(63 rows of the 37-antenna hexagon, 2 channels; 165 rows of 91 antennas at lmax 150, nside 128:
ducc 0.75 s, rings 9.2 s, sht 9.3 s) put ducc first at every size tried, hence
``RESPONSE_DUCC_MIN_LMAX = 0``.  The peak is the result plus ~0.8 GB (the sky grid at nside
512, the kernels, 2 chunk maps and their a_lm, JAX and healpy themselves): the result is
built in place in a 64-byte-aligned buffer that JAX adopts without a copy.  Where the time
goes (profile, 32 rows at lmax 650, load ~2, before that restriction): ~45% the transforms, the rest filling the maps
(one sin and cos per summed pixel and row, on ``nthreads`` threads) and the projection.
"""

from __future__ import annotations

import logging
import os
import threading

import jax
import numpy as np

from ..base.units import SPEED_OF_LIGHT
from ..sphere.modes import n_alm, n_params
from .antennas import AntennaArray, baseline_vectors
from .polarization import baseline_kernels, normalise_pols
from .skygrid import sky_grid

__all__ = ["ducc_available", "response_matrix_ducc"]

log = logging.getLogger(__name__)


def ducc_available() -> bool:
    """Whether ``ducc0`` (with ``ducc0.sht.experimental.adjoint_synthesis``) can be imported."""
    try:
        _ducc()
    except ImportError:
        return False
    return True


def _ducc():
    """The ``ducc0`` module, imported lazily; an :class:`ImportError` naming the package if missing."""
    try:
        import ducc0
        from ducc0.sht.experimental import adjoint_synthesis  # noqa: F401
    except ImportError as err:
        raise ImportError(
            "response_matrix(method='ducc') needs the package ducc0 (>= 0.34; `pip install ducc0`); "
            "method='sht' (healpy) or 'rings' computes the same response without it"
        ) from err
    return ducc0


def _ring_subset(ducc0, nside: int, pix: np.ndarray):
    """The ring geometry of the rings holding any of the pixels ``pix``, and where they lie in it.

    Args:
        ducc0: the module.
        nside: HEALPix nside.
        pix: (Ns,) RING indices of the summed pixels (above the horizon and the floor).

    Returns:
        ``(geom, cidx)``: ``geom`` the keyword arguments ``theta, phi0, nphi, ringstart`` of
        the rings holding a summed pixel (``ringstart`` into the compact map of those rings
        only, ``npix_sub = sum(nphi)`` values); ``cidx`` (Ns,) each pixel's index in that map.
    """
    info = ducc0.healpix.Healpix_Base(int(nside), "RING").sht_info()
    start = info["ringstart"].astype(np.int64)
    ring = np.searchsorted(start, pix, side="right") - 1  # (Np,) ring of each pixel
    rings = np.unique(ring)
    nphi = info["nphi"][rings]
    newstart = np.concatenate([[0], np.cumsum(nphi.astype(np.int64))[:-1]])
    geom = {
        "theta": np.ascontiguousarray(info["theta"][rings]),
        "phi0": np.ascontiguousarray(info["phi0"][rings]),
        "nphi": np.ascontiguousarray(nphi),
        "ringstart": newstart.astype(info["ringstart"].dtype),
    }
    slot = np.full(start.size, -1, np.int64)
    slot[rings] = np.arange(rings.size)
    cidx = newstart[slot[ring]] + (pix - start[ring])
    return geom, cidx


def _aligned_empty(shape, dtype, align: int = 64) -> np.ndarray:
    """An uninitialised C-contiguous array whose data start at a multiple of ``align`` bytes.

    JAX's CPU client adopts such a buffer without a copy (``device_put(..., may_alias=True)``),
    so the (possibly several GB) result is never held twice.
    """
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    buf = np.empty(nbytes + align, np.uint8)
    off = (-buf.ctypes.data) % align
    return buf[off : off + nbytes].view(dtype).reshape(shape)


def _adopt(out: np.ndarray) -> jax.Array:
    """``out`` as a JAX array, without a copy where this JAX's ``device_put`` takes ``may_alias``."""
    try:
        return jax.device_put(out, may_alias=True)
    except TypeError:  # older JAX: no may_alias (one transient copy)
        return jax.numpy.asarray(out)


def _write_projection(out_rows: np.ndarray, alm: np.ndarray, nb: int, lmax: int, w: float) -> None:
    """``out_rows = P[Re M] + i P[Im M]`` in place, ``P`` the realified projection of ``w a_lm``.

    Args:
        out_rows: (nb, (lmax+1)**2) complex view of the result.
        alm: (2 nb, 1, nalm) complex ``a_lm`` of the maps ``Re M`` (first ``nb``) and ``Im M``.
        nb: rows in this batch.
        lmax: maximum degree.
        w: the pixel weight ``4 pi / Npix``.
    """
    nalm = n_alm(lmax)
    a_re, a_im = alm[:nb, 0], alm[nb:, 0]
    re, im = out_rows.real, out_rows.imag  # views: written in place
    # entries 0..nalm-1: Re a_lm, times 1 (m = 0: the first lmax+1) or 2 (m > 0)
    np.multiply(a_re.real, 2 * w, out=re[:, :nalm])
    np.multiply(a_im.real, 2 * w, out=im[:, :nalm])
    re[:, : lmax + 1] *= 0.5
    im[:, : lmax + 1] *= 0.5
    # entries nalm..: 2 Im a_lm for m > 0
    np.multiply(a_re.imag[:, lmax + 1 :], 2 * w, out=re[:, nalm:])
    np.multiply(a_im.imag[:, lmax + 1 :], 2 * w, out=im[:, nalm:])


class _MapFiller:
    """Writes ``Re M`` and ``Im M`` of a batch of rows into the compact ring maps, on threads.

    ``M_p = K_b(p) exp(+2 pi i b.s_p / lambda)`` on the summed pixels (the others stay 0).
    One row at a time per thread, through per-thread buffers of one row (no full-batch
    temporaries); NumPy's ufuncs release the GIL, so ``nthreads`` rows proceed at once.

    Args:
        K: (Nf, Nk, Ns) kernels on the summed pixels, real or complex.
        kidx: (Nbl,) kernel of each row.
        enu_t: (3, Ns) ENU unit vectors of the summed pixels.
        cidx: (Ns,) their index in the compact map.
        nthreads: worker threads.
    """

    def __init__(self, K, kidx, enu_t, cidx, nthreads: int):
        from concurrent.futures import ThreadPoolExecutor

        self.K, self.kidx, self.enu_t, self.cidx = K, kidx, enu_t, cidx
        self.pool = ThreadPoolExecutor(max(1, nthreads))
        self.local = threading.local()

    def _row(self, maps, nb: int, f: int, b: int, row: int, b_wl) -> None:
        loc = self.local
        if not hasattr(loc, "ph"):
            loc.ph, loc.c, loc.s = (np.empty(self.cidx.size) for _ in range(3))
        ph, c, s = loc.ph, loc.c, loc.s
        np.matmul((2 * np.pi) * b_wl, self.enu_t, out=ph)  # +: matvis/pyuvdata sign
        np.cos(ph, out=c)
        np.sin(ph, out=s)
        beam = self.K[f, self.kidx[b]]
        if np.isrealobj(beam):
            maps[row, 0, self.cidx] = np.multiply(beam, c, out=ph)
            maps[nb + row, 0, self.cidx] = np.multiply(beam, s, out=ph)
        else:  # (K_r + i K_i)(c + i s)
            maps[row, 0, self.cidx] = beam.real * c - beam.imag * s
            maps[nb + row, 0, self.cidx] = beam.real * s + beam.imag * c

    def __call__(self, maps: np.ndarray, f: int, sl: slice, bvec_wl: np.ndarray) -> None:
        """Fill ``maps[:nb]`` (Re) and ``maps[nb:2nb]`` (Im) for rows ``sl`` at channel ``f``."""
        nb = sl.stop - sl.start
        jobs = [self.pool.submit(self._row, maps, nb, f, sl.start + r, r, bvec_wl[r]) for r in range(nb)]
        for j in jobs:
            j.result()

    def close(self) -> None:
        self.pool.shutdown()


def _check_args(array: AntennaArray, pairs, freqs_hz, lmax, nside, chunk):
    """``(freqs (Nf,), pairs (Nbl, 2), lmax, nside, chunk)`` checked (as ``response_matrix_sht``)."""
    import healpy as hp

    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    if freqs.ndim != 1 or not np.all(freqs > 0):
        raise ValueError("freqs_hz must be a 1-D array of positive frequencies")
    if int(lmax) != lmax or lmax < 0:
        raise ValueError(f"lmax must be a non-negative integer, got {lmax!r}")
    if not hp.isnsideok(nside):
        raise ValueError(f"nside must be a valid HEALPix nside, got {nside}")
    if lmax > 3 * nside - 1:
        raise ValueError(
            f"lmax={lmax} exceeds 3*nside-1={3 * nside - 1} for nside={nside}: "
            "the HEALPix quadrature cannot resolve these modes; raise nside"
        )
    if int(chunk) != chunk or chunk < 1:
        raise ValueError(f"chunk must be a positive integer, got {chunk!r}")
    pairs = np.asarray(pairs, np.int64)
    nant = array.positions_enu_m.shape[0]
    if pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.min() < 0 or pairs.max() >= nant:
        raise ValueError(f"pairs must be (Nbl, 2) antenna indices in [0, {nant}), got shape {pairs.shape}")
    return freqs, pairs, int(lmax), int(nside), int(chunk)


def response_matrix_ducc(
    array: AntennaArray,
    pairs: np.ndarray,
    freqs_hz,
    lmax: int,
    nside: int,
    lst_ref_rad: float = 0.0,
    *,
    beam_floor: float = 1e-16,
    chunk: int = 8,
    nthreads: int | None = None,
    pols=None,
) -> jax.Array:
    """Same response as :func:`gcrsky.instrument.response_matrix`, built with ducc0 transforms.

    Args:
        array: the :class:`~gcrsky.instrument.AntennaArray` (positions, latitude, beams).
        pairs: (Nbl, 2) antenna index pairs (i, j); autos (i, i) allowed.
        freqs_hz: (Nf,) frequencies, Hz.
        lmax: maximum degree, ``<= 3 nside - 1``.
        nside: HEALPix nside of the quadrature grid (a power of 2).
        lst_ref_rad: local sidereal angle of the reference grid, radians.
        beam_floor: pixels where every kernel ``|K|`` (all frequencies and rows) is at
            most ``beam_floor`` times the peak are left out, as in ``response_matrix``, and
            the rings holding none of the others are skipped (0: every pixel above the
            horizon, the healpy route's sum).
        chunk: rows transformed per ducc0 call (``2 chunk`` real maps); the maps take
            ``2 chunk Npix_rings 8`` bytes (244 MB at nside 512, chunk 8, for the dish above).
        nthreads: ducc0 threads; default the CPUs this process may use.
        pols: the visibility product of each row (``None``: the unpolarised ``A_i A_j``),
            as for :func:`gcrsky.instrument.response_matrix`.

    Returns:
        (Nf, Nbl, (lmax+1)**2) complex128 response in K sr per unit coefficient (K), a JAX
        array that adopts the NumPy buffer it was built in (no second full-size copy).
    """
    ducc0 = _ducc()
    from ducc0.sht.experimental import adjoint_synthesis

    freqs, pairs, lmax, nside, chunk = _check_args(array, pairs, freqs_hz, lmax, nside, chunk)
    if not (0.0 <= beam_floor < 1.0):
        raise ValueError(f"beam_floor must be in [0, 1), got {beam_floor!r}")
    nthreads = len(os.sched_getaffinity(0)) if nthreads is None else int(nthreads)
    pols = normalise_pols(pols, pairs.shape[0])
    grid = sky_grid(nside, array.latitude_rad, lst_ref_rad)
    w = float(grid.weight_sr)

    kern = baseline_kernels(array.beams, pairs, grid.az_uvbeam, grid.za, freqs, pols)  # (Nf, Nk, Np)
    peak = np.max(np.abs(kern.kernels), axis=(0, 1))  # (Np,)
    keep = peak > beam_floor * peak.max() if beam_floor > 0 else np.ones(peak.size, bool)
    geom, cidx = _ring_subset(ducc0, nside, grid.pix[keep])
    K = kern.kernels[:, :, keep]  # (Nf, Nk, Ns)
    enu = grid.enu[keep]
    npix_sub = int(geom["ringstart"][-1] + geom["nphi"][-1]) if geom["nphi"].size else 0
    log.info(
        "ducc response: %d of %d rings, %d map pixels, %d summed pixels (of %d above the horizon)",
        geom["nphi"].size, 4 * nside - 1, npix_sub, cidx.size, grid.pix.size,
    )  # fmt: skip
    bvec = baseline_vectors(np.asarray(array.positions_enu_m, np.float64), pairs)  # (Nbl, 3) m

    nbl = pairs.shape[0]
    out = _aligned_empty((freqs.size, nbl, n_params(lmax)), np.complex128)
    if npix_sub == 0:
        out[...] = 0
        return _adopt(out)
    maps = np.zeros((2 * min(chunk, nbl), 1, npix_sub), np.float64)
    alm = np.empty((2 * min(chunk, nbl), 1, n_alm(lmax)), np.complex128)
    fill = _MapFiller(K, kern.index, np.ascontiguousarray(enu.T), cidx, nthreads)
    try:
        for f, nu in enumerate(freqs):
            bvec_wl = bvec * (nu / SPEED_OF_LIGHT)  # (Nbl, 3) wavelengths
            for b0 in range(0, nbl, chunk):
                sl = slice(b0, min(b0 + chunk, nbl))
                nb = sl.stop - sl.start
                fill(maps[: 2 * nb], f, sl, bvec_wl[sl])
                a = adjoint_synthesis(
                    map=maps[: 2 * nb], lmax=lmax, spin=0, nthreads=nthreads, alm=alm[: 2 * nb], **geom
                )
                _write_projection(out[f, sl], a, nb, lmax, w)
    finally:
        fill.close()
    return _adopt(out)
