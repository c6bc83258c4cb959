"""A multi-frequency observation of the GSM simulated by matvis, for the frequency-coupled priors.

The check behind issue 25's "what it must show": a channel flagged in the data is inpainted by
the joint posterior (:mod:`gcrsky.solvers.joint`) through the prior's frequency covariance
``R``.  This module makes the observation; the test (``tests/test_frequency_matvis.py``) and
any notebook share it.

The simulation (:func:`simulate_gsm_observation`):

* Sky: pyradiosky's shipped GSM (:func:`gcrsky.model.gsmsky.gsm_maps`, ICRS, nside 8, offline)
  at every channel (default 32 channels 100-131 MHz).  **Band limit.**  The GSM has structure
  beyond any small model lmax; this check is about the frequency model, not about
  truncation, so the truth is the GSM *truncated to the model's lmax before matvis sees it*:
  per channel ``a_true = map2alm(gsm, lmax)`` (realified, K), and matvis gets the
  band-limited map ``alm2map(a_true)`` on an nside ``nside_matvis`` ICRS grid.  The data
  then hold no sky beyond lmax; what is left between model and data is the noise and the
  two codes' quadrature difference (``model_error``, reported per channel, far below the
  noise at the defaults).
* Instrument: a small array (default the 10-antenna 14.6 m hexagon of 14 m Gaussian dishes,
  45 cross-correlations) at the HERA site, ``ntimes`` real UTC times evenly over 24 h (the
  last not repeating the first), matvis CPU ``precision=2`` with its ERFA coordinate
  transform, its fluxes carrying the annual-aberration solid-angle factor as
  :func:`gcrsky.checks.matvis.compare_with_matvis` does, and pixels that never come within
  35 deg of the zenith left out (:func:`matvis_channel_maps`; the 14 m Gaussian's power
  there is ~1e-10 of its peak).  Neither shortcut shows in ``model_error``: 0.0338 sigma at
  worst with or without them (to 2e-5 of it; nside_matvis 32, nside 64, snr 50).
  Visibilities are converted to gcrsky's convention and units:
  ``V = 2 V_matvis / kelvin_sr_to_jy(nu)``, K sr.
* Thermal noise: sky-dominated system temperature, so the per-component standard deviation
  follows the sky's spectrum, ``sigma(nu) = sigma_0 (nu / nu_mid)^-2.55`` (``nu_mid`` the
  geometric mean of the first and last channel) with ``sigma_0`` the rms of the noiseless
  visibilities over all channels divided by ``snr``; complex
  Gaussian with variance ``sigma^2`` in each of the real and imaginary parts.
* Flags: whole channels in contiguous blocks (default two blocks of 4 of 32, 25 %): their
  ``inv_noise`` and data are 0.

The model: gcrsky's real-time operator (``observing_geometry``: local Earth rotation angles
and the ICRS -> CIRS-of-date frame map; response at ``nside`` over lmax + pad), parameters the
realified ICRS coefficients at lmax, per channel (:class:`MultifreqObservation`;
:func:`joint_system` adds a :class:`gcrsky.model.spectral.FrequencyPrior`).  The operator has a
frame map, so the joint *dense* sampler applies (the m-mode one needs ``frame is None``).

matvis and pyradiosky are imported lazily (``require``): this module imports without them.
"""

from __future__ import annotations

import logging
import time as _time
from typing import NamedTuple

import healpy as hp
import jax.numpy as jnp
import numpy as np

from ..base.extras import require
from ..base.units import kelvin_sr_to_jy
from ..instrument.antennas import antpairs, hex_array, make_array
from ..instrument.beams import gaussian_beam
from ..instrument.response import response_matrix
from ..model.gsmsky import gsm_maps
from ..model.operator import VisOperator, apply
from ..model.spectral import FrequencyPrior
from ..solvers.joint import JointSystem
from ..sphere.frames import observing_geometry, time_array
from ..sphere.maps import alm_to_map
from ..sphere.modes import realify
from .matvis import HERA_SITE, aberration_solid_angle_factor, observing_times, site

__all__ = [
    "MultifreqObservation",
    "flag_blocks_mask",
    "gsm_truth",
    "joint_system",
    "matvis_channel_maps",
    "simulate_gsm_observation",
]

log = logging.getLogger(__name__)

#: Spectral index of the sky-dominated system temperature (the noise's frequency dependence).
TSYS_INDEX = -2.55
#: Start of the default observation: inside astropy's bundled IERS tables (no download).
START_UTC = "2025-03-01T00:00:00"


