"""Visibility response at the reference rotation angle (a sky quadrature).

``R[f, b, k] = sum_p  w_p A_i(p) A_j(p) exp(+2 pi i b_ij . s_p nu_f / c) f_k(p)``
over the HEALPix pixels ``p`` above the horizon at the reference local sidereal
angle, with ``b_ij = x_j - x_i`` (pyuvdata's ant2 - ant1), ``w_p = 4 pi / Npix``
(steradians), ``s_p`` the ENU unit vector of the pixel, ``A`` the unpolarised
voltage beams and ``f_k`` the real basis maps.  The fringe sign is matvis' and
pyuvdata's (``V_ij = <E_i^* E_j>``), and ``V`` is twice matvis' unpolarised
feed-x visibility (matvis gives each feed I/2); both pinned in
``tests/test_matvis.py``, see ``docs/conventions.md``.
A sky in Kelvin gives visibilities in K sr (multiply by ``2 k nu^2 / c^2`` for
Jy; see :func:`kelvin_sr_to_jy`).

Frames (idealised LST mode, the paper's): the coefficients live in an equatorial
frame that co-rotates with local sidereal angle; at LST ``t`` (radians) the
direction with hour angle ``h`` sees right ascension ``t - h``.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import healpy as hp
import jax
import jax.numpy as jnp
import numpy as np

from .harmonics import real_basis
from .instrument import Array, beam_amplitude, baseline_vectors
from .layout import n_params

__all__ = ["SkyGrid", "sky_grid", "response_matrix", "unique_beams", "kelvin_sr_to_jy", "SPEED_OF_LIGHT"]

SPEED_OF_LIGHT = 299792458.0  # m/s
BOLTZMANN = 1.380649e-23  # J/K


class SkyGrid(NamedTuple):
    """HEALPix pixels above the horizon at one local sidereal angle.

    Attributes:
        pix: (Npix_up,) RING pixel indices.
        theta, phi: (Npix_up,) equatorial colatitude and RA, radians.
        enu: (Npix_up, 3) topocentric unit vectors (East, North, Up).
        az_uvbeam, za: (Npix_up,) azimuth (North of East) and zenith angle, radians.
        weight_sr: solid angle per pixel, 4 pi / Npix.
        nside: HEALPix nside.
        lst_rad: the local sidereal angle of this grid, radians.
    """

    pix: np.ndarray
    theta: np.ndarray
    phi: np.ndarray
    enu: np.ndarray
    az_uvbeam: np.ndarray
    za: np.ndarray
    weight_sr: float
    nside: int
    lst_rad: float


def equatorial_to_enu(theta, phi, lst_rad: float, latitude_rad: float) -> np.ndarray:
    """ENU unit vectors of equatorial directions at local sidereal angle ``lst_rad``.

    Hour angle ``h = lst - RA``; standard spherical astronomy (no refraction,
    aberration or precession: the idealised co-rotating frame).
    """
    dec = np.pi / 2 - np.asarray(theta)
    ha = lst_rad - np.asarray(phi)
    sl, cl = np.sin(latitude_rad), np.cos(latitude_rad)
    e = -np.cos(dec) * np.sin(ha)
    n = cl * np.sin(dec) - sl * np.cos(dec) * np.cos(ha)
    u = sl * np.sin(dec) + cl * np.cos(dec) * np.cos(ha)
    return np.stack([e, n, u], axis=-1)


def sky_grid(nside: int, latitude_rad: float, lst_rad: float = 0.0) -> SkyGrid:
    """Pixels strictly above the horizon (Up > 0) at ``lst_rad``."""
    if not hp.isnsideok(nside):
        raise ValueError(f"nside must be a power of two, got {nside}")
    npix = hp.nside2npix(nside)
    theta, phi = hp.pix2ang(nside, np.arange(npix))
    enu = equatorial_to_enu(theta, phi, lst_rad, latitude_rad)
    up = enu[:, 2] > 0
    enu = enu[up]
    az = np.mod(np.arctan2(enu[:, 1], enu[:, 0]), 2 * np.pi)  # North of East (UVBeam)
    za = np.arccos(np.clip(enu[:, 2], -1.0, 1.0))
    return SkyGrid(
        pix=np.flatnonzero(up),
        theta=theta[up],
        phi=phi[up],
        enu=enu,
        az_uvbeam=az,
        za=za,
        weight_sr=4 * np.pi / npix,
        nside=int(nside),
        lst_rad=float(lst_rad),
    )


def kelvin_sr_to_jy(freqs_hz) -> np.ndarray:
    """Factor ``2 k nu^2 / c^2 * 1e26`` converting K sr to Jy, per frequency."""
    f = np.asarray(freqs_hz, np.float64)
    return 2 * BOLTZMANN * f**2 / SPEED_OF_LIGHT**2 * 1e26


@partial(jax.jit, static_argnums=(0, 1))
def _quadrature(lmax, chunk, theta, phi, enu, weight, amp, pair_a, pair_b, bvec_wl):
    """Accumulate R over pixel chunks.  Inputs padded to a multiple of ``chunk``.

    theta, phi, weight: (Nc, chunk); enu: (Nc, chunk, 3); amp: (Nc, Nf, Nbeam, chunk);
    pair_a/pair_b: (Nbl,) beam indices; bvec_wl: (Nf, Nbl, 3) baselines in wavelengths.
    """
    nf, nbl = bvec_wl.shape[:2]
    n = n_params(lmax)

    def body(acc, xs):
        th, ph, s, w, A = xs
        F = real_basis(lmax, th, ph)  # (chunk, n)
        phase = 2 * jnp.pi * jnp.einsum("fbd,pd->fbp", bvec_wl, s)  # +: matvis/pyuvdata sign
        beam = A[:, pair_a, :] * A[:, pair_b, :] * w[None, None, :]  # (Nf, Nbl, chunk)
        kr = beam * jnp.cos(phase)
        ki = beam * jnp.sin(phase)
        acc_r, acc_i = acc
        acc_r = acc_r + jnp.einsum("fbp,pk->fbk", kr, F)
        acc_i = acc_i + jnp.einsum("fbp,pk->fbk", ki, F)
        return (acc_r, acc_i), None

    zero = jnp.zeros((nf, nbl, n), theta.dtype)
    (rr, ri), _ = jax.lax.scan(body, (zero, zero), (theta, phi, enu, weight, amp))
    return rr + 1j * ri


def unique_beams(beams) -> tuple[list, np.ndarray]:
    """Distinct beam objects (by identity) and, per antenna, the index of its beam."""
    uniq: list = []
    idx = np.empty(len(beams), np.int64)
    for i, b in enumerate(beams):
        for j, u in enumerate(uniq):
            if u is b:
                idx[i] = j
                break
        else:
            uniq.append(b)
            idx[i] = len(uniq) - 1
    return uniq, idx


def response_matrix(
    array: Array,
    pairs: np.ndarray,
    freqs_hz,
    lmax: int,
    nside: int,
    *,
    lst_ref_rad: float = 0.0,
    chunk: int = 4096,
) -> jax.Array:
    """Complex response of each baseline and frequency to each realified mode.

    Args:
        array: the :class:`~gcrsky.instrument.Array` (positions, latitude, beams).
        pairs: (Nbl, 2) antenna index pairs (i, j); autos (i, i) allowed.
        freqs_hz: (Nf,) frequencies, Hz.
        lmax: maximum degree (static).
        nside: HEALPix nside of the quadrature grid.
        lst_ref_rad: local sidereal angle of the reference grid, radians.
        chunk: pixels per batch; memory is O(chunk * (lmax+1)**2 + Nf*Nbl*chunk).

    Returns:
        (Nf, Nbl, (lmax+1)**2) complex128 response in K sr per unit coefficient (K).
    """
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    if freqs.ndim != 1 or not np.all(freqs > 0):
        raise ValueError("freqs_hz must be a 1-D array of positive frequencies")
    pairs = np.asarray(pairs, np.int64)
    nant = array.positions_enu_m.shape[0]
    if pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.min() < 0 or pairs.max() >= nant:
        raise ValueError(f"pairs must be (Nbl, 2) antenna indices in [0, {nant}), got shape {pairs.shape}")
    grid = sky_grid(nside, array.latitude_rad, lst_ref_rad)

    uniq, beam_idx = unique_beams(array.beams)  # amplitude maps once per distinct beam
    amp = np.stack([beam_amplitude(b, grid.az_uvbeam, grid.za, freqs) for b in uniq], axis=1)  # (Nf, Nb, Np)

    npix = grid.theta.size
    nchunk = -(-npix // chunk)
    pad = nchunk * chunk - npix

    def padded(x, axis=0):
        widths = [(0, 0)] * x.ndim
        widths[axis] = (0, pad)
        return np.pad(x, widths)

    theta = padded(grid.theta).reshape(nchunk, chunk)
    phi = padded(grid.phi).reshape(nchunk, chunk)
    enu = padded(grid.enu).reshape(nchunk, chunk, 3)
    weight = padded(np.full(npix, grid.weight_sr)).reshape(nchunk, chunk)
    amp = padded(amp, axis=2).reshape(freqs.size, len(uniq), nchunk, chunk).transpose(2, 0, 1, 3)
    bvec = baseline_vectors(array.positions_enu_m, pairs)
    bvec_wl = bvec[None, :, :] * (freqs[:, None, None] / SPEED_OF_LIGHT)
    return _quadrature(
        int(lmax),
        int(chunk),
        jnp.asarray(theta),
        jnp.asarray(phi),
        jnp.asarray(enu),
        jnp.asarray(weight),
        jnp.asarray(amp),
        jnp.asarray(beam_idx[pairs[:, 0]]),
        jnp.asarray(beam_idx[pairs[:, 1]]),
        jnp.asarray(bvec_wl),
    )
