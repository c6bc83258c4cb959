"""Beam files as they come: UVBeam files, and primary-beam images in a SIN RA/Dec projection converted to az/za.

:func:`read_beam` is what :func:`gcrsky.instrument.beams.load_beam` does with a path: a file
``UVBeam.from_file`` reads (beamfits, CST, MWA), or a one-plane Stokes I image whose axes are
``RA---SIN`` / ``DEC--SIN`` about the zenith (a CASA/AIPS primary-beam image such as HERA's
``HERABEAM.FITS``), converted by :func:`image_beam`: the image centre is taken as the zenith,
direction cosines ``l`` (east, RA increasing) and ``m`` (north) give ``za = arcsin sqrt(l^2 + m^2)``
and pyuvdata's azimuth ``az = atan2(m, l)`` (east = 0, north = pi/2).  A file pyuvdata cannot read
completely, or whose values cannot be a beam (:func:`check_beam_values`: NaN or infinite values, a
channel whose power is nowhere positive, power more negative than :data:`NEGATIVE_POWER_TOL` of
its peak or negative at more than :data:`NEGATIVE_POWER_MAX_FRACTION` of its values), is a
``ValueError`` naming the file and the problem, when it is read: before any response is built or
draw made.  This module imports nothing
of gcrsky's, so both the beam evaluation (:mod:`gcrsky.instrument.beams`) and the preparation
(:mod:`gcrsky.instrument.beamprep`) can use it.
"""

from __future__ import annotations

import logging
import os
import warnings

import numpy as np

__all__ = [
    "IMAGE_EDGE_MAX",
    "NEGATIVE_POWER_MAX_FRACTION",
    "NEGATIVE_POWER_TOL",
    "check_beam_values",
    "image_beam",
    "is_image_beam",
    "read_beam",
    "same_feed_pols",
]

log = logging.getLogger(__name__)

#: Largest value (relative to the peak) an image beam may have on its border: the beam must be mapped to ~0.
IMAGE_EDGE_MAX = 1e-3
#: Negative power (relative to its channel's peak) that is taken for a cubic interpolant's ringing next to a
#: null and clipped to 0 (logged); deeper is refused in a file (:func:`check_beam_values`) and logged as a
#: warning where an interpolated power is clipped (:func:`gcrsky.instrument.beams.clip_power`).
NEGATIVE_POWER_TOL = 0.01
#: Largest fraction of a file's same-feed power values that may be (shallowly) negative: ringing is confined to
#: the neighbourhood of nulls and clipped edges; more is a sign error or not a power pattern.
NEGATIVE_POWER_MAX_FRACTION = 0.05


def is_image_beam(path) -> bool:
    """Whether ``path`` is a FITS image with celestial axes (``RA---``/``DEC--``): a primary-beam image."""
    if not str(path).lower().endswith((".fits", ".fit", ".fts")):
        return False
    from astropy.io import fits

    try:
        hdr = fits.getheader(os.fspath(path), 0)
    except OSError:
        return False
    ctypes = [str(hdr.get(f"CTYPE{i}", "")) for i in range(1, int(hdr.get("NAXIS", 0)) + 1)]
    return any(c.startswith("RA--") for c in ctypes) and any(c.startswith("DEC-") for c in ctypes)


def _image_plane(path):
    """``(image (Ny, Nx), celestial WCS, frequency Hz, header)`` of a one-plane Stokes I beam image."""
    from astropy.io import fits
    from astropy.wcs import WCS

    with fits.open(os.fspath(path)) as hdul:
        hdr = hdul[0].header
        data = np.asarray(hdul[0].data, np.float64)
    with warnings.catch_warnings():  # astropy's notes on fixing old AIPS/CASA headers (DATE-OBS -> MJD-OBS)
        warnings.simplefilter("ignore", category=Warning)
        w = WCS(hdr)
    cel = w.celestial
    proj = [c[-3:] for c in cel.wcs.ctype]
    if proj != ["SIN", "SIN"]:
        raise ValueError(f"{path}: a beam image must be in the orthographic (SIN) projection about the zenith; got "
                         f"{list(cel.wcs.ctype)}: reproject it, or give an az/za beam file UVBeam reads")
    if any(v != 0 for *_, v in cel.wcs.get_pv()):
        raise ValueError(f"{path}: a SIN projection with non-zero PV terms (a slant) is not an image about the "
                         "zenith: give an az/za beam file UVBeam reads")
    freq = None
    stokes = 1
    for i, ct in enumerate(w.wcs.ctype):
        ax = w.naxis - 1 - i  # numpy axis of WCS axis i
        if ct.startswith("FREQ"):
            if data.shape[ax] != 1:
                raise ValueError(f"{path}: {data.shape[ax]} frequency planes; gcrsky reads one-plane beam images")
            freq = float(w.wcs.crval[i] + (1 - w.wcs.crpix[i]) * w.wcs.cdelt[i])
        if ct.startswith("STOKES"):
            stokes = int(round(w.wcs.crval[i] + (1 - w.wcs.crpix[i]) * w.wcs.cdelt[i]))
    if stokes != 1 or data.squeeze().ndim != 2:
        raise ValueError(f"{path}: a beam image must be one Stokes I plane (got Stokes {stokes}, shape "
                         f"{data.shape})")
    if freq is None:
        raise ValueError(f"{path}: the image has no FREQ axis: gcrsky needs the beam's frequency")
    return data.squeeze(), cel, freq, hdr