class MultifreqObservation(NamedTuple):
    """A simulated multi-channel observation, ready for :class:`gcrsky.solvers.joint.JointSystem`.

    Attributes:
        op: gcrsky's real-time :class:`~gcrsky.model.operator.VisOperator`: response
            (Nf, Nbl, n(lmax + pad)) complex, angles (Nt,) radians, ICRS -> of-date frame map.
        data: (Nf, Nt, Nbl) complex visibilities from matvis plus noise, K sr (gcrsky's
            convention); 0 in flagged channels.
        inv_noise: (Nf, Nt, Nbl) per-component inverse noise variance, (K sr)^-2; 0 in flagged
            channels.
        truth: (Nf, n) realified ICRS coefficients of the sky matvis saw (the GSM truncated to
            ``lmax``), K.
        flags: (Nf,) bool, True where the channel is flagged.
        freqs_hz: (Nf,) channel frequencies, Hz.
        sigma: (Nf,) noise standard deviation per component, K sr (also in flagged channels:
            what the noise would have been).
        model_error: (Nf,) rms over times and baselines of ``V_matvis - X a_true`` (noiseless,
            every channel), K sr: the two codes' quadrature difference, to compare with ``sigma``.
        lmax: the model's (and the truth's) band limit.
        pairs: (Nbl, 2) antenna pairs (i < j).
        lsts_rad: (Nt,) local Earth rotation angles of the times, radians.
        t_matvis_s: wall time of the matvis simulation, seconds.
    """

    op: VisOperator
    data: np.ndarray
    inv_noise: np.ndarray
    truth: np.ndarray
    flags: np.ndarray
    freqs_hz: np.ndarray
    sigma: np.ndarray
    model_error: np.ndarray
    lmax: int
    pairs: np.ndarray
    lsts_rad: np.ndarray
    t_matvis_s: float


def flag_blocks_mask(nf: int, blocks) -> np.ndarray:
    """(nf,) bool mask of whole flagged channels from contiguous ``blocks`` ``((start, length), ...)``.

    Raises:
        ValueError: a block outside ``0..nf-1``, empty, overlapping another, or no channel left.
    """
    mask = np.zeros(int(nf), bool)
    for start, length in blocks:
        start, length = int(start), int(length)
        if length < 1 or start < 0 or start + length > nf:
            raise ValueError(f"flag block (start {start}, length {length}) is not inside channels 0..{nf - 1}")
        if np.any(mask[start:start + length]):
            raise ValueError(f"flag block (start {start}, length {length}) overlaps another block")
        mask[start:start + length] = True
    if mask.all():
        raise ValueError("every channel is flagged: nothing left to inpaint from")
    return mask


def gsm_truth(freqs_hz, lmax: int) -> np.ndarray:
    """The GSM truncated to ``lmax``: realified ICRS coefficients (Nf, n) K, per channel.

    ``healpy.map2alm`` (3 Jacobi iterations) of :func:`gcrsky.model.gsmsky.gsm_maps` at
    ``freqs_hz``; the map is nside 8, reliable for l <= 16, so ``lmax`` must be <= 16.

    Raises:
        ValueError: ``lmax`` outside 1..16 (and the frequency errors of ``gsm_maps``).
    """
    if not 1 <= int(lmax) <= 16:
        raise ValueError(f"lmax must be in 1..16 (the shipped GSM map is nside 8), got {lmax}")
    maps, _ = gsm_maps(freqs_hz)
    alm = np.stack([hp.map2alm(m, lmax=int(lmax), iter=3) for m in maps])
    return np.asarray(realify(alm, int(lmax)), np.float64)


