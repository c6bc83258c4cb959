"""What a run on a file would use, without solving: :func:`inspect_uvdata` (``gcrsky inspect FILE``).

It reads the selection (so flags and autos are known), applies the calibration, runs the data
checks as a run would (reporting, not refusing: what a run would refuse becomes a ``"problems"``
line), and sizes the problem at the band limit a run would choose.
"""

from __future__ import annotations

import numpy as np

from ..io.selection import read_bytes
from ..io.visdata import POLS, Observation, parse_products
from ..model.bandlimit import observation_lmax
from ..model.observed import conventions, kelvin_sr_per_unit, modelled_product, raw_variance
from ..sphere.modes import n_params
from .beamprior import feed_pol_of
from .beams import prepared_beams
from .datachecks import inspect_checks, read_checked
from .spec import IngestSpec
from .uvdata import read_selection

__all__ = ["SIZES_LMAX", "describe_observation", "inspect_beams", "inspect_uvdata", "memory_sizes",
           "noise_sigma_median"]


def inspect_uvdata(path, spec: IngestSpec | None = None, *, redundancy_tol_m: float = 0.5, **keywords) -> dict:
    """What :func:`gcrsky.ingest.ingest` would use, without building the response or solving (a JSON-friendly dict).

    Args:
        path: a visibility file (or a ``UVData``).
        spec: the :class:`~gcrsky.ingest.IngestSpec` a run would use (its selection, checks, beam,
            ``lmax``, ``nside``, ``frame_pad``); or None and ``keywords``: its settings by keyword
            (:meth:`IngestSpec.from_keywords`; here ``flux_scale`` defaults to ``"check"``, a run's).
        redundancy_tol_m: tolerance (m) on baseline vectors when counting unique baselines.

    Reads the selection (so flags and autos are known), applies ``cal`` if given, and reports
    the antennas, baselines (and unique ones, within ``redundancy_tol_m`` metres), times and
    LST coverage, channels, products, units, conventions, the flagged fraction, a radiometer
    noise estimate from the autos (median per-component sigma of the modelled product, K sr,
    or the file's units when uncalibrated: the run's own noise, :func:`gcrsky.model.observed.raw_variance`),
    the memory of the read and, with ``lmax`` (and ``nside``), of the dense posterior
    precision; then the data checks (``"data_checks"``: calibration, noise excess and
    outliers, fully flagged antennas, the flux scale with ``beam`` or ``dish_diameter_m``;
    :func:`gcrsky.ingest.datachecks.inspect_checks`) and ``"problems"``: what a run would refuse.
    With a beam, ``"band_limit"`` is the lmax a run would choose (the reach of every used
    baseline, :func:`gcrsky.model.bandlimit.observation_lmax`) and the sizes are at it
    (``"lmax_for_sizes"``: ``lmax`` if given, else that reach, else :data:`SIZES_LMAX`).
    """
    if spec is None:
        spec = IngestSpec.from_keywords(**{"flux_scale": "check", **keywords})
    elif keywords:
        raise TypeError(f"give an IngestSpec or keywords, not both (got {sorted(keywords)})")
    pol = feed_pol_of(path, spec.selection.pol)[0]
    prods, _ = parse_products(pol)
    obs, checks = read_checked(path, cal=spec.checks.cal, pol=pol, **read_selection(spec))
    out = describe_observation(obs, prods, redundancy_tol_m)
    read_flags = np.asarray(obs.flags).copy()  # the file's flags (and the calibration's), before gcrsky's checks
    beams, beam_problem = inspect_beams(spec, obs)
    obs, checks, problems = inspect_checks(obs, checks, pol=pol, flag=spec.checks.flag_outliers,
                                           flux_scale=spec.checks.flux_scale,
                                           beam=None if beams is None else beams[0])
    problems = problems + ([beam_problem] if beam_problem else [])
    out["flagged_fraction"] = obs.flagged_fraction  # after the outliers are flagged, as a run would use them
    out["flags"] = flag_sources(read_flags, np.asarray(obs.flags), np.asarray(obs.nsamples))
    try:
        to_ksr, out["noise_units"] = kelvin_sr_per_unit(obs), "K sr"
    except ValueError:
        to_ksr, out["noise_units"] = np.ones(obs.n_freqs), obs.vis_units
    out["noise_sigma_median_k_sr"] = noise_sigma_median(obs, prods[0], to_ksr)
    out["read_bytes"] = read_bytes(obs.nblts_read, obs.n_freqs, obs.n_pols)
    lat, lon, _ = obs.site_lat_lon_alt
    out["site_lat_lon_deg"] = [lat, lon]
    lmax = spec.lmax
    if beams is not None:  # the band limit a run would choose: the reach of every used baseline (lmax None)
        chosen, out["band_limit"] = observation_lmax(obs, beams, lmax, n_products=len(prods))
        lmax = chosen if lmax is None else lmax
    out["lmax_for_sizes"] = lmax = SIZES_LMAX if lmax is None else lmax
    out.update(memory_sizes(obs, len(prods), out["n_rows_exact"], lmax, spec.nside, spec.frame_pad))
    out["data_checks"] = checks
    out["problems"] = problems
    return out


