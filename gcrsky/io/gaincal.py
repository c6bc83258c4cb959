"""Sampled gains as a calibration file pyuvdata reads: the posterior-mean gains as calfits or calh5.

The gains are given (:func:`gcrsky.ingest.posterior_mean_gains` averages :func:`gcrsky.model.gains.unit_gains`);
they are (``g_u = gbar_u sqrt(q(nu)) (1 + x_u)``), with the
model ``V_ij = g_i conj(g_j) V^sky`` of row ``(ant_1, ant_2)``: pyuvdata's ``gain_convention``
``"divide"`` (its ``uvcalibrate`` divides row ``(1, 2)`` by ``g_1 conj(g_2)``), ``cal_style``
``"sky"``.  A unit that is one gain per antenna (``pI`` rows) is written to both linear feeds
(``Jee``/``Jnn`` as ``xx``/``yy`` Jones terms); ``xx``/``yy`` units to their own feed, the
other feed flagged.  Antennas without a unit are flagged.

The overall phase of the gains is the gauge's (unobservable; no common imaginary part of the
perturbations), so only ``g_i conj(g_j)`` is meaningful.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

__all__ = ["write_gain_calibration"]

log = logging.getLogger(__name__)


def write_gain_calibration(path, gains, model, *, antenna_numbers, antenna_names, antpos_enu_m, freqs_hz,
                           times_jd, latitude_deg: float, longitude_deg: float, altitude_m: float,
                           telescope_name: str = "gcrsky", overwrite: bool = False) -> Path:
    """Write gains (Nf, Nt, U) as a calibration file: calfits (``.calfits``) or calh5 (``.calh5``, ``.h5``).

    Args:
        path: the file to write.
        gains: (Nf, Nt, U) complex (e.g. :func:`gcrsky.ingest.posterior_mean_gains`).
        model: the layout whose ``units`` ((antenna index, feed)) the last axis follows.
        antenna_numbers, antenna_names: (Nant,) of the file the gains calibrate, in the order of the
            antenna indices of ``Problem.antpairs``.
        antpos_enu_m: (Nant, 3) their ENU positions, metres.
        freqs_hz: (Nf,); times_jd: (Nt,) the data's times (JD).
        latitude_deg, longitude_deg, altitude_m: the telescope's site.
        telescope_name: written as the telescope's name (no lookup: the site is the one given).
        overwrite: replace an existing file.

    Returns:
        The path written.

    Raises:
        ValueError: shapes that do not match, an unknown extension, or an existing file without ``overwrite``.
    """
    from astropy.coordinates import EarthLocation
    from pyuvdata import Telescope, UVCal
    from pyuvdata.utils import ECEF_from_ENU

    path = Path(path)
    if path.suffix not in (".calfits", ".calh5", ".h5"):
        raise ValueError(f"{path}: write a .calfits or a .calh5 file")
    if path.exists() and not overwrite:
        raise ValueError(f"{path} exists: remove it or pass overwrite=True")
    g = np.asarray(gains, complex)
    nf, nt = len(freqs_hz), len(times_jd)
    units = np.asarray(model.units)
    if g.shape != (nf, nt, units.shape[0]):
        raise ValueError(f"gains have shape {g.shape}, expected (Nf, Nt, U) = {(nf, nt, units.shape[0])}")
    nums = np.asarray(antenna_numbers, int)
    loc = EarthLocation.from_geodetic(lon=longitude_deg, lat=latitude_deg, height=altitude_m)
    ecef = ECEF_from_ENU(np.asarray(antpos_enu_m, float), center_loc=loc)
    rel = ecef - np.array([c.to_value("m") for c in loc.geocentric])[None, :]
    tel = Telescope.new(name=telescope_name, location=loc, antenna_positions=rel,
                        antenna_names=list(antenna_names), antenna_numbers=nums, feed_array=["x", "y"],
                        feed_angle=[np.pi / 2, 0.0], mount_type="fixed",
                        update_from_known=False)
    cal = UVCal.new(cal_style="sky", gain_convention="divide", jones_array=np.array([-5, -6]), telescope=tel,
                    time_array=np.asarray(times_jd, float), freq_array=np.asarray(freqs_hz, float),
                    ant_array=nums, integration_time=np.full(nt, 1.0), channel_width=_widths(freqs_hz),
                    ref_antenna_name="none (zero mean phase)", sky_catalog="gcrsky: the sky sampled with the gains",
                    history="gcrsky: posterior-mean gains sampled with the sky")
    arr = np.ones((nums.size, nf, nt, 2), complex)
    flags = np.ones(arr.shape, bool)
    for u, (ant, feed) in enumerate(units):
        for j in ((0, 1) if feed == 0 else (feed - 1,)):
            arr[ant, :, :, j] = g[:, :, u]
            flags[ant, :, :, j] = False
    cal.gain_array, cal.flag_array = arr, flags
    cal.quality_array = np.zeros(arr.shape)
    cal.check()
    if path.suffix == ".calfits":
        cal.write_calfits(str(path), clobber=overwrite)
    else:
        cal.write_calh5(str(path), clobber=overwrite)
    log.info("wrote %s: %d antennas, %d channels, %d times", path, nums.size, nf, nt)
    return path


def _widths(freqs_hz) -> np.ndarray:
    """Channel widths (Nf,), Hz: the spacing of the channels (1 MHz for one channel)."""
    f = np.asarray(freqs_hz, float)
    return np.full(f.size, float(np.median(np.diff(f))) if f.size > 1 else 1e6)
