"""Real observations in: a :class:`~gcrsky.model.Problem` from any file pyuvdata reads.

:func:`from_uvdata` turns a visibility file (UVH5; UVFITS, Measurement Sets, MIRIAD
where pyuvdata's optional readers are installed) or a ``UVData`` object into the
inference problem whose parameters are the ICRS coefficients of the sky (DESIGN
section 2, mode (b): the file's real observing times at the file's site).
:func:`inspect_uvdata` says what would be used without solving.

Two steps, each usable on its own:

1. :func:`gcrsky.io.read_observation`: the file, selected and read partially, in gcrsky's
   conventions (baseline order and conjugation, drift-scan phase), as an
   :class:`~gcrsky.io.Observation` (:mod:`gcrsky.io.observation`);
2. :func:`gcrsky.model.problem_from_observation`: the physics (modelled products, units,
   radiometer noise, weights, responses, redundant compression;
   :mod:`gcrsky.model.observed`).

This module adds what reads files besides the visibilities: the beams (a beam object or
file, per antenna by number or name) and the prior (``"gsm"``, ``"flat"``, a C_l file or
a HEALPix map / alm FITS file as the prior mean).  The conventions are on the docs'
ingest page (``docs/ingest.md``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..io.files import check_input_file, reading
from ..io.observation import read_bytes, read_uvdata
from ..io.visdata import POLS, Observation, parse_products
from ..model.bandlimit import check_quadrature, observation_lmax, observation_reach
from ..model.observed import (
    COMPRESS_RTOL,
    DataConfig,
    check_observation,
    conventions,
    default_prior,
    kelvin_sr_per_unit,
    modelled_product,
    noise_kind,
    problem_from_observation,
    raw_variance,
)
from ..model.prior import Prior, flat_prior, isotropic_prior
from ..model.problem import Problem
from ..model.skyprior import check_gsm_cl_frequencies, gsm_cl
from ..sphere.modes import n_params

__all__ = [
    "COMPRESS_RTOL",
    "DataConfig",
    "POLS",
    "from_uvdata",
    "inspect_uvdata",
    "read_uvdata",
]

log = logging.getLogger(__name__)


# ---------------------------------------------------------------- beams and priors


def _resolve_beams(beam, dish_diameter_m, obs: Observation):
    """One beam object per antenna of ``obs`` (in its ``antenna_numbers`` order) and a description."""
    from ..instrument.beams import gaussian_beam, load_beam

    if beam is None and dish_diameter_m is None:
        raise ValueError("give the beam (a pyuvdata beam object or a beam file) or dish_diameter_m (a Gaussian beam "
                         "with the Airy FWHM of that dish)")
    if beam is not None and dish_diameter_m is not None:
        raise ValueError("give beam or dish_diameter_m, not both")
    if beam is None:
        b = gaussian_beam(float(dish_diameter_m))
        return [b] * obs.n_antennas, f"Gaussian, Airy-matched FWHM of a {float(dish_diameter_m):g} m dish"
    if isinstance(beam, (list, tuple)):
        nums = [int(n) for n in obs.telescope_antenna_numbers]
        if len(beam) != len(nums):
            raise ValueError(f"a beam list needs one beam per antenna of the file's telescope ({len(nums)}), "
                             f"in its antenna_numbers order; got {len(beam)} (or pass a dict number/name -> beam)")
        beam = dict(zip(nums, beam))
    if isinstance(beam, dict):
        return _beams_by_antenna(beam, obs)
    b = load_beam(beam)
    return [b] * obs.n_antennas, _describe_beam(beam, b)


def _beams_by_antenna(beam: dict, obs: Observation):
    """Per-antenna beams from a dict antenna number or name -> beam (object or file; each file read once)."""
    from ..instrument.beams import load_beam

    names = [str(n) for n in obs.telescope_antenna_names]
    nums = [int(n) for n in obs.telescope_antenna_numbers]
    by_num = {}
    for key, b in beam.items():
        num = int(key) if isinstance(key, (int, np.integer)) else (
            nums[names.index(str(key))] if str(key) in names else None)
        if num is None:
            raise ValueError(f"beam key {key!r} is neither an antenna number nor a name in the file")
        by_num[num] = b
    missing = [int(a) for a in obs.antenna_numbers if int(a) not in by_num]
    if missing:
        raise ValueError(f"no beam given for antennas {missing}")
    cache: dict = {}
    out = []
    for a in obs.antenna_numbers:
        b = by_num[int(a)]
        key = id(b) if not isinstance(b, (str, Path)) else str(b)
        if key not in cache:
            cache[key] = load_beam(b)
        out.append(cache[key])
    return out, f"per antenna ({len(cache)} distinct beams)"


def _describe_beam(arg, b) -> str:
    if isinstance(arg, (str, Path)):
        return f"file {arg}"
    return type(b).__name__


def _read_cl_file(path: Path, nf: int, lmax: int) -> np.ndarray:
    arr = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, ndmin=2)
    arr = np.asarray(arr, np.float64)
    if arr.ndim == 1:
        arr = arr[None]
    if path.suffix != ".npy" and arr.shape[1] >= 2 and np.array_equal(arr[:, 0], np.arange(arr.shape[0])):
        arr = arr[:, 1:].T  # text: a column of l then one column per frequency
    if arr.shape[-1] < lmax + 1:
        raise ValueError(f"{path}: the C_l table stops at l = {arr.shape[-1] - 1}, lmax is {lmax}")
    arr = arr[..., : lmax + 1]
    if arr.shape[0] not in (1, nf):
        raise ValueError(f"{path}: {arr.shape[0]} spectra for {nf} frequencies")
    return np.broadcast_to(arr, (nf, lmax + 1))


def _fits_mean(path: Path, nf: int, lmax: int) -> np.ndarray:
    """Realified ICRS coefficients (Nf, n) from a HEALPix map or alm FITS file."""
    import healpy as hp

    from ..sphere.modes import realify

    try:
        alm = hp.read_alm(str(path), hdu=1)
        lmax_f = hp.Alm.getlmax(alm.size)
        cols = [alm]
        hdu = 2
        while True:
            try:
                cols.append(hp.read_alm(str(path), hdu=hdu))
                hdu += 1
            except (IndexError, OSError, ValueError):
                break
        out = np.zeros((len(cols), hp.Alm.getsize(lmax)), complex)
        ell, m = hp.Alm.getlm(min(lmax, lmax_f))
        for k, c in enumerate(cols):
            out[k, hp.Alm.getidx(lmax, ell, m)] = c[hp.Alm.getidx(lmax_f, ell, m)]
        a = realify(out, lmax)
    except Exception:  # noqa: BLE001 - not an alm file: read it as a map
        maps = np.atleast_2d(hp.read_map(str(path), field=None))
        a = realify(np.stack([hp.map2alm(m, lmax=lmax, iter=3) for m in maps]), lmax)
    if a.shape[0] not in (1, nf):
        raise ValueError(f"{path}: {a.shape[0]} columns for {nf} frequencies")
    return np.broadcast_to(a, (nf, n_params(lmax)))


#: What a prior file may be, for read errors.
PRIOR_FORMATS = "HEALPix map or alm FITS file, .npy or text C_l file"


def _resolve_prior(prior, prior_scale, freqs, lmax) -> tuple[Prior, str]:
    """The prior and its description (module docstring of :func:`from_uvdata`)."""
    nf, n = freqs.size, n_params(lmax)
    if not (np.isfinite(prior_scale) and prior_scale > 0):
        raise ValueError(f"prior_scale must be a positive finite number, got {prior_scale!r}")
    if isinstance(prior, Prior):
        if np.shape(prior.mean) != (nf, n) or np.shape(prior.inv_var) != (nf, n):
            raise ValueError(f"the prior's arrays must be (Nf, n) = {(nf, n)}")
        return prior, "given (a Prior)"
    if prior is None or (isinstance(prior, str) and prior == "gsm"):
        return default_prior(freqs, lmax, prior_scale)
    if isinstance(prior, str) and prior == "flat":
        return flat_prior(nf, n), "flat (S^-1 = 0: the posterior may be improper where the data are blind)"
    if isinstance(prior, (str, Path)):
        if not Path(prior).exists():
            raise ValueError(f"prior {prior!r} is neither 'gsm', 'flat' nor an existing file")
        path = check_input_file(prior, "prior file")
        if path.suffix.lower() in (".fits", ".fit", ".fz") or path.name.endswith(".fits.gz"):
            with reading(path, "a prior (HEALPix map or alm FITS, ICRS, K)", PRIOR_FORMATS):
                mean = _fits_mean(path, nf, lmax)
            cl = prior_scale * gsm_cl(freqs, lmax)
            return isotropic_prior(cl, n, mean=mean), (f"mean from {path} (HEALPix map or alm, ICRS), variance "
                                                       f"{prior_scale:g} x the GSM's C_l")
        with reading(path, "a prior's C_l (.npy, or text: l and C_l per frequency)", PRIOR_FORMATS):
            cl = prior_scale * _read_cl_file(path, nf, lmax)
        return isotropic_prior(cl, n), f"isotropic, zero mean, C_l from {path} x {prior_scale:g}"
    cl = np.asarray(prior, np.float64)
    if cl.ndim not in (1, 2) or cl.shape[-1] != lmax + 1 or (cl.ndim == 2 and cl.shape[0] not in (1, nf)):
        raise ValueError(f"a C_l prior must be (lmax+1,) or (Nf, lmax+1) = {(nf, lmax + 1)}, got {cl.shape}")
    return isotropic_prior(prior_scale * np.broadcast_to(cl, (nf, lmax + 1)), n), \
        f"isotropic, zero mean, given C_l x {prior_scale:g}"


# ---------------------------------------------------------------- the problem


def _checked_observation(data, *, pol, noise, prior, cal, flag_outliers, **read) -> tuple[Observation, dict]:
    """``(obs, checks)``: the file read (and calibrated), checked, its outliers flagged, checked again; the GSM
    prior's band checked too: everything that can refuse a file before a beam is read or a response built."""
    from .datachecks import flag_checks, read_checked

    obs, checks = read_checked(data, cal=cal, pol=pol, autos=noise_kind(noise) == "autos", **read)
    for line in obs.notes:
        log.warning(line)
    check_observation(obs, pol, noise)  # units, products, autos, data
    if prior is None or (isinstance(prior, str) and prior == "gsm"):
        check_gsm_cl_frequencies(obs.freqs_hz)  # the prior's band
    obs, flags = flag_checks(obs, flag=flag_outliers)
    checks.update(flags)
    check_observation(obs, pol, noise)  # still something to fit once the outliers are flagged
    return obs, checks


