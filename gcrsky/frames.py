"""Real observing times: sidereal angles and the fixed ICRS -> apparent-of-date map.

The idealised frame of :mod:`gcrsky.response` co-rotates with the Earth: it is the
CIRS of the observing epoch, with the "LST" of a time equal to the *local Earth
rotation angle* (ERA + east longitude); that identification is good to 3.5e-6 rad
(diurnal aberration and polar motion; ``tests/test_matvis.py``).  A sky given in
ICRS differs from it by frame bias, precession-nutation (~0.3 deg in 2026) and annual
aberration (~1e-4 rad, not a rigid rotation).  DESIGN section 2, mode (b):

    V(t) = R(lst_ref) . rotate(M a_icrs, ERA_loc(t) - lst_ref)

with one fixed linear map ``M`` from realified ICRS coefficients (lmax) to apparent
CIRS coefficients (``lmax_out`` >= lmax, a few degrees more to hold aberration's
tiny leakage).  ``M`` is computed exactly by astropy's transform of a Gauss-Legendre
grid and quadrature projection: any astropy frame pair works, so ``M`` is a Wigner-D
rotation when the transform is a rotation (tested against healpy's ``rotate_alm``).
"""

from __future__ import annotations

import numpy as np

from .harmonics import real_basis
from .layout import mode_table, n_params

__all__ = ["local_sidereal_angles", "alm_frame_matrix", "icrs_to_apparent_matrix"]


def local_sidereal_angles(times, longitude_deg: float) -> np.ndarray:
    """Local Earth rotation angle (radians, in [0, 2 pi)) of astropy ``Time``s.

    This is the rotation angle of gcrsky's co-rotating (CIRS-of-date) frame: pass it
    as the LSTs of a problem whose coefficients are apparent CIRS coefficients.
    """
    import astropy.units as u

    return np.asarray(times.earth_rotation_angle(longitude=longitude_deg * u.deg).rad, np.float64)


def _gl_grid(nlat: int, nlon: int):
    x, w = np.polynomial.legendre.leggauss(nlat)
    theta = np.arccos(x)
    phi = 2 * np.pi * np.arange(nlon) / nlon
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    wt = np.repeat(w[:, None] * (2 * np.pi / nlon), nlon, axis=1)
    return th.ravel(), ph.ravel(), wt.ravel()


def alm_frame_matrix(lmax_in: int, lmax_out: int, source_frame, target_frame) -> np.ndarray:
    """Realified map ``M`` (n_out, n_in): coefficients in ``source_frame`` -> ``target_frame``.

    ``M[k', k] = int f_k'(c) f_k(s(c)) dOmega / ||f_k'||^2`` where ``c`` runs over target
    directions and ``s(c)`` is the same physical direction in the source frame (astropy
    ``SkyCoord.transform_to``).  Evaluated on a Gauss-Legendre grid that integrates
    products of degree ``< 2 (lmax_in + lmax_out + 2)`` exactly, so ``M`` is exact for
    rotations and accurate to the (negligible) band-limit leakage otherwise.

    Args:
        lmax_in, lmax_out: degrees of the input and output coefficients.
        source_frame, target_frame: astropy frame instances (e.g. ``ICRS()``,
            ``CIRS(obstime=t)``, ``Galactic()``).
    """
    import astropy.units as u
    from astropy.coordinates import SkyCoord, UnitSphericalRepresentation

    if lmax_out < 0 or lmax_in < 0:
        raise ValueError("lmax_in and lmax_out must be non-negative")
    L = lmax_in + lmax_out + 2
    theta, phi, w = _gl_grid(L, 2 * L + 1)
    rep = UnitSphericalRepresentation(lon=phi * u.rad, lat=(np.pi / 2 - theta) * u.rad)
    c = SkyCoord(target_frame.realize_frame(rep))
    s = c.transform_to(source_frame).represent_as(UnitSphericalRepresentation)
    th_s = np.pi / 2 - s.lat.to_value(u.rad)
    ph_s = np.mod(s.lon.to_value(u.rad), 2 * np.pi)
    f_out = np.asarray(real_basis(int(lmax_out), theta, phi))  # (P, n_out)
    f_in = np.asarray(real_basis(int(lmax_in), th_s, ph_s))  # (P, n_in)
    norm = np.where(mode_table(lmax_out).m == 0, 1.0, 2.0)
    return (f_out * w[:, None]).T @ f_in / norm[:, None]


def icrs_to_apparent_matrix(lmax: int, obstime, *, pad: int = 4) -> tuple[np.ndarray, int]:
    """``M`` from ICRS coefficients (lmax) to apparent CIRS-of-date ones (lmax + pad).

    Args:
        lmax: degree of the ICRS sky parameters.
        obstime: astropy ``Time`` (a scalar; use the middle of the observation: the map
            changes by ~2e-6 rad per day through annual aberration).
        pad: extra degrees of the apparent coefficients (aberration leaks ~1e-4 of each
            mode into l +- 1).

    Returns:
        (M of shape ((lmax+pad+1)**2, (lmax+1)**2), lmax + pad).
    """
    from astropy.coordinates import CIRS, ICRS

    lmax_out = int(lmax) + int(pad)
    M = alm_frame_matrix(int(lmax), lmax_out, ICRS(), CIRS(obstime=obstime))
    assert M.shape == (n_params(lmax_out), n_params(lmax))
    return M, lmax_out
