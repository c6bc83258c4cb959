"""The paper's standard case (DESIGN section 7) and any simulated problem a :class:`Config` describes.

:func:`standard_case` (with keyword overrides of any :class:`Config` field) and
:func:`problem_from_config` simulate the truth sky (:mod:`gcrsky.sim.sky`), the
hexagonal array, the paper's prior and radiometer noise, then build the problem
with :func:`gcrsky.build_problem`.
"""

from __future__ import annotations

import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np

from ..instrument.antennas import antpairs, hex_array, make_array
from ..instrument.beams import gaussian_beam
from ..instrument.response import check_response_memory
from ..model.prior import flat_prior, paper_prior
from ..model.problem import Problem, build_problem
from ..sphere.frames import hours_to_rad
from ..sphere.modes import n_params
from .config import Config

__all__ = ["beam_for_config", "instrument_key", "problem_from_config", "standard_case"]

log = logging.getLogger(__name__)


def instrument_key(cfg: Config) -> tuple:
    """What the response at the reference angle depends on (the response-cache key of
    :func:`problem_from_config`)."""
    return (
        tuple(cfg.rows), float(cfg.antenna_spacing), float(cfg.dish_diameter), cfg.beam_fwhm_deg,
        float(cfg.latitude_deg), tuple(float(f) for f in cfg.freqs_hz), int(cfg.lmax), int(cfg.nside),
        cfg.obs_date,
    )


_OVERRIDES = {f.name for f in dataclasses.fields(Config)}


def standard_case(**overrides) -> Problem:
    """The paper's standard case, with keyword overrides of any :class:`Config` field.

    10-antenna hexagon (rows 3, 4, 3; 14.6 m), 14 m Gaussian dishes at latitude
    -30.7215 deg, channels 100 and 102 MHz, 10 LSTs over 0-8 h, dt = 60 s,
    dnu = 1 MHz, lmax 20, nside 128, GSM truth (GSM2016 if on disk, else the
    pyradiosky GSM map shipped offline), radiometer noise from the autos, the 10%
    prior with 0.5 K floor and ``a0 ~ N(a_true, S)`` (monopole kept true).

    Common overrides: ``lmax, nside, n_lst, lst_range_hours, dish_diameter,
    noise_scale, prior_scale, flat_prior, zero_prior_mean, seed``.
    """
    unknown = set(overrides) - _OVERRIDES
    if unknown:
        raise TypeError(f"unknown standard_case overrides {sorted(unknown)}; allowed: {sorted(_OVERRIDES)}")
    for k in ("freqs_hz", "lst_range_hours", "rows"):
        if k in overrides:
            overrides[k] = tuple(np.atleast_1d(overrides[k]).tolist())
    cfg = Config(**overrides).validate()
    return problem_from_config(cfg)


def beam_for_config(cfg: Config):
    """The (pyuvdata) dish beam a :class:`Config` describes (see ``beam_fwhm_deg``)."""
    if cfg.beam_fwhm_deg is None:
        return gaussian_beam(cfg.dish_diameter)
    from pyuvdata.analytic_beam import GaussianBeam

    # power P = E^2 = exp(-za^2 / (2 sigma_P^2)) with FWHM = 2 sqrt(2 ln 2) sigma_P, so the
    # E-field sigma is sqrt(2) sigma_P.  (pyuvdata 3's sigma_type="power" gives a power beam
    # sqrt(2) wider than asked, measured, so the E-field form is used.)
    sigma_p = np.deg2rad(cfg.beam_fwhm_deg) / (2 * np.sqrt(2 * np.log(2)))
    return GaussianBeam(
        sigma=float(np.sqrt(2) * sigma_p), sigma_type="efield", spectral_index=-1.0,
        reference_frequency=float(cfg.freqs_hz[0]),
    )


def problem_from_config(cfg: Config, *, response_cache: dict | None = None) -> Problem:
    """Build the simulated problem a :class:`Config` describes.

    Args:
        cfg: the configuration.
        response_cache: optional dict shared between calls: the response (which does
            not depend on LSTs, noise or prior) is reused for configurations with the
            same :func:`instrument_key`.
    """
    from .sky import sky_truth  # pyradiosky / pygdsm only when a truth is made

    freqs = np.asarray(cfg.freqs_hz, np.float64)
    array = make_array(hex_array(cfg.rows, cfg.antenna_spacing), cfg.latitude_deg, beam_for_config(cfg))
    if response_cache is None or instrument_key(cfg) not in response_cache:  # refuse before the sky is made
        nant = array.positions_enu_m.shape[0]
        check_response_memory(array, antpairs(nant), freqs, cfg.lmax, cfg.nside, None)
    truth = sky_truth(freqs, cfg.lmax, source=cfg.sky_source, extend_seed=cfg.extend_seed)
    log.info("sky truth: %s", truth.note)
    k_noise, k_prior = jax.random.split(jax.random.PRNGKey(cfg.seed))
    a_true = jnp.asarray(truth.alm)
    if cfg.flat_prior:
        prior = flat_prior(freqs.size, n_params(cfg.lmax), mean=np.zeros((freqs.size, n_params(cfg.lmax))))
    else:
        prior = paper_prior(
            a_true,
            k_prior,
            frac=cfg.prior_frac,
            floor_std=cfg.prior_floor_std,
            prior_scale=cfg.prior_scale,
            zero_mean=cfg.zero_prior_mean,
        )
    if cfg.obs_date is None:
        when = dict(lsts_rad=hours_to_rad(cfg.lsts_hours))
    else:
        import astropy.units as u
        from astropy.coordinates import EarthLocation

        from ..sphere.frames import times_for_lsts

        site = EarthLocation.from_geodetic(cfg.longitude_deg * u.deg, cfg.latitude_deg * u.deg, cfg.height_m * u.m)
        times = times_for_lsts(cfg.obs_date, hours_to_rad(cfg.lsts_hours), cfg.longitude_deg)
        when = dict(lsts_rad=None, times=times, location=site)
    key = None
    if response_cache is not None:
        key = instrument_key(cfg)
        if key in response_cache:
            when["responses"] = response_cache[key]
            log.info("reusing the response for %s", key)
    prob = build_problem(
        array,
        freqs,
        lmax=cfg.lmax,
        nside=cfg.nside,
        **when,
        a_true=a_true,
        prior=prior,
        dt_s=cfg.dt_s,
        dnu_hz=cfg.dnu_hz,
        noise_scale=cfg.noise_scale,
        key=k_noise,
        config=cfg,
        sky_note=truth.note,
    )
    if key is not None:
        response_cache[key] = (prob.response, prob.auto_response)
    return prob