def _lm_to_radec(l, m, ra0, dec0):
    """RA, Dec (rad) of direction cosines ``l`` (east), ``m`` (north) about ``(ra0, dec0)`` (rad)."""
    n = np.sqrt(np.clip(1.0 - l**2 - m**2, 0.0, None))
    dec = np.arcsin(np.clip(m * np.cos(dec0) + n * np.sin(dec0), -1, 1))
    ra = ra0 + np.arctan2(l, n * np.cos(dec0) - m * np.sin(dec0))
    return ra, dec


def image_beam(path, *, n_za: int = 181, n_az: int = 361):
    """A zenith-centred az/za power UVBeam from a SIN-projected primary-beam image (module docstring).

    The image's centre (``CRVAL``) is taken as the zenith (the image of a zenith-pointed
    dish at one time); each az/za grid point's direction cosines ``l = sin(za) cos(az)``
    (east), ``m = sin(za) sin(az)`` (north) are mapped to RA/Dec about it and to the
    image's pixels by its WCS, and the image is interpolated bilinearly (non-negative).
    Outside the image the beam is 0: the image must fall to 0 inside it.

    Args:
        path: the FITS image (one frequency plane, Stokes I, ``RA---SIN``/``DEC--SIN``).
        n_za, n_az: grid points over za in [0, 90] deg and az in [0, 360] deg.

    Returns:
        A power ``UVBeam`` (pols xx and yy, both the image; peak-normalised; feed x east),
        with ``extra_keywords`` naming the image.

    Raises:
        ValueError: another projection, several planes or Stokes, no frequency, an image
            that does not fall to 0 at its border (with what is needed instead).
    """
    from astropy.coordinates import SkyCoord
    from pyuvdata import UVBeam
    from scipy import ndimage

    img, cel, freq, hdr = _image_plane(path)
    finite = np.isfinite(img)
    peak = float(np.max(img[finite])) if finite.any() else float("nan")
    if not peak > 0:  # all NaN (blanked), all zero or all negative: no beam in it
        raise ValueError(f"beam image {path}: no positive value ({int(finite.sum())} finite pixels of {img.size}, "
                         f"largest {peak:.3g}): it holds no beam pattern")
    edge = max(np.nanmax(np.abs(img[[0, -1], :])), np.nanmax(np.abs(img[:, [0, -1]])))
    if edge > IMAGE_EDGE_MAX * peak:
        raise ValueError(f"{path}: the beam image reaches {edge / peak:.3g} of its peak at its border: it must map the "
                         "beam until it falls to 0 (or give an az/za beam file UVBeam reads, to the horizon)")
    ra0, dec0 = np.deg2rad(cel.wcs.crval)
    az = np.linspace(0, 2 * np.pi, n_az)
    za = np.linspace(0, np.pi / 2, n_za)
    azg, zag = np.meshgrid(az, za)
    ra, dec = _lm_to_radec(np.sin(zag) * np.cos(azg), np.sin(zag) * np.sin(azg), ra0, dec0)
    x, y = cel.world_to_pixel(SkyCoord(ra, dec, unit="rad", frame=cel.wcs.radesys.lower() or "icrs"))
    vals = ndimage.map_coordinates(np.nan_to_num(img) / peak, [y.ravel(), x.ravel()], order=1, cval=0.0)
    vals = np.clip(vals, 0.0, None).reshape(zag.shape)
    data = np.stack([vals, vals])[None, :, None]  # (1, 2 pols, 1 freq, Nza, Naz)
    beam = UVBeam.new(telescope_name=str(hdr.get("TELESCOP", "unknown")).strip() or "unknown",
                      data_normalization="peak", freq_array=np.array([freq]), beam_type="power",
                      polarization_array=np.array([-5, -6]), x_orientation="east",
                      axis1_array=az, axis2_array=za, data_array=data,
                      model_name=os.path.basename(os.fspath(path)),
                      history=f"gcrsky: az/za power beam from the SIN image {os.fspath(path)}")
    log.info("beam image %s (%.6g MHz) converted to an az/za power beam (centre RA %.4f, Dec %.4f deg as the zenith)",
             path, freq / 1e6, *np.rad2deg([ra0, dec0]))
    return beam


