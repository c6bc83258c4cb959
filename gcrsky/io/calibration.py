"""Gain solutions applied to a visibility file: a UVCal (calfits, calh5) read offline, matched, applied.

:func:`read_calibrated_observation` reads the data selection (:func:`gcrsky.io.read_uvdata`),
reads the solutions (:func:`read_calibration`), matches antennas by number
(:func:`match_antennas`), applies them with pyuvdata's ``uvcalibrate`` (``gain_convention``
respected, the solutions' flags propagated to the data), then arranges the samples as
:func:`gcrsky.io.read_observation` does.  What was done is returned as a JSON-friendly dict
(``DataConfig.checks["calibration"]``).

* Offline: a calfits file without a telescope location makes pyuvdata look the telescope
  up by name, first in astropy's site registry, which astropy downloads (and which fails
  without a network).  The read runs with an empty astropy registry so that pyuvdata's own
  table of known telescopes answers, and the solutions' location is then replaced by the
  data file's (the distance between them is recorded).
* Antennas are matched by number: where a number's name differs (HERA's omnical files say
  ``ant0`` where the data say ``HH0``) the solutions take the data's names (pyuvdata
  matches by name), with a log line.
* Units: solutions with a ``gain_scale`` give the data those units (pyuvdata); solutions
  without one (redundant calibration) leave the scale arbitrary: the data are then taken
  to be in Jy, and the flux-scale check (:mod:`gcrsky.model.fluxscale`) judges that.
* ``cal_style`` "redundant": redundant calibration determines neither the overall
  amplitude nor the two phase gradients across the array (nor the overall phase, which
  is unobservable): a warning says so.
"""

from __future__ import annotations

import contextlib
import logging
import warnings

import numpy as np

from .observation import observation_of, read_uvdata, unproject
from .visdata import Observation

__all__ = ["apply_calibration", "check_coverage", "match_antennas", "read_calibrated_observation", "read_calibration"]

log = logging.getLogger(__name__)

#: What a redundant solution leaves undetermined (the warning's text).
REDUNDANT_WARNING = ("the gain solutions are redundant (cal_style 'redundant') without a gain_scale: redundant "
                     "calibration fixes neither the overall amplitude nor the two phase gradients across the array "
                     "(nor the overall phase, which is unobservable); the flux scale and the sky's position are "
                     "the solver's convention, not the sky's")


@contextlib.contextmanager
def _offline_sites():
    """Within: astropy's site registry, unless already loaded, holds one placeholder (astropy reloads an empty one
    from the network): no download, and pyuvdata's own table of telescopes answers."""
    from astropy.coordinates import EarthLocation
    from astropy.coordinates.sites import SiteRegistry

    had = EarthLocation._site_registry
    if not had:
        reg = SiteRegistry()
        reg.add_site(["gcrsky offline placeholder"], EarthLocation.from_geocentric(0.0, 0.0, 0.0, unit="m"))
        EarthLocation._site_registry = reg
    try:
        yield
    finally:
        if not had:
            EarthLocation._site_registry = had


def read_calibration(path, *, location=None):
    """A UVCal from a calfits / calh5 file (anything ``UVCal.from_file`` reads), offline.

    Args:
        path: the solutions' file.
        location: an astropy ``EarthLocation`` (the data file's) that replaces the
            solutions' own (or pyuvdata's known telescope's) location; None keeps it.

    Returns:
        (the UVCal, the distance in metres between its own location and ``location``, or None).
    """
    from pyuvdata import UVCal

    from .files import READ_ERRORS, check_input_file

    path = check_input_file(path, "calibration file")
    with _offline_sites(), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            uvc = UVCal.from_file(str(path))
        except READ_ERRORS as err:
            raise ValueError(f"{path}: not a calibration file pyuvdata reads ({type(err).__name__}: {err})") from err
    for w in caught:
        log.info("reading %s: %s", path, w.message)
    offset = None
    if location is not None:
        own = uvc.telescope.location
        if own is not None:
            offset = float(np.linalg.norm([(own.x - location.x).to_value("m"), (own.y - location.y).to_value("m"),
                                           (own.z - location.z).to_value("m")]))
        uvc.telescope.location = location
        if uvc.time_array is not None:
            uvc.set_lsts_from_time_array()
    return uvc, offset