def noise_sigma_median(obs: Observation, prod: str, to_ksr) -> float | None:
    """The median radiometer sigma (autos) per component of the modelled product ``prod`` over the usable
    samples, times ``to_ksr`` (Nf,) per channel; None without autos or usable samples."""
    if not obs.has_autos:
        return None
    var = {r: raw_variance(obs, r, "autos") for r in POLS[prod]}
    v, ok = modelled_product(obs, prod, var)[1:]
    with np.errstate(invalid="ignore"):
        s = np.where(ok, np.sqrt(v) * to_ksr[:, None, None], np.nan)
        return float(np.nanmedian(s)) if np.any(ok) else None


def inspect_beams(spec: IngestSpec, obs: Observation) -> tuple[list | None, str | None]:
    """``(beams or None, problem or None)``: the beams a run would use (prepared, frequencies checked: the
    flux check's and the reach's), None without ``beam`` / ``dish_diameter_m``; a beam that fails is a problem."""
    b = spec.beam
    if b.beam is None and b.dish_diameter_m is None:
        return None, None
    try:
        return prepared_beams(b.beam, b.dish_diameter_m, obs, normalization=b.beam_normalization,
                              freq_scaling=b.beam_freq_scaling,
                              accept_x_orientation_mismatch=b.accept_x_orientation_mismatch).beams, None
    except ValueError as e:
        return None, f"the beam: {e}"


def describe_observation(obs: Observation, prods, redundancy_tol_m: float = 0.5) -> dict:
    """The part of :func:`inspect_uvdata`'s report that describes the file (in the report's key order)."""
    from ..instrument.redundancy import redundant_groups
    from ..model.observed import COMPRESS_TOL_M

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
        # what the run's compression keeps (its grouping tolerance: positions read back through ECEF are ~1e-9 m off)
        "n_rows_exact": redundant_groups(obs.antpos_enu_m, obs.antpairs, tol_m=COMPRESS_TOL_M).n_groups,
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


def flag_sources(read_flags: np.ndarray, flags: np.ndarray, nsamples: np.ndarray) -> dict:
    """Where the unusable samples come from (fractions of all samples): ``file`` (flagged in the file, or by
    its calibration), ``zero_nsample`` (unflagged but nsample 0), ``gcrsky`` (flagged by gcrsky's checks:
    noise-excess outliers, fully flagged antennas) and ``unusable`` (all three: what a run does not use)."""
    total = max(int(flags.size), 1)
    unflagged = ~flags
    return {"file": float(read_flags.sum() / total),
            "zero_nsample": float((unflagged & ~(nsamples > 0)).sum() / total),
            "gcrsky": float((flags & ~read_flags).sum() / total),
            "unusable": float((flags | ~(nsamples > 0)).sum() / total)}


def memory_sizes(obs: Observation, nprods: int, n_unique: int, lmax: int, nside: int | None,
                 frame_pad: int = 4) -> dict:
    """Sizes of the dense precision, the real data values and (with ``nside``) the response."""
    n = n_params(lmax)
    out = {"n_params": n, "dense_precision_bytes": float(obs.n_freqs * n * n * 8),
           "real_data_values": int(2 * n_unique * obs.n_times * obs.n_freqs * nprods)}
    if nside is not None:
        out["response_bytes"] = float(obs.n_freqs * n_unique * nprods * n_params(lmax + frame_pad) * 16)
    return out


#: The degree :func:`inspect_uvdata` sizes the problem at when neither ``lmax`` nor a beam (a reach) is given.
SIZES_LMAX = 20
