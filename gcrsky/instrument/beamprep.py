"""Beams as they come: normalisation, frequencies, image beams and feed orientation checked before use.

:func:`prepare_beam` takes a beam the way a file gives it and returns the beam gcrsky's
response needs, with a JSON-friendly record of what it found and did (copied into a run's
``summary.json`` under ``data_checks["beam"]``):

* **Normalisation.** Visibilities in Jy or K sr assume a peak-normalised power beam,
  ``P_xx(peak) = 1`` (DESIGN section 11).  A UVBeam with ``data_normalization ==
  "physical"`` is in directivity units (the HERA CST E-field peaks at ``|E|^2 = 8243``):
  used as it is it makes the sky ``8243 x`` too faint.  ``normalization="peak"`` (the
  default) divides each channel by its peak power (an E-field beam by its square root,
  one factor for both feeds, so their relative gains stay) and logs the factor;
  ``"physical"`` keeps the file's numbers (and says so).  A beam the file calls
  ``"peak"`` is used as it is (its measured peak is recorded; more than 1 % off 1 is logged).  ``"solid_angle"`` beams are
  refused (pyuvdata cannot convert them either).
* **Frequencies.** A power UVBeam is resampled onto the data's channels *linearly* in
  frequency (weights in [0, 1] of non-negative channels: the power stays >= 0, where
  pyuvdata's default cubic interpolation of a clipped beam overshoots below zero); any
  negative input value is clipped to 0 and counted.  An E-field beam keeps its channels
  (resampling an E-field decoheres its phase); its power is interpolated between them
  where it is evaluated.  A single-frequency beam used at other
  frequencies needs ``freq_scaling``: ``"none"`` (the same pattern at every frequency) or
  ``"lambda"`` (angular size ~ 1/nu: ``P_nu(za) = P_nu0(arcsin(sin(za) nu / nu0))``, an
  aperture's pattern as a function of ``sin(za) D / lambda``; zero where the argument
  passes the horizon).
* **Values.** A beam whose tabulated values cannot be a beam is refused when it is read,
  naming the file and the problem (:func:`gcrsky.instrument.beamfiles.check_beam_values`):
  NaN or infinite values, a channel whose power is nowhere positive, power below
  ``-NEGATIVE_POWER_TOL`` (1 %) of its channel's peak or negative at more than
  ``NEGATIVE_POWER_MAX_FRACTION`` (5 %) of the values; shallower, rarer negative power in a
  file (its maker's interpolant ringing) is clipped to 0 and logged.
* **Interpolated power stays >= 0.**  The power is interpolated with pyuvdata's cubic
  spline in direction (``az_za_map_coordinates``, matvis' choice; cubic in frequency
  between four or more E-field channels), which rings slightly below 0 next to nulls
  (matvis' HERA dipole beam from 100.8 to 101 MHz, next to a null at az 90 deg, za 17.3
  deg: down to 1.1e-5 of the peak); those values are clipped to 0 where the power is evaluated
  (:func:`gcrsky.instrument.beams.clip_power`), so the power equals the spline wherever
  the spline is >= 0.  The first clipping of each beam in a process is logged as a
  warning (the fraction clipped and its depth relative to the peak), later ones at debug
  level unless deeper than ``NEGATIVE_POWER_TOL`` of the peak.  Clipping was chosen over
  interpolants that cannot go negative because it is the most faithful of those that
  interpolate the power: leaving every other row of the dipole's 2-degree grid out and
  interpolating it from the rest, the error where ``P < 1e-2`` (rms, relative) is 11 % for
  the clipped cubic, 44 % for ``sqrt(P)`` interpolated cubically and squared, 68 % for
  ``log P``, 108 % for linear; everywhere (rms, of the peak) 1.8e-3, 1.6e-3, 3.9e-3,
  8.2e-3.  Interpolating an E-field beam's field and forming ``|E|^2`` was better still
  (0.5 %, 1.5e-3), but the response interpolates power in direction as matvis'
  unpolarised mode does (DESIGN section 9), and clipping keeps that.
* **Image beams.** A FITS image of the beam in an orthographic (``SIN``) RA/Dec projection
  about the zenith (a CASA/AIPS primary-beam image such as ``HERABEAM.FITS``) is converted
  to a zenith-centred az/za power beam (:func:`image_beam`): direction cosines about the
  image centre ``l`` (east), ``m`` (north), ``za = arcsin(sqrt(l^2 + m^2))`` and
  pyuvdata's azimuth (North of East: ``az = arctan2(m, l)``, Az(E) = 0, Az(N) = pi/2).
  The image's Stokes I is taken as the power of both feeds (an unpolarised, peak-1
  pattern).  Images in other projections, not centred on the zenith, or not falling to
  zero inside the image are refused with what is needed.
* **Feed orientation.** The beam's feed x (``get_x_orientation_from_feeds``, pyuvdata's
  ``feed_angle``; no deprecated attribute) must point where the file's does; a mismatch is
  a ``ValueError`` unless ``accept_x_orientation_mismatch``.  Azimuthally symmetric
  analytic beams (Gaussian, Airy, uniform) need no check.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from .beamfiles import check_beam_values, image_beam, is_image_beam, read_beam, same_feed_pols
from .beams import FREQ_TOL_HZ, beam_name, check_beam_frequencies

__all__ = [
    "BEAM_NORMALIZATIONS",
    "FREQ_SCALINGS",
    "beam_x_orientation",
    "check_x_orientation",
    "image_beam",
    "is_image_beam",
    "normalize_beam",
    "prepare_beam",
    "read_beam",
    "resample_beam",
]

log = logging.getLogger(__name__)

#: What :func:`prepare_beam` can make of a beam's amplitude.
BEAM_NORMALIZATIONS = ("peak", "physical")
#: How a single-frequency beam is used at other frequencies.
FREQ_SCALINGS = ("none", "lambda")
#: Analytic beams whose power is azimuthally symmetric: the feed orientation does not change it.
_SYMMETRIC = ("GaussianBeam", "AiryBeam", "UniformBeam")
#: How far from 1 the peak power of a beam labelled "peak" may be without a warning.
PEAK_TOL = 0.01


# ---------------------------------------------------------------- normalisation


def _peak_power(uvb) -> np.ndarray:
    """(Nfreqs,) the largest same-feed power of a UVBeam per channel (E-field: sum over vector components)."""
    d = np.asarray(uvb.data_array)
    if uvb.beam_type == "efield":
        p = np.sum(np.abs(d) ** 2, axis=0)  # (Nfeeds, Nfreqs, ...)
        return np.max(p.reshape(p.shape[0], p.shape[1], -1), axis=(0, 2))
    same = _same_feed_pols(uvb)
    if not same:
        raise ValueError(f"power beam {beam_name(uvb)} has no same-feed polarisation (xx, yy, pI, ...) to normalise by")
    p = np.abs(d[:, same]).reshape(d.shape[0], len(same), d.shape[2], -1)
    return np.max(p, axis=(0, 1, 3))


_same_feed_pols = same_feed_pols


def normalize_beam(uvb, normalization: str = "peak"):
    """``(beam, record)``: a UVBeam brought to ``normalization`` (module docstring), on a copy when changed.

    Args:
        uvb: an E-field or power ``UVBeam``.
        normalization: ``"peak"`` (a ``"physical"`` beam divided by its peak power per
            channel; a ``"peak"`` beam kept) or ``"physical"`` (as it is).

    Returns:
        The beam and ``{"normalization_found", "normalization_used", "peak_power_found"}``
        (peak power per channel before any change; a list when channels differ).

    Raises:
        ValueError: an unknown ``normalization``; a ``"solid_angle"`` beam.
    """
    if normalization not in BEAM_NORMALIZATIONS:
        raise ValueError(f"beam normalization must be one of {BEAM_NORMALIZATIONS}, got {normalization!r}")
    found = uvb.data_normalization
    if found == "solid_angle":
        raise ValueError(f"beam {beam_name(uvb)} is solid-angle normalised: convert it to a peak-normalised beam "
                         "first (pyuvdata cannot); gcrsky needs peak normalisation (or physical, kept as it is)")
    peak = _peak_power(uvb)
    rec = {"normalization_found": found, "normalization_used": normalization,
           "peak_power_found": _compact(peak)}
    if normalization == "physical":
        if found != "peak" or np.any(np.abs(peak - 1) > 1e-3):
            log.warning("beam %s used with its file's amplitude (peak power %s): the sky scales as 1 / that",
                        beam_name(uvb), rec["peak_power_found"])
        return uvb, rec
    if found == "peak":  # the file's own peak normalisation is kept (a CST beam's is ~1e-4 off 1 on its grid)
        if np.any(np.abs(peak - 1) > PEAK_TOL):
            log.warning("beam %s says it is peak-normalised but its peak power is %s", beam_name(uvb), rec["peak_power_found"])
        return uvb, rec
    if not np.all(peak > 0):
        raise ValueError(f"beam {beam_name(uvb)} is zero on some channel: cannot peak-normalise it")
    out = uvb.copy()
    scale = np.sqrt(peak) if uvb.beam_type == "efield" else peak
    out.data_array = out.data_array / scale.reshape((1, 1, -1) + (1,) * (out.data_array.ndim - 3))
    out.bandpass_array = np.asarray(out.bandpass_array) * scale
    out.data_normalization = "peak"
    log.info("beam %s (%s) peak-normalised: divided the power by %s", beam_name(uvb), found, rec["peak_power_found"])
    return out, rec


def _compact(x: np.ndarray):
    """A float when all entries agree to 1e-9, else a list (for the record)."""
    x = np.atleast_1d(np.asarray(x, np.float64))
    return float(x[0]) if np.allclose(x, x[0], rtol=1e-9, atol=0) else [float(v) for v in x]


# ---------------------------------------------------------------- frequencies


def resample_beam(uvb, freqs_hz, freq_scaling: str | None = None):
    """``(beam, record)``: a UVBeam made usable at ``freqs_hz`` without negative power (module docstring).

    Args:
        uvb: an E-field or power ``UVBeam``.
        freqs_hz: (Nf,) the data's frequencies, Hz.
        freq_scaling: for a single-frequency beam used at other frequencies: ``"none"`` or
            ``"lambda"``; ignored (and recorded so) for a beam with several channels.

    Raises:
        ValueError: a single-frequency beam without ``freq_scaling``; an unknown scaling;
            frequencies outside a multi-channel beam's range.
    """
    f = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    ch = np.asarray(uvb.freq_array, np.float64).ravel()
    if freq_scaling is not None and freq_scaling not in FREQ_SCALINGS:
        raise ValueError(f"beam freq_scaling must be one of {FREQ_SCALINGS}, got {freq_scaling!r}")
    if ch.size == 1:
        if np.all(np.abs(f - ch[0]) <= FREQ_TOL_HZ):
            return uvb, {"frequency": f"single channel {ch[0] / 1e6:.6g} MHz, the data's"}
        if freq_scaling is None:
            raise ValueError(f"beam {beam_name(uvb)} has one frequency ({ch[0] / 1e6:.6g} MHz) and the data "
                             f"{f.min() / 1e6:.6g}-{f.max() / 1e6:.6g} MHz: say how it scales, freq_scaling='none' "
                             "(the same pattern at every frequency) or 'lambda' (angular size ~ 1/nu) "
                             "(--beam-freq-scaling none|lambda)")
        return _scale_single(uvb, f, freq_scaling)
    check_beam_frequencies(uvb, f)
    note = "" if freq_scaling is None else f"; freq_scaling {freq_scaling!r} ignored (the beam has {ch.size} channels)"
    if uvb.beam_type == "efield":
        kind = "cubically" if ch.size >= 4 else "linearly"
        return uvb, {"frequency": f"{ch.size} E-field channels; power interpolated {kind} between them where "
                     f"evaluated, undershoot below 0 clipped{note}"}
    out = uvb.interp(freq_array=np.clip(f, ch.min(), ch.max()), freq_interp_kind="linear", new_object=True)
    n_neg = _clip_negative(out)
    return out, {"frequency": f"{ch.size} channels, power resampled linearly onto the data's {f.size} (stays >= 0)"
                 f"{note}", "negative_power_clipped": n_neg}


def _clip_negative(uvb) -> int:
    """Clip the negative same-feed power of a power UVBeam to 0 in place; the number clipped (logged)."""
    d = np.array(uvb.data_array)
    same = _same_feed_pols(uvb)
    neg = np.zeros(d.shape, bool)
    neg[:, same] = np.real(d[:, same]) < 0
    n = int(neg.sum())
    if n:
        log.warning("beam %s: %d negative power values clipped to 0", beam_name(uvb), n)
        d[neg] = 0.0
        uvb.data_array = d
    return n


def _scale_single(uvb, f: np.ndarray, scaling: str):
    """A single-channel UVBeam on the channels ``f``: the same pattern (``"none"``) or scaled as 1/nu."""
    nu0 = float(np.asarray(uvb.freq_array).ravel()[0])
    d = np.asarray(uvb.data_array)
    if scaling == "none":
        data = np.repeat(d, f.size, axis=2)
    else:
        if uvb.pixel_coordinate_system != "az_za":
            raise ValueError(f"beam {beam_name(uvb)}: freq_scaling 'lambda' needs an az/za beam, this one is "
                             f"{uvb.pixel_coordinate_system!r} (use 'none', or give a beam with several channels)")
        data = np.concatenate([_lambda_plane(uvb, nu0, nu) for nu in f], axis=2)
    out = uvb.copy()
    out.freq_array = f.copy()
    out.Nfreqs = f.size
    out.bandpass_array = np.ones(f.size)
    out.data_array = data
    note = ("the same pattern at every frequency" if scaling == "none"
            else "angular size ~ 1/nu: P(za) = P0(arcsin(sin(za) nu / nu0))")
    return out, {"frequency": f"single channel {nu0 / 1e6:.6g} MHz used at {f.min() / 1e6:.6g}-{f.max() / 1e6:.6g} "
                 f"MHz, freq_scaling {scaling!r}: {note}", "freq_scaling": scaling}


def _lambda_plane(uvb, nu0: float, nu: float) -> np.ndarray:
    """(Naxes_vec, Npols/Nfeeds, 1, Nza, Naz) the beam's pattern at ``nu`` from its one channel at ``nu0``."""
    az = np.asarray(uvb.axis1_array, np.float64)
    za = np.asarray(uvb.axis2_array, np.float64)
    azg, zag = np.meshgrid(az, za)  # (Nza, Naz)
    s = np.sin(zag) * nu / nu0
    inside = (s <= 1.0) & (zag <= np.pi / 2 + 1e-12)
    za_src = np.where(inside, np.arcsin(np.clip(s, 0.0, 1.0)), 0.0)
    za_src = np.minimum(za_src, za.max())
    vals = uvb.interp(az_array=azg.ravel(), za_array=za_src.ravel(), interpolation_function="az_za_map_coordinates",
                      spline_opts={"order": 1}, check_azza_domain=False)[0]
    vals = np.asarray(vals).reshape(vals.shape[:2] + (1,) + azg.shape)
    return np.where(inside, vals, 0.0).astype(uvb.data_array.dtype)


