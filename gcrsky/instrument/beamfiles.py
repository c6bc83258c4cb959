"""Beam files as they come: UVBeam files, and primary-beam images in a SIN RA/Dec projection converted to az/za.

:func:`read_beam` is what :func:`gcrsky.instrument.beams.load_beam` does with a path: a file
``UVBeam.from_file`` reads (beamfits, CST, MWA), or a one-plane Stokes I image whose axes are
``RA---SIN`` / ``DEC--SIN`` about the zenith (a CASA/AIPS primary-beam image such as HERA's
``HERABEAM.FITS``), converted by :func:`image_beam`: the image centre is taken as the zenith,
direction cosines ``l`` (east, RA increasing) and ``m`` (north) give ``za = arcsin sqrt(l^2 + m^2)``
and pyuvdata's azimuth ``az = atan2(m, l)`` (east = 0, north = pi/2).  A file pyuvdata cannot read
completely is a ``ValueError`` naming the file and what is needed.  This module imports nothing
of gcrsky's, so both the beam evaluation (:mod:`gcrsky.instrument.beams`) and the preparation
(:mod:`gcrsky.instrument.beamprep`) can use it.
"""

from __future__ import annotations

import logging
import os
import warnings

import numpy as np

__all__ = ["IMAGE_EDGE_MAX", "image_beam", "is_image_beam", "read_beam"]

log = logging.getLogger(__name__)

#: Largest value (relative to the peak) an image beam may have on its border: the beam must be mapped to ~0.
IMAGE_EDGE_MAX = 1e-3


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
    edge = max(np.abs(img[[0, -1], :]).max(), np.abs(img[:, [0, -1]]).max())
    peak = float(np.nanmax(img))
    if not np.isfinite(peak) or peak <= 0 or edge > IMAGE_EDGE_MAX * peak:
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

    A file pyuvdata cannot read completely (e.g. an image without ``data_normalization``)
    is a ``ValueError`` naming the file and what is needed.
    """
    from pyuvdata import UVBeam

    if is_image_beam(path):
        if read_kwargs:
            raise ValueError(f"read options {sorted(read_kwargs)} do not apply to the beam image {path}")
        return image_beam(path), {"file": os.fspath(path), "kind": "SIN RA/Dec image converted to az/za "
                                  "(centre = zenith; Stokes I as both feeds' power)"}
    try:
        beam = UVBeam.from_file(os.fspath(path), **read_kwargs)
    except ValueError as err:
        raise ValueError(f"beam file {path}: pyuvdata cannot read it as a beam ({err}); gcrsky reads beamfits, CST "
                         "and MWA beam files, or a one-plane Stokes I beam image in a SIN projection") from err
    return beam, {"file": os.fspath(path), "kind": f"UVBeam {beam.beam_type}, {beam.pixel_coordinate_system}"}
