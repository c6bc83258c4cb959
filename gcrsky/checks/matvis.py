"""Forward-model validation against ``matvis.simulate_vis`` with real observing times.

One configuration (:class:`MatvisCase`: beam, layout, site, UTC times, frequencies)
is simulated twice from the same band-limited random ICRS sky:

* gcrsky, real-time mode: :func:`gcrsky.sphere.observing_geometry` gives the local
  Earth rotation angles and the fixed ICRS -> co-rotating (CIRS-of-date) frame map;
  the response is a HEALPix quadrature at one reference angle, ``V = R rotate(M a)``.
* matvis (CPU, ``precision=2``, unpolarised, its default astropy ``ICRS -> AltAz``
  transform per time with ``pressure=0``): one point source per HEALPix pixel of the
  ICRS sky map, at the pixel centre, with flux ``I_p [K] * 4 pi / Npix * 2 k nu^2 / c^2``.

The two are independent quadratures of the same integral (gcrsky's pixels are fixed
in the co-rotating frame at the reference angle, matvis' in ICRS), so the
comparison also checks gcrsky's quadrature, rotation and frame map, not only the
conventions pinned at rounding level in ``tests/test_matvis.py``.  Conventions:
``V_gcrsky = 2 V_matvis`` (matvis gives each feed ``I/2``), pair ``(i, j)`` is
``<E_i^* E_j>`` with baseline ``x_j - x_i``; both codes evaluate the feed-x power beam
``P`` through the same pyuvdata call (``BeamInterface.compute_response``, UVBeams
with ``az_za_map_coordinates``) and use ``A = sqrt(P)``.

Error figure (per configuration): ``max |V_gcrsky - 2 V_matvis| / rms(V_gcrsky)``
over all cross-correlations, times and frequencies.

Aberration and brightness: gcrsky's frame map remaps the brightness field
(``I_app(n) = I_icrs(n_natural)``), while a point source keeps its flux, so matvis fed
``I Omega`` per ICRS pixel sees the apparent brightness scaled by the aberration
solid-angle factor, ``1 +- 2 beta`` (``beta = 1e-4``).  ``MatvisCase.flux_jacobian``
(default) multiplies matvis' fluxes by :func:`aberration_solid_angle_factor` so both
codes simulate the same brightness; without it the figure rises by ~3e-4 (Gaussian,
hexagon, HERA: 4.5e-4 instead of 1.1e-4).

Accuracy floors (measured with ``benchmarks/validate_matvis.py``):

* Geometry: gcrsky's co-rotating frame omits diurnal aberration and polar motion
  (<= 3.5e-6 rad) and holds annual aberration fixed at mid-span: ~1e-4 of the rms
  (measured by replacing matvis' astropy transform with gcrsky's idealised geometry).
* Quadrature: the codes sum over different pixel sets (CIRS-of-date HEALPix at the
  reference angle vs ICRS HEALPix), both converging to the same integral.  14 m
  Gaussian, random layout (to 58.6 m) at Green Bank: 3.6e-3 (nside 64), 6.6e-4 (128),
  1.5e-4 (256); the hexagon at HERA is at its 1.1e-4 floor from nside 64.  Beams with
  horizon response converge more slowly because of the hard horizon cut (pixel
  centres with Up > 0): 14 m Airy, random layout, Green Bank ~3.5e-3 (128), 1.1e-3
  (256), 3.3e-4 (512); the same Airy tapered to zero above za 70 deg gives 6.5e-4 at
  128, the Gaussian's value.  matvis' HERA dipole UVBeam (horizon response ~5e-4 of the
  peak), random layout, HERA: 9.7e-3 (64), 4.3e-3 (128), 1.4e-3 (256), 4.4e-4 (512),
  with no interpolation difference (both codes call the same pyuvdata interpolation,
  see :func:`hera_dipole_power_beam`).

matvis is imported lazily: this module imports without it.
"""

from __future__ import annotations

import time as _time
from pathlib import Path
from typing import NamedTuple

import healpy as hp
import numpy as np

from ..base.extras import require
from ..base.units import kelvin_sr_to_jy
from ..instrument.antennas import antpairs, make_array
from ..sphere.frames import time_array
from ..sphere.maps import alm_to_map
from ..sphere.modes import n_alm, n_params, realify, unrealify

__all__ = [
    "GREEN_BANK_SITE",
    "HERA_SITE",
    "MatvisCase",
    "MatvisComparison",
    "aberration_solid_angle_factor",
    "compare_with_matvis",
    "error_figure",
    "gcrsky_visibilities",
    "hera_dipole_power_beam",
    "matvis_hera_beam_path",
    "matvis_visibilities",
    "observing_times",
    "pad_realified",
    "random_layout",
    "random_sky",
    "site",
]

