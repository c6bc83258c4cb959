"""A HERA-core-like visibility file at scale, from the unique baselines' responses only.

:func:`simulate_hera_file` writes a UVH5 file that ``gcrsky run --data`` reads: a
hexagonal array (``n_side`` antennas on a side: 7 gives HERA's 127-antenna core, rows
7..13..7, 14.6 m apart), zenith-pointed Gaussian dishes, a drift scan of ``n_times``
LSTs over ``span_hours`` at the HERA site, and a sky that is one draw from the
isotropic C_l of the GSM at the data's frequencies (:func:`gcrsky.model.gsm_cl`: the
measured table up to l = 16, a power law in l above it) up to a degree ``lmax_sky``
*above* the reach of the longest baseline, so that a run's band-limit rule has
something to cut (:mod:`gcrsky.model.bandlimit`).

What makes it cheap: a regular array has few distinct baselines (127 antennas: 8001
pairs ``i < j`` in 234 redundant groups), so the response is built for one baseline per
group (:func:`gcrsky.instrument.unique_response`) and one autocorrelation, the
noiseless visibilities are gcrsky's own forward model of the sky through it
(:func:`gcrsky.model.operator.apply` with the ICRS -> CIRS-of-date frame map of the real
observing times, :func:`gcrsky.model.problem.observation_geometry`), and only then expanded to
every baseline of the group, each with its own noise.  This is gcrsky's model, not an
independent simulator: a run on the file tests the pipeline at scale and the
posterior's calibration, not the response (that is :mod:`gcrsky.checks.uvsim`'s job,
with matvis, on small arrays).

Conventions (those :mod:`gcrsky.checks.uvsim` writes and the ingest expects): pyuvdata's
``V_ij = <V_i^* V_j>``, ``uvw = x_j - x_i``, a drift-scan ("unprojected") phase centre,
feed products ``xx`` and ``yy``, ``pol_convention`` ``"sum"`` (a feed sees half of
Stokes I: ``V_xx = V_yy = V_I / 2`` for the unpolarised Gaussian beam), ``vis_units``
``"Jy"`` (Rayleigh-Jeans, :func:`gcrsky.base.kelvin_sr_to_jy`), autocorrelations
included and noiseless.

Noise (per component, per feed product of pair ``(i, j)``):
``sigma^2 = |V_ii V_jj| / (2 dt dnu)`` on the noiseless autocorrelations.  The channel
width ``dnu_hz`` is fixed (HERA's 97.66 kHz by default) and the integration time ``dt``
is chosen so that the pseudo-Stokes-I noise (``xx + yy``) has a complex rms of
``noise_fraction`` x the rms cross-correlation (over every baseline, time and channel).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..base.units import kelvin_sr_to_jy
from ..instrument.antennas import antpairs, hex_array, make_array
from ..instrument.beams import gaussian_beam
from ..instrument.redundancy import groups_for_array, unique_response
from .matvis import HERA_SITE, observing_times, site

__all__ = ["HeraSimulation", "hex_rows", "reach_lmax", "simulate_hera_file"]

#: HERA's fine channel width, Hz (the default ``dnu_hz``).
HERA_CHANNEL_HZ = 97656.25


class HeraSimulation(NamedTuple):
    """What :func:`simulate_hera_file` wrote (JSON-friendly apart from the arrays).

    Attributes:
        path: the UVH5 file.
        n_antennas, n_baselines, n_groups: antennas, cross pairs ``i < j``, redundant groups.
        freqs_hz: (Nf,) channel centres, Hz.
        n_times: LSTs; ``span_hours`` their span.
        lmax_sky: degree of the simulated sky.
        reach: ``2 pi (|b| + D_eq) nu / c`` of the longest baseline at the highest frequency
            (:func:`reach_lmax`): the lmax a run on the file should choose.
        nside: HEALPix nside of the simulation's response quadrature.
        dt_s, dnu_hz: integration time and channel width written to the file (the noise's).
        noise_fraction: complex rms of the pI noise / rms pI cross-correlation, as simulated.
        a_true: (Nf, (lmax_sky+1)^2) the sky's realified ICRS coefficients, K.
        cl: (Nf, lmax_sky+1) the C_l it was drawn from, K^2.
        seconds: wall time by step (``"response"``, ``"visibilities"``, ``"write"``), s.
    """

    path: Path
    n_antennas: int
    n_baselines: int
    n_groups: int
    freqs_hz: np.ndarray
    n_times: int
    span_hours: float
    lmax_sky: int
    reach: int
    nside: int
    dt_s: float
    dnu_hz: float
    noise_fraction: float
    a_true: np.ndarray
    cl: np.ndarray
    seconds: dict


def hex_rows(n_side: int) -> tuple[int, ...]:
    """Row lengths of a hexagon with ``n_side`` antennas on a side (7: 7..13..7, 127 antennas)."""
    if n_side < 1:
        raise ValueError(f"n_side must be at least 1, got {n_side}")
    up = list(range(n_side, 2 * n_side))
    return tuple(up + up[-2::-1])


def reach_lmax(positions_enu_m, freq_hz: float, dish_m: float) -> int:
    """The reach (:func:`gcrsky.model.bandlimit.baseline_reach`, ENU form) of the longest baseline
    of ``positions_enu_m`` (Nant, 3) at ``freq_hz`` for the Gaussian beam of a ``dish_m`` dish, with
    the D a run uses (:func:`gcrsky.model.bandlimit.beam_dish_m`: the Airy equivalent of the
    measured FWHM, ~1.03 ``dish_m``), rounded up: the lmax a run on the file chooses."""
    from ..model.bandlimit import baseline_reach, beam_dish_m

    pos = np.asarray(positions_enu_m, np.float64)
    pairs = antpairs(pos.shape[0])
    dish = beam_dish_m([gaussian_beam(dish_m)], [freq_hz])
    return int(math.ceil(float(np.max(baseline_reach(pos[pairs[:, 1]] - pos[pairs[:, 0]], [freq_hz], dish)))))


def _sky(freqs_hz, lmax: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(a (Nf, n), cl (Nf, lmax+1))``: one draw from the GSM's isotropic C_l (the same
    standard normals at every channel, scaled by each channel's C_l), the monopole at +1 sd."""
    from ..model.prior import isotropic_prior
    from ..model.skyprior import gsm_cl

    cl = gsm_cl(np.asarray(freqs_hz, np.float64), lmax)
    sd = 1.0 / np.sqrt(isotropic_prior(cl, (lmax + 1) ** 2).inv_var)
    z = np.random.default_rng(seed).standard_normal((lmax + 1) ** 2)
    z[0] = 1.0  # the monopole at +1 prior sd (~1150 K at 100 MHz): positive autos near the GSM's
    return sd * z[None, :], cl


def _model_visibilities(array, groups, times, location, freqs, a, lmax: int, nside: int, frame_pad: int):
    """Noiseless pI-equivalent visibilities, K sr: ``(cross (Nf, Nt, Ngroups), auto (Nf, Nt))``.

    The response of each group's representative and of one autocorrelation (every antenna
    has the same beam) at ``lmax + frame_pad``, of-date frame at the first LST, through
    the ICRS -> of-date frame map and the LST rotations (:func:`gcrsky.model.operator.apply`).
    """
    import jax.numpy as jnp

    from ..model.operator import VisOperator, apply
    from ..model.problem import observation_geometry

    geom = observation_geometry(array, lmax, times=times, location=location, frame_pad=frame_pad)
    lst_ref = float(geom.lsts_rad[0])
    angles = jnp.asarray(geom.lsts_rad - lst_ref)
    r_u = unique_response(array, groups, freqs, geom.lmax_response, nside, lst_ref_rad=lst_ref)
    cross = np.asarray(apply(VisOperator(r_u, angles, geom.frame), jnp.asarray(a)))
    del r_u
    auto_groups = groups_for_array(array, np.array([[0, 0]]))
    r_a = unique_response(array, auto_groups, freqs, geom.lmax_response, nside, lst_ref_rad=lst_ref)
    auto = np.asarray(apply(VisOperator(r_a, angles, geom.frame), jnp.asarray(a)).real)[:, :, 0]
    return cross, auto


def _integration_time(cross, auto, counts, noise_fraction: float, dnu_hz: float) -> float:
    """The ``dt`` (s) whose pI noise has complex rms ``noise_fraction`` x the rms cross-correlation.

    pI = ``xx + yy`` with ``V_xx = V_yy = V / 2``: per component ``sigma_pI^2 = 2 (V_auto / 2)^2
    / (2 dt dnu)``, complex rms ``sqrt(2) sigma_pI``; the rms is over every baseline (``counts``
    per group), time and channel, with the median autocorrelation.
    """
    rms = math.sqrt(float(np.sum(np.abs(cross) ** 2 * counts) / (np.sum(counts) * cross.shape[0] * cross.shape[1])))
    auto_med = float(np.median(np.abs(auto)))
    return auto_med**2 / (2.0 * noise_fraction**2 * rms**2 * dnu_hz)


def _file_data(cross, auto, groups, nant: int, dt_s: float, dnu_hz: float, seed: int):
    """``(data (Nf, Nt, Npairs, 2) K sr, noise_fraction)`` of the feed products ``xx``, ``yy`` for
    every pair ``i <= j`` (:func:`gcrsky.instrument.antpairs` with autos), noise per baseline."""
    pairs = antpairs(nant, autos=True)
    is_auto = pairs[:, 0] == pairs[:, 1]
    cross_rows = np.flatnonzero(~is_auto)
    nf, nt = auto.shape
    half = np.empty((nf, nt, pairs.shape[0]), np.complex128)  # one feed product: V / 2 ("sum")
    half[:, :, is_auto] = (auto / 2.0)[:, :, None]
    half[:, :, cross_rows] = cross[:, :, groups.group_of] / 2.0
    sigma = np.abs(auto / 2.0)[:, :, None] / math.sqrt(2.0 * dt_s * dnu_hz)  # every antenna's auto is the same
    rng = np.random.default_rng(seed + 1)
    data = np.repeat(half[..., None], 2, axis=-1)
    shape = (nf, nt, cross_rows.size, 2)
    noise = sigma[..., None] * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))
    data[:, :, cross_rows, :] += noise
    pi_noise = noise.sum(axis=-1)
    frac = math.sqrt(float(np.mean(np.abs(pi_noise) ** 2) / np.mean(np.abs(2 * half[:, :, cross_rows]) ** 2)))
    return data, pairs, frac


