"""Instrument: antenna layouts, baselines, site, and beams evaluated on the sky.

Conventions:

* Antenna positions are local East-North-Up (ENU) in metres.
* A baseline (i, j) has vector ``b_ij = x_j - x_i`` (pyuvdata's ant2 - ant1), and the
  visibility is ``V_ij = sum A_i^* A_j I exp(+2 pi i b_ij . s / lambda)``, i.e.
  ``<E_i^* E_j>`` (matvis' and pyuvdata's sign, pinned against matvis in
  ``tests/test_matvis.py``).
* Beams are pyuvdata beam objects (``GaussianBeam``, ``AiryBeam``, any
  ``AnalyticBeam``, ``UVBeam``).  For Stokes-I (unpolarised) work we follow
  matvis: the feed-``x`` power beam ``P_i`` is evaluated and ``A_i = sqrt(P_i)``,
  so identical antennas give ``A_i^* A_j = P``.  Azimuth passed to pyuvdata is
  in the UVBeam convention (North of East: Az(E)=0, Az(N)=pi/2), zenith angle in
  radians.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

__all__ = [
    "HERA_LATITUDE_DEG",
    "Array",
    "hex_array",
    "make_array",
    "antpairs",
    "baseline_vectors",
    "beam_amplitude",
    "gaussian_beam",
    "fwhm_airy_rad",
    "beam_fwhm_rad",
]

#: HERA's geodetic latitude (degrees); the paper's site.  Pass it explicitly.
HERA_LATITUDE_DEG = -30.7215
#: HERA's east longitude (degrees) and height (m), for real observing times.
HERA_LONGITUDE_DEG = 21.4283
HERA_HEIGHT_M = 1073.0


class Array(NamedTuple):
    """An array of antennas at a site.

    Attributes:
        positions_enu_m: (Nants, 3) ENU antenna positions in metres.
        latitude_rad: site geodetic latitude in radians.
        beams: tuple of pyuvdata beam objects, one per antenna (may repeat the same object).
    """

    positions_enu_m: np.ndarray
    latitude_rad: float
    beams: tuple


def hex_array(rows: Sequence[int] = (3, 4, 3), spacing_m: float = 14.6) -> np.ndarray:
    """Close-packed hexagonal layout (the paper's 10 antennas: rows of 3, 4, 3).

    Rows run East-West and are stacked North-South ``spacing * sqrt(3)/2`` apart;
    each row is centred on the array centre.  Returns (Nants, 3) ENU metres,
    antennas numbered row by row (north row first), west to east.
    """
    rows = [int(r) for r in rows]
    if not rows or any(r <= 0 for r in rows):
        raise ValueError(f"rows must be positive antenna counts, got {rows}")
    if not spacing_m > 0:
        raise ValueError(f"spacing_m must be positive, got {spacing_m}")
    dy = spacing_m * np.sqrt(3.0) / 2.0
    pos = []
    nrow = len(rows)
    for r, count in enumerate(rows):
        north = ((nrow - 1) / 2.0 - r) * dy
        for k in range(count):
            east = (k - (count - 1) / 2.0) * spacing_m
            pos.append((east, north, 0.0))
    return np.asarray(pos, dtype=np.float64)


def gaussian_beam(diameter_m: float):
    """pyuvdata ``GaussianBeam(diameter=D)``: FWHM ~ 1.03 lambda/D (Airy-matched)."""
    from pyuvdata.analytic_beam import GaussianBeam

    if not diameter_m > 0:
        raise ValueError(f"dish diameter must be positive, got {diameter_m}")
    return GaussianBeam(diameter=float(diameter_m))


def fwhm_airy_rad(diameter_m: float, freq_hz: float) -> float:
    """Small-angle FWHM of an Airy-disk power pattern, ``1.029 lambda/D``, radians.

    Not the width of ``GaussianBeam(diameter=D)`` (pyuvdata's, ~lambda/D: 12.28 deg at
    100 MHz for 14 m); use :func:`beam_fwhm_rad` for the beam actually simulated.
    """
    lam = 299792458.0 / freq_hz
    return 1.02899 * lam / diameter_m


def beam_fwhm_rad(beam, freq_hz: float, *, n_grid: int = 20001) -> float:
    """Full width at half maximum of a beam's power pattern, measured, in radians.

    The power (feed x, as used for Stokes I) is evaluated along zenith angle at
    azimuths 0 and pi/2 (UVBeam convention); the half-power angle is found by
    linear interpolation on a ``n_grid`` grid over [0, pi/2] and the two cuts are
    averaged (FWHM = 2 x mean half-power zenith angle).  Raises ``ValueError`` if the
    power never falls to half of its zenith value above the horizon.
    """
    za = np.linspace(0.0, np.pi / 2, n_grid)
    half = []
    for az in (0.0, np.pi / 2):
        p = beam_amplitude(beam, np.full_like(za, az), za, np.array([float(freq_hz)]))[0] ** 2
        below = np.flatnonzero(p <= 0.5 * p[0])
        if below.size == 0:
            raise ValueError(f"beam power does not fall to half above the horizon at {freq_hz:g} Hz")
        k = below[0]
        half.append(np.interp(0.5 * p[0], [p[k], p[k - 1]], [za[k], za[k - 1]]))
    return float(2 * np.mean(half))


def make_array(positions_enu_m, latitude_deg: float, beams) -> Array:
    """Validate and bundle an array.

    Args:
        positions_enu_m: (Nants, 3) or (Nants, 2) ENU metres (Up = 0 if 2 columns).
        latitude_deg: site latitude in degrees (no default: HERA is
            :data:`HERA_LATITUDE_DEG`).
        beams: one pyuvdata beam object for all antennas, or a sequence of Nants.
    """
    pos = np.asarray(positions_enu_m, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] not in (2, 3) or pos.shape[0] < 2:
        raise ValueError(f"positions_enu_m must be (Nants>=2, 2 or 3), got shape {pos.shape}")
    if pos.shape[1] == 2:
        pos = np.concatenate([pos, np.zeros((pos.shape[0], 1))], axis=1)
    if not np.all(np.isfinite(pos)):
        raise ValueError("antenna positions contain non-finite values")
    if not -90.0 <= latitude_deg <= 90.0:
        raise ValueError(f"latitude_deg must be in [-90, 90], got {latitude_deg}")
    if isinstance(beams, (list, tuple)):
        if len(beams) != pos.shape[0]:
            raise ValueError(f"got {len(beams)} beams for {pos.shape[0]} antennas")
        beams = tuple(beams)
    else:
        beams = (beams,) * pos.shape[0]
    return Array(pos, float(np.deg2rad(latitude_deg)), beams)


def antpairs(nants: int, autos: bool = False) -> np.ndarray:
    """Antenna pairs (i, j) with i < j (or i <= j with ``autos``), (Nbl, 2), row-major order."""
    iu = np.triu_indices(nants, k=0 if autos else 1)
    return np.stack(iu, axis=1).astype(np.int64)


def baseline_vectors(positions_enu_m: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Baseline vectors ``x_j - x_i`` for each pair (i, j): (Nbl, 3) metres."""
    return positions_enu_m[pairs[:, 1]] - positions_enu_m[pairs[:, 0]]


def beam_amplitude(beam, az_uvbeam_rad: np.ndarray, za_rad: np.ndarray, freqs_hz: np.ndarray) -> np.ndarray:
    """Unpolarised voltage beam ``A = sqrt(P_xx)`` on a set of directions.

    Args:
        beam: pyuvdata AnalyticBeam / UVBeam / BeamInterface.
        az_uvbeam_rad: (Npix,) azimuth, UVBeam convention (North of East), radians.
        za_rad: (Npix,) zenith angle, radians (<= pi/2).
        freqs_hz: (Nfreq,) frequencies in Hz.

    Returns:
        (Nfreq, Npix) real, non-negative amplitudes.
    """
    from pyuvdata import BeamInterface

    bi = beam if isinstance(beam, BeamInterface) else BeamInterface(beam)
    if bi.beam_type == "efield":
        bi = bi.as_power_beam(include_cross_pols=False)
    if bi.Npols > 1:
        bi = bi.with_feeds(["x"])
    kw = {}
    if bi._isuvbeam:
        kw = dict(interpolation_function="az_za_map_coordinates", check_azza_domain=False)
    power = bi.compute_response(
        az_array=np.asarray(az_uvbeam_rad, np.float64),
        za_array=np.asarray(za_rad, np.float64),
        freq_array=np.asarray(freqs_hz, np.float64),
        **kw,
    )
    power = np.real(np.asarray(power)[0, 0])  # (Nfreq, Npix)
    if np.any(power < -1e-12 * np.max(np.abs(power))):
        raise ValueError("beam power is negative somewhere; cannot take an unpolarised amplitude")
    return np.sqrt(np.clip(power, 0.0, None))
