"""Point sources: the model visibilities of unit-flux sources at known positions.

For a source at the ENU unit vector ``s(t)`` (above the horizon, Up > 0) the
visibility of the pair ``(i, j)`` is the response quadrature of
:mod:`gcrsky.instrument.response` with one term:

    K[f, t, b, s] = A_i(s) A_j(s) exp(+2 pi i b_ij . s nu_f / c) / u(nu_f)

with ``b_ij = x_j - x_i`` (pyuvdata's ant2 - ant1), ``A = sqrt(P_x)`` the unpolarised
voltage beams, and ``u`` the flux unit: a source of 1 K sr (a sky ``delta(s) K sr``,
``flux_unit="K sr"``: ``u = 1``) or of 1 Jy (``flux_unit="Jy"``: ``u =
kelvin_sr_to_jy(nu) = 2 k nu^2 / c^2 * 1e26``, so that a source of ``S`` Jy is a sky of
``S c^2 / (2 k nu^2)`` K sr concentrated at one direction).  ``K`` is in the units of
gcrsky's visibilities (K sr) per unit flux, and ``V = X a + K s`` is the model of a
sky ``a`` plus sources of fluxes ``s``.  Below the horizon ``K = 0``.  ``V`` is twice
matvis' unpolarised single-feed visibility of the same source (``tests/test_point_sources.py``).

Where a source is, per time:

* idealised LSTs (the paper's; a :class:`~gcrsky.model.Problem` with ``frame=None``):
  ``(ra, dec)`` are coordinates of the co-rotating equatorial frame, and at LST ``t``
  the direction of hour angle ``h`` sees RA ``t - h``
  (:func:`gcrsky.instrument.equatorial_to_enu`);
* real observing times (``times`` and ``location``; a Problem built from them): ``(ra,
  dec)`` are ICRS.  The source is put where gcrsky's frame map puts the ICRS sky
  (:func:`gcrsky.sphere.observing_geometry`): annual aberration and
  bias-precession-nutation at the middle of the observation, from the same astropy
  astrometry context (:func:`icrs_to_corotating`), then rotated by each time's local
  Earth rotation angle.  Like the frame map this omits light deflection by the Sun
  (``1.97e-8 cot(psi/2)`` rad at angle ``psi`` from it: <= 2e-8 rad beyond 90 deg,
  8.5e-7 rad at 2.6 deg), diurnal aberration and polar motion (<= 3.5e-6 rad), and the
  drift of aberration over the observation (~2e-6 rad/day).

Redundancy-compressed problems (:func:`gcrsky.compress_problem`) keep one
representative pair per group, whose row is the group's common row: the same formula
holds for its antpairs.

Built once in NumPy (a set-up step, like the response); returned as a JAX array.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..base.dtypes import require_x64
from ..base.units import SPEED_OF_LIGHT, kelvin_sr_to_jy
from ..sphere.frames import FrameMap, local_sidereal_angles, time_array
from ..sphere.rotation import euler_zyz
from .antennas import AntennaArray, baseline_vectors
from .beams import beam_amplitude, unique_beams
from .response import equatorial_to_enu

__all__ = ["FLUX_UNITS", "icrs_to_corotating", "point_source_response", "problem_source_response",
           "source_enu"]

#: Flux units of :func:`point_source_response`: its value per unit flux is in K sr per ...
FLUX_UNITS = ("Jy", "K sr")


def _radec(ra_rad, dec_rad) -> tuple[np.ndarray, np.ndarray]:
    """Source coordinates as two finite (Ns,) float64 arrays; ValueError otherwise."""
    ra = np.asarray(ra_rad, np.float64)
    dec = np.asarray(dec_rad, np.float64)
    if ra.shape != dec.shape:
        raise ValueError(f"ra_rad and dec_rad must have the same shape, got {ra.shape} and {dec.shape}")
    if ra.ndim > 1:
        raise ValueError(f"ra_rad and dec_rad must be scalars or 1-d (Ns,), got shape {ra.shape}")
    ra, dec = np.atleast_1d(ra), np.atleast_1d(dec)
    if ra.size == 0:
        raise ValueError("no sources: ra_rad and dec_rad are empty")
    if not (np.all(np.isfinite(ra)) and np.all(np.isfinite(dec))):
        raise ValueError("ra_rad and dec_rad must be finite")
    if np.any(np.abs(dec) > np.pi / 2):
        raise ValueError(f"dec_rad must lie in [-pi/2, pi/2] (radians), got {dec[np.abs(dec) > np.pi / 2][0]!r}")
    return ra, dec


def _mid_time(times):
    """The epoch of gcrsky's frame map for ``times`` (as :func:`gcrsky.sphere.observing_geometry`)."""
    return times.min() + (times.max() - times.min()) / 2