def _prepared_beams(beam, dish_diameter_m, obs: Observation, **how) -> tuple[list, str, dict]:
    """``(beams per antenna, description, checks["beam"])``: the beams resolved and prepared for ``obs``
    (:func:`gcrsky.ingest.beamprior.prepare_beams`; ``how``: its normalisation and frequency options)."""
    from .beamprior import prepare_beams

    beams, note = _resolve_beams(beam, dish_diameter_m, obs)
    beams, rec = prepare_beams(beams, beam, obs, **how)
    return beams, note, rec


def from_uvdata(
    data,
    *,
    lmax: int | None = None,
    nside: int,
    beam=None,
    dish_diameter_m: float | None = None,
    pol="pI",
    prior=None,
    prior_scale: float = 1.0,
    noise="autos",
    freq_chans=None,
    freq_range_hz=None,
    times_jd=None,
    lst_range_hours=None,
    antennas=None,
    bls=None,
    compress: bool = True,
    frame_pad: int = 4,
    memory_budget: float | None = None,
    beam_normalization: str = "peak",
    beam_freq_scaling: str | None = None,
    accept_x_orientation_mismatch: bool = False,
    prior_mean: str | None = None,
    band_limit: str = "truncate",
    cal=None,
    flag_outliers: bool = True,
    flux_scale: str = "accept",
) -> Problem:
    """The inference problem of a visibility file: ICRS coefficients at ``lmax`` (module docstring).

    Args:
        data: a path to any file ``UVData.from_file`` reads, or a ``UVData`` (not modified).
        lmax: degree of the ICRS coefficients; None: every used baseline's reach at the highest
            frequency, capped by memory (:func:`gcrsky.model.bandlimit.observation_lmax`).
        beam: a pyuvdata beam object (``UVBeam``, ``AnalyticBeam``, ``BeamInterface``), a beam
            file's path (UVBeam files, SIN beam images), a dict from antenna numbers or names
            to beams, or a list of beams in the file's ``antenna_numbers`` order.
        dish_diameter_m: instead of ``beam``: a Gaussian beam with the Airy FWHM of that dish.
        pol: ``"pI"`` (``xx + yy``), ``"xx"``, ``"yy"``, ``("xx", "yy")`` / ``"xx,yy"`` (both, of one sky).
        prior: ``None`` / ``"gsm"`` (isotropic, zero mean, the GSM's C_l, :func:`gcrsky.model.gsm_cl`),
            ``"flat"``, a :class:`~gcrsky.model.Prior`, a C_l array ((lmax+1,) or (Nf, lmax+1),
            K^2) or file (``.npy``, or text: l and C_l per frequency), or a HEALPix map / alm
            FITS file (ICRS, K: the prior's *mean*, with the GSM's C_l as its variance).
        prior_scale, nside: factor on the prior variance; HEALPix nside of the response quadrature.
        noise: ``"autos"`` (radiometer equation on the autos), ``"diff"`` (time-adjacent
            differences), or each raw product's per-component sigma in the file's units
            (broadcastable to (Nf, Nt, Nbl)).
        freq_chans, freq_range_hz: channel indices, and/or a (lo, hi) range in Hz.
        times_jd, lst_range_hours: times (JD) to keep, and/or an LST range (h; ``(22, 2)`` wraps).
        antennas, bls: antenna numbers or names to keep (pairs among them); antenna pairs to keep.
        compress: merge redundant baselines (only identical responses, :func:`gcrsky.compress_problem`).
        frame_pad, memory_budget: degree margin of the ICRS -> of-date map; bytes the read may use.
        beam_normalization, beam_freq_scaling, accept_x_orientation_mismatch: how a beam is
            prepared (:func:`gcrsky.instrument.beamprep.prepare_beam`): ``"peak"`` (a physical
            UVBeam peak-normalised) or ``"physical"``; a single-frequency beam's ``"none"`` or
            ``"lambda"`` scaling; whether the beam's feed x may point elsewhere than the file's.
        prior_mean: None / ``"zero"`` (the prior's own mean) or ``"gsm"`` (the GSM's
            coefficients at the data's frequencies, :func:`gcrsky.model.skyprior.gsm_prior_mean`).
        band_limit: rows whose reach exceeds ``lmax`` (:mod:`gcrsky.model.bandlimit`): ``"cut"``
            (the CLI's default), ``"marginalise"`` (the sky above ``lmax`` as noise) or
            ``"truncate"`` (default here, with a warning: right for data simulated at ``lmax``).
        cal: a gain solutions file (calfits, calh5) applied first (:mod:`gcrsky.io.calibration`).
        flag_outliers: flag the noise-excess outliers (:mod:`gcrsky.model.datachecks`).
        flux_scale: ``"accept"`` (default: the data / GSM autos ratio recorded, a warning outside
            :data:`gcrsky.model.fluxscale.FLUX_BOUNDS`), ``"check"`` (refused outside them: the
            CLI's default) or ``"off"``.

    ``pol`` may name products by compass direction (``"ee"``, ``"nn"``): the file's feed
    products through its ``x_orientation``.

    Returns:
        a :class:`~gcrsky.model.Problem` (``pols``: each row's product; ``config``: a
        :class:`DataConfig` whose ``checks`` say what was checked: calibration, flags,
        flux_scale, beam, prior, band_limit, pol).
    """
    from ..base.dtypes import require_x64
    from .beamprior import apply_prior_mean, feed_pol_of, with_checks
    from .datachecks import flux_checks

    require_x64("from_uvdata")
    pol, pol_rec = feed_pol_of(data, pol)
    parse_products(pol)
    obs, checks = _checked_observation(
        data, pol=pol, noise=noise, prior=prior, cal=cal, flag_outliers=flag_outliers, freq_chans=freq_chans,
        freq_range_hz=freq_range_hz, times_jd=times_jd, lst_range_hours=lst_range_hours, antennas=antennas, bls=bls,
        memory_budget=memory_budget)
    beams, beam_note, beam_rec = _prepared_beams(
        beam, dish_diameter_m, obs, normalization=beam_normalization, freq_scaling=beam_freq_scaling,
        accept_x_orientation_mismatch=accept_x_orientation_mismatch)
    checks.update(flux_checks(obs, beams[0], pol=pol, mode=flux_scale))  # through the prepared beam
    lmax, band_note = observation_lmax(obs, beams, lmax, n_products=len(parse_products(pol)[0]),
                                       frame_pad=frame_pad, budget_bytes=memory_budget,
                                       compress=compress and band_limit != "marginalise")
    check_quadrature(observation_reach(obs, beams, isotropic=True)[0], lmax, nside, band_limit, frame_pad=frame_pad)
    prior_obj, prior_note, prior_rec = apply_prior_mean(*_resolve_prior(prior, prior_scale, obs.freqs_hz, lmax),
                                                        prior_mean, prior, obs.freqs_hz, lmax)
    prob = problem_from_observation(obs, beams, lmax=lmax, nside=nside, pol=pol, prior=prior_obj, noise=noise,
                                    compress=compress, frame_pad=frame_pad, beam_note=beam_note,
                                    prior_note=prior_note, band_limit=band_limit, band_note=band_note,
                                    checks=checks)
    return with_checks(prob, {"beam": beam_rec, "prior": prior_rec, **({"pol": pol_rec} if pol_rec else {})})