def match_antennas(uvc, uvd) -> dict:
    """Give the solutions the data's antenna names where the numbers agree (in place); the renames.

    Returns:
        ``{number: [solutions' name, data's name]}`` of the renamed antennas (JSON-friendly).
    """
    data_names = {int(n): str(s) for n, s in zip(uvd.telescope.antenna_numbers, uvd.telescope.antenna_names)}
    names = [str(s) for s in uvc.telescope.antenna_names]
    renamed = {}
    for k, num in enumerate(np.asarray(uvc.telescope.antenna_numbers)):
        want = data_names.get(int(num))
        if want is not None and names[k] != want:
            renamed[int(num)] = [names[k], want]
            names[k] = want
    if renamed:
        uvc.telescope.antenna_names = np.asarray(names)
        log.info("calibration: antennas matched by number, the solutions' names replaced by the data's: %s",
                 ", ".join(f"{a} {b}->{c}" for a, (b, c) in sorted(renamed.items())))
    missing = sorted({int(a) for a in np.unique(np.r_[uvd.ant_1_array, uvd.ant_2_array])}
                     - {int(a) for a in uvc.ant_array})
    if missing:
        raise ValueError(f"the calibration file has no solutions for the data's antennas {missing}: select the "
                         f"others (--antennas) or give solutions for them")
    return renamed


def _flagged_in_solutions(uvc) -> list[int]:
    """Antenna numbers whose every solution is flagged."""
    flags = np.asarray(uvc.flag_array, bool)
    return [int(a) for a, f in zip(uvc.ant_array, flags) if np.all(f)]


#: How solutions are interpolated in time (``UVCal.interpolate_in_time`` keywords): linear in amplitude and
#: phase, never extrapolated.
INTERPOLATION = {"kind": "linear", "allow_extrapolation": False}

#: A data time matches a solution time within this (days: 0.1 s); otherwise the solutions are interpolated.
TIME_MATCH_DAYS = 0.1 / 86400.0


def check_coverage(uvc, uvd, cal_path) -> str:
    """Refuse data times or channels the solutions do not cover, naming them (pyuvdata's own error names
    neither the file nor which); whether the solutions must be interpolated in time.

    A data time is covered by a solution at that time (within :data:`TIME_MATCH_DAYS`), or between
    the first and last solution times (then every time is interpolated linearly in amplitude and
    phase by pyuvdata's ``UVCal.interpolate_in_time``, no extrapolation), or by a solution's time
    range; solutions at one time only (a bandpass) apply to every data time; a channel within half a
    channel width of a solution's (pyuvdata does not interpolate in frequency).

    Returns:
        ``"exact"`` (every data time is a solution time, or in a time range), ``"interpolate"`` or
        ``"one time"`` (one solution time for all).
    """
    jd = np.unique(np.asarray(uvd.time_array, float))
    mode = "exact"
    if getattr(uvc, "time_range", None) is not None and uvc.time_array is None:
        lo, hi = np.min(uvc.time_range), np.max(uvc.time_range)
        outside = jd[(jd < lo - 1e-7) | (jd > hi + 1e-7)]
    else:
        ct = np.asarray(uvc.time_array, float)
        exact = np.min(np.abs(jd[:, None] - ct[None, :]), axis=1) <= TIME_MATCH_DAYS
        outside = jd[~exact & ((jd < ct.min() - TIME_MATCH_DAYS) | (jd > ct.max() + TIME_MATCH_DAYS))]
        if ct.size == 1:
            outside, mode = jd[:0], "exact" if np.all(exact) else "one time"
        elif not np.all(exact):
            mode = "interpolate"
    if outside.size:
        from astropy.time import Time

        lst = np.degrees(np.asarray(Time(outside, format="jd", location=uvd.telescope.location)
                                    .sidereal_time("apparent").rad)) / 15.0
        ct_all = np.asarray(uvc.time_array if uvc.time_array is not None else uvc.time_range, float)
        raise ValueError(f"{cal_path}: its solutions cover JD {ct_all.min():.6f}-{ct_all.max():.6f}, but {outside.size} "
                         f"of the data's {jd.size} times are not covered (JD {outside.min():.6f}-{outside.max():.6f}, "
                         f"LST {lst.min():.3f}-{lst.max():.3f} h): give the solutions of those times, or select the "
                         "covered ones (--lst-range)")
    if getattr(uvc, "freq_array", None) is not None and np.size(uvc.freq_array) > 1:
        cf = np.asarray(uvc.freq_array, float).ravel()
        df = float(np.median(np.abs(np.diff(np.sort(cf))))) if cf.size > 1 else 0.0
        f = np.asarray(uvd.freq_array, float).ravel()
        missing = f[np.min(np.abs(f[:, None] - cf[None, :]), axis=1) > 0.5 * df + 1.0]
        if missing.size:
            raise ValueError(f"{cal_path}: its solutions cover {cf.min() / 1e6:.4f}-{cf.max() / 1e6:.4f} MHz "
                             f"({cf.size} channels), but {missing.size} of the data's channels are not among them "
                             f"({missing.min() / 1e6:.4f}-{missing.max() / 1e6:.4f} MHz): give solutions for them, or "
                             "select the covered channels (--freq-range, --chans)")
    return mode