def read_beam(path, **read_kwargs):
    """``(beam, record)`` from a beam file: a UVBeam file (``UVBeam.from_file``) or a SIN beam image.

    A file pyuvdata cannot read completely (e.g. an image without ``data_normalization``),
    or not at all (not FITS, another format), is a ``ValueError`` naming the file and what
    is needed; so is a UVBeam whose values cannot be a beam (:func:`check_beam_values`,
    whose record the returned one includes).  A missing file is a ``FileNotFoundError``.
    """
    from pyuvdata import UVBeam

    if is_image_beam(path):
        if read_kwargs:
            raise ValueError(f"read options {sorted(read_kwargs)} do not apply to the beam image {path}")
        return image_beam(path), {"file": os.fspath(path), "kind": "SIN RA/Dec image converted to az/za "
                                  "(centre = zenith; Stokes I as both feeds' power)"}
    if not os.path.exists(os.fspath(path)):
        raise FileNotFoundError(f"beam file {path}: no such file")
    try:
        beam = UVBeam.from_file(os.fspath(path), **read_kwargs)
    except (ValueError, OSError, KeyError, IndexError, NotImplementedError) as err:  # not a beam file pyuvdata reads
        raise ValueError(f"beam file {path}: pyuvdata cannot read it as a beam ({type(err).__name__}: {err}); gcrsky "
                         "reads beamfits, CST and MWA beam files, or a one-plane Stokes I beam image in a SIN "
                         "projection") from err
    if beam.beam_type not in ("efield", "power"):
        raise ValueError(f"beam file {path}: a UVBeam of beam_type {beam.beam_type!r}; gcrsky needs an E-field or a "
                         "power beam")
    beam, values = check_beam_values(beam, f"beam file {path}", copy=False)
    return beam, {"file": os.fspath(path), "kind": f"UVBeam {beam.beam_type}, {beam.pixel_coordinate_system}",
                  **values}


def same_feed_pols(uvb) -> list[int]:
    """Indices of a power UVBeam's same-feed polarisations (xx, yy, ..., and Stokes, which are real powers)."""
    from pyuvdata.utils.pol import polnum2str

    return [k for k, p in enumerate(np.asarray(uvb.polarization_array))
            if int(p) > 0 or len(set(str(polnum2str(int(p))).lower())) == 1]


def _channel_list(freqs_hz, mask) -> str:
    f = np.asarray(freqs_hz, np.float64).ravel()[np.asarray(mask)]
    shown = ", ".join(f"{x / 1e6:.6g}" for x in f[:6]) + (", ..." if f.size > 6 else "")
    return f"{f.size} channel{'s' if f.size != 1 else ''} ({shown} MHz)"


