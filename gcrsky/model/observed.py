"""The inference problem of an :class:`~gcrsky.io.Observation`: products, units, noise, rows.

:func:`problem_from_observation` turns what a file says (an Observation, read by
:func:`gcrsky.io.read_observation`) plus the antennas' beams into the
:class:`~gcrsky.model.Problem` whose parameters are the ICRS coefficients of the sky at
the file's real observing times at the file's site (DESIGN section 2, mode (b)).

* Polarisation: gcrsky models *I-equivalent* visibilities of an unpolarised sky,
  ``V = int K I e^{...}`` with the product's cross power beam ``K`` (``"xx"``: ``K_xx``;
  ``"pI"``: ``(K_xx + K_yy)/2``; :mod:`gcrsky.instrument.response`).  A file's
  ``pol_convention`` (absent means ``"sum"``, what pyuvsim, matvis and hera_sim write)
  fixes the factor (:func:`product_factor`): under ``"sum"`` a feed sees half of Stokes I,
  so ``"xx"`` models ``2 V_xx`` and ``"pI"`` models ``V_xx + V_yy``; under ``"avg"``
  ``V_xx`` and ``(V_xx + V_yy)/2``.  ``("xx", "yy")`` fits both products as separate
  rows of the same sky.  Feed ``x`` is pyuvdata's (the file's and the beam's must agree).
* Units: ``"Jy"`` are converted to K sr by Rayleigh-Jeans
  (:func:`gcrsky.base.kelvin_sr_to_jy`), ``"K str"`` are used as they are, ``"uncalib"``
  is refused (:func:`kelvin_sr_per_unit`).
* Noise (per component, :func:`raw_variance`): by default the radiometer equation on the
  file's own autocorrelations, ``sigma^2_pq = |V_ii,pp V_jj,qq| / (2 dt dnu N)``
  (:func:`gcrsky.model.radiometer_variance`, the one implementation, also behind
  :func:`gcrsky.ingest.inspect_uvdata`'s estimate); ``"diff"``: one level per channel,
  baseline and product from time-adjacent differences
  (:func:`gcrsky.model.noise.time_difference_variance`); or a given per-component sigma in the
  file's units.  Variances add as products are combined and scale with the factor squared.
* Weights: a flagged or absent sample, a zero nsample, or a sample without a noise
  estimate (a missing or flagged autocorrelation) gets weight 0; a non-finite unflagged
  sample is an error naming it (:func:`gcrsky.model.problem.assemble_problem`).
* Redundant baselines are merged exactly (:func:`gcrsky.model.compress_problem`, within
  :data:`COMPRESS_RTOL`) unless ``compress=False``.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from ..base.units import kelvin_sr_to_jy
from ..instrument.antennas import make_array
from ..instrument.beams import unique_beams
from ..instrument.response import response_matrix
from ..io.visdata import POLS, Observation, parse_products
from .compress import COMPRESS_TOL_M
from .datachecks import refuse_empty, refuse_nonfinite
from .noise import adjacent_times, radiometer_variance, time_difference_variance
from .prior import Prior
from .problem import Problem, assemble_problem, observation_geometry
from .skyprior import gsm_cl_source, gsm_prior

__all__ = [
    "COMPRESS_RTOL",
    "COMPRESS_TOL_M",
    "DataConfig",
    "check_observation",
    "conventions",
    "kelvin_sr_per_unit",
    "modelled_product",
    "problem_from_observation",
    "product_factor",
    "raw_variance",
]

log = logging.getLogger(__name__)

#: Response tolerance of the automatic compression: antenna positions read from a file go through ECEF
#: (6.4e6 m), so "redundant" baselines differ by ~1e-9 m and their responses by ~1e-9 relative (measured
#: 1.6e-9 at 102 MHz); merging within 1e-8 changes the model far below any noise or simulator agreement.
COMPRESS_RTOL = 1e-8


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """How a Problem was read from a file (recorded in ``Problem.config`` and the run's outputs).

    Attributes:
        source: the file's path (or ``"<UVData object>"``).
        pol: the modelled product(s), e.g. ``"pI"`` or ``("xx", "yy")``.
        lmax, nside: degree of the ICRS coefficients and HEALPix nside of the quadrature.
        beam: description of the beam model.
        prior: description of the prior.
        noise: ``"autos"``, ``"diff"`` or ``"given"``.
        selection: the selections applied when reading (JSON-friendly).
        conventions: what was read and converted (units, pol_convention, phase, ...).
        compressed: redundant baselines merged (exact).
        latitude_deg: the site's latitude (the beam centre of a zenith-pointing drift scan).
        lst_range_hours: (first, last) local sidereal time of the data, hours (last may
            exceed 24 when the data wrap through 0 h): the observed strip's RA range.
        fwhm_deg: (Nf,) FWHM of the first antenna's beam (feed x power), degrees.
        checks: what the ingest checked and decided, by section (e.g. ``"beam"``,
            ``"calibration"``, ``"flux_scale"``, ``"flags"``, ``"band_limit"``, ``"prior"``):
            JSON-friendly dicts, copied into ``summary.json``'s ``"data_checks"``.
    """

    source: str
    pol: Any
    lmax: int
    nside: int
    beam: str
    prior: str
    noise: str
    selection: dict
    conventions: dict
    compressed: bool
    latitude_deg: float
    lst_range_hours: tuple
    fwhm_deg: tuple
    checks: dict = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["pol"] = list(self.pol) if isinstance(self.pol, tuple) else self.pol
        d["lst_range_hours"] = list(self.lst_range_hours)
        d["fwhm_deg"] = list(self.fwhm_deg)
        return d


# ---------------------------------------------------------------- products, units, conventions


def noise_kind(noise) -> str:
    """``"autos"``, ``"diff"`` or ``"given"`` (a per-component sigma) for the ``noise`` argument."""
    kind = noise if isinstance(noise, str) else "given"
    if kind not in ("autos", "diff", "given"):
        raise ValueError(f"noise must be 'autos', 'diff' or a per-component sigma, got {noise!r}")
    return kind


def product_factor(prod: str, pol_convention: str | None) -> float:
    """The factor that makes ``prod``'s sum of feed products I-equivalent under ``pol_convention`` (None: "sum")."""
    if prod == "pI":
        return 1.0 if (pol_convention or "sum") == "sum" else 0.5
    return 2.0 if (pol_convention or "sum") == "sum" else 1.0


def kelvin_sr_per_unit(obs: Observation) -> np.ndarray:
    """(Nf,) K sr per unit of the file's visibilities; uncalibrated or unknown units are refused."""
    if obs.vis_units == "uncalib":
        raise ValueError("the file's visibilities are uncalibrated (vis_units 'uncalib'): gcrsky needs Jy or K str; "
                         "calibrate them first, apply gain solutions with --cal FILE (cal=, a calfits/calh5 UVCal), or infer the "
                         "amplitude with the sky (--amplitude infer, amplitude='infer')")
    if obs.vis_units == "Jy":
        return 1.0 / kelvin_sr_to_jy(obs.freqs_hz)
    if obs.vis_units == "K str":
        return np.ones(obs.n_freqs)
    raise ValueError(f"unknown vis_units {obs.vis_units!r} (gcrsky reads 'Jy' and 'K str')")


def conventions(obs: Observation) -> dict:
    """The file's units and conventions as recorded in ``DataConfig.conventions`` and by ``inspect``."""
    conv = obs.pol_convention
    return {"vis_units": obs.vis_units, "pol_convention": conv if conv is not None else "sum (absent in the file)",
            "phase": obs.phase_description, "x_orientation": obs.x_orientation}


def check_observation(obs: Observation, pol="pI", noise="autos") -> None:
    """Refuse, before anything is built, an Observation that cannot give a Problem in physical units.

    Checks the units (:func:`kelvin_sr_per_unit`), that the feed products ``pol`` needs
    are there, that the radiometer noise (``noise="autos"``) has autocorrelations, and that
    some cross-correlation is unflagged with a positive nsample (:func:`gcrsky.model.datachecks.refuse_empty`) and
    none of those used is NaN or Inf (:func:`gcrsky.model.datachecks.refuse_nonfinite`).
    """
    refuse_empty(obs)
    refuse_nonfinite(obs)
    kelvin_sr_per_unit(obs)
    _, raw = parse_products(pol)
    missing = [r for r in raw if r not in obs.pol_names]
    if missing:
        raise ValueError(f"the observation holds products {list(obs.pol_names)}; pol needs {list(raw)} "
                         f"(missing {missing})")
    if noise_kind(noise) == "autos" and not obs.has_autos:
        raise ValueError("the file (selection) has no autocorrelations for the radiometer noise: pass noise='diff' "
                         "(time-adjacent differences) or a per-component sigma")


# ---------------------------------------------------------------- noise and data rows


def _auto_amplitudes(obs: Observation, name: str) -> np.ndarray:
    """(Nf, Nt, Nant) ``|Re V_ii|`` of the product ``name``, NaN where flagged or absent."""
    k = obs.pol_index(name)
    return np.where(~obs.auto_flags[k], np.abs(obs.autos[k].real), np.nan)


def raw_variance(obs: Observation, raw: str, noise="autos") -> np.ndarray:
    """(Nf, Nt, Nbl) per-component noise variance of the feed product ``raw``, in the file's units squared.

    ``noise``: ``"autos"``: the radiometer equation on the autocorrelations
    ``|V_ii,pp V_jj,qq|`` of the product ``pq``, the integration time, the channel width
    and the nsample (:func:`gcrsky.model.radiometer_variance`); ``"diff"``: from
    time-adjacent differences (:func:`gcrsky.model.noise.time_difference_variance`); or a
    per-component sigma broadcastable to (Nf, Nt, Nbl), divided by the nsample.  NaN (or
    Inf) where there is no estimate.
    """
    k = obs.pol_index(raw)
    kind = noise_kind(noise)
    if kind == "autos":
        au_p = _auto_amplitudes(obs, raw[0] * 2)
        au_q = au_p if raw[1] == raw[0] else _auto_amplitudes(obs, raw[1] * 2)
        ai, aj = au_p[:, :, obs.antpairs[:, 0]], au_q[:, :, obs.antpairs[:, 1]]
        return radiometer_variance(ai, aj, obs.integration_time_s[None], obs.channel_width_hz[:, None, None],
                                   obs.nsamples[k])
    if kind == "diff":
        return time_difference_variance(obs.vis[k], obs.usable[k], obs.nsamples[k],
                                        adjacent_times(obs.times_jd, obs.integration_time_s))
    ns = obs.nsamples[k]
    s = np.broadcast_to(np.asarray(noise, np.float64), ns.shape)
    with np.errstate(divide="ignore"):
        return np.where(ns > 0, s**2 / np.where(ns > 0, ns, 1.0), np.nan)


def modelled_product(obs: Observation, prod: str, var: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One modelled product in the file's units: ``(data, variance, usable)``, each (Nf, Nt, Nbl).

    ``data = c sum_r V_r`` and ``variance = c^2 sum_r var[r]`` over the feed products ``r``
    of ``prod`` (:data:`POLS`), with ``c`` the convention's factor (:func:`product_factor`);
    ``usable``: every component unflagged with a positive nsample and a finite positive
    variance.  ``var``: feed product -> (Nf, Nt, Nbl) variance (:func:`raw_variance`).
    """
    comps = POLS[prod]
    c = product_factor(prod, obs.pol_convention)
    d = c * sum(obs.vis[obs.pol_index(r)] for r in comps)
    v = c**2 * sum(var[r] for r in comps)
    ok = np.all([obs.usable[obs.pol_index(r)] for r in comps], axis=0) & np.isfinite(v) & (v > 0)
    return d, v, ok


def noise_causes(obs: Observation, raw, noise, bad) -> str:
    """Why the samples ``bad`` (one (Nf, Nt, Nbl) mask per feed product of ``raw``) have no noise estimate:
    the file's channel widths, integration times, nsamples or autocorrelations, counted and named."""
    hit = np.any(bad, axis=0)
    reasons = []
    if noise_kind(noise) == "autos":
        width = np.asarray(obs.channel_width_hz, np.float64)
        chans = np.flatnonzero(~(np.isfinite(width) & (width > 0)) & hit.any(axis=(1, 2)))
        if chans.size:
            reasons.append(f"the channel width is {width[chans[0]]:g} Hz at {chans.size} channel(s) (first "
                           f"{chans[:5].tolist()}): the radiometer equation needs a positive width")
        dt = np.asarray(obs.integration_time_s, np.float64)
        times = ~(np.isfinite(dt) & (dt > 0)) & hit.any(axis=0)
        if times.any():
            reasons.append(f"the integration time is {dt[times][0]:g} s at {int(times.sum())} baseline-time(s): "
                           "the radiometer equation needs a positive time")
        autos = 0
        for r, b in zip(raw, bad):
            amp = _auto_amplitudes(obs, r[0] * 2)
            amq = amp if r[1] == r[0] else _auto_amplitudes(obs, r[1] * 2)
            ai, aj = amp[:, :, obs.antpairs[:, 0]], amq[:, :, obs.antpairs[:, 1]]
            autos += int(np.sum(b & ~(np.isfinite(ai) & np.isfinite(aj))))
            zero = int(np.sum(b & np.isfinite(ai) & np.isfinite(aj) & ((ai == 0) | (aj == 0))))
            if zero:
                reasons.append(f"{zero} samples' autocorrelations are exactly 0")
        if autos:
            reasons.append(f"{autos} samples' autocorrelations are flagged or missing")
    ns = sum(np.sum(b & ~(obs.nsamples[obs.pol_index(r)] > 0)) for r, b in zip(raw, bad))
    if ns:
        reasons.append(f"{int(ns)} samples have nsample <= 0")
    if noise_kind(noise) == "diff":
        reasons.append("time-differenced noise needs a time-adjacent unflagged pair")
    reasons = reasons or ["the noise variance is not finite and positive"]
    fix = "; fix the file, or give --noise diff or a per-component sigma" if noise_kind(noise) == "autos" else ""
    return "; ".join(reasons) + fix


def _data_rows(obs: Observation, prods, raw, noise):
    """``(data K sr, sigma K sr, weights)`` (Nf, Nt, Nrow) and the rows' ``(pairs, products)``."""
    var = {r: raw_variance(obs, r, noise) for r in raw}
    to_ksr = kelvin_sr_per_unit(obs)[:, None, None]
    rows_d, rows_v, rows_ok, row_pols = [], [], [], []
    for p in prods:
        d, v, ok = modelled_product(obs, p, var)
        rows_d.append(d * to_ksr)
        rows_v.append(np.where(ok, v, 1.0) * to_ksr**2)
        rows_ok.append(ok)
        row_pols += [p] * obs.n_baselines
    unflagged = [~obs.flags[obs.pol_index(r)] for r in raw]
    bad = [(~np.isfinite(var[r]) | ~(var[r] > 0)) & u for r, u in zip(raw, unflagged)]
    n_bad = int(sum(np.sum(b) for b in bad))
    if n_bad:
        causes = noise_causes(obs, raw, noise, bad)
        if not any(np.any(ok) for ok in rows_ok):
            raise ValueError(f"no unflagged sample has a noise estimate ({n_bad} samples): {causes}; nothing "
                             "constrains the sky")
        log.warning("%d unflagged samples have no noise estimate (%s): weight 0", n_bad, causes)
    data = np.concatenate(rows_d, axis=2)
    sigma = np.sqrt(np.concatenate(rows_v, axis=2))
    weights = np.concatenate(rows_ok, axis=2).astype(np.float64)
    return data, sigma, weights, np.concatenate([obs.antpairs] * len(prods), axis=0), row_pols


# ---------------------------------------------------------------- the problem


def default_prior(freqs_hz, lmax: int, scale: float = 1.0) -> tuple[Prior, str]:
    """The default prior of real data and its description: isotropic, zero mean, ``scale`` x the GSM's C_l."""
    return gsm_prior(freqs_hz, lmax, scale=scale), (
        f"isotropic, zero mean, C_l = {scale:g} x the GSM's angular power spectrum at the data's frequencies "
        f"({gsm_cl_source()})")


def _per_antenna_beams(obs: Observation, beams) -> tuple[list, str]:
    """One beam per antenna of ``obs`` and a description of them."""
    if not isinstance(beams, (list, tuple)):
        return [beams] * obs.n_antennas, type(beams).__name__
    if len(beams) != obs.n_antennas:
        raise ValueError(f"got {len(beams)} beams for the observation's {obs.n_antennas} antennas "
                         f"{[int(a) for a in obs.antenna_numbers]} (one per antenna, in that order)")
    return list(beams), f"per antenna ({len(unique_beams(beams)[0])} distinct beams)"


def _fwhm_deg(beam, freq_hz) -> float:
    """FWHM of a beam (feed x power) in degrees, NaN where it does not fall to half above the horizon."""
    from ..instrument.beams import beam_fwhm_rad

    try:
        return float(np.rad2deg(beam_fwhm_rad(beam, float(freq_hz))))
    except ValueError:
        return float("nan")


def _check_beam_freqs(beams, freqs):
    """Refuse frequencies outside any beam's range (no extrapolation)."""
    from ..instrument.beams import check_beam_frequencies

    for b in {id(b): b for b in beams}.values():
        check_beam_frequencies(b, freqs)


def _response(array, pairs, freqs, lmax_resp, nside, lst_ref, pols):
    """The response rows of ``pairs`` for the products ``pols`` (one per row)."""
    return response_matrix(array, pairs, freqs, lmax_resp, nside, lst_ref_rad=lst_ref, pols=list(pols))


def _instrument(obs: Observation, array, beams, lmax, nside, frame_pad, pairs, row_pols):
    """``(geometry, (cross, auto) responses, lst_ref)`` of the rows ``pairs`` at the file's times and site.

    The autocorrelations' response is built once per distinct beam (every auto has separation 0)
    and gathered to the antennas.
    """
    from astropy.time import Time

    from ..instrument.redundancy import groups_for_array

    times = Time(obs.times_jd, format="jd", scale="utc")
    geom = observation_geometry(array, lmax, times=times, location=obs.location, frame_pad=frame_pad)
    lst_ref = float(geom.lsts_rad[0])
    _check_beam_freqs(beams, obs.freqs_hz)
    resp = _response(array, pairs, obs.freqs_hz, geom.lmax_response, nside, lst_ref, row_pols)
    auto_groups = groups_for_array(array, np.stack([np.arange(obs.n_antennas)] * 2, 1))
    auto_u = _response(array, auto_groups.representative_antpairs, obs.freqs_hz, geom.lmax_response, nside, lst_ref,
                       [row_pols[0]] * auto_groups.n_groups)
    auto = auto_u[:, np.asarray(auto_groups.group_of)]
    return geom, (resp, auto), lst_ref


def _merge_before_response(obs: Observation, array, data, sigma, weights, pairs, row_pols):
    """Redundant rows merged *before* any response is built: ``(data, sigma, weights, pairs, row_pols,
    n_before)`` of one row per group, or the inputs unchanged (``n_before`` None) where nothing merges.

    Groups (:func:`gcrsky.model.compress.row_groups`: per product, by separation within
    :data:`COMPRESS_TOL_M` and ordered beam pair) are exact where every member's offset from its
    representative moves the fringe phase by at most :data:`COMPRESS_RTOL` at the highest frequency
    (the guard of :func:`gcrsky.instrument.unique_response`): then the members' response rows equal
    the representative's to that tolerance and are never computed.  The data merge is
    :func:`gcrsky.model.compress.compress_rows` (what :func:`gcrsky.model.compress_problem` does).
    """
    from ..base.units import SPEED_OF_LIGHT
    from ..instrument.redundancy import groups_for_array
    from .compress import compress_rows, row_groups

    try:
        groups = row_groups(pairs, row_pols, lambda p: groups_for_array(array, p, tol_m=COMPRESS_TOL_M))
    except ValueError as err:  # an irregular layout: the rows are merged after the response, if at all
        log.info("redundant compression before the response skipped: %s", err)
        return data, sigma, weights, pairs, row_pols, None
    phase = 2 * np.pi * float(np.max(groups.max_offset_m)) * float(np.max(obs.freqs_hz)) / SPEED_OF_LIGHT
    if phase > COMPRESS_RTOL or groups.n_groups == pairs.shape[0]:
        return data, sigma, weights, pairs, row_pols, None
    data_g, sigma_g, w_g = compress_rows(data, sigma, weights, groups)
    rep = groups.representative
    log.info("redundant compression: %d -> %d rows before the response (members within %.2g m: fringe phase "
             "%.2g rad)", pairs.shape[0], groups.n_groups, float(np.max(groups.max_offset_m)), phase)
    return (np.asarray(data_g), sigma_g, w_g, groups.representative_antpairs.copy(),
            [row_pols[int(r)] for r in rep], pairs.shape[0])


def _data_config(obs: Observation, prods, geom, beams, *, lmax, nside, noise, beam_note, prior_note) -> DataConfig:
    lst_h = np.unwrap(np.asarray(geom.lsts_rad, np.float64)) * 12.0 / np.pi
    lst_h = lst_h - 24.0 * np.floor(lst_h[0] / 24.0)
    pol_conv = obs.pol_convention or "sum"
    factor = f"{'sum' if pol_conv == 'sum' else 'avg'} convention: modelled as {', '.join(prods)} I-equivalent"
    return DataConfig(
        source=obs.source, pol=prods[0] if len(prods) == 1 else prods, lmax=int(lmax), nside=int(nside),
        beam=beam_note, prior=prior_note, noise=noise_kind(noise), selection=obs.selection,
        conventions={**conventions(obs), "factor": factor,
                     "antenna_numbers": [int(a) for a in obs.antenna_numbers],
                     "antenna_names": [str(a) for a in obs.antenna_names], "telescope_name": obs.telescope_name,
                     "times_jd": [float(t) for t in obs.times_jd],
                     "site_lat_lon_alt": [float(obs.location.lat.deg), float(obs.location.lon.deg),
                                          float(obs.location.height.to_value("m"))]},
        compressed=False, latitude_deg=float(obs.location.lat.deg),
        lst_range_hours=(float(lst_h.min()), float(lst_h.max())),
        fwhm_deg=tuple(_fwhm_deg(beams[0], f) for f in obs.freqs_hz),
    )


def _compress(prob: Problem, array, cfg: DataConfig) -> Problem:
    from .compress import compress_problem

    try:
        out = compress_problem(prob, array, rtol=COMPRESS_RTOL, tol_m=COMPRESS_TOL_M)
    except ValueError as err:  # not exactly redundant (e.g. per-antenna beams): keep every baseline
        log.info("redundant compression skipped: %s", err)
        return prob
    if out.antpairs.shape[0] == prob.antpairs.shape[0]:
        return prob
    log.info("redundant compression: %d -> %d rows (responses equal to %g)", prob.antpairs.shape[0],
             out.antpairs.shape[0], COMPRESS_RTOL)
    return dataclasses.replace(out, config=dataclasses.replace(cfg, compressed=True))


def problem_from_observation(
    obs: Observation,
    beams,
    *,
    lmax: int,
    nside: int,
    pol="pI",
    prior: Prior | None = None,
    noise="autos",
    compress: bool = True,
    frame_pad: int = 4,
    beam_note: str | None = None,
    prior_note: str | None = None,
    band_limit: str | None = "truncate",
    band_note: dict | None = None,
    checks: dict | None = None,
) -> Problem:
    """The inference problem of an Observation: ICRS coefficients at ``lmax`` (module docstring).

    Args:
        obs: the :class:`~gcrsky.io.Observation` (:func:`gcrsky.io.read_observation`).
        beams: one pyuvdata beam object for every antenna, or a sequence of them, one per
            antenna of ``obs`` in its ``antenna_numbers`` order.
        lmax: maximum degree of the sky's ICRS coefficients.
        nside: HEALPix nside of the response quadrature.
        pol: ``"pI"`` (pseudo-Stokes I), ``"xx"``, ``"yy"``, or ``("xx", "yy")`` (or
            ``"xx,yy"``: both products, separately, of the same sky).
        prior: a :class:`~gcrsky.model.Prior` (Nf, n); None: the GSM's (isotropic, zero
            mean, C_l of the GSM at the data's frequencies, :func:`gcrsky.model.gsm_prior`).
        noise: ``"autos"``, ``"diff"`` or a per-component sigma in the file's units
            (:func:`raw_variance`).
        compress: merge redundant baselines (exactly: only identical responses merge).
        frame_pad: degree margin of the ICRS -> of-date frame map.
        beam_note, prior_note: descriptions recorded in ``config`` (default: from the objects).
        band_limit: rows whose reach exceeds ``lmax`` (:mod:`gcrsky.model.bandlimit`):
            ``"cut"``, ``"marginalise"``, ``"truncate"`` (default: kept as they are, with a
            warning), or None (not checked); recorded in ``config.checks["band_limit"]``.
        band_note: how ``lmax`` was chosen (:func:`gcrsky.model.bandlimit.observation_lmax`).
        checks: what the ingest checked, by section (``DataConfig.checks``; JSON-friendly).

    Returns:
        a :class:`~gcrsky.model.Problem` with ``pols`` recording each row's product and
        ``config`` a :class:`DataConfig`.
    """
    from ..base.dtypes import require_x64

    require_x64("problem_from_observation")
    prods, raw = parse_products(pol)
    check_observation(obs, pol, noise)
    beams, note = _per_antenna_beams(obs, beams)
    if prior is None:
        prior, default_note = default_prior(obs.freqs_hz, lmax)
        prior_note = prior_note or default_note
    data, sigma, weights, pairs, row_pols = _data_rows(obs, prods, raw, noise)
    array = make_array(obs.antpos_enu_m, float(obs.location.lat.deg), list(beams))
    merged = None
    if compress and band_limit != "marginalise":  # marginalise adds each baseline's high-l variance first
        data, sigma, weights, pairs, row_pols, merged = _merge_before_response(obs, array, data, sigma, weights,
                                                                               pairs, row_pols)
    geom, responses, lst_ref = _instrument(obs, array, beams, lmax, nside, frame_pad, pairs, row_pols)
    cfg = _data_config(obs, prods, geom, beams, lmax=lmax, nside=nside, noise=noise, beam_note=beam_note or note,
                       prior_note=prior_note or "given (a Prior)")
    cfg = dataclasses.replace(cfg, checks=dict(checks or {}))
    log.info("problem_from_observation: %s; %d antennas, %d baselines x %d products, %d times, %d channels; "
             "prior: %s", obs.source, obs.n_antennas, obs.n_baselines, len(prods), obs.n_times, obs.n_freqs,
             cfg.prior)
    prob = assemble_problem(array, obs.freqs_hz, geom, responses, lmax, nside, data, sigma, weights=weights,
                            prior=prior, lst_ref_rad=lst_ref, config=cfg, pairs=pairs, pols=row_pols,
                            sky_note=f"data: {obs.source}")
    if band_limit is not None:
        from .bandlimit import apply_band_limit, observation_lmax

        note = band_note if band_note is not None else observation_lmax(obs, beams, lmax)[1]
        prob = apply_band_limit(prob, array, band_limit, note, nside=nside)
        cfg = prob.config
    if merged is not None:
        return dataclasses.replace(prob, config=dataclasses.replace(cfg, compressed=True))
    return _compress(prob, array, cfg) if compress else prob