# ---------------------------------------------------------------- feed orientation


def beam_x_orientation(beam) -> str | None:
    """Where a beam's feed x points (``"east"``, ``"north"`` or None), from pyuvdata's feed angles."""
    from pyuvdata import BeamInterface

    obj = beam.beam if isinstance(beam, BeamInterface) else beam
    get = getattr(obj, "get_x_orientation_from_feeds", None)
    if get is None or getattr(obj, "feed_array", None) is None:
        return None
    return get()


def _same_feed_patterns(beam) -> bool:
    """A power UVBeam whose xx and yy are the same pattern (and holds no cross products): rotating its feeds by
    90 deg changes nothing (a Stokes-I image converted by :func:`gcrsky.instrument.beamfiles.image_beam`)."""
    if type(beam).__name__ != "UVBeam" or getattr(beam, "beam_type", None) != "power":
        return False
    arr = getattr(beam, "polarization_array", None)
    pols = [] if arr is None else [int(p) for p in np.atleast_1d(arr)]
    if sorted(pols) not in ([-6, -5], [-8, -7]):
        return False
    d = np.asarray(beam.data_array)
    return bool(np.array_equal(d[:, pols.index(max(pols))], d[:, pols.index(min(pols))]))


def check_x_orientation(beam, file_x_orientation: str | None, *, accept_mismatch: bool = False) -> dict:
    """The feed-orientation record; ``ValueError`` when the beam's feed x and the file's differ.

    Args:
        beam: a pyuvdata beam object.
        file_x_orientation: the visibility file's (``Observation.x_orientation``).
        accept_mismatch: log a warning instead of raising.
    """
    if type(beam).__name__ in _SYMMETRIC:
        return {"x_orientation": {"file": file_x_orientation, "beam": None,
                                  "check": f"not needed ({type(beam).__name__} is azimuthally symmetric)"}}
    bx = beam_x_orientation(beam)
    rec = {"file": file_x_orientation, "beam": bx}
    if _same_feed_patterns(beam):
        rec["check"] = "not needed (the beam's xx and yy are one pattern, e.g. a Stokes-I image: no feed orientation)"
        return {"x_orientation": rec}
    if bx is None or file_x_orientation is None:
        rec["check"] = "not possible (unknown on one side)"
        log.warning("x_orientation: file %s, beam %s: cannot check that the feeds agree", file_x_orientation, bx)
    elif bx == file_x_orientation:
        rec["check"] = "agree"
    elif accept_mismatch:
        rec["check"] = "MISMATCH accepted"
        log.warning("x_orientation: the file's feed x points %s, the beam's %s (accepted)", file_x_orientation, bx)
    else:
        raise ValueError(f"the file's feed x points {file_x_orientation}, the beam's {beam_name(beam)} {bx}: the beam's "
                         "feeds must be the file's (give the matching beam, or accept_x_orientation_mismatch="
                         "True / --accept-x-orientation-mismatch if you know the pattern is symmetric)")
    return {"x_orientation": rec}


