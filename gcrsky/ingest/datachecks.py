"""The ingest's data checks, in the order a run and ``inspect`` need them (``DataConfig.checks`` sections).

1. :func:`read_checked`: the file's selection, calibrated with ``cal`` (:mod:`gcrsky.io.calibration`) or
   not (``checks["calibration"]``);
2. :func:`flag_checks`: the noise excess and its outliers (flagged with ``flag_outliers``), dead
   channels, fully flagged antennas (``checks["flags"]``; :mod:`gcrsky.model.datachecks`);
3. :func:`flux_checks`: the flux-scale ratio (``checks["flux_scale"]``, :mod:`gcrsky.model.fluxscale`),
   refused outside its bounds unless ``flux_scale="accept"``.

All sections are JSON-friendly.  Nothing here builds a response.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np

from ..io.observation import read_observation
from ..io.visdata import Observation, parse_products
from ..model.datachecks import DEFAULT_K, find_outliers, flag_outliers, flagged_antennas, noise_excess
from ..model.fluxscale import FLUX_BOUNDS, flux_scale_check

__all__ = ["AMPLITUDE_MODES", "FLUX_SCALE_MODES", "amplitude_checks", "amplitude_needed", "CheckedObservation", "InspectedChecks", "flag_checks", "flux_checks", "inspect_checks",
           "read_checked"]

log = logging.getLogger(__name__)

class CheckedObservation(NamedTuple):
    """An Observation and the record of its checks so far (``DataConfig.checks`` sections)."""

    obs: Observation
    checks: dict


class InspectedChecks(NamedTuple):
    """``inspect``'s checks: the Observation a run would fit, the checks' record, what a run would refuse."""

    obs: Observation
    checks: dict
    problems: list


#: ``flux_scale``: refuse a ratio outside the bounds, accept it (recorded, a warning), or skip the check.
FLUX_SCALE_MODES = ("check", "accept", "off")
#: ``amplitude``: inferred with the sky where the data are not absolutely calibrated (``"auto"``), always
#: (``"infer"``), or fixed (the data taken as calibrated, ``"fixed"``).
AMPLITUDE_MODES = ("auto", "infer", "fixed")


def _not_absolute(units: str, cal_given: bool, gain_scale, cal_style) -> str | None:
    """Why data with these units and calibration are not absolutely calibrated, or None."""
    if units == "uncalib" and not cal_given:
        return "the file's visibilities are uncalibrated (vis_units 'uncalib')"
    if cal_given and gain_scale is None:
        return (f"the gain solutions ({cal_style}) carry no gain_scale: their overall amplitude is the solver's "
                "convention")
    return None


def amplitude_needed(data, cal=None) -> str | None:
    """Why the amplitude must be inferred (None: the data are absolutely calibrated), from the headers of the
    visibility file (or a ``UVData``, or the first of several files) and of the gain solutions ``cal`` (a path, or
    the first of several), before anything is read."""
    from pyuvdata import UVData

    from ..io.files import check_input_file, reading
    from ..io.manyfiles import first_file
    from ..io.selection import VIS_FORMATS

    data, cal = first_file(data), first_file(cal)  # several files: one array and units (checked when read)
    if isinstance(data, UVData):
        units = data.vis_units
    else:
        path = check_input_file(data, "visibility file", measurement_set=True)
        with reading(path, "a visibility file", VIS_FORMATS):  # the reader's own message for a bad file
            try:
                units = UVData.from_file(str(path), read_data=False).vis_units
            except (TypeError, NotImplementedError):  # a format without a metadata-only read
                units = UVData.from_file(str(path)).vis_units
    if cal is None:
        return _not_absolute(units, False, None, None)
    from ..io.calibration import read_calibration

    uvc, _ = read_calibration(cal)  # offline: a file without a location is not looked up by name on the internet
    return _not_absolute(units, True, uvc.gain_scale, uvc.cal_style)


def amplitude_checks(obs: Observation, checks: dict, mode: str = "auto") -> CheckedObservation:
    """Whether the overall amplitude is inferred (:mod:`gcrsky.run.amplitude`): ``(obs, {"amplitude": ...})``.

    The data are absolutely calibrated when their units are Jy or K str and no gain solutions were
    applied, or the applied ones carry a ``gain_scale``.  Otherwise (``vis_units`` ``"uncalib"``, or
    solutions without a ``gain_scale``, e.g. redundant ones) ``"auto"`` infers the amplitude, and
    ``"uncalib"`` data are then read as Jy (the amplitude ``q`` carries the scale).

    Raises:
        ValueError: an unknown mode.
    """
    import dataclasses

    if mode not in AMPLITUDE_MODES:
        raise ValueError(f"amplitude must be one of {AMPLITUDE_MODES}, got {mode!r}")
    applied = (checks.get("calibration") or {}).get("applied")
    why = _not_absolute(obs.vis_units, applied is not None, (applied or {}).get("gain_scale"),
                        (applied or {}).get("cal_style"))
    infer = mode == "infer" or (mode == "auto" and why is not None)
    rec = {"mode": "infer" if infer else "fixed", "asked": mode,
           "why": why if infer and why else ("asked (--amplitude infer)" if infer else
                                             "the data are taken as absolutely calibrated" if why is None else
                                             f"asked (--amplitude fixed), although {why}")}
    if infer and obs.vis_units == "uncalib":
        obs = dataclasses.replace(obs, vis_units="Jy")
        rec["units"] = "uncalib, read as Jy: the inferred amplitude carries the scale"
    return CheckedObservation(obs, {"amplitude": rec})


def read_checked(data, *, cal=None, pol="pI", **selection) -> CheckedObservation:
    """The Observation of the selection (calibrated with ``cal`` if given) and ``{"calibration": ...}``."""
    if cal is None:
        obs = read_observation(data, pol=pol, **selection)
        state = {"applied": None, "vis_units": obs.vis_units}
        return CheckedObservation(obs, {"calibration": state})
    from ..io.calibration import read_calibrated_observation

    obs, info = read_calibrated_observation(data, cal, pol=pol, **selection)
    used = {str(int(a)) for a in obs.antenna_numbers}
    info["renamed_antennas"] = {k: v for k, v in info["renamed_antennas"].items() if k in used}
    return CheckedObservation(obs, {"calibration": {"applied": info, "vis_units": obs.vis_units}})


def flag_checks(obs: Observation, *, flag: bool = True, k: float = DEFAULT_K,
                refuse: bool = True) -> CheckedObservation:
    """Noise excess, outliers (flagged if ``flag``), fully flagged antennas: (Observation, ``{"flags": ...}``).

    The excess needs the autos and two integrations; without them it is skipped with the reason.
    Flagging that leaves nothing usable raises a ``ValueError`` saying so if ``refuse``, else is
    recorded (``"emptied"``).
    """
    rec: dict = {"flagged_fraction_read": obs.flagged_fraction, "outlier_flagging": bool(flag)}
    try:
        ex = noise_excess(obs)
    except ValueError as err:
        rec["noise_excess"] = {"skipped": str(err)}
        rec["fully_flagged_antennas"] = flagged_antennas(obs)
        return CheckedObservation(obs, {"flags": rec})
    pc = ex.per_channel()
    rec["noise_excess"] = {
        "per_channel_median": [None if not np.isfinite(x) else float(x) for x in pc],
        "per_channel_max": [None if not np.any(np.isfinite(row)) else float(np.nanmax(row))
                            for row in np.moveaxis(ex.excess, 1, 0).reshape(obs.n_freqs, -1)],
        "products": list(ex.pol_names),
    }
    if ex.per_file:
        rec["noise_excess"]["per_file"] = [{"file": f, "median_excess": x} for f, x in zip(obs.files, ex.per_file)]
    had = bool(np.any(obs.usable))
    if flag:
        obs, out = flag_outliers(obs, k=k)
    else:
        out = find_outliers(obs, ex, k=k)
    if had and not np.any(obs.usable):
        rec["emptied"] = ("every usable sample was flagged by the data checks (noise-excess outlier channels "
                          f"{list(out.channels)}, dead channels {list(out.dead_channels)}, baselines "
                          f"{list(out.baselines)}, times {list(out.times)}): select other data, or keep them with "
                          "--no-flag-outliers (flag_outliers=False)")
    rec["outliers"] = out.to_dict(obs)
    rec["fully_flagged_antennas"] = flagged_antennas(obs)
    rec["flagged_fraction_used"] = obs.flagged_fraction
    if refuse and "emptied" in rec:
        raise ValueError(rec["emptied"])
    if rec["fully_flagged_antennas"]:
        log.warning("antennas flagged entirely (every cross-correlation): %s", rec["fully_flagged_antennas"])
    return CheckedObservation(obs, {"flags": rec})


def flux_checks(obs: Observation, beam, *, pol="pI", mode: str = "check", bounds=FLUX_BOUNDS,
                inferred: bool = False) -> dict:
    """``{"flux_scale": ...}``: the ratio (:func:`gcrsky.model.fluxscale.flux_scale_check`) and the decision
    (``inferred``: the amplitude is inferred with the sky: the ratio is recorded as a check, never refused).

    Raises:
        ValueError: ``mode == "check"`` and the ratio is outside ``bounds`` (the message names
            ``--flux-scale accept``); an unknown mode.
    """
    if mode not in FLUX_SCALE_MODES:
        raise ValueError(f"flux_scale must be one of {FLUX_SCALE_MODES}, got {mode!r}")
    if mode == "off":
        return {"flux_scale": {"mode": "off"}}
    if not obs.has_autos:
        return {"flux_scale": {"mode": mode, "skipped": "no autocorrelations in the selection"}}
    prods, _ = parse_products(pol)
    from ..model.gsmsky import GSM_RANGE_HZ

    lo, hi = GSM_RANGE_HZ
    if obs.freqs_hz.min() < lo or obs.freqs_hz.max() > hi:
        why = f"the GSM sky is known over {lo / 1e6:g}-{hi / 1e6:g} MHz only"
        log.warning("flux-scale check skipped: %s", why)
        return {"flux_scale": {"mode": mode, "skipped": why}}
    try:
        rec = {"mode": "check beside the inferred amplitude" if inferred else mode,
               **flux_scale_check(obs, beam, prod=prods[0], bounds=bounds)}
    except ImportError as err:  # the GSM map is pyradiosky's (the "sim" extra)
        log.warning("flux-scale check skipped: %s", err)
        return {"flux_scale": {"mode": mode, "skipped": str(err)}}
    ratio = rec["ratio"]
    if inferred:
        mode = "accept"
    if ratio is not None and not rec["within"]:
        what = (f"the data's autocorrelations are {ratio:.4g} x the GSM sky's through the beam (expected "
                f"{bounds[0]:g}-{bounds[1]:g} for calibrated data in {rec['units']}): the flux scale is off by that "
                "factor (calibration, units or beam normalisation)")
        if mode == "check":
            raise ValueError(what + "; fix the calibration, or accept the scale with --flux-scale accept "
                             "(flux_scale='accept'; the posterior is then on the data's scale), or infer the amplitude "
                             "with the sky (--amplitude infer)")
        if inferred:
            log.info("flux scale: the data's autocorrelations are %.4g x the GSM sky's through the beam; the amplitude "
                     "is inferred with the sky (this ratio is a check beside it)", ratio)
        else:
            log.warning("%s; accepted (flux_scale='accept')", what)
    return {"flux_scale": rec}


def inspect_checks(obs: Observation, checks: dict, *, pol="pI", flag: bool = True, flux_scale: str = "check",
                   beam=None) -> InspectedChecks:
    """``inspect``'s checks: everything is reported, and what a run would refuse becomes a PROBLEM line.

    Args:
        obs: the Observation read (and calibrated) by :func:`read_checked`; ``checks`` its record.
        pol: the modelled product(s).  flag: flag the outliers (as a run would).
        flux_scale: as a run's (``"off"`` skips the check).  beam: a beam object, or None
            (the flux-scale check is then skipped with a note).

    Returns:
        (the Observation a run would fit, the checks, the problems: messages of what a run refuses).
    """
    from ..model.datachecks import refuse_empty, refuse_nonfinite
    from ..model.observed import kelvin_sr_per_unit

    problems = []
    obs, flags = flag_checks(obs, flag=flag, refuse=False)
    checks.update(flags)
    if "emptied" in flags["flags"]:
        problems.append(flags["flags"]["emptied"])
    for check in (refuse_empty, kelvin_sr_per_unit, refuse_nonfinite):
        try:
            check(obs)
        except ValueError as err:
            problems.append(str(err))
    if flux_scale == "off":
        checks["flux_scale"] = {"mode": "off"}
    elif beam is None:
        checks["flux_scale"] = {"mode": flux_scale, "skipped": "no beam: give --beam FILE or --dish-diameter D"}
    else:
        try:
            checks.update(flux_checks(obs, beam, pol=pol, mode="accept"))
        except ValueError as err:
            checks["flux_scale"] = {"mode": flux_scale, "skipped": str(err)}
        rec = checks["flux_scale"]
        if rec.get("ratio") is not None and not rec["within"] and flux_scale == "check":
            problems.append(f"flux scale: the data's autos are {rec['ratio']:.4g} x the GSM's through the beam "
                            f"(bounds {rec['bounds'][0]:g}-{rec['bounds'][1]:g}): a run refuses it unless "
                            "--flux-scale accept")
    cal = checks["calibration"]
    if cal["applied"] is not None:
        problems += [f"calibration: {w}" for w in cal["applied"]["warnings"] if "redundant" in w]
    return InspectedChecks(obs, checks, problems)