# ---------------------------------------------------------------- inspect


def inspect_uvdata(path, *, pol="pI", lmax: int | None = None, nside: int | None = None, cal=None,
                  flag_outliers: bool = True, flux_scale: str = "check", beam=None,
                  dish_diameter_m: float | None = None, redundancy_tol_m: float = 0.5, **selection) -> dict:
    """What :func:`from_uvdata` would use, without building the response or solving (a JSON-friendly dict).

    Reads the selection (so flags and autos are known), applies ``cal`` if given, and reports
    the antennas, baselines (and unique ones, within ``redundancy_tol_m`` metres), times and
    LST coverage, channels, products, units, conventions, the flagged fraction, a radiometer
    noise estimate from the autos (median per-component sigma of the modelled product, K sr,
    or the file's units when uncalibrated: the run's own noise, :func:`gcrsky.model.raw_variance`),
    the memory of the read and, with ``lmax`` (and ``nside``), of the dense posterior
    precision; then the data checks (``"data_checks"``: calibration, noise excess and
    outliers, fully flagged antennas, the flux scale with ``beam`` or ``dish_diameter_m``;
    :func:`gcrsky.ingest.datachecks.inspect_checks`) and ``"problems"``: what a run would refuse.
    With a beam, ``"band_limit"`` is the lmax a run would choose (the reach of every used
    baseline, :func:`gcrsky.model.bandlimit.observation_lmax`) and the sizes are at it
    (``"lmax_for_sizes"``: ``lmax`` if given, else that reach, else :data:`SIZES_LMAX`).
    """
    from .beamprior import feed_pol_of
    from .datachecks import inspect_checks, read_checked

    pol = feed_pol_of(path, pol)[0]
    prods, _ = parse_products(pol)
    obs, checks = read_checked(path, cal=cal, pol=pol, **selection)
    out = _describe_observation(obs, prods, redundancy_tol_m)
    beams, b, beam_problem = None, None, None
    if beam is not None or dish_diameter_m is not None:
        try:  # the beams a run would use (peak-normalised, frequencies checked): the flux check's, the reach's
            beams = _prepared_beams(beam, dish_diameter_m, obs)[0]
            b = beams[0]
        except ValueError as e:
            beam_problem = f"the beam: {e}"
    obs, checks, problems = inspect_checks(obs, checks, pol=pol, flag=flag_outliers, flux_scale=flux_scale, beam=b)
    problems = problems + ([beam_problem] if beam_problem else [])
    out["flagged_fraction"] = obs.flagged_fraction  # after the outliers are flagged, as a run would use them
    try:
        to_ksr, out["noise_units"] = kelvin_sr_per_unit(obs), "K sr"
    except ValueError:
        to_ksr, out["noise_units"] = np.ones(obs.n_freqs), obs.vis_units
    sig = None
    if obs.has_autos:
        var = {r: raw_variance(obs, r, "autos") for r in POLS[prods[0]]}
        v, ok = modelled_product(obs, prods[0], var)[1:]
        with np.errstate(invalid="ignore"):
            s = np.where(ok, np.sqrt(v) * to_ksr[:, None, None], np.nan)
            sig = float(np.nanmedian(s)) if np.any(ok) else None
    out["noise_sigma_median_k_sr"] = sig
    out["read_bytes"] = read_bytes(obs.nblts_read, obs.n_freqs, obs.n_pols)
    lat, lon, _ = obs.site_lat_lon_alt
    out["site_lat_lon_deg"] = [lat, lon]
    if beams is not None:  # the band limit a run would choose: the reach of every used baseline (lmax None)
        chosen, out["band_limit"] = observation_lmax(obs, beams, lmax, n_products=len(prods))
        lmax = chosen if lmax is None else lmax
    out["lmax_for_sizes"] = lmax = SIZES_LMAX if lmax is None else lmax
    out.update(_memory(obs, len(prods), out["n_rows_exact"], lmax, nside))
    out["data_checks"] = checks
    out["problems"] = problems
    return out


