"""A complete inference problem: instrument, operator, data, noise and prior.

:func:`standard_case` builds the paper's standard case (DESIGN section 7);
:func:`build_problem` builds any other from explicit ingredients.  A
:class:`Problem` is an equinox Module (a PyTree), so it can be passed through
``jax.jit``; its configuration is static metadata.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .instrument import HERA_HEIGHT_M, HERA_LATITUDE_DEG, HERA_LONGITUDE_DEG, Array, antpairs, gaussian_beam, hex_array, make_array
from .layout import ModeTable, lmax_from_nparams, mode_table, n_params
from .noise import clean_data, draw_noise, inverse_variance, radiometer_sigma, weights_from_flags
from .normal import LinearSystem, precision_matrix, require_x64
from .frames import FrameMap, observing_geometry
from .operator import VisOperator, apply, frame_shape
from .prior import Prior, flat_prior, paper_prior
from .response import response_matrix

__all__ = ["Config", "Problem", "standard_case", "build_problem", "hours_to_rad"]

log = logging.getLogger(__name__)


def hours_to_rad(hours) -> np.ndarray:
    """Sidereal hours -> radians of rotation (24 h = 2 pi)."""
    return np.asarray(hours, np.float64) * (2 * np.pi / 24.0)


@dataclasses.dataclass(frozen=True)
class Config:
    """Scalar configuration of a simulated problem (defaults: the paper's standard case).

    Units: frequencies Hz, LSTs sidereal hours, lengths metres, latitude degrees,
    dt seconds, dnu Hz.  ``noise_scale`` multiplies the noise *variance* N,
    ``prior_scale`` the prior variance S (paper cases B2-B8).  The dishes are
    pyuvdata's ``GaussianBeam(diameter=dish_diameter)`` (FWHM ~ lambda/D, 12.28 deg
    at 100 MHz for 14 m) unless ``beam_fwhm_deg`` is set: then a Gaussian power beam
    of exactly that FWHM at the first frequency, scaling as 1/frequency (the paper's
    D1 quotes FWHM = lambda/D = 57.3 deg for 3 m dishes, which the Airy-matched
    ``GaussianBeam(diameter=3)``, 63.4 deg, does not reproduce).  ``obs_date`` None
    is the paper's idealised mode (sky coefficients in the co-rotating frame);
    a date (e.g. ``"2026-03-21"``) observes at the real UTC times of that date
    whose local Earth rotation angles are the LSTs, with the sky in ICRS
    (DESIGN section 2, mode b; the site is longitude/latitude/height).
    """

    lmax: int = 20
    nside: int = 128
    freqs_hz: tuple = (100e6, 102e6)
    n_lst: int = 10
    lst_range_hours: tuple = (0.0, 8.0)
    dish_diameter: float = 14.0
    beam_fwhm_deg: Optional[float] = None
    antenna_spacing: float = 14.6
    rows: tuple = (3, 4, 3)
    latitude_deg: float = HERA_LATITUDE_DEG
    longitude_deg: float = HERA_LONGITUDE_DEG
    height_m: float = HERA_HEIGHT_M
    obs_date: Optional[str] = None
    dt_s: float = 60.0
    dnu_hz: float = 1e6
    noise_scale: float = 1.0
    prior_scale: float = 1.0
    prior_frac: float = 0.1
    prior_floor_std: float = 0.5
    flat_prior: bool = False
    zero_prior_mean: bool = False
    seed: int = 0
    sky_source: str = "auto"
    extend_seed: int = 2024

    def validate(self) -> "Config":
        if int(self.lmax) != self.lmax or self.lmax < 1:
            raise ValueError(f"lmax must be an integer >= 1, got {self.lmax}")
        if self.n_lst < 1:
            raise ValueError(f"n_lst must be >= 1, got {self.n_lst}")
        if len(self.lst_range_hours) != 2:
            raise ValueError("lst_range_hours must be (start, stop) in hours")
        if self.beam_fwhm_deg is not None and not 0 < self.beam_fwhm_deg < 180:
            raise ValueError(f"beam_fwhm_deg must be in (0, 180), got {self.beam_fwhm_deg}")
        for name in ("dish_diameter", "antenna_spacing", "dt_s", "dnu_hz", "noise_scale", "prior_scale", "prior_frac"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.obs_date is not None:
            from astropy.time import Time

            try:
                Time(self.obs_date, scale="utc")
            except ValueError as e:
                raise ValueError(f"obs_date {self.obs_date!r} is not a date astropy understands: {e}") from None
        if 3 * self.nside - 1 < self.lmax:
            raise ValueError(f"nside={self.nside} cannot resolve lmax={self.lmax} (need 3*nside-1 >= lmax)")
        return self

    @property
    def lsts_hours(self) -> np.ndarray:
        """The observation LSTs: ``linspace(start, stop, n_lst)`` (endpoints included)."""
        return np.linspace(self.lst_range_hours[0], self.lst_range_hours[1], self.n_lst)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}


class Problem(eqx.Module):
    """Data, noise, prior and operator of one inference problem.

    Array attributes (leading Nf = number of frequencies; n = (lmax+1)**2):
        freqs_hz (Nf,); lsts_rad (Nt,); antpairs (Nbl, 2) with baseline x_j - x_i;
        response (Nf, Nbl, n) complex at ``lst_ref_rad``; auto_response (Nf, Nant, n);
        data (Nf, Nt, Nbl) complex (K sr); sigma (Nf, Nt, Nbl) per-component noise std;
        weights (Nf, Nt, Nbl) in [0, 1]; prior (mean, inv_var (Nf, n));
        a_true (Nf, n) or None; frame: None (parameters are coefficients of the
        co-rotating frame, the paper's idealised LSTs) or the map from the
        parameters' frame (e.g. ICRS) to it (dense (n_resp, n) or a
        :class:`gcrsky.frames.FrameMap`), with the response at the map's output degree.
    """

    freqs_hz: jax.Array
    lsts_rad: jax.Array
    antpairs: np.ndarray
    response: jax.Array
    auto_response: jax.Array
    data: jax.Array
    sigma: jax.Array
    weights: jax.Array
    prior: Prior
    a_true: Optional[jax.Array]
    frame: Optional[object]
    lst_ref_rad: float = eqx.field(static=True)
    lmax: int = eqx.field(static=True)
    nside: int = eqx.field(static=True)
    config: Optional[Config] = eqx.field(static=True, default=None)
    sky_note: str = eqx.field(static=True, default="")

    @property
    def n(self) -> int:
        return n_params(self.lmax)

    @property
    def modes(self) -> ModeTable:
        return mode_table(self.lmax)

    def operator(self) -> VisOperator:
        """The visibility operator for this problem's LSTs."""
        return VisOperator(self.response, self.lsts_rad - self.lst_ref_rad, self.frame)

    def system(self) -> LinearSystem:
        """The linear system (operator, data, inverse noise, prior)."""
        iv = self.weights / self.sigma**2
        return LinearSystem(self.operator(), self.data, iv, self.prior)

    def visibilities(self, a) -> jax.Array:
        """Noiseless model visibilities for realified ``a`` (Nf, n): complex (Nf, Nt, Nbl)."""
        return apply(self.operator(), jnp.asarray(a))

    def auto_visibilities(self, a) -> jax.Array:
        """Real auto-correlations ``V_ii`` (Nf, Nt, Nant) of the sky ``a``."""
        return apply(VisOperator(self.auto_response, self.lsts_rad - self.lst_ref_rad, self.frame), jnp.asarray(a)).real

    def precision_matrix(self) -> jax.Array:
        """Dense realified posterior precision P, (Nf, n, n)."""
        return precision_matrix(self.system())


