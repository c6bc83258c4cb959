"""The GSM map that pyradiosky ships, at any frequency of 30-250 MHz (K, ICRS, HEALPix RING).

pyradiosky's ``data/gsm_icrs.skyh5`` (HEALPix nside 8, RING, ICRS, 10 channels 50-150 MHz,
Stokes I in K) is the one GSM every install has offline.  The model layer uses it where the
data need a sky they cannot give themselves: the flux-scale check (the autos' model through
the beam) and a prior mean (``--prior-mean gsm``); :mod:`gcrsky.sim.sky` builds its
offline truth from the same reader.

Inside the map's band a pixel's brightness is interpolated as a power law between the two
bracketing channels (exact at the channels).  Outside it, down to 30 MHz and up to
250 MHz (:data:`GSM_RANGE_HZ`), each pixel follows its own power law, least-squares in
log T - log nu over all ten channels: synchrotron dominates the diffuse sky there and is a
power law to a few per cent (spectral index ~ -2.5, steepening slowly with frequency), so
the extrapolated map is good to that order (measured against held-out channels in
``tests/test_gsmsky.py``), which is all a flux-scale bound of a factor 2 or a prior mean
needs.  Beyond 30-250 MHz nothing is extrapolated: a ``ValueError`` says so.
"""

from __future__ import annotations

import functools
import importlib.resources
import os

import numpy as np

from ..base.extras import require

__all__ = ["GSM_RANGE_HZ", "gsm_maps", "gsm_source_maps"]

#: Frequencies (Hz) at which :func:`gsm_maps` gives a map: the shipped 50-150 MHz, extended by per-pixel
#: power laws to the band of the instruments gcrsky serves (MWA/LOFAR-low 30-80 MHz, HERA 50-250 MHz).
GSM_RANGE_HZ = (30e6, 250e6)

#: Relative slack when checking a frequency against a channel range (channel frequencies are not round).
_FREQ_RTOL = 1e-9


def _pyradiosky_gsm_path() -> str:
    require("pyradiosky", "sim", "the GSM sky (pyradiosky's shipped map)")
    path = str(importlib.resources.files("pyradiosky").joinpath("data/gsm_icrs.skyh5"))
    if not os.path.isfile(path):
        raise RuntimeError(
            f"pyradiosky's shipped GSM map was not found at {path}; "
            "reinstall pyradiosky (the file is part of its package data)"
        )
    return path


def _checked_layout(sm, path):
    """Stokes I (nchan, ncomp) K and the pixel indices of a full-spectrum HEALPix ICRS SkyModel, checked."""
    import astropy.units as u

    if sm.component_type != "healpix":
        raise RuntimeError(f"{path}: expected a HEALPix sky model, got {sm.component_type!r}")
    frame = getattr(sm, "frame", None)
    if frame is None and sm.skycoord is not None:  # older pyradiosky
        frame = sm.skycoord.frame.name
    if str(frame).lower() != "icrs":
        raise RuntimeError(f"{path}: expected the ICRS frame, got {frame!r}")
    if sm.spectral_type != "full":
        raise RuntimeError(f"{path}: expected spectral_type 'full', got {sm.spectral_type!r}")
    if sm.stokes.unit != u.K:
        raise RuntimeError(f"{path}: expected stokes in K, got {sm.stokes.unit}")
    return np.asarray(sm.stokes[0].to_value(u.K), dtype=np.float64), np.asarray(sm.hpx_inds, dtype=np.int64)


@functools.lru_cache(maxsize=1)
def gsm_source_maps():
    """The shipped map, read once and checked rather than assumed.

    Returns:
        ``(freqs_hz (nchan,), maps (nchan, npix) K Stokes I RING ICRS, nside, path)``, arrays
        read-only; HEALPix, ICRS, full spectral type, K, full sky, increasing channels and
        positive finite brightness are checked (NEST is reordered to RING).
    """
    import astropy.units as u
    import healpy as hp
    from pyradiosky import SkyModel

    path = _pyradiosky_gsm_path()
    sm = SkyModel.from_file(path)
    stokes_i, inds = _checked_layout(sm, path)
    nside = int(sm.nside)
    npix = hp.nside2npix(nside)
    if inds.size != npix or np.unique(inds).size != npix:
        raise RuntimeError(f"{path}: expected a full-sky map of {npix} pixels, got {inds.size}")
    maps = np.empty((stokes_i.shape[0], npix))
    maps[:, inds] = stokes_i
    order = str(sm.hpx_order).lower()
    if order.startswith("nest"):
        maps = np.stack([hp.reorder(x, n2r=True) for x in maps])
    elif order != "ring":
        raise RuntimeError(f"{path}: unknown HEALPix ordering {sm.hpx_order!r}")
    freqs = np.asarray(sm.freq_array.to_value(u.Hz), dtype=np.float64).reshape(-1)
    if not np.all(np.diff(freqs) > 0):
        raise RuntimeError(f"{path}: channel frequencies are not increasing: {freqs}")
    if not np.all(maps > 0) or not np.all(np.isfinite(maps)):
        raise RuntimeError(f"{path}: Stokes I must be positive and finite for log-log interpolation")
    freqs.setflags(write=False)
    maps.setflags(write=False)
    return freqs, maps, nside, path