def simulate_hera_file(
    path,
    *,
    n_side: int = 7,
    spacing_m: float = 14.6,
    dish_m: float = 14.0,
    freqs_hz=(100e6,),
    n_times: int = 30,
    span_hours: float = 8.0,
    start_utc: str = "2025-03-21T18:00:00",
    lmax_sky: int | None = None,
    sky_margin: float = 0.15,
    nside: int | None = None,
    noise_fraction: float = 0.2,
    dnu_hz: float = HERA_CHANNEL_HZ,
    frame_pad: int = 4,
    seed: int = 0,
) -> HeraSimulation:
    """Write a HERA-core-like drift scan as UVH5 (module docstring) and say what was written.

    Args:
        path: the UVH5 file to write (overwritten).
        n_side, spacing_m: the hexagon (:func:`hex_rows`, :func:`gcrsky.instrument.hex_array`), metres.
        dish_m: diameter of every antenna's Gaussian dish (:func:`gcrsky.instrument.gaussian_beam`), m;
            a run reads the file with ``--dish-diameter`` of the same value.
        freqs_hz: (Nf,) channel centres, Hz (30-250 MHz: the GSM's table).
        n_times, span_hours, start_utc: the LSTs: ``n_times`` UTC times evenly over ``span_hours``.
        lmax_sky: degree of the sky; default ``ceil((1 + sky_margin) x reach)`` (:func:`reach_lmax`).
        nside: nside of the simulation's response; default the smallest power of 2 with
            ``3 nside - 1 >= lmax_sky + frame_pad``.  Run the file at the same nside for the same quadrature.
        noise_fraction: complex rms of the pI noise over the rms pI cross-correlation.
        dnu_hz: channel width, Hz (the integration time follows from ``noise_fraction``).
        frame_pad: degree margin of the ICRS -> of-date map (the run's default is 4).
        seed: seed of the sky (``seed``) and of the noise (``seed + 1``).

    Returns:
        :class:`HeraSimulation`.
    """
    from .uvsim import uvdata_of

    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    pos = hex_array(hex_rows(n_side), spacing_m)
    nant = pos.shape[0]
    reach = reach_lmax(pos, float(freqs.max()), dish_m)
    lmax_sky = int(math.ceil((1.0 + sky_margin) * reach)) if lmax_sky is None else int(lmax_sky)
    if nside is None:
        nside = 1 << max(0, math.ceil(math.log2((lmax_sky + frame_pad + 1) / 3.0)))
    location = site(*HERA_SITE)
    times = observing_times(start_utc, span_hours, n_times)
    array = make_array(pos, HERA_SITE[0], [gaussian_beam(dish_m)] * nant)
    groups = groups_for_array(array, antpairs(nant))
    a, cl = _sky(freqs, lmax_sky, seed)
    t0 = time.perf_counter()
    cross, auto = _model_visibilities(array, groups, times, location, freqs, a, lmax_sky, nside, frame_pad)
    t1 = time.perf_counter()
    dt_s = _integration_time(cross, auto, groups.counts, noise_fraction, dnu_hz)
    data, pairs, frac = _file_data(cross, auto, groups, nant, dt_s, dnu_hz, seed)
    jy = kelvin_sr_to_jy(freqs)[:, None, None, None]
    blt = np.transpose(data * jy, (1, 2, 0, 3)).reshape(n_times * pairs.shape[0], freqs.size, 2)  # time-major
    t2 = time.perf_counter()
    uvd = uvdata_of(pos, location, np.arange(nant), pairs, times, freqs, ("xx", "yy"), blt, "Jy", "sum", dt_s,
                  dnu_hz, f"gcrsky.checks.hera_sim: {nant}-antenna hexagon, GSM C_l sky to lmax {lmax_sky} (reach "
                  f"{reach}), unique-baseline responses at nside {nside}, radiometer noise dt={dt_s:.4g} s "
                  f"dnu={dnu_hz:g} Hz")
    uvd.write_uvh5(str(path), clobber=True)
    secs = {"response_and_visibilities": t1 - t0, "noise": t2 - t1, "write": time.perf_counter() - t2}
    return HeraSimulation(Path(path), nant, int(groups.n_baselines), int(groups.n_groups), freqs, int(n_times),
                          float(span_hours), lmax_sky, reach, int(nside), float(dt_s), float(dnu_hz), frac, a, cl,
                          secs)