def _check_calibrated(uvd, cross, usable_before: int, cal_path) -> None:
    """Refuse solutions that flag every cross-correlation the data had, or that make unflagged data non-finite
    (zero or non-finite gains), naming the file (the data checks would blame the data)."""
    flags = np.asarray(uvd.flag_array, bool)[cross]
    if usable_before and not np.any(~flags):
        raise ValueError(f"{cal_path}: its solutions flag every one of the {usable_before} unflagged cross-correlation "
                         "samples of the data (every gain flagged at these times and channels): check the solutions")
    bad = ~flags & ~np.isfinite(np.asarray(uvd.data_array)[cross])
    if np.any(bad):
        raise ValueError(f"{cal_path}: applying its solutions made {int(bad.sum())} unflagged samples non-finite "
                         "(zero or non-finite gains that are not flagged): flag them in the solutions")


def apply_calibration(uvd, cal_path, *, quiet: bool = False) -> dict:
    """Apply the solutions in ``cal_path`` to the UVData ``uvd`` in place (module docstring); what was done.

    ``quiet``: the warnings are returned, not logged (several files' are logged once, merged).

    Returns:
        a JSON-friendly dict: file, cal_style, cal_type, gain_convention, gain_scale, the
        units the data now have, renamed antennas, antennas flagged in the solutions, the
        location offset, whether the solutions were interpolated in time, and the warnings.
    """
    from pyuvdata.utils import uvcalibrate

    uvc, offset = read_calibration(cal_path, location=uvd.telescope.location)
    mode = check_coverage(uvc, uvd, cal_path)
    interpolate = mode == "interpolate"
    if mode == "one time":
        log.info("%s: solutions at one time (JD %.6f) applied to every data time", cal_path,
                 float(np.asarray(uvc.time_array).ravel()[0]))
    if interpolate:
        log.info("%s: the solutions (%d times) are interpolated linearly in time onto the data's %d times "
                 "(pyuvdata's UVCal.interpolate_in_time)", cal_path, uvc.Ntimes, len(np.unique(uvd.time_array)))
    renamed = match_antennas(uvc, uvd)
    before = str(uvd.vis_units)
    cross = np.asarray(uvd.ant_1_array) != np.asarray(uvd.ant_2_array)
    usable_before = int(np.sum(~np.asarray(uvd.flag_array, bool)[cross]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            uvcalibrate(uvd, uvc, inplace=True, prop_flags=True, interpolate=interpolate, time_check=mode != "one time",
                        interp_kwargs=INTERPOLATION if interpolate else None)
        except ValueError as err:
            raise ValueError(f"applying {cal_path}: {err}") from None
    for w in caught:
        log.info("uvcalibrate: %s", w.message)
    _check_calibrated(uvd, cross, usable_before, cal_path)
    notes = []
    if uvc.gain_scale is None:
        uvd.vis_units = "Jy"
        notes.append(f"the solutions have no gain_scale: the calibrated data (were {before!r}) are taken to be in "
                     "Jy; the flux-scale check tests that")
    if uvc.cal_style == "redundant" and uvc.gain_scale is None:
        notes.append(REDUNDANT_WARNING)
    for line in () if quiet else notes:
        log.warning(line)
    return {"file": str(cal_path), "cal_style": str(uvc.cal_style), "cal_type": str(uvc.cal_type),
            "gain_convention": str(uvc.gain_convention), "gain_scale": uvc.gain_scale, "units_before": before,
            "units_after": str(uvd.vis_units), "renamed_antennas": {str(k): v for k, v in renamed.items()},
            "flagged_antennas_in_solutions": _flagged_in_solutions(uvc), "location_offset_m": offset,
            "interpolated_in_time": interpolate, "one_time_for_all": mode == "one time", "warnings": notes}


def read_calibrated_observation(data, cal, *, pol=None, **selection) -> tuple[Observation, dict]:
    """The Observation of a file (or UVData) after applying the gain solutions in ``cal``.

    Args:
        data: a visibility file's path, a list of them (:mod:`gcrsky.io.manyfiles`) or a ``UVData`` (not
            modified).
        cal: the solutions' file (calfits, calh5: anything ``UVCal.from_file`` reads); with several
            visibility files one for all of them or a list, one per file in their order.
        pol, **selection: as :func:`gcrsky.io.read_observation`.

    Returns:
        (the :class:`~gcrsky.io.Observation`, the calibration record of :func:`apply_calibration`).
    """
    if isinstance(data, (list, tuple)) and len(data) == 1:
        data = data[0]
    if isinstance(data, (list, tuple)):
        return _calibrated_files(list(data), cal, pol=pol, **selection)
    if isinstance(cal, (list, tuple)):
        if len(cal) != 1:
            raise ValueError(f"{len(cal)} calibration files for one visibility file: give one")
        cal = cal[0]
    uvd, source, sel = read_uvdata(data, pol=pol, **selection)
    if uvd is data:
        uvd = uvd.copy()
    info = apply_calibration(uvd, cal)
    phase_type, notes = unproject(uvd)
    notes = [*notes, f"calibrated with {cal} ({info['cal_style']}, gain_convention {info['gain_convention']})"]
    return observation_of(uvd, source=source, selection=sel, phase_type=phase_type, notes=notes), info


def _calibrated_files(paths: list, cal, *, pol, **selection) -> tuple[Observation, dict]:
    """Several files, each calibrated by its own solutions (``cal`` a list in the files' order) or all by
    one, before they are joined (:mod:`gcrsky.io.manyfiles`)."""
    from .manyfiles import join_parts, read_parts, source_name
    from .observation import many_selection

    cals = list(cal) if isinstance(cal, (list, tuple)) else [cal] * len(paths)
    if len(cals) not in (1, len(paths)):
        raise ValueError(f"{len(cals)} calibration files for {len(paths)} visibility files: give one for all, or "
                         "one per visibility file in the same order")
    cals = cals * len(paths) if len(cals) == 1 else cals
    cal_of = {str(p): c for p, c in zip(paths, cals)}
    parts, _ = read_parts(paths, pol=pol, **selection)
    infos = [apply_calibration(part.uvd, cal_of[part.path], quiet=True) for part in parts]
    info = _merged_records(infos, [p.path for p in parts])
    for line in info["warnings"]:
        log.warning(line)
    uvd = join_parts(parts)
    phase_type, notes = unproject(uvd)
    used = list(dict.fromkeys(str(i["file"]) for i in infos))
    named = used[0] if len(used) == 1 else f"{len(used)} solution files, one per visibility file"
    notes = [*notes, f"calibrated with {named} ({info['cal_style']}, gain_convention {info['gain_convention']})"]
    obs = observation_of(uvd, source=source_name([p.path for p in parts]), selection=many_selection(parts),
                         phase_type=phase_type, notes=notes)
    return obs, info


def _merged_records(infos: list[dict], paths: list[str]) -> dict:
    """One calibration record of several files' (:func:`apply_calibration`), refusing solutions that leave
    the files in different units or conventions."""
    if len(infos) == 1:
        return infos[0]
    for key in ("cal_style", "gain_convention", "gain_scale", "units_after"):
        values = {str(i[key]) for i in infos}
        if len(values) > 1:
            raise ValueError(f"the calibration files disagree on {key} ({sorted(values)}): the calibrated files would "
                             "not be in one convention and one unit")
    out = dict(infos[0])
    files = list(dict.fromkeys(str(i["file"]) for i in infos))
    out["file"] = files[0] if len(files) == 1 else files
    out["interpolated_in_time"] = any(i["interpolated_in_time"] for i in infos)
    out["flagged_antennas_in_solutions"] = sorted({a for i in infos for a in i["flagged_antennas_in_solutions"]})
    out["renamed_antennas"] = {k: v for i in infos for k, v in i["renamed_antennas"].items()}
    out["warnings"] = list(dict.fromkeys(w for i in infos for w in i["warnings"]))
    out["per_file"] = [{"data": p, "cal": str(i["file"]), "interpolated_in_time": i["interpolated_in_time"],
                        "flagged_antennas_in_solutions": i["flagged_antennas_in_solutions"]}
                       for p, i in zip(paths, infos)]
    return out