def loglog_interp(src_freqs: np.ndarray, src_maps: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """Per-pixel power-law interpolation between bracketing channels.

    ``src_maps (nchan, npix)`` at increasing ``src_freqs (nchan,)`` -> ``(nfreq, npix)``.  Exact
    channel frequencies return the channel map unchanged.  Frequencies outside the channel
    range raise ``ValueError`` (no extrapolation here: :func:`gsm_maps` does it, by fit).
    """
    lo, hi = src_freqs[0], src_freqs[-1]
    bad = (freqs < lo * (1 - _FREQ_RTOL)) | (freqs > hi * (1 + _FREQ_RTOL))
    if np.any(bad):
        raise ValueError(
            f"frequencies {freqs[bad] / 1e6} MHz are outside the pyradiosky GSM map's "
            f"channel range [{lo / 1e6:.4f}, {hi / 1e6:.4f}] MHz "
            f"({src_freqs.size} channels); no extrapolation is done"
        )
    f = np.clip(freqs, lo, hi)
    i = np.clip(np.searchsorted(src_freqs, f, side="right") - 1, 0, src_freqs.size - 2)
    t0, t1 = src_maps[i], src_maps[i + 1]
    beta = np.log(t1 / t0) / np.log(src_freqs[i + 1] / src_freqs[i])[:, None]
    out = t0 * (f / src_freqs[i])[:, None] ** beta
    for k in np.flatnonzero(np.isin(f, src_freqs)):
        out[k] = src_maps[np.searchsorted(src_freqs, f[k])]
    return out


def powerlaw_extrapolate(src_freqs: np.ndarray, src_maps: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """Per-pixel least-squares power law ``log T = c + beta log(nu / nu_mid)`` over all channels, at ``freqs``.

    ``src_maps (nchan, npix)`` positive -> ``(nfreq, npix)``.
    """
    x = np.log(src_freqs / np.sqrt(src_freqs[0] * src_freqs[-1]))
    design = np.stack([np.ones_like(x), x], axis=1)  # (nchan, 2)
    coef, *_ = np.linalg.lstsq(design, np.log(src_maps), rcond=None)  # (2, npix)
    xf = np.log(np.asarray(freqs, dtype=np.float64) / np.sqrt(src_freqs[0] * src_freqs[-1]))
    return np.exp(coef[0][None, :] + xf[:, None] * coef[1][None, :])


def gsm_maps(freqs_hz) -> tuple[np.ndarray, int]:
    """The GSM's Stokes I at ``freqs_hz`` (30-250 MHz): ``(maps (Nf, npix) K, RING, ICRS, nside)``.

    Inside 50-150 MHz: power-law interpolation between the bracketing channels; outside, each
    pixel's power law fitted over all channels (module docstring).  The map is pyradiosky's
    nside 8 (pixels of 7.3 deg): reliable for l <= 16.

    Raises:
        ValueError: a frequency outside :data:`GSM_RANGE_HZ`, not finite or not positive.
    """
    f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    if f.ndim != 1 or f.size == 0 or not np.all(np.isfinite(f)) or np.any(f <= 0):
        raise ValueError(f"freqs_hz must be a non-empty 1-D array of positive frequencies (Hz), got {freqs_hz!r}")
    lo, hi = GSM_RANGE_HZ
    bad = (f < lo * (1 - _FREQ_RTOL)) | (f > hi * (1 + _FREQ_RTOL))
    if np.any(bad):
        raise ValueError(f"the GSM sky is available over {lo / 1e6:g}-{hi / 1e6:g} MHz (pyradiosky's 50-150 MHz "
                         f"map, extended by per-pixel power laws); got {f[bad] / 1e6} MHz")
    src_f, src_maps, nside, _ = gsm_source_maps()
    inside = (f >= src_f[0] * (1 - _FREQ_RTOL)) & (f <= src_f[-1] * (1 + _FREQ_RTOL))
    out = np.empty((f.size, src_maps.shape[1]))
    if np.any(inside):
        out[inside] = loglog_interp(src_f, src_maps, f[inside])
    if np.any(~inside):
        out[~inside] = powerlaw_extrapolate(src_f, src_maps, f[~inside])
    return out, nside