def _describe_observation(obs: Observation, prods, redundancy_tol_m: float = 0.5) -> dict:
    """The part of :func:`inspect_uvdata`'s report that describes the file (in the report's key order)."""
    from ..instrument.redundancy import redundant_groups

    groups = redundant_groups(obs.antpos_enu_m, obs.antpairs, tol_m=redundancy_tol_m)
    return {
        "source": obs.source,
        "selection": obs.selection,
        "antennas": [int(a) for a in obs.antenna_numbers],
        "n_antennas": obs.n_antennas,
        "n_baselines": obs.n_baselines,
        "n_unique_baselines": groups.n_groups,
        "redundancy_tol_m": float(redundancy_tol_m),
        "redundancy_max_offset_m": float(np.max(groups.max_offset_m)),
        "n_rows_exact": redundant_groups(obs.antpos_enu_m, obs.antpairs).n_groups,  # what the run's compression keeps
        "n_times": obs.n_times,
        "time_range_jd": [float(obs.times_jd.min()), float(obs.times_jd.max())],
        "lst_range_hours": [float(np.rad2deg(obs.lsts_rad.min()) / 15), float(np.rad2deg(obs.lsts_rad.max()) / 15)],
        "n_channels": obs.n_freqs,
        "freq_range_hz": [float(obs.freqs_hz.min()), float(obs.freqs_hz.max())],
        "channel_width_hz": float(np.median(obs.channel_width_hz)),
        "file_polarizations": list(obs.file_pol_names),
        "modelled_products": list(prods),
        "conventions": conventions(obs),
        "notes": list(obs.notes),
        "flagged_fraction": obs.flagged_fraction,
        "has_autos": obs.has_autos,
    }


def _memory(obs: Observation, nprods: int, n_unique: int, lmax: int, nside: int | None) -> dict:
    """Sizes of the dense precision, the real data values and (with ``nside``) the response."""
    n = n_params(lmax)
    out = {"n_params": n, "dense_precision_bytes": float(obs.n_freqs * n * n * 8),
           "real_data_values": int(2 * n_unique * obs.n_times * obs.n_freqs * nprods)}
    if nside is not None:
        out["response_bytes"] = float(obs.n_freqs * n_unique * nprods * n_params(lmax + frame_pad_default()) * 16)
    return out


#: The degree :func:`inspect_uvdata` sizes the problem at when neither ``lmax`` nor a beam (a reach) is given.
SIZES_LMAX = 20


def frame_pad_default() -> int:
    """The default degree margin of the frame map (:func:`from_uvdata`'s ``frame_pad``)."""
    return 4