#: Sites used by the validation: (latitude deg, east longitude deg, height m).
HERA_SITE = (-30.7215, 21.4283, 1073.0)
GREEN_BANK_SITE = (38.4331, -79.8398, 807.0)


class MatvisCase(NamedTuple):
    """One validation configuration.

    Attributes:
        name: label for tables.
        beam: pyuvdata beam object (``AnalyticBeam`` or ``UVBeam``), the same for
            every antenna and handed unchanged to both codes.
        positions_enu_m: (Nant, 3) ENU antenna positions, metres, relative to ``location``.
        location: astropy ``EarthLocation`` of the array centre.
        times: astropy ``Time`` (Nt,) observing times (UTC); must be covered by the
            IERS tables in use (the caller decides whether astropy may download).
        freqs_hz: (Nf,) frequencies, Hz.
        lmax: degree of the random ICRS sky.
        nside: HEALPix nside of gcrsky's response quadrature.
        nside_matvis: nside of the ICRS pixel sky given to matvis (default ``nside``).
        seed: seed of the random sky.
        flux_jacobian: multiply matvis' pixel fluxes by the annual-aberration solid-angle
            factor (:func:`aberration_solid_angle_factor`) so that matvis simulates the
            same apparent *brightness* as gcrsky (see the module docstring).
    """

    name: str
    beam: object
    positions_enu_m: np.ndarray
    location: object
    times: object
    freqs_hz: np.ndarray
    lmax: int = 20
    nside: int = 128
    nside_matvis: int | None = None
    seed: int = 0
    flux_jacobian: bool = True


class MatvisComparison(NamedTuple):
    """Result of :func:`compare_with_matvis` (all visibilities in Jy).

    Attributes:
        rel_err: ``max_abs_err / rms`` (the error figure).
        max_abs_err: ``max |V_gcrsky - 2 V_matvis|`` over cross-correlations, Jy.
        rms: rms of ``V_gcrsky`` over the same visibilities, Jy.
        worst: (freq index, time index, (i, j)) of the largest difference.
        worst_baseline_m: length of the worst pair's baseline, metres.
        v_gcrsky: (Nf, Nt, Nbl) complex, gcrsky's visibilities.
        v_matvis: (Nf, Nt, Nbl) complex, matvis' raw output (half of gcrsky's convention).
        pairs: (Nbl, 2) antenna pairs (i < j) of the last axis.
        lsts_rad: (Nt,) local Earth rotation angles of the times.
        t_gcrsky_s, t_matvis_s: wall times of the two simulations, seconds
            (gcrsky's includes the frame map, the response build and JIT compilation).
    """

    rel_err: float
    max_abs_err: float
    rms: float
    worst: tuple
    worst_baseline_m: float
    v_gcrsky: np.ndarray
    v_matvis: np.ndarray
    pairs: np.ndarray
    lsts_rad: np.ndarray
    t_gcrsky_s: float
    t_matvis_s: float


def random_sky(lmax: int, seed: int = 0, *, min_fraction: float = 0.1, nside: int = 64) -> np.ndarray:
    """White band-limited random sky, realified ICRS coefficients (n,), in K.

    Every realified entry is standard normal except the monopole, which is set so that
    the map's minimum (checked on an nside-``nside`` grid) is ``min_fraction`` of its
    mean: the sky is positive, so matvis needs no positive/negative split.
    """
    rng = np.random.default_rng(seed)
    a = rng.normal(size=n_params(lmax))
    a[0] = 0.0
    m = alm_to_map(a, lmax, nside)
    y00 = 1.0 / np.sqrt(4 * np.pi)
    # mean = a0 y00 and min = mean + min(m) = min_fraction * mean
    a[0] = -m.min() / ((1.0 - min_fraction) * y00)
    return a


def random_layout(nant: int, extent_m: float, min_sep_m: float, seed: int = 0) -> np.ndarray:
    """Irregular (non-redundant) layout: ``nant`` points uniform in a square, (Nant, 3) ENU m.

    Points are drawn uniformly in ``[-extent/2, extent/2]^2`` with rejection of any
    closer than ``min_sep_m`` to an earlier one (dish clearance); Up = 0.  The longest
    baseline is at most ``extent * sqrt(2)``.
    """
    rng = np.random.default_rng(seed)
    pos: list[np.ndarray] = []
    for _ in range(100000):
        p = rng.uniform(-extent_m / 2, extent_m / 2, size=2)
        if all(np.hypot(*(p - q)) >= min_sep_m for q in pos):
            pos.append(p)
            if len(pos) == nant:
                break
    else:
        raise ValueError(f"could not place {nant} antennas {min_sep_m} m apart in {extent_m} m")
    xy = np.asarray(pos)
    return np.concatenate([xy, np.zeros((nant, 1))], axis=1)