def _astrom(obstime):
    """astropy's ICRS -> CIRS astrometry context at ``obstime`` (what the frame map is built from)."""
    from astropy.coordinates import CIRS
    from astropy.coordinates.erfa_astrom import erfa_astrom

    return erfa_astrom.get().apco(CIRS(obstime=obstime))


def icrs_to_corotating(ra_rad, dec_rad, obstime) -> tuple[np.ndarray, np.ndarray]:
    """Where gcrsky's frame map puts ICRS point sources: CIRS-of-date (RA, Dec) at ``obstime``.

    The frame map (:func:`gcrsky.sphere.icrs_to_cirs_map`) remaps the brightness field
    by relativistic annual aberration (ERFA ``ab`` with the observer's barycentric
    velocity) and the bias-precession-nutation matrix ``bpn``, both from astropy's
    ``ICRS -> CIRS`` astrometry context at ``obstime``; a point source at the natural
    direction ``p`` therefore appears at ``bpn . ab(p)``.  This is astropy's own ICRS ->
    CIRS transform without light deflection by the Sun (which the frame map also
    omits: ``1.97e-8 cot(psi/2)`` rad at angle ``psi`` from the Sun, <= 2e-8 rad beyond
    90 deg; ``tests/test_point_sources.py`` checks that this is the whole difference).

    Args:
        ra_rad, dec_rad: (Ns,) ICRS right ascension and declination, radians.
        obstime: astropy ``Time`` scalar (the frame map's: the middle of the observation).

    Returns:
        ``(ra, dec)`` (Ns,) each, radians, RA in [0, 2 pi): the co-rotating frame's coordinates.
    """
    import erfa

    ra, dec = _radec(ra_rad, dec_rad)
    astrom = _astrom(obstime)
    p = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=-1)
    q = erfa.ab(p, np.asarray(astrom["v"], np.float64), float(astrom["em"]), float(astrom["bm1"]))
    q = q @ np.asarray(astrom["bpn"], np.float64).T
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.mod(np.arctan2(q[:, 1], q[:, 0]), 2 * np.pi), np.arcsin(np.clip(q[:, 2], -1.0, 1.0))


def source_enu(
    ra_rad, dec_rad, *, latitude_rad: float, lsts_rad=None, times=None, location=None
) -> np.ndarray:
    """ENU unit vectors of sources at every time: (Nt, Ns, 3).

    Either ``lsts_rad`` (Nt,) radians, with ``(ra, dec)`` in the co-rotating frame
    (idealised LSTs), or ``times`` (astropy ``Time`` (Nt,)) and ``location`` (astropy
    ``EarthLocation``, whose latitude must be ``latitude_rad``), with ``(ra, dec)`` ICRS
    (see the module docstring).
    """
    ra, dec = _radec(ra_rad, dec_rad)
    if times is not None:
        import astropy.units as u

        if lsts_rad is not None:
            raise ValueError("give either lsts_rad (idealised frame) or times with location, not both")
        if location is None:
            raise ValueError("real observing times need the site: pass location (astropy EarthLocation)")
        times = time_array(times)
        span = (times.max() - times.min()).to_value(u.day)
        if span > 2.0:  # as gcrsky.sphere.observing_geometry: one fixed epoch for the frame
            raise ValueError(f"times span {span:.1f} days: one fixed frame epoch is accurate for a few days at most "
                             "(annual aberration drifts ~2e-6 rad per day); split the observation")
        lat = float(location.lat.to_value(u.rad))
        if abs(lat - float(latitude_rad)) > np.deg2rad(1e-6):  # build_problem's tolerance
            raise ValueError(f"the array is at latitude {np.rad2deg(latitude_rad)} deg but location at "
                             f"{np.rad2deg(lat)} deg")
        ra, dec = icrs_to_corotating(ra, dec, _mid_time(times))
        lsts_rad = local_sidereal_angles(times, float(location.lon.to_value(u.deg)))
    elif location is not None:
        raise ValueError("location is only used with times")
    if lsts_rad is None:
        raise ValueError("give lsts_rad (idealised frame) or times and location (real observing times)")
    lsts = np.atleast_1d(np.asarray(lsts_rad, np.float64))
    if lsts.ndim != 1 or not np.all(np.isfinite(lsts)):
        raise ValueError(f"lsts_rad must be a finite 1-d array (Nt,), got shape {lsts.shape}")
    return np.stack([equatorial_to_enu(np.pi / 2 - dec, ra, t, float(latitude_rad)) for t in lsts])