# ---------------------------------------------------------------- all together


def prepare_beam(beam, freqs_hz, *, normalization: str = "peak", freq_scaling: str | None = None,
                 x_orientation: str | None = None, accept_x_orientation_mismatch: bool = False,
                 **read_kwargs):
    """``(beam, record)``: a beam as it comes, made ready for the response (module docstring).

    Args:
        beam: a beam file path (UVBeam file or SIN beam image) or a pyuvdata beam object.
        freqs_hz: (Nf,) the data's frequencies, Hz.
        normalization: ``"peak"`` (default; physical beams are peak-normalised, logged) or
            ``"physical"`` (kept as the file has it).
        freq_scaling: ``None``, ``"none"`` or ``"lambda"`` (single-frequency beams only).
        x_orientation: the visibility file's (compared with the beam's).
        accept_x_orientation_mismatch: a mismatch is logged, not an error.
        **read_kwargs: passed to ``UVBeam.from_file`` for a file.

    Returns:
        The beam and a JSON-friendly record: ``file``, ``kind``, ``normalization_found``,
        ``normalization_used``, ``peak_power_found``, ``frequency``, ``x_orientation``, ...
    """
    from pyuvdata import BeamInterface, UVBeam

    if normalization not in BEAM_NORMALIZATIONS:
        raise ValueError(f"beam normalization must be one of {BEAM_NORMALIZATIONS}, got {normalization!r}")
    if freq_scaling is not None and freq_scaling not in FREQ_SCALINGS:
        raise ValueError(f"beam freq_scaling must be one of {FREQ_SCALINGS}, got {freq_scaling!r}")
    if isinstance(beam, (str, os.PathLike)):
        beam, rec = read_beam(beam, **read_kwargs)
    else:
        rec = {"file": None, "kind": beam_name(beam.beam if isinstance(beam, BeamInterface) else beam)}
    obj = beam.beam if isinstance(beam, BeamInterface) else beam
    if isinstance(obj, UVBeam):
        if obj.beam_type not in ("efield", "power"):
            raise ValueError(f"UVBeam of beam_type {obj.beam_type!r}: gcrsky needs an E-field or a power beam")
        obj, r = check_beam_values(obj, f"beam file {rec['file']}" if rec["file"] else f"beam {beam_name(obj)}")
        rec.update(r)
        obj, r = normalize_beam(obj, normalization)
        rec.update(r)
        obj, r = resample_beam(obj, freqs_hz, freq_scaling)
        rec.update(r)
        beam = obj
    else:
        rec.update({"normalization_found": "analytic", "normalization_used": "analytic (peak 1)",
                    "frequency": "analytic"})
    rec.update(check_x_orientation(beam, x_orientation, accept_mismatch=accept_x_orientation_mismatch))
    return beam, rec