def site(latitude_deg: float, longitude_deg: float, height_m: float = 0.0):
    """astropy ``EarthLocation`` from geodetic coordinates (degrees, metres)."""
    import astropy.units as u
    from astropy.coordinates import EarthLocation

    return EarthLocation.from_geodetic(lon=longitude_deg * u.deg, lat=latitude_deg * u.deg, height=height_m * u.m)


def observing_times(start_utc: str, span_hours: float, ntimes: int):
    """``ntimes`` UTC times evenly spread over ``span_hours`` from ``start_utc`` (astropy ``Time``)."""
    import astropy.units as u
    from astropy.time import Time

    return Time(start_utc, scale="utc") + np.linspace(0.0, span_hours, ntimes) * u.hour


def matvis_hera_beam_path() -> Path:
    """Path of the HERA dipole E-field beam shipped with matvis (``NF_HERA_Dipole_small.fits``).

    az_za grid, 2 deg in zenith angle, 180 azimuths 0..359 deg, feeds x and y, 100 and
    101 MHz, peak-normalised.
    """
    matvis = require("matvis", "validate", "the matvis comparison")
    return Path(matvis.__file__).parent / "data" / "NF_HERA_Dipole_small.fits"


def hera_dipole_power_beam(pedestal: float = 1e-4, path=None):
    """matvis' HERA dipole beam as the feed-x power UVBeam both codes evaluate, plus a floor.

    The E-field beam is converted once with pyuvdata's ``efield_to_power(calc_cross_pols=
    False)`` and reduced to the ``xx`` polarisation: exactly what matvis'
    ``prepare_beam_unpolarized`` and gcrsky's ``beam_amplitude`` do internally, so
    handing them this power beam changes nothing in either code path.  Both then call
    ``BeamInterface.compute_response(interpolation_function="az_za_map_coordinates")``
    (cubic spline, ``scipy.ndimage.map_coordinates``) at their own directions.

    ``pedestal`` (relative to the peak power) is added to every grid value: the cubic
    interpolant of the raw 101 MHz power undershoots to -1.3e-5 of the peak near
    sidelobe nulls, where matvis' ``sqrt(P)`` would give NaN and gcrsky refuses a
    negative power (matvis raises "Beam interpolation resulted in an invalid value"
    with the raw file at 101 MHz).  The spline interpolation is linear and reproduces
    constants, so the floor adds exactly ``pedestal * peak`` to the interpolated power
    above the horizon (checked to 1e-9 in ``tests/test_validate_matvis.py``): both codes
    see the same beam, raised by 1e-4 of the peak (its horizon response is ~4e-4).
    """
    from pyuvdata import UVBeam

    beam = UVBeam.from_file(str(path or matvis_hera_beam_path()))
    power = beam.efield_to_power(calc_cross_pols=False, inplace=False)
    power.select(polarizations=["xx"])
    data = np.real(power.data_array)
    power.data_array = (data + pedestal * data.max()).astype(power.data_array.dtype)
    return power


def pad_realified(a: np.ndarray, lmax: int, lmax_out: int) -> np.ndarray:
    """Zero-pad realified coefficients (..., n(lmax)) to degree ``lmax_out`` (..., n(lmax_out))."""
    if lmax_out < lmax:
        raise ValueError(f"lmax_out {lmax_out} < lmax {lmax}")
    alm = unrealify(np.asarray(a, np.float64), lmax)
    ell, m = hp.Alm.getlm(lmax, np.arange(n_alm(lmax)))
    out = np.zeros(alm.shape[:-1] + (n_alm(lmax_out),), complex)
    out[..., hp.Alm.getidx(lmax_out, ell, m)] = alm
    return realify(out, lmax_out)