def point_source_response(
    array: AntennaArray,
    pairs,
    freqs_hz,
    *,
    ra_rad,
    dec_rad,
    lsts_rad=None,
    times=None,
    location=None,
    flux_unit: str = "Jy",
):
    """Model visibilities of unit-flux point sources: (Nf, Nt, Nbl, Ns) complex.

    ``K[f, t, b, s] = A_i A_j exp(+2 pi i (x_j - x_i) . s nu_f / c) / u(nu_f)`` for the
    pair ``pairs[b] = (i, j)``, source ``s`` at time ``t`` (0 below the horizon); see the
    module docstring for the conventions and the two frames.

    Args:
        array: the :class:`~gcrsky.instrument.AntennaArray` (positions, latitude, beams).
        pairs: (Nbl, 2) antenna index pairs (i, j) (e.g. a problem's ``antpairs``).
        freqs_hz: (Nf,) frequencies, Hz.
        ra_rad, dec_rad: (Ns,) source coordinates, radians: the co-rotating frame's with
            ``lsts_rad``, ICRS with ``times``.
        lsts_rad: (Nt,) local sidereal angles, radians (idealised frame).
        times, location: astropy ``Time`` (Nt,) and ``EarthLocation`` (real observing
            times; the location's latitude must be the array's).
        flux_unit: ``"Jy"`` (default: K sr per Jy) or ``"K sr"`` (K sr per K sr).

    Returns:
        (Nf, Nt, Nbl, Ns) complex128 JAX array, K sr per unit flux; ``V = einsum("ftbs,fs->ftb", K, s)``.

    Raises:
        ValueError: mismatched or non-finite ``ra_rad`` / ``dec_rad``, bad pairs,
            frequencies or unit, inconsistent frame arguments.
    """
    require_x64("point_source_response")
    if flux_unit not in FLUX_UNITS:
        raise ValueError(f"flux_unit must be one of {FLUX_UNITS}, got {flux_unit!r}")
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    if freqs.ndim != 1 or not np.all(freqs > 0):
        raise ValueError("freqs_hz must be a 1-d array of positive frequencies (Hz)")
    pairs = np.asarray(pairs, np.int64)
    nant = array.positions_enu_m.shape[0]
    if pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.size == 0 or pairs.min() < 0 or pairs.max() >= nant:
        raise ValueError(f"pairs must be (Nbl, 2) antenna indices in [0, {nant}), got shape {pairs.shape}")
    enu = source_enu(ra_rad, dec_rad, latitude_rad=array.latitude_rad, lsts_rad=lsts_rad, times=times,
                     location=location)  # (Nt, Ns, 3)
    nt, ns = enu.shape[:2]
    s = enu.reshape(-1, 3)
    up = s[:, 2] > 0  # the response's rule: directions strictly above the horizon
    az = np.mod(np.arctan2(s[:, 1], s[:, 0]), 2 * np.pi)  # UVBeam convention: North of East
    za = np.arccos(np.clip(s[:, 2], -1.0, 1.0))
    uniq, beam_idx = unique_beams(array.beams)
    amp = np.zeros((freqs.size, len(uniq), s.shape[0]))
    if up.any():
        amp[:, :, up] = np.stack([beam_amplitude(b, az[up], za[up], freqs) for b in uniq], axis=1)
    beam = amp[:, beam_idx[pairs[:, 0]]] * amp[:, beam_idx[pairs[:, 1]]]  # (Nf, Nbl, Nt*Ns)
    bvec_wl = baseline_vectors(array.positions_enu_m, pairs)[None] * (freqs[:, None, None] / SPEED_OF_LIGHT)
    phase = 2 * np.pi * np.einsum("fbd,pd->fbp", bvec_wl, s)  # +: matvis/pyuvdata sign
    k = beam * np.exp(1j * phase)
    if flux_unit == "Jy":
        k = k / kelvin_sr_to_jy(freqs)[:, None, None]
    k = k.reshape(freqs.size, pairs.shape[0], nt, ns).transpose(0, 2, 1, 3)
    return jnp.asarray(k, jnp.complex128)


def _check_frame_map(fm: FrameMap, times) -> None:
    """Raise unless ``fm`` is the frame map of ``times`` (its Euler angles, recomputed)."""
    astrom = _astrom(_mid_time(times))
    vhat = np.asarray(astrom["v"], np.float64) / np.linalg.norm(astrom["v"])
    ex = np.cross([0.0, 0.0, 1.0], vhat)
    ex /= np.linalg.norm(ex)
    r_v = np.stack([ex, np.cross(vhat, ex), vhat])
    want = np.concatenate([euler_zyz(r_v), euler_zyz(np.asarray(astrom["bpn"], np.float64) @ r_v.T)])
    have = np.concatenate([np.asarray(fm.euler_in), np.asarray(fm.euler_out)])
    err = np.abs(np.angle(np.exp(1j * (want - have)))).max()
    if err > 1e-8:
        raise ValueError(f"the problem's frame map was built for other times (its Euler angles differ by {err:.1e} "
                         "rad from those of these times' mid-point): pass the times the problem was built from")