def simulate_gsm_observation(
    freqs_hz=None,
    *,
    lmax: int = 8,
    flag_blocks=((8, 4), (20, 4)),
    ntimes: int = 16,
    snr: float = 50.0,
    positions_enu_m=None,
    dish_m: float = 14.0,
    location=HERA_SITE,
    start_utc: str = START_UTC,
    nside: int = 64,
    nside_matvis: int = 32,
    max_za_deg: float = 35.0,
    pad: int = 4,
    seed: int = 0,
) -> MultifreqObservation:
    """Simulate the GSM over many channels with matvis; flag channel blocks; add thermal noise.

    Module docstring for the choices.  The caller keeps astropy offline (the default start is
    inside its bundled IERS tables).

    Args:
        freqs_hz: (Nf,) channel frequencies, Hz (default 32 channels, 100-131 MHz).
        lmax: the model's band limit; the truth is the GSM truncated to it (<= 16).
        flag_blocks: contiguous flagged channel blocks ``((start, length), ...)``.
        ntimes: number of times, evenly over 24 h (endpoint excluded).
        snr: rms of the noiseless visibilities (all channels) over the noise sigma at ``nu_mid``
            (module docstring).
        positions_enu_m: (Nant, 3) ENU positions, metres (default :func:`hex_array`).
        dish_m: diameter of the Gaussian dishes, metres.
        location: (latitude deg, east longitude deg, height m) of the array centre.
        start_utc: first time (UTC, ISO).
        nside: HEALPix nside of gcrsky's response quadrature.
        nside_matvis: nside of the band-limited ICRS map handed to matvis (one source per pixel).
        max_za_deg: matvis skips pixels never within this of the zenith (default 35 deg: the 14 m
            Gaussian's power there is ~1e-10 of the peak at 100 MHz; :func:`matvis_channel_maps`).
        pad: extra degrees of the response (the frame map's aberration leakage).
        seed: seed of the noise.

    Returns:
        a :class:`MultifreqObservation`.

    Raises:
        ValueError: bad channels, flags, ``snr`` or ``ntimes``.
    """
    freqs = np.arange(100e6, 132e6, 1e6) if freqs_hz is None else np.asarray(freqs_hz, np.float64)
    if freqs.ndim != 1 or freqs.size < 2 or np.any(np.diff(freqs) <= 0):
        raise ValueError("freqs_hz must be a 1-d increasing array of at least 2 frequencies (Hz)")
    if not (np.isfinite(snr) and snr > 0):
        raise ValueError(f"snr must be finite and positive, got {snr}")
    if int(ntimes) < 2:
        raise ValueError(f"ntimes must be >= 2, got {ntimes}")
    flags = flag_blocks_mask(freqs.size, flag_blocks)
    truth = gsm_truth(freqs, lmax)

    pos = hex_array() if positions_enu_m is None else np.asarray(positions_enu_m, np.float64)
    pairs = antpairs(pos.shape[0])
    loc = site(*location)
    times = observing_times(start_utc, 24.0 * (1.0 - 1.0 / int(ntimes)), int(ntimes))
    beam = gaussian_beam(float(dish_m))

    # gcrsky's operator: real-time geometry, response at the reference angle of the first time
    geom = observing_geometry(time_array(times), loc, int(lmax), pad=int(pad))
    arr = make_array(pos, geom.latitude_deg, beam)
    lsts = np.asarray(geom.lsts_rad, np.float64)
    resp = response_matrix(arr, pairs, freqs, geom.lmax_response, int(nside), lst_ref_rad=float(lsts[0]))
    op = VisOperator(resp, jnp.asarray(np.unwrap(lsts) - lsts[0]), geom.frame)

    # matvis: the band-limited truth as one source per ICRS pixel, brightness kept under aberration
    mid = times.min() + (times.max() - times.min()) / 2
    factor = aberration_solid_angle_factor(int(nside_matvis), mid)
    sky = np.stack([alm_to_map(a, int(lmax), int(nside_matvis)) for a in truth]) * factor  # (Nf, npix) K
    t0 = _time.perf_counter()
    vm = matvis_channel_maps(pos, loc, times, freqs, beam, sky, pairs, max_za_deg=max_za_deg)
    t_matvis = _time.perf_counter() - t0
    log.info("matvis: %d channels, %d times, %d baselines in %.1f s", freqs.size, ntimes, pairs.shape[0], t_matvis)
    v = 2.0 * vm / kelvin_sr_to_jy(freqs)[:, None, None]  # K sr, gcrsky's convention

    v_model = np.asarray(apply(op, jnp.asarray(truth)))
    model_error = np.sqrt(np.mean(np.abs(v - v_model) ** 2, axis=(1, 2)))

    sigma = np.sqrt(np.mean(np.abs(v) ** 2)) / snr * (freqs / np.sqrt(freqs[0] * freqs[-1])) ** TSYS_INDEX
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal(v.shape) + 1j * rng.standard_normal(v.shape)
    data = v + sigma[:, None, None] * noise
    inv_noise = np.broadcast_to(sigma[:, None, None] ** -2.0, v.shape).copy()
    data[flags] = 0.0
    inv_noise[flags] = 0.0
    return MultifreqObservation(op, data, inv_noise, truth, flags, freqs, sigma, model_error, int(lmax),
                                pairs, lsts, t_matvis)