def aberration_solid_angle_factor(nside: int, obstime) -> np.ndarray:
    """``dOmega_apparent / dOmega_ICRS`` of each ICRS HEALPix pixel under annual aberration.

    Relativistic aberration by the observer's barycentric velocity ``beta`` (astropy's
    ``ICRS -> CIRS`` astrometry context at ``obstime``) moves a direction at angle
    ``theta`` from the apex to ``cos theta' = (cos theta + beta) / (1 + beta cos theta)``,
    so solid angles scale by ``(1 - beta^2) / (1 + beta cos theta)^2`` (1 -+ 2e-4).
    A point source keeps its flux, so a pixel of ICRS brightness ``I`` and solid angle
    ``Omega`` handed to matvis as flux ``I Omega`` appears with brightness ``I / factor``;
    flux ``I Omega factor`` keeps the apparent brightness ``I``, which is gcrsky's frame
    map (a coordinate remapping of the brightness field).  Light deflection (<= 2e-8 rad
    beyond 90 deg from the Sun) and diurnal aberration (1.5e-6) are ignored.

    Returns:
        (12 nside**2,) factors, RING order.
    """
    from astropy.coordinates import CIRS
    from astropy.coordinates.erfa_astrom import erfa_astrom

    astrom = erfa_astrom.get().apco(CIRS(obstime=obstime))
    v = np.asarray(astrom["v"], np.float64)  # observer's barycentric velocity / c
    beta = float(np.linalg.norm(v))
    n = np.stack(hp.pix2vec(int(nside), np.arange(hp.nside2npix(int(nside)))), axis=1)
    cos = n @ (v / beta)
    return (1.0 - beta**2) / (1.0 + beta * cos) ** 2


def gcrsky_visibilities(case: MatvisCase, a_icrs: np.ndarray, pairs: np.ndarray, *, drop_frame: bool = False):
    """gcrsky's real-time visibilities of the ICRS sky ``a_icrs``.

    Args:
        case: the configuration.
        a_icrs: (n,) realified ICRS coefficients at ``case.lmax``, K.
        pairs: (Nbl, 2) antenna pairs.
        drop_frame: negative control: skip the ICRS -> of-date frame map (treat the
            ICRS coefficients as co-rotating ones, zero-padded to the response degree).

    Returns:
        (V, lsts): V (Nf, Nt, Nbl) complex Jy, lsts (Nt,) radians.
    """
    import jax.numpy as jnp

    from ..instrument.response import response_matrix
    from ..model.operator import VisOperator, apply
    from ..sphere.frames import observing_geometry

    times = time_array(case.times)
    freqs = np.asarray(case.freqs_hz, np.float64)
    geom = observing_geometry(times, case.location, int(case.lmax))
    arr = make_array(case.positions_enu_m, geom.latitude_deg, case.beam)
    lsts = np.asarray(geom.lsts_rad, np.float64)
    lst_ref = float(lsts[0])
    resp = response_matrix(arr, pairs, freqs, geom.lmax_response, int(case.nside), lst_ref_rad=lst_ref)
    # unwrap so the angles are small and monotonic (rotation is 2 pi periodic anyway)
    angles = jnp.asarray(np.unwrap(lsts) - lst_ref)
    a = np.broadcast_to(np.asarray(a_icrs, np.float64), (freqs.size, n_params(case.lmax)))
    if drop_frame:
        op = VisOperator(resp, angles, None)
        a = pad_realified(a, int(case.lmax), int(geom.lmax_response))
    else:
        op = VisOperator(resp, angles, geom.frame)
    v = np.asarray(apply(op, jnp.asarray(a)))  # K sr
    return v * kelvin_sr_to_jy(freqs)[:, None, None], lsts