def problem_source_response(problem, array: AntennaArray, *, ra_rad, dec_rad, times=None, location=None,
                            flux_unit: str = "Jy"):
    """:func:`point_source_response` for a :class:`~gcrsky.model.Problem`: its pairs, channels and times.

    The Problem records its antenna positions but not its beam objects, so the
    :class:`~gcrsky.instrument.AntennaArray` it was built from is passed too (its positions
    are checked against the Problem's).  Redundancy-compressed problems work as they are
    (their ``antpairs`` are the groups' representatives).

    * ``problem.frame is None`` (idealised LSTs): ``(ra, dec)`` in the co-rotating frame,
      the Problem's ``lsts_rad``; ``times`` must not be given.
    * built from real ``times`` (``problem.frame`` a :class:`~gcrsky.sphere.FrameMap`):
      ``(ra, dec)`` ICRS; pass the same ``times`` and ``location``: the Problem does not
      record them.  Their local Earth rotation angles must equal ``problem.lsts_rad``
      (to 1e-9 rad) and their frame map the Problem's (Euler angles to 1e-8 rad).

    Args:
        problem: the Problem (``freqs_hz``, ``lsts_rad``, ``antpairs``, ``frame``,
            ``antpos_enu_m`` are read).
        array: its :class:`~gcrsky.instrument.AntennaArray`.
        ra_rad, dec_rad: (Ns,) source coordinates, radians.
        times, location: astropy ``Time`` (Nt,) and ``EarthLocation`` of a real-time Problem.
        flux_unit: ``"Jy"`` or ``"K sr"``.

    Returns:
        (Nf, Nt, Nbl, Ns) complex, K sr per unit flux, in the Problem's baseline order.

    Raises:
        ValueError: the array (positions, beam grouping) or the times do not match the Problem;
            bad source coordinates.
        NotImplementedError: a Problem with a hand-made dense ``frame`` matrix (the
            direction of a point source in its co-rotating frame cannot be read off an
            arbitrary coefficient map: use :func:`point_source_response` with co-rotating
            coordinates and ``lsts_rad=problem.lsts_rad``).
    """
    pos = getattr(problem, "antpos_enu_m", None)
    if pos is not None:
        mine = np.asarray(array.positions_enu_m, np.float64)
        if mine.shape != np.shape(pos) or np.abs(mine - np.asarray(pos)).max() > 1e-9:
            raise ValueError("array.positions_enu_m differ from the problem's antpos_enu_m: pass the array the "
                             "problem was built from")
    ids = getattr(problem, "beam_ids", None)
    if ids is not None and not np.array_equal(unique_beams(array.beams)[1], np.asarray(ids)):
        raise ValueError("the array's beams are grouped differently from the problem's beam_ids: pass the array "
                         "the problem was built from")
    pairs = np.asarray(problem.antpairs)
    freqs = np.asarray(problem.freqs_hz)
    lsts = np.asarray(problem.lsts_rad, np.float64)
    kw = dict(ra_rad=ra_rad, dec_rad=dec_rad, flux_unit=flux_unit)
    if problem.frame is None:
        if times is not None or location is not None:
            raise ValueError("this problem has idealised LSTs (frame None): give no times or location; (ra, dec) "
                             "are co-rotating coordinates")
        return point_source_response(array, pairs, freqs, lsts_rad=lsts, **kw)
    if not isinstance(problem.frame, FrameMap):
        raise NotImplementedError(
            "the problem's frame is a hand-made dense coefficient map, from which a point source's direction in "
            "the co-rotating frame cannot be derived; give co-rotating coordinates to point_source_response("
            "array, problem.antpairs, problem.freqs_hz, ra_rad=..., dec_rad=..., lsts_rad=problem.lsts_rad)")
    if times is None or location is None:
        raise ValueError("this problem was built from real observing times (ICRS sky): pass the same times and "
                         "location (the problem does not record them)")
    import astropy.units as u

    times = time_array(times)
    era = local_sidereal_angles(times, float(location.lon.to_value(u.deg)))
    if era.shape != lsts.shape or np.abs(np.angle(np.exp(1j * (era - lsts)))).max() > 1e-9:
        raise ValueError("the local Earth rotation angles of these times differ from the problem's lsts_rad: pass "
                         "the times (and location) the problem was built from")
    _check_frame_map(problem.frame, times)
    return point_source_response(array, pairs, freqs, times=times, location=location, **kw)
