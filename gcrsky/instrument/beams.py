"""Beams: pyuvdata beam objects evaluated on the sky.

Beams are pyuvdata beam objects (``GaussianBeam``, ``AiryBeam``, any
``AnalyticBeam``, ``UVBeam``).  For Stokes-I (unpolarised) work we follow
matvis: the feed-``x`` power beam ``P_i`` is evaluated and ``A_i = sqrt(P_i)``,
so identical antennas give ``A_i^* A_j = P``.  Azimuth passed to pyuvdata is
in the UVBeam convention (North of East: Az(E)=0, Az(N)=pi/2), zenith angle in
radians.
"""

from __future__ import annotations

import numpy as np

from ..base.units import SPEED_OF_LIGHT

__all__ = ["beam_amplitude", "beam_fwhm_rad", "fwhm_airy_rad", "gaussian_beam", "unique_beams"]


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
    lam = SPEED_OF_LIGHT / freq_hz
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
