"""The quadrature grid of the response: HEALPix pixels above the horizon, in ENU.

Shared by the two response routes (:mod:`gcrsky.instrument.response`, rings / direct,
and :mod:`gcrsky.instrument.response_sht`, healpy transforms), which therefore never
import each other's module for it.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

__all__ = ["SkyGrid", "equatorial_to_enu", "sky_grid"]


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
    """Pixels strictly above the horizon (Up > 0) at ``lst_rad`` (cached; arrays read-only)."""
    return _sky_grid(int(nside), float(latitude_rad), float(lst_rad))


@lru_cache(maxsize=16)
def _sky_grid(nside: int, latitude_rad: float, lst_rad: float) -> SkyGrid:
    import healpy as hp

    if not hp.isnsideok(nside):
        raise ValueError(f"nside must be a power of two, got {nside}")
    npix = hp.nside2npix(nside)
    theta, phi = hp.pix2ang(nside, np.arange(npix))
    enu = equatorial_to_enu(theta, phi, lst_rad, latitude_rad)
    up = enu[:, 2] > 0
    enu = enu[up]
    az = np.mod(np.arctan2(enu[:, 1], enu[:, 0]), 2 * np.pi)  # North of East (UVBeam)
    za = np.arccos(np.clip(enu[:, 2], -1.0, 1.0))
    grid = SkyGrid(
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
    for x in grid:
        if isinstance(x, np.ndarray):
            x.setflags(write=False)
    return grid
