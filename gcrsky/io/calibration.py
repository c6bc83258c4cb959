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


def check_coverage(uvc, uvd, cal_path) -> None:
    """Refuse data times or channels the solutions do not cover, naming them (pyuvdata's own error names
    neither the file nor which): a time is covered within half a solution's integration of one, a channel
    within half a channel width of one (a calibration with one time range covers the range)."""
    jd = np.unique(np.asarray(uvd.time_array, float))
    if getattr(uvc, "time_range", None) is not None and uvc.time_array is None:
        lo, hi = np.min(uvc.time_range), np.max(uvc.time_range)
        outside = jd[(jd < lo - 1e-7) | (jd > hi + 1e-7)]
    else:
        ct = np.asarray(uvc.time_array, float)
        half = 0.5 * float(np.max(np.asarray(uvc.integration_time, float))) / 86400.0 + 1e-7
        outside = jd[np.min(np.abs(jd[:, None] - ct[None, :]), axis=1) > half]
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


def apply_calibration(uvd, cal_path) -> dict:
    """Apply the solutions in ``cal_path`` to the UVData ``uvd`` in place (module docstring); what was done.

    Returns:
        a JSON-friendly dict: file, cal_style, cal_type, gain_convention, gain_scale, the
        units the data now have, renamed antennas, antennas flagged in the solutions, the
        location offset, and the warnings.
    """
    from pyuvdata.utils import uvcalibrate

    uvc, offset = read_calibration(cal_path, location=uvd.telescope.location)
    check_coverage(uvc, uvd, cal_path)
    renamed = match_antennas(uvc, uvd)
    before = str(uvd.vis_units)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            uvcalibrate(uvd, uvc, inplace=True, prop_flags=True)
        except ValueError as err:
            raise ValueError(f"applying {cal_path}: {err}") from None
    for w in caught:
        log.info("uvcalibrate: %s", w.message)
    notes = []
    if uvc.gain_scale is None:
        uvd.vis_units = "Jy"
        notes.append(f"the solutions have no gain_scale: the calibrated data (were {before!r}) are taken to be in "
                     "Jy; the flux-scale check tests that")
    if uvc.cal_style == "redundant" and uvc.gain_scale is None:
        notes.append(REDUNDANT_WARNING)
    for line in notes:
        log.warning(line)
    return {"file": str(cal_path), "cal_style": str(uvc.cal_style), "cal_type": str(uvc.cal_type),
            "gain_convention": str(uvc.gain_convention), "gain_scale": uvc.gain_scale, "units_before": before,
            "units_after": str(uvd.vis_units), "renamed_antennas": {str(k): v for k, v in renamed.items()},
            "flagged_antennas_in_solutions": _flagged_in_solutions(uvc), "location_offset_m": offset,
            "warnings": notes}


def read_calibrated_observation(data, cal, *, pol=None, **selection) -> tuple[Observation, dict]:
    """The Observation of a file (or UVData) after applying the gain solutions in ``cal``.

    Args:
        data: a visibility file's path or a ``UVData`` (not modified).
        cal: the solutions' file (calfits, calh5: anything ``UVCal.from_file`` reads).
        pol, **selection: as :func:`gcrsky.io.read_observation`.

    Returns:
        (the :class:`~gcrsky.io.Observation`, the calibration record of :func:`apply_calibration`).
    """
    uvd, source, sel = read_uvdata(data, pol=pol, **selection)
    if uvd is data:
        uvd = uvd.copy()
    info = apply_calibration(uvd, cal)
    phase_type, notes = unproject(uvd)
    notes = [*notes, f"calibrated with {cal} ({info['cal_style']}, gain_convention {info['gain_convention']})"]
    return observation_of(uvd, source=source, selection=sel, phase_type=phase_type, notes=notes), info