def matvis_channel_maps(positions_enu_m, location, times, freqs_hz, beam, maps_k, pairs, *,
                        max_za_deg: float = 90.0, coord_method: str = "CoordinateRotationERFA") -> np.ndarray:
    """matvis' unpolarised visibilities of one ICRS HEALPix map per channel, in one call.

    As :func:`gcrsky.checks.matvis.matvis_visibilities` (one point source per pixel centre,
    flux ``I_p 4 pi / Npix * 2 k nu^2 / c^2``, CPU, ``precision=2``, pixels never above the
    horizon dropped, negative pixels simulated apart and subtracted), but with a different map
    at every channel: matvis takes per-channel fluxes (Nsrc, Nf), so the per-time coordinate
    transforms are done once for all channels.  Pixels that never come within ``max_za_deg``
    of the zenith at any time are dropped too (for a narrow beam whose power there is
    negligible: the caller's choice, visible in the comparison with gcrsky's full-sky model).

    Args:
        positions_enu_m: (Nant, 3) ENU positions, metres.
        location: astropy ``EarthLocation``.
        times: astropy ``Time`` (Nt,).
        freqs_hz: (Nf,) Hz.
        beam: pyuvdata beam, the same for every antenna.
        maps_k: (Nf, 12 nside**2) RING maps, K, ICRS.
        pairs: (Nbl, 2) antenna pairs.
        max_za_deg: pixels never closer to the zenith than this are not simulated, degrees.
        coord_method: matvis' ICRS -> topocentric transform; default its ERFA one (accurate to
            6 mas, ~3x faster here than the astropy one, which matvis repeats per channel).

    Returns:
        (Nf, Nt, Nbl) complex Jy, matvis' single-feed convention (``I/2``).
    """
    import astropy.units as u

    from ..instrument.response import equatorial_to_enu
    from ..sphere.frames import local_sidereal_angles

    matvis = require("matvis", "validate", "the matvis simulation")
    maps_k = np.asarray(maps_k, np.float64)
    freqs = np.asarray(freqs_hz, np.float64)
    if maps_k.ndim != 2 or maps_k.shape[0] != freqs.size:
        raise ValueError(f"maps_k must be (Nf, npix) with Nf = {freqs.size}, got shape {maps_k.shape}")
    npix = maps_k.shape[1]
    nside_m = hp.npix2nside(npix)
    theta, phi = hp.pix2ang(nside_m, np.arange(npix))
    times = time_array(times)
    lsts = local_sidereal_angles(times, float(location.lon.to_value(u.deg)))
    lat = float(location.lat.to_value(u.rad))
    ever_up = np.zeros(npix, bool)
    cut = np.cos(np.deg2rad(min(float(max_za_deg) + 2.0, 92.0)))
    for lst in lsts:  # ICRS taken as CIRS here (<= 0.4 deg off in 2025), hence the 2 deg margin
        ever_up |= equatorial_to_enu(theta, phi, lst, lat)[:, 2] > cut
    jy = kelvin_sr_to_jy(freqs)[None, :] * (4 * np.pi / npix)
    ants = {i: np.asarray(p, np.float64) for i, p in enumerate(np.asarray(positions_enu_m))}
    out = 0.0
    for sign in (1.0, -1.0):
        part = np.clip(sign * maps_k.T, 0.0, None)  # (npix, Nf)
        keep = np.any(part > 0, axis=1) & ever_up
        if not np.any(keep):
            continue
        vis = matvis.simulate_vis(
            ants=ants, fluxes=part[keep] * jy, ra=phi[keep], dec=np.pi / 2 - theta[keep], freqs=freqs,
            times=times, beams=[beam], telescope_loc=location, polarized=False, precision=2,
            antpairs=np.asarray(pairs, np.int64), coord_method=coord_method,
        )
        out = out + sign * np.asarray(vis)
    return np.asarray(out)


def joint_system(obs: MultifreqObservation, prior: FrequencyPrior) -> JointSystem:
    """The :class:`~gcrsky.solvers.joint.JointSystem` of ``obs`` under ``prior`` (mean (Nf, n) at ``obs.lmax``).

    Raises:
        ValueError: the prior's shape does not match the observation's channels and lmax.
    """
    want = obs.truth.shape
    if tuple(np.shape(prior.mean)) != want or np.shape(prior.freq_cov) != (want[0], want[0]):
        raise ValueError(f"the prior must be over (Nf, n) = {want}; got mean {np.shape(prior.mean)}, "
                         f"freq_cov {np.shape(prior.freq_cov)}")
    return JointSystem(obs.op, jnp.asarray(obs.data), jnp.asarray(obs.inv_noise), prior)