def build_problem(
    array: Array,
    freqs_hz,
    lsts_rad,
    lmax: int,
    nside: int,
    *,
    a_true=None,
    data=None,
    sigma=None,
    weights=None,
    flags=None,
    prior: Prior | None = None,
    dt_s: float = 60.0,
    dnu_hz: float = 1e6,
    noise_scale: float = 1.0,
    key: jax.Array | None = None,
    lst_ref_rad: float = 0.0,
    frame=None,
    times=None,
    location=None,
    frame_pad: int = 4,
    responses: tuple | None = None,
    config: Config | None = None,
    sky_note: str = "",
) -> Problem:
    """Assemble a :class:`Problem`.

    Flags: ``flags`` (bool, True = bad, broadcastable to (Nf, Nt, Nbl)) and/or
    ``weights`` (in [0, 1]) set the per-sample weights (0 under a flag); flagged data
    may hold anything, NaN and Inf included, and are stored as 0; an unflagged
    non-finite sample is an error naming its (freq, time, baseline) and antennas.

    Either give ``data`` (Nf, Nt, Nbl) complex with ``sigma`` (per-component std), or
    give ``a_true`` (Nf, n) to simulate: model visibilities plus radiometer noise
    whose sigma comes from the simulated autos (``sigma^2 = V_ii V_jj / (2 dt dnu)``,
    times ``noise_scale``), drawn with ``key``.  The prior defaults to flat.

    Two frame modes (DESIGN section 2):

    * idealised (the paper's): ``lsts_rad`` (Nt,) radians; the parameters are
      coefficients of the co-rotating frame.
    * real observing times: ``lsts_rad=None``, ``times`` (astropy ``Time`` (Nt,))
      and ``location`` (astropy ``EarthLocation``, whose latitude must be the
      array's).  The parameters (and ``a_true``, the prior) are then ICRS
      coefficients at ``lmax``; :func:`gcrsky.frames.observing_geometry` supplies
      the local Earth rotation angles and the fixed ICRS -> CIRS-of-date
      :class:`gcrsky.frames.FrameMap`, and the response is built at
      ``lmax + frame_pad``.

    An explicit ``frame`` (dense (n_resp, n) array or ``FrameMap``) with
    ``lsts_rad`` is also accepted.  ``responses``: optional precomputed
    ``(cross, auto)`` responses for exactly this array, frequencies, degree, nside
    and ``lst_ref_rad`` (reused across problems that differ only in LSTs, noise or
    prior; shapes are checked, the contents cannot be).
    """
    require_x64("build_problem")
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    if times is not None:
        if lsts_rad is not None or frame is not None:
            raise ValueError("give either times (with location) or lsts_rad (with an optional frame), not both")
        if location is None:
            raise ValueError("real observing times need the site: pass location (astropy EarthLocation)")
        geom = observing_geometry(times, location, lmax, pad=frame_pad)
        if abs(geom.latitude_deg - float(np.rad2deg(array.latitude_rad))) > 1e-6:
            raise ValueError(
                f"the array is at latitude {float(np.rad2deg(array.latitude_rad))} deg but location is at "
                f"{geom.latitude_deg} deg; build the array with make_array(..., location latitude, ...)"
            )
        lsts_rad, frame = geom.lsts_rad, geom.frame
    elif location is not None:
        raise ValueError("location is only used with times")
    if lsts_rad is None:
        raise ValueError("give lsts_rad (idealised frame) or times and location (real observing times)")
    lsts = np.atleast_1d(np.asarray(lsts_rad, np.float64))
    nant = array.positions_enu_m.shape[0]
    pairs = antpairs(nant)
    n = n_params(lmax)
    lmax_resp = lmax
    if frame is not None:
        if not isinstance(frame, FrameMap):
            frame = jnp.asarray(frame, jnp.float64)
        n_resp, n_frame = frame_shape(frame)
        if n_frame != n:
            raise ValueError(f"frame map takes {n_frame} coefficients, lmax={lmax} has {n}")
        lmax_resp = lmax_from_nparams(n_resp)
    if responses is None:
        resp = response_matrix(array, pairs, freqs, lmax_resp, nside, lst_ref_rad=lst_ref_rad)
        auto = response_matrix(
            array, np.stack([np.arange(nant)] * 2, 1), freqs, lmax_resp, nside, lst_ref_rad=lst_ref_rad
        )
    else:  # precomputed for this array, frequencies, degree, nside and lst_ref_rad
        resp, auto = responses
        want = ((freqs.size, pairs.shape[0], n_params(lmax_resp)), (freqs.size, nant, n_params(lmax_resp)))
        if (tuple(resp.shape), tuple(auto.shape)) != want:
            raise ValueError(f"precomputed responses have shapes {resp.shape}, {auto.shape}; expected {want}")
    angles = jnp.asarray(lsts - lst_ref_rad)
    if key is None:
        key = jax.random.PRNGKey(0)
    shape = (freqs.size, lsts.size, pairs.shape[0])
    if a_true is not None:
        a_true = jnp.asarray(a_true, jnp.float64)
        if a_true.shape != (freqs.size, n):
            raise ValueError(f"a_true has shape {a_true.shape}, expected {(freqs.size, n)}")
    if data is None:
        if a_true is None:
            raise ValueError("give either data (with sigma) or a_true to simulate from")
        autos = np.asarray(apply(VisOperator(auto, angles, frame), a_true).real)  # (Nf, Nt, Nant)
        if sigma is None:
            sigma = radiometer_sigma(autos[:, :, pairs[:, 0]], autos[:, :, pairs[:, 1]], dt_s, dnu_hz)
        sigma = np.asarray(sigma, np.float64) * np.sqrt(noise_scale)
        model = apply(VisOperator(resp, angles, frame), a_true)
        data = model + draw_noise(key, jnp.asarray(sigma))
    else:
        if sigma is None:
            raise ValueError("real data need their per-component noise sigma")
        data = np.asarray(data)
        sigma = np.asarray(sigma, np.float64) * np.sqrt(noise_scale)
    data = np.asarray(data)
    if data.shape != shape:
        raise ValueError(f"data have shape {data.shape}, expected (Nf, Nt, Nbl) = {shape}")
    sigma = np.broadcast_to(sigma, shape)
    if flags is not None:
        w = weights_from_flags(flags, weights, shape=shape)
    elif weights is None:
        w = np.ones(shape)
    else:
        w = weights_from_flags(np.zeros((), bool), weights, shape=shape)
    iv = inverse_variance(sigma, w)
    data = clean_data(data, iv, antpairs=pairs)
    if prior is None:
        prior = flat_prior(freqs.size, n)
    if prior.mean.shape != (freqs.size, n) or prior.inv_var.shape != (freqs.size, n):
        raise ValueError(f"prior arrays must be (Nf, n) = {(freqs.size, n)}")
    return Problem(
        freqs_hz=jnp.asarray(freqs),
        lsts_rad=jnp.asarray(lsts),
        antpairs=pairs,
        response=resp,
        auto_response=auto,
        data=jnp.asarray(data, jnp.complex128),
        sigma=jnp.asarray(sigma),
        weights=jnp.asarray(w),
        prior=Prior(jnp.asarray(prior.mean, jnp.float64), jnp.asarray(prior.inv_var, jnp.float64)),
        a_true=a_true,
        frame=frame,
        lst_ref_rad=float(lst_ref_rad),
        lmax=int(lmax),
        nside=int(nside),
        config=config,
        sky_note=sky_note,
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
            same :func:`gcrsky.scenarios.instrument_key`.
    """
    from .sky import sky_truth

    freqs = np.asarray(cfg.freqs_hz, np.float64)
    truth = sky_truth(freqs, cfg.lmax, source=cfg.sky_source, extend_seed=cfg.extend_seed)
    log.info("sky truth: %s", truth.note)
    array = make_array(hex_array(cfg.rows, cfg.antenna_spacing), cfg.latitude_deg, beam_for_config(cfg))
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

        from .frames import times_for_lsts

        site = EarthLocation.from_geodetic(cfg.longitude_deg * u.deg, cfg.latitude_deg * u.deg, cfg.height_m * u.m)
        times = times_for_lsts(cfg.obs_date, hours_to_rad(cfg.lsts_hours), cfg.longitude_deg)
        when = dict(lsts_rad=None, times=times, location=site)
    key = None
    if response_cache is not None:
        from .scenarios import instrument_key

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
