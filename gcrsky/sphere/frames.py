"""Real observing times: sidereal angles and the fixed ICRS -> CIRS-of-date map.

The idealised frame of :mod:`gcrsky.instrument.response` co-rotates with the Earth: it is the
CIRS of the observing epoch, with the "LST" of a time equal to the *local Earth
rotation angle* (ERA + east longitude); that identification is good to 3.5e-6 rad
(diurnal aberration and polar motion; ``tests/test_matvis.py``).  A sky given in
ICRS differs from it by frame bias, precession-nutation (~0.3 deg in 2026) and annual
aberration (~1e-4 rad, not a rigid rotation).  DESIGN section 2, mode (b):

    V(t) = R(lst_ref) . rotate(M a_icrs, ERA_loc(t) - lst_ref)

with one fixed linear map ``M`` from realified ICRS coefficients (lmax) to CIRS ones
(``lmax + pad``, a few degrees more to hold aberration's tiny leakage).

* :func:`observing_geometry` / :func:`icrs_to_cirs_map` build ``M`` as a
  :class:`FrameMap`: a Wigner-D rotation to the apex frame, annual aberration (one
  real matrix per m there), and a Wigner-D rotation by astropy's
  bias-precession-nutation matrix, applied matrix-free in O(lmax^3).
* :func:`alm_frame_matrix` / :func:`icrs_to_apparent_matrix` are the independent
  dense reference: astropy's whole transform of a Gauss-Legendre grid projected by
  quadrature (O(lmax^4) memory; used by the tests).
* :func:`rotate_between_frames` does rigid frame changes (Galactic -> ICRS).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .harmonics import legendre_table, real_basis
from .modes import mode_table, n_params
from .rotation import (
    WignerBlocks,
    euler_zyz,
    from_lm_grid,
    rotate_euler,
    rotate_euler_transpose,
    to_lm_grid,
    wigner_blocks,
    wigner_lmax,
)

__all__ = [
    "hours_to_rad",
    "local_sidereal_angles",
    "alm_frame_matrix",
    "icrs_to_apparent_matrix",
    "ObservingGeometry",
    "observing_geometry",
    "FrameMap",
    "frame_lmax",
    "apply_frame",
    "transpose_frame",
    "frame_matrix",
    "icrs_to_cirs_map",
    "frame_rotation_matrix",
    "rotate_between_frames",
    "times_for_lsts",
]


def time_array(times):
    """``times`` (an astropy ``Time``, scalar or array) as a 1-D ``Time`` array (jd1/jd2 kept exactly, same scale).

    Raises:
        TypeError: ``times`` is not an astropy ``Time``.
    """
    from astropy.time import Time

    if not isinstance(times, Time):
        raise TypeError(f"times must be an astropy Time array, got {type(times).__name__}")
    return Time(np.atleast_1d(times.jd1), np.atleast_1d(times.jd2), format="jd", scale=times.scale)


def hours_to_rad(hours) -> np.ndarray:
    """Sidereal hours -> radians of rotation (24 h = 2 pi)."""
    return np.asarray(hours, np.float64) * (2 * np.pi / 24.0)


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


class ObservingGeometry(NamedTuple):
    """Everything the operator needs from real timestamps and a site (DESIGN section 2, mode b).

    Attributes:
        lsts_rad: (Nt,) local Earth rotation angles of the times (rotation angles of the
            co-rotating CIRS-of-date frame), radians in [0, 2 pi).
        latitude_deg, longitude_deg: geodetic site coordinates (degrees; the array's ENU
            frame is the site's local tangent frame at this latitude).
        frame: the fixed :class:`FrameMap` from ICRS coefficients (``lmax``) to
            co-rotating ones (``lmax_response``); pass as ``VisOperator(frame=...)``.
        lmax_response: degree at which the response must be built.
        obstime: the astropy ``Time`` the fixed frame map was evaluated at (mid-span).
    """

    lsts_rad: np.ndarray
    latitude_deg: float
    longitude_deg: float
    frame: object
    lmax_response: int
    obstime: object


def observing_geometry(times, location, lmax: int, *, pad: int = 4) -> ObservingGeometry:
    """Sidereal angles, site latitude and the ICRS -> of-date frame map for real times.

    Args:
        times: astropy ``Time`` array (Nt,), UTC or any scale astropy converts.
        location: astropy ``EarthLocation`` of the array's reference position.
        lmax: degree of the ICRS sky parameters.
        pad: extra degrees of the response (annual aberration leaks ~1e-4 of a mode
            into l +- 1).
    """
    import astropy.units as u
    from astropy.time import Time

    if not isinstance(times, Time):
        raise TypeError(f"times must be an astropy Time array, got {type(times).__name__}")
    times = Time(np.atleast_1d(times.jd1), np.atleast_1d(times.jd2), format="jd", scale=times.scale)
    if times.size == 0:
        raise ValueError("times is empty")
    lon = float(location.lon.to_value(u.deg))
    lat = float(location.lat.to_value(u.deg))
    span = (times.max() - times.min()).to_value(u.day)
    if span > 2.0:
        raise ValueError(
            f"times span {span:.1f} days: one fixed frame map is accurate for a few days at most "
            "(annual aberration drifts ~2e-6 rad per day); split the observation"
        )
    mid = times.min() + (times.max() - times.min()) / 2
    fm = icrs_to_cirs_map(int(lmax), mid, pad=pad)
    return ObservingGeometry(local_sidereal_angles(times, lon), lat, lon, fm, int(lmax) + int(pad), mid)


# ----------------------------------------------------------------------------------
# The structured ICRS -> co-rotating map: Wigner-D rotations plus annual aberration.
# ----------------------------------------------------------------------------------


class FrameMap(NamedTuple):
    """Fixed linear map from ICRS coefficients (``lmax_in``) to CIRS-of-date ones (``lmax_out``).

    ``M = D(euler_out) . A . D(euler_in)`` (all realified, applied matrix-free):
    ``D(euler_in)`` rotates ICRS to the *apex frame* (z along the Earth's barycentric
    velocity), ``A`` is annual aberration, which is axisymmetric there and so acts
    on each m separately, and ``D(euler_out)`` rotates the apex frame to the CIRS of
    date (frame bias, precession and nutation: astropy's ``bpn`` matrix).  Light
    deflection by the Sun (<= 2e-8 rad beyond 90 deg from the Sun) is neglected.

    Attributes:
        blocks: :class:`gcrsky.sphere.WignerBlocks` up to ``lmax_out``.
        euler_in: (3,) ZYZ angles of ICRS -> apex frame.
        aberration: (lmax_out+1 [m], lmax_out+1 [l'], lmax_in+1 [l]) real per-m blocks:
            ``b_l'm = sum_l aberration[m, l', l] a_lm`` in the apex frame.
        euler_out: (3,) ZYZ angles of apex frame -> CIRS of date.
    """

    blocks: WignerBlocks
    euler_in: jax.Array
    aberration: jax.Array
    euler_out: jax.Array


def frame_lmax(fm: FrameMap) -> tuple[int, int]:
    """``(lmax_in, lmax_out)`` of a :class:`FrameMap` (static: read from array shapes)."""
    return fm.aberration.shape[2] - 1, fm.aberration.shape[1] - 1


def apply_frame(fm: FrameMap, a: jax.Array) -> jax.Array:
    """``M a``: realified ICRS coefficients (..., (lmax_in+1)^2) -> (..., (lmax_out+1)^2)."""
    lin, lout = frame_lmax(fm)
    if a.shape[-1] != (lin + 1) ** 2:
        raise ValueError(f"coefficients have length {a.shape[-1]}, the frame map expects {(lin + 1) ** 2}")
    g = to_lm_grid(rotate_euler(a, *fm.euler_in, fm.blocks))  # (..., lin+1, lin+1)
    g = jnp.pad(g, [(0, 0)] * (g.ndim - 1) + [(0, lout - lin)])  # m up to lout
    h = jnp.einsum("mab,...bm->...am", fm.aberration.astype(a.dtype), g)
    return rotate_euler(from_lm_grid(h), *fm.euler_out, fm.blocks)


def transpose_frame(fm: FrameMap, b: jax.Array) -> jax.Array:
    """``M^T b`` (plain transpose on realified vectors): (..., (lmax_out+1)^2) -> (..., (lmax_in+1)^2)."""
    lin, lout = frame_lmax(fm)
    if b.shape[-1] != (lout + 1) ** 2:
        raise ValueError(f"vector has length {b.shape[-1]}, the frame map's output is {(lout + 1) ** 2}")
    h = to_lm_grid(rotate_euler_transpose(b, *fm.euler_out, fm.blocks))  # (..., lout+1, lout+1)
    # per m the realified weight W is constant, so A's transpose is the plain one
    g = jnp.einsum("mab,...am->...bm", fm.aberration.astype(b.dtype), h)[..., : lin + 1]
    return rotate_euler_transpose(from_lm_grid(g), *fm.euler_in, fm.blocks)


def frame_matrix(fm: FrameMap) -> np.ndarray:
    """Dense ``M`` ((lmax_out+1)^2, (lmax_in+1)^2), for tests and small problems."""
    lin, _ = frame_lmax(fm)
    return np.asarray(apply_frame(fm, jnp.eye((lin + 1) ** 2))).T


def _aberration_colatitude(theta_obs: np.ndarray, astrom) -> np.ndarray:
    """Natural colatitude (from the apex) of light seen at ``theta_obs`` from the apex.

    Inverts ERFA's ``ab`` (relativistic annual aberration, as astropy applies it)
    by fixed-point iteration; it is axisymmetric about the velocity.
    """
    import erfa

    speed = float(np.linalg.norm(astrom["v"]))
    v = np.array([0.0, 0.0, speed])
    target = np.stack([np.sin(theta_obs), np.zeros_like(theta_obs), np.cos(theta_obs)], axis=1)
    p = target.copy()
    for _ in range(8):  # each step gains a factor ~|v| = 1e-4
        q = erfa.ab(p, v, float(astrom["em"]), float(astrom["bm1"]))
        p = p + (target - q)
        p /= np.linalg.norm(p, axis=1, keepdims=True)
    resid = np.abs(erfa.ab(p, v, float(astrom["em"]), float(astrom["bm1"])) - target).max()
    if resid > 1e-14:
        raise RuntimeError(f"aberration inversion did not converge (residual {resid:.1e})")
    return np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2])


def _aberration_blocks(lmax_in: int, lmax_out: int, astrom) -> np.ndarray:
    """Per-m aberration matrices in the apex frame by Gauss-Legendre quadrature in cos(theta)."""
    nq = lmax_in + lmax_out + 48  # the integrand is a polynomial of degree lmax_in + lmax_out up to O(|v|)
    x, w = np.polynomial.legendre.leggauss(nq)
    theta = np.arccos(x)
    theta_nat = _aberration_colatitude(theta, astrom)
    p_out = np.asarray(legendre_table(lmax_out, x, np.sin(theta)))  # (lout+1, nq, lout+1) [l, j, m]
    p_in = np.asarray(legendre_table(lmax_in, np.cos(theta_nat), np.sin(theta_nat)))  # [l, j, m]
    p_in = np.pad(p_in, [(0, 0), (0, 0), (0, lmax_out - lmax_in)])
    return 2 * np.pi * np.einsum("ajm,bjm,j->mab", p_out, p_in, w)


def icrs_to_cirs_map(lmax: int, obstime, *, pad: int = 4, blocks: WignerBlocks | None = None) -> FrameMap:
    """The :class:`FrameMap` from ICRS coefficients (lmax) to CIRS-of-date ones (lmax + pad).

    The rotation (frame bias, precession-nutation) and the aberration velocity come
    from astropy's own ICRS -> CIRS astrometry context (``erfa_astrom.apco``), so
    the map is astropy's transform expressed in harmonic space.

    Args:
        lmax: degree of the ICRS sky parameters.
        obstime: astropy ``Time`` (scalar; use the middle of the observation: annual
            aberration changes by ~2e-6 rad per day).
        pad: extra output degrees (aberration leaks ~l * 1e-4 of a mode into l +- 1).
        blocks: optional precomputed :func:`gcrsky.sphere.wigner_blocks` (>= lmax + pad).
    """
    from astropy.coordinates import CIRS
    from astropy.coordinates.erfa_astrom import erfa_astrom

    lmax, pad = int(lmax), int(pad)
    if pad < 0:
        raise ValueError(f"pad must be >= 0, got {pad}")
    lout = lmax + pad
    astrom = erfa_astrom.get().apco(CIRS(obstime=obstime))
    vhat = np.asarray(astrom["v"], np.float64) / np.linalg.norm(astrom["v"])
    # R_v: ICRS coordinates -> apex coordinates (rows: an orthonormal basis with z = vhat)
    ex = np.cross([0.0, 0.0, 1.0], vhat)
    ex /= np.linalg.norm(ex)
    r_v = np.stack([ex, np.cross(vhat, ex), vhat])
    bpn = np.asarray(astrom["bpn"], np.float64)
    if blocks is None or wigner_lmax(blocks) < lout:
        blocks = wigner_blocks(lout)
    return FrameMap(
        blocks=blocks,
        euler_in=jnp.asarray(euler_zyz(r_v)),
        aberration=jnp.asarray(_aberration_blocks(lmax, lout, astrom)),
        euler_out=jnp.asarray(euler_zyz(bpn @ r_v.T)),
    )


def frame_rotation_matrix(source_frame, target_frame) -> np.ndarray:
    """3x3 rotation ``R`` with ``p_target = R p_source`` between two astropy frames.

    Read off astropy's transform of the three unit vectors; raises if the transform
    is not a rigid rotation to 1e-12 (e.g. ICRS -> CIRS includes aberration: use
    :func:`icrs_to_cirs_map` for that).
    """
    import astropy.units as u
    from astropy.coordinates import CartesianRepresentation, SkyCoord

    eye = CartesianRepresentation(np.eye(3) * u.one, xyz_axis=0)
    c = SkyCoord(source_frame.realize_frame(eye)).transform_to(target_frame)
    r = np.asarray(c.cartesian.xyz.to_value(u.one), np.float64)  # columns: images of x, y, z
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-12 or np.linalg.det(r) < 0:
        raise ValueError(f"{type(source_frame).__name__} -> {type(target_frame).__name__} is not a rigid rotation")
    # verify rigidity on a few more directions (aberration would show here)
    rng = np.random.default_rng(0)
    p = rng.normal(size=(3, 16))
    p /= np.linalg.norm(p, axis=0)
    q = SkyCoord(source_frame.realize_frame(CartesianRepresentation(p * u.one, xyz_axis=0))).transform_to(target_frame)
    if np.abs(np.asarray(q.cartesian.xyz.to_value(u.one)) - r @ p).max() > 1e-12:
        raise ValueError(f"{type(source_frame).__name__} -> {type(target_frame).__name__} is not a rigid rotation")
    return r


def rotate_between_frames(a, source_frame, target_frame, *, blocks: WignerBlocks | None = None) -> jax.Array:
    """Realified coefficients of a sky in ``source_frame`` -> the same sky in ``target_frame``.

    For rigid frame changes (e.g. ``Galactic()`` -> ``ICRS()``): one Wigner-D rotation
    with the Euler angles of astropy's rotation matrix, exact to rounding.

    Args:
        a: (..., (lmax+1)^2) realified coefficients.
        source_frame, target_frame: astropy frame instances.
        blocks: optional precomputed :func:`gcrsky.sphere.wigner_blocks`.
    """
    a = jnp.asarray(a)
    lmax = int(np.sqrt(a.shape[-1])) - 1
    if blocks is None:
        blocks = wigner_blocks(lmax)
    r = frame_rotation_matrix(source_frame, target_frame)
    return rotate_euler(a, *euler_zyz(r), blocks)


#: Earth rotation angle rate, revolutions per UT1 day (IAU 2000 ERA definition).
_ERA_RATE = 1.00273781191135448


def times_for_lsts(date, lsts_rad, longitude_deg: float):
    """UTC times on or after ``date`` at which the local Earth rotation angle equals ``lsts_rad``.

    The first LST is reached at the first such instant after ``date``; the others
    follow at the sidereal rate, so LSTs beyond 2 pi continue into the next day
    (increasing ``lsts_rad`` give increasing times).

    Args:
        date: anything astropy ``Time`` accepts (e.g. ``"2026-03-21"``), UTC.
        lsts_rad: (Nt,) non-decreasing local Earth rotation angles, radians.
        longitude_deg: east longitude of the site, degrees.

    Returns:
        astropy ``Time`` (Nt,) with ``local_sidereal_angles(times, lon) == lsts mod 2 pi``
        to ~1e-9 rad.
    """
    import astropy.units as u
    from astropy.time import Time

    lsts = np.atleast_1d(np.asarray(lsts_rad, np.float64))
    if lsts.size > 1 and np.any(np.diff(lsts) < 0):
        raise ValueError("lsts_rad must be non-decreasing")
    t0 = Time(date, scale="utc")
    era0 = float(local_sidereal_angles(t0, longitude_deg))
    offset_days = (np.mod(lsts[0] - era0, 2 * np.pi) + (lsts - lsts[0])) / (2 * np.pi * _ERA_RATE)
    times = t0 + offset_days * u.day
    for _ in range(2):  # UT1 - UTC drifts by < 1 ms/day: polish
        err = np.angle(np.exp(1j * (lsts - local_sidereal_angles(times, longitude_deg))))
        times = times + err / (2 * np.pi * _ERA_RATE) * u.day
    err = np.angle(np.exp(1j * (lsts - local_sidereal_angles(times, longitude_deg))))
    if np.abs(err).max() > 1e-8:
        raise RuntimeError(f"could not match the LSTs to 1e-8 rad (residual {np.abs(err).max():.1e})")
    return times