def matvis_visibilities(case: MatvisCase, sky_map_k: np.ndarray, pairs: np.ndarray, **matvis_kw) -> np.ndarray:
    """matvis' unpolarised visibilities of a HEALPix ICRS map (one source per pixel centre).

    Args:
        case: the configuration (beam, positions, location, times, freqs).
        sky_map_k: (12 nside_m**2,) RING map in K, ICRS.
        pairs: (Nbl, 2) antenna pairs (i, j): matvis' ``V_ij = <Z_i^* Z_j>``.
        **matvis_kw: extra ``simulate_vis`` arguments (e.g. ``coord_method``).

    Returns:
        (Nf, Nt, Nbl) complex Jy: matvis' output (the single-feed convention, I/2);
        negative pixels, if any, are simulated separately and subtracted (matvis
        takes ``sqrt(I)``).
    """
    import astropy.units as u

    from ..instrument.response import equatorial_to_enu

    matvis = require("matvis", "validate", "the matvis comparison")
    from ..sphere.frames import local_sidereal_angles

    sky_map_k = np.asarray(sky_map_k, np.float64)
    nside_m = hp.npix2nside(sky_map_k.size)
    freqs = np.asarray(case.freqs_hz, np.float64)
    theta, phi = hp.pix2ang(nside_m, np.arange(sky_map_k.size))
    jy = kelvin_sr_to_jy(freqs)[None, :] * (4 * np.pi / sky_map_k.size)
    ants = {i: np.asarray(p, np.float64) for i, p in enumerate(np.asarray(case.positions_enu_m))}
    times = time_array(case.times)
    # Pixels below the horizon at every time contribute nothing (matvis drops Up <= 0);
    # not handing them over saves matvis' per-time transforms.  ICRS taken as CIRS here
    # (<= 0.4 deg off in 2025), hence the 2 deg margin.
    lsts = local_sidereal_angles(times, float(case.location.lon.to_value(u.deg)))
    lat = float(case.location.lat.to_value(u.rad))
    ever_up = np.zeros(sky_map_k.size, bool)
    for lst in lsts:
        ever_up |= equatorial_to_enu(theta, phi, lst, lat)[:, 2] > -np.sin(np.deg2rad(2.0))
    out = 0.0
    for sign in (1.0, -1.0):
        part = np.clip(sign * sky_map_k, 0.0, None)
        keep = (part > 0) & ever_up
        if not np.any(keep):
            continue
        vis = matvis.simulate_vis(
            ants=ants,
            fluxes=part[keep, None] * jy,
            ra=phi[keep],
            dec=np.pi / 2 - theta[keep],
            freqs=freqs,
            times=times,
            beams=[case.beam],
            telescope_loc=case.location,
            polarized=False,
            precision=2,
            antpairs=np.asarray(pairs, np.int64),
            **matvis_kw,
        )
        out = out + sign * np.asarray(vis)
    return np.asarray(out)


def error_figure(v_gcrsky: np.ndarray, v_matvis: np.ndarray) -> tuple[float, float, float, tuple]:
    """``(max |V_g - 2 V_m| / rms(V_g), max |V_g - 2 V_m|, rms(V_g), argmax index)``.

    Args:
        v_gcrsky, v_matvis: (Nf, Nt, Nbl) complex, the same cross-correlations.
    """
    diff = np.abs(np.asarray(v_gcrsky) - 2.0 * np.asarray(v_matvis))
    rms = float(np.sqrt(np.mean(np.abs(v_gcrsky) ** 2)))
    idx = np.unravel_index(int(np.argmax(diff)), diff.shape)
    mx = float(diff[idx])
    return mx / rms, mx, rms, tuple(int(i) for i in idx)


def compare_with_matvis(case: MatvisCase, **matvis_kw) -> MatvisComparison:
    """Simulate ``case`` with gcrsky and matvis from one random ICRS sky and compare.

    The sky is :func:`random_sky` (``case.lmax``, ``case.seed``), mapped with healpy to
    the ICRS HEALPix grid of ``case.nside_matvis`` for matvis (times the aberration
    solid-angle factor at mid-span if ``case.flux_jacobian``).  All cross-correlations
    ``i < j`` of the layout are compared.

    Returns:
        :class:`MatvisComparison` (figure, worst visibility, both visibility sets, wall times).
    """
    pairs = antpairs(np.asarray(case.positions_enu_m).shape[0])
    a = random_sky(int(case.lmax), int(case.seed))
    nside_m = int(case.nside_matvis or case.nside)
    sky_map = alm_to_map(a, int(case.lmax), nside_m)
    if case.flux_jacobian:
        times = time_array(case.times)
        sky_map = sky_map * aberration_solid_angle_factor(nside_m, times.min() + (times.max() - times.min()) / 2)

    t0 = _time.perf_counter()
    vg, lsts = gcrsky_visibilities(case, a, pairs)
    t1 = _time.perf_counter()
    vm = matvis_visibilities(case, sky_map, pairs, **matvis_kw)
    t2 = _time.perf_counter()

    rel, mx, rms, (f, t, b) = error_figure(vg, vm)
    bvec = np.asarray(case.positions_enu_m)[pairs[b, 1]] - np.asarray(case.positions_enu_m)[pairs[b, 0]]
    return MatvisComparison(
        rel_err=rel,
        max_abs_err=mx,
        rms=rms,
        worst=(f, t, (int(pairs[b, 0]), int(pairs[b, 1]))),
        worst_baseline_m=float(np.linalg.norm(bvec)),
        v_gcrsky=vg,
        v_matvis=vm,
        pairs=pairs,
        lsts_rad=lsts,
        t_gcrsky_s=t1 - t0,
        t_matvis_s=t2 - t1,
    )
