"""pyradiosky ``SkyModel`` products: HEALPix maps as a ``skyh5`` file.

The model has ``component_type="healpix"``, every pixel of a RING-ordered full-sky
map (``hpx_inds = arange(12 nside^2)``), ``spectral_type="full"`` with
``freq_array`` the run's channels (Hz), Stokes I in kelvin (Q = U = V = 0) and,
optionally, a per-pixel standard deviation as ``stokes_error``.  pyradiosky knows
astropy frames only: runs at real observing times are in ``"icrs"`` (exactly);
for the paper's idealised LSTs the coefficients live in the idealised co-rotating
equatorial frame, which has no astropy name; it is written as ``"icrs"`` (the frame
its simulated truth comes from, and the nearest astropy frame) and the file's
``history`` says so.  ``SkyModel.from_file(path)`` reads the file back equal.

pyradiosky is the ``[sim]`` extra, imported when a file is written.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .atomic import atomic_path

__all__ = ["FRAME_NOTES", "healpix_skymodel", "write_skyh5"]

#: What the ``frame`` argument means, as written into the model's history.
FRAME_NOTES = {
    "icrs": "Frame: ICRS (the sky coefficients of a run at real observing times are ICRS).",
    "idealised": (
        "Frame: the idealised co-rotating equatorial frame of the paper's idealised LSTs (the sky rotates "
        "rigidly about its pole; no precession, nutation or aberration). pyradiosky has no name for it; it is "
        "labelled 'icrs', the nearest astropy frame and the frame of the simulated truth it was read from."
    ),
}


def _require_pyradiosky():
    from ..base.extras import require

    return require("pyradiosky", "sim", "the SkyModel (skyh5) product")


def healpix_skymodel(maps, freqs_hz, *, frame: str, history: str = "", std_maps=None):
    """A pyradiosky ``SkyModel`` of HEALPix RING maps (Stokes I, kelvin, full spectral type).

    Args:
        maps: ``(Nf, 12 nside^2)`` Stokes I maps, RING, kelvin.
        freqs_hz: ``(Nf,)`` channel frequencies, Hz (``freq_array``).
        frame: ``"icrs"`` or ``"idealised"`` (:data:`FRAME_NOTES`; both are labelled ``"icrs"``).
        history: text for the model's history (the frame note is appended).
        std_maps: optional ``(Nf, 12 nside^2)`` per-pixel standard deviations, kelvin
            (``stokes_error`` of Stokes I); left out when not all finite.

    Returns:
        ``pyradiosky.SkyModel``.
    """
    _require_pyradiosky()
    import astropy.units as u
    import healpy as hp
    from pyradiosky import SkyModel

    if frame not in FRAME_NOTES:
        raise ValueError(f"frame must be one of {sorted(FRAME_NOTES)}, got {frame!r}")
    maps = np.asarray(maps, np.float64)
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    if maps.ndim != 2 or maps.shape[0] != freqs.size:
        raise ValueError(f"maps must be (Nf, Npix) with Nf = {freqs.size} channels, got shape {maps.shape}")
    npix = maps.shape[1]
    nside = hp.npix2nside(npix)
    stokes = np.zeros((4, freqs.size, npix))
    stokes[0] = maps
    kw = {}
    if std_maps is not None:
        std = np.asarray(std_maps, np.float64)
        if std.shape != maps.shape:
            raise ValueError(f"std_maps must have the shape of maps {maps.shape}, got {std.shape}")
        if np.isfinite(std).all():
            err = np.zeros_like(stokes)
            err[0] = std
            kw["stokes_error"] = err * u.K
    note = FRAME_NOTES[frame]
    with warnings.catch_warnings():
        # a posterior-mean map may dip below zero where the data say little: not an error here
        warnings.filterwarnings("ignore", message="Some Stokes I values are negative")
        return SkyModel(
            component_type="healpix", nside=int(nside), hpx_inds=np.arange(npix), hpx_order="ring",
            stokes=stokes * u.K, spectral_type="full", freq_array=freqs * u.Hz, frame="icrs",
            history=(history.rstrip() + " " if history else "") + note, **kw,
        )


def write_skyh5(path, maps, freqs_hz, *, frame: str, history: str = "", std_maps=None) -> Path:
    """Write HEALPix maps as a pyradiosky ``skyh5`` file (:func:`healpix_skymodel`), atomically.

    ``pyradiosky.SkyModel.from_file(path)`` returns a model equal to
    :func:`healpix_skymodel` of the same arguments (values bit for bit).

    Args:
        path: output file (``.skyh5``; replaced atomically if it exists).
        maps, freqs_hz, frame, history, std_maps: as :func:`healpix_skymodel`.

    Returns:
        the path written.
    """
    sky = healpix_skymodel(maps, freqs_hz, frame=frame, history=history, std_maps=std_maps)
    path = Path(path)
    with atomic_path(path) as tmp, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Some Stokes I values are negative")
        sky.write_skyh5(str(tmp), clobber=True, data_compression="gzip")
    return path