def check_beam_values(uvb, label: str, *, copy: bool = True):
    """``(beam, record)``: a UVBeam's tabulated values checked before it is used; refused with the problem named.

    The checks, on the file's own values (before any interpolation):

    * every value finite: a NaN or infinity propagates through any interpolant (a spline
      spreads it over its neighbours) into the response and the beam's FWHM;
    * the power (E-field: ``|E|^2`` summed over its components, per feed; power beam: its
      same-feed polarisations, real part) positive somewhere on every channel: an all-zero
      channel is no beam (it cannot be peak-normalised, and its FWHM is undefined);
    * no power below ``-NEGATIVE_POWER_TOL`` x its channel's peak, and at most
      ``NEGATIVE_POWER_MAX_FRACTION`` of the power values negative: power is never negative;
      shallow negative values here and there are the ringing of the interpolant the file was
      made with (next to a null or a clipped edge) and are clipped to 0 (logged, with how
      many and how deep); deeper or widespread ones are a sign error or not a power
      pattern, and are refused.

    Args:
        uvb: an E-field or power ``UVBeam``.
        label: how messages name it (e.g. ``"beam file PATH"``).
        copy: clip on a copy (the caller's object is left as it is); False: in place.

    Returns:
        The beam (clipped where it had shallow negative power) and
        ``{"values": ..., "negative_power_clipped": {count, fraction, min_relative_to_peak}}``
        (the latter only when something was clipped).

    Raises:
        ValueError: NaN or infinite values; a channel with no positive power; power more
            negative than ``NEGATIVE_POWER_TOL`` of its channel's peak; a power beam without
            a same-feed polarisation.
    """
    d = np.asarray(uvb.data_array)
    freqs = np.asarray(uvb.freq_array, np.float64).ravel()
    bad = ~np.isfinite(d)
    if bad.any():
        chans = bad.reshape(d.shape[0] * d.shape[1], d.shape[2], -1).any(axis=(0, 2))
        raise ValueError(f"{label}: {int(bad.sum())} of {d.size} beam values are NaN or infinite, on "
                         f"{_channel_list(freqs, chans)}: a beam cannot be interpolated through them (give a beam "
                         "without them, or select the good channels: UVBeam.select(frequencies=...))")
    if uvb.beam_type == "efield":
        power = np.sum(np.abs(d) ** 2, axis=0)  # (Nfeeds, Nfreqs, ...)
        same = None
    else:
        same = same_feed_pols(uvb)
        if not same:
            raise ValueError(f"{label}: a power beam with no same-feed polarisation (xx, yy, pI, ...): gcrsky needs "
                             "each feed's power")
        power = np.real(d[:, same]).reshape((-1,) + d.shape[2:])  # (Naxes_vec x Nsame, Nfreqs, ...)
    per_chan = np.moveaxis(power, 1, 0).reshape(power.shape[1], -1)  # (Nfreqs, everything else)
    peak, low = per_chan.max(axis=1), per_chan.min(axis=1)
    if not np.all(peak > 0):
        what = "zero everywhere" if np.all(per_chan[peak <= 0] == 0) else "nowhere positive"
        raise ValueError(f"{label}: its power is {what} on {_channel_list(freqs, peak <= 0)} (largest "
                         f"{float(np.min(peak)):.3g}, smallest {float(np.min(low)):.3g}): that is no beam pattern")
    depth = -low / peak
    if np.any(depth > NEGATIVE_POWER_TOL):
        deep = depth > NEGATIVE_POWER_TOL
        raise ValueError(f"{label}: its power is negative, down to {-float(depth.max()):.3g} of the peak on "
                         f"{_channel_list(freqs, deep)} ({int((per_chan < 0).sum())} values): power is never negative; "
                         f"an interpolant's ringing next to a null stays within {NEGATIVE_POWER_TOL:g} of the peak, "
                         "this is a sign error or not a power pattern: fix the file")
    neg = per_chan < 0
    if neg.mean() > NEGATIVE_POWER_MAX_FRACTION:
        raise ValueError(f"{label}: {100 * neg.mean():.3g} % of its power values are negative (down to "
                         f"{-float(depth.max()):.3g} of the peak): power is never negative, and an interpolant's "
                         f"ringing next to nulls makes at most a few ({100 * NEGATIVE_POWER_MAX_FRACTION:g} % here): "
                         "a sign error or not a power pattern: fix the file")
    rec = {"values": f"finite; power positive on all {freqs.size} channels"}
    if neg.any():  # power beams only (|E|^2 >= 0): shallow ringing in the file, clipped
        n = int(neg.sum())
        rec["negative_power_clipped"] = {"count": n, "fraction": n / neg.size,
                                         "min_relative_to_peak": -float(depth.max())}
        log.warning("%s: %d tabulated power values below 0 (%.3g %% of them, down to %.3g of the peak: an "
                    "interpolant's ringing) clipped to 0", label, n, 100 * n / neg.size, -float(depth.max()))
        out = uvb.copy() if copy else uvb
        data = np.array(out.data_array)
        sub = data[:, same]
        sub.real[sub.real < 0] = 0.0
        data[:, same] = sub
        out.data_array = data
        uvb = out
    return uvb, rec
