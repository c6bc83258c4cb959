"""Sky maps and accuracy metrics from posterior draws (pure NumPy + healpy).

Everything here works on plain arrays; nothing depends on JAX.

Conventions:

* Maps are HEALPix RING-ordered, in the equatorial frame of the coefficients
  (:func:`gcrsky.sphere.alm_to_map`): ``theta`` is the colatitude, so the
  declination is ``dec = 90 deg - theta``, and ``phi`` is the right ascension.
  All angles in this module's public API are in **degrees**.
* Maps are in the units of the coefficients (Kelvin for gcrsky's skies).
* "Posterior mean" below is the sample mean of the draws, as in the paper
  (it converges to the Wiener filter as the number of draws grows).
* The observed RA range of a drift scan is the LST range: ``RA = 15 * LST`` (hours
  -> degrees).  A range ``(start, stop)`` runs *eastwards* from ``start`` to
  ``stop`` modulo 360 deg, so ``(330, 390)`` and ``(330, 30)`` both mean the 60 deg
  from RA 330 through 0 to 30; a width of 360 deg or more is the whole circle.

The beam region (paper section 4.1: "within 1 FWHM of the beam centre declination
the posterior mean is within 10% of truth, within 5% at the centre"), see
:func:`beam_region_masks`:

* *centre line*: the one HEALPix iso-latitude ring whose declination is closest to
  the beam-centre declination (for a zenith-pointing drift scan, the site
  latitude).  Rings are ~``58.6/nside`` deg apart near the equator, so the chosen
  ring is within half a ring spacing of the centre.  Ties (the centre exactly
  half-way between two rings) go to the northern ring.
* *FWHM band*: pixels with ``|dec - centre_dec| <= fwhm`` (i.e. "within +-1
  FWHM", a band of full width 2 FWHM, as in the paper's Fig. 5).

Both are restricted to pixel centres inside the observed RA range.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import healpy as hp
import numpy as np

from ..run.maps import mode_z_scores  # the per-mode z-scores a run stores in results.h5

__all__ = [
    "frac_diff_map",
    "pixel_radec_deg",
    "ra_in_range",
    "nearest_ring",
    "ring_slice",
    "moving_average",
    "BeamRegion",
    "beam_region_masks",
    "summary_metrics",
    "std_metrics",
    "mode_z_scores",
    "z_score_stats",
]


def frac_diff_map(mean_map, truth_map):
    """Fractional difference ``(mean - truth) / truth`` (dimensionless; NaN where truth == 0)."""
    mean_map = np.asarray(mean_map, np.float64)
    truth_map = np.asarray(truth_map, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = (mean_map - truth_map) / truth_map
    return np.where(truth_map == 0, np.nan, out)


# ---------------------------------------------------------------- geometry


def pixel_radec_deg(nside: int):
    """Right ascension in [0, 360) and declination in [-90, 90] (degrees) of every RING pixel."""
    theta, phi = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))
    return np.rad2deg(phi) % 360.0, 90.0 - np.rad2deg(theta)


def ra_in_range(ra_deg, ra_range_deg: Sequence[float]):
    """Boolean mask of RAs inside the eastward range ``(start, stop)`` (degrees, wraps at 360).

    ``stop - start >= 360`` selects everything; ``stop < start`` is read as wrapping
    through RA 0 (``(330, 30)`` is 60 deg wide).  Endpoints are included (with a
    1e-9 deg tolerance).
    """
    start, stop = (float(x) for x in ra_range_deg)
    ra = np.asarray(ra_deg, np.float64)
    width = stop - start
    if width >= 360.0:
        return np.ones(ra.shape, bool)
    width %= 360.0
    off = (ra - start) % 360.0
    eps = 1e-9
    return (off <= width + eps) | (off >= 360.0 - eps)


def nearest_ring(nside: int, dec_deg: float):
    """The HEALPix iso-latitude ring nearest to a declination.

    Returns:
        ``(ring, ring_dec_deg, pixels)``: the 1-based ring number (healpy's
        convention, 1 .. 4 nside - 1, north to south), its declination in degrees,
        and the RING-scheme indices of its pixels.  Ties go to the northern ring.
    """
    rings = np.arange(1, 4 * nside)
    start, npix_ring, costheta, _, _ = hp.ringinfo(nside, rings)
    ring_dec = np.rad2deg(np.arcsin(np.clip(costheta, -1.0, 1.0)))  # dec = 90 - theta
    k = int(np.argmin(np.abs(ring_dec - float(dec_deg))))  # first (northern) on ties
    pix = np.arange(start[k], start[k] + npix_ring[k], dtype=np.int64)
    return int(rings[k]), float(ring_dec[k]), pix


def ring_slice(map_, nside: int, dec_deg: float):
    """Values of a map along the HEALPix iso-latitude ring nearest to a declination.

    The paper's "slice through the centre of the primary beam region" (Figs. 6, 8):
    the ring is chosen by :func:`nearest_ring` (its exact declination is the second
    item that function returns).

    Args:
        map_: RING-ordered map ``(12 nside^2,)`` (any units; returned unchanged).
        nside: HEALPix resolution of ``map_``.
        dec_deg: declination in degrees.

    Returns:
        ``(ra_deg, values)``, each ``(npix_ring,)`` (``4 nside`` pixels in the
        equatorial belt ``|dec| <= 41.8 deg``, fewer in the polar caps): the pixels'
        right ascensions in [0, 360) degrees, sorted increasingly, and the map's
        values there.
    """
    map_ = np.asarray(map_)
    if map_.ndim != 1 or map_.size != hp.nside2npix(nside):
        raise ValueError(f"map_ must be a RING map of {hp.nside2npix(nside)} pixels for nside {nside}, got shape {map_.shape}")
    _, _, pix = nearest_ring(nside, dec_deg)
    _, phi = hp.pix2ang(nside, pix)
    ra = np.rad2deg(phi) % 360.0
    order = np.argsort(ra, kind="stable")
    return ra[order], map_[pix[order]]


def moving_average(y, window: int, passes: int = 2, *, circular: bool = True):
    """``passes`` successive centred box-car (moving-average) filters of ``window`` samples.

    The paper smooths its declination slices with "a pair of moving average
    filters": the default ``passes = 2`` is that pair (two box cars in a row are a
    triangular kernel of ``2 window - 1`` samples).  Each pass replaces ``y[i]`` by
    the mean of ``y[i - h] .. y[i + h]`` with ``h = (window - 1) // 2``.

    Edges: with ``circular=True`` (the default, right for a full HEALPix ring, whose
    last pixel neighbours its first) indices wrap around modulo ``len(y)``; with
    ``circular=False`` the window is truncated at the ends (mean of the samples that
    exist).  NaNs propagate into every window that contains them.

    Args:
        y: ``(..., N)`` samples, filtered along the last axis (any units; kept).
        window: odd positive number of samples per box car (1 = no smoothing).
        passes: number of box cars applied (0 returns a copy of ``y``).

    Returns:
        ``(..., N)`` float64 array.
    """
    y = np.array(y, dtype=np.float64)  # copy
    window, passes = int(window), int(passes)
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be an odd positive integer (a centred box car), got {window}")
    if passes < 0:
        raise ValueError(f"passes must be >= 0, got {passes}")
    n = y.shape[-1]
    if n == 0 or window == 1 or passes == 0:
        return y
    h = window // 2
    offs = np.arange(-h, h + 1)
    idx = np.arange(n)[:, None] + offs[None, :]  # (N, window)
    if circular:
        idx %= n
        for _ in range(passes):
            y = y[..., idx].mean(axis=-1)
        return y
    valid = (idx >= 0) & (idx < n)
    idx = np.clip(idx, 0, n - 1)
    count = valid.sum(axis=1)
    for _ in range(passes):
        y = np.where(valid, y[..., idx], 0.0).sum(axis=-1) / count
    return y


class BeamRegion(NamedTuple):
    """Pixel masks of the beam region (RING order, length ``12 nside^2``).

    Attributes:
        centre: the ring nearest to the beam-centre declination, within the RA range.
        fwhm: ``|dec - centre_dec| <= fwhm``, within the RA range.
        ra: RA inside the observed range (any declination).
        centre_ring_dec_deg: declination of the centre ring (degrees).
    """

    centre: np.ndarray
    fwhm: np.ndarray
    ra: np.ndarray
    centre_ring_dec_deg: float


def beam_region_masks(nside: int, centre_dec_deg: float, fwhm_deg: float, ra_range_deg: Sequence[float]) -> BeamRegion:
    """Masks of the beam-centre ring and of the +-1 FWHM band over the observed RA range.

    Args:
        nside: HEALPix resolution.
        centre_dec_deg: beam-centre declination (degrees; the site latitude for a
            zenith-pointing drift scan).
        fwhm_deg: beam FWHM (degrees); the band is ``|dec - centre| <= fwhm_deg``.
        ra_range_deg: observed ``(start, stop)`` RA in degrees (see :func:`ra_in_range`).

    Returns:
        :class:`BeamRegion`.
    """
    if not fwhm_deg > 0:
        raise ValueError(f"fwhm_deg must be positive, got {fwhm_deg}")
    if not -90.0 <= centre_dec_deg <= 90.0:
        raise ValueError(f"centre_dec_deg must be in [-90, 90], got {centre_dec_deg}")
    ra, dec = pixel_radec_deg(nside)
    in_ra = ra_in_range(ra, ra_range_deg)
    _, ring_dec, ring_pix = nearest_ring(nside, centre_dec_deg)
    centre = np.zeros(ra.shape, bool)
    centre[ring_pix] = True
    centre &= in_ra
    band = (np.abs(dec - centre_dec_deg) <= fwhm_deg) & in_ra
    return BeamRegion(centre, band, in_ra, ring_dec)


# ---------------------------------------------------------------- metrics


def _region_stats(absfrac: np.ndarray, prefix: str) -> dict:
    v = absfrac[np.isfinite(absfrac)]
    if v.size == 0:
        nan = float("nan")
        return {f"{prefix}_median": nan, f"{prefix}_p90": nan, f"{prefix}_max": nan,
                f"{prefix}_within_10pct": nan, f"{prefix}_within_5pct": nan, f"{prefix}_npix": 0}
    return {
        f"{prefix}_median": float(np.median(v)),
        f"{prefix}_p90": float(np.percentile(v, 90)),
        f"{prefix}_max": float(np.max(v)),
        f"{prefix}_within_10pct": float(np.mean(v <= 0.10)),
        f"{prefix}_within_5pct": float(np.mean(v <= 0.05)),
        f"{prefix}_npix": int(v.size),
    }


def summary_metrics(
    mean_map,
    truth_map,
    centre_dec_deg: float,
    fwhm_deg: float,
    ra_range_deg: Sequence[float],
    std_map=None,
) -> dict:
    """Accuracy of a posterior-mean map against the truth in the beam region (one frequency).

    ``|frac| = |mean - truth| / |truth|`` per pixel, summarised over

    * ``frac_diff_centre_*``: the beam-centre ring within the RA range,
    * ``frac_diff_fwhm_*``: the +-1 FWHM band within the RA range,
    * ``frac_diff_sky_*``: the whole sky,

    each with ``_median``, ``_p90`` (90th percentile), ``_max``, ``_within_10pct``
    and ``_within_5pct`` (fractions of pixels with ``|frac| <= 0.10 / 0.05``) and
    ``_npix``.  If ``std_map`` is given, also ``zmap_fwhm_rms`` and
    ``zmap_fwhm_max_abs``: the RMS / max of ``(mean - truth) / std`` over the band.

    Args:
        mean_map, truth_map (, std_map): RING maps ``(12 nside^2,)``, same units.
        centre_dec_deg, fwhm_deg, ra_range_deg: the region (degrees), see
            :func:`beam_region_masks`.

    Returns:
        dict of Python floats / ints, plus ``centre_ring_dec_deg``.
    """
    mean_map = np.asarray(mean_map, np.float64)
    truth_map = np.asarray(truth_map, np.float64)
    if mean_map.shape != truth_map.shape or mean_map.ndim != 1:
        raise ValueError(f"need two maps of equal 1-d shape, got {mean_map.shape} and {truth_map.shape}")
    nside = hp.npix2nside(mean_map.size)
    reg = beam_region_masks(nside, centre_dec_deg, fwhm_deg, ra_range_deg)
    absfrac = np.abs(frac_diff_map(mean_map, truth_map))
    out = {"centre_ring_dec_deg": reg.centre_ring_dec_deg}
    out.update(_region_stats(absfrac[reg.centre], "frac_diff_centre"))
    out.update(_region_stats(absfrac[reg.fwhm], "frac_diff_fwhm"))
    out.update(_region_stats(absfrac, "frac_diff_sky"))
    if std_map is not None:
        std_map = np.asarray(std_map, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = ((mean_map - truth_map) / std_map)[reg.fwhm]
        z = z[np.isfinite(z)]
        out["zmap_fwhm_rms"] = float(np.sqrt(np.mean(z**2))) if z.size else float("nan")
        out["zmap_fwhm_max_abs"] = float(np.max(np.abs(z))) if z.size else float("nan")
    return out


def std_metrics(std_map, centre_dec_deg: float, fwhm_deg: float, ra_range_deg: Sequence[float]) -> dict:
    """Where the data constrain the sky, without a truth: the posterior standard deviation by region.

    ``std_centre_median`` / ``std_fwhm_median`` / ``std_sky_median``: the median per-pixel
    posterior std (K) on the beam-centre ring and within +-1 FWHM over the observed RA range
    (:func:`beam_region_masks`), and over the whole sky; ``std_fwhm_over_sky``: their
    ratio (well below 1 where the observed strip is constrained by the data).
    """
    std_map = np.asarray(std_map, np.float64)
    reg = beam_region_masks(hp.npix2nside(std_map.size), centre_dec_deg, fwhm_deg, ra_range_deg)
    out = {
        "std_centre_median": float(np.median(std_map[reg.centre])) if reg.centre.any() else float("nan"),
        "std_fwhm_median": float(np.median(std_map[reg.fwhm])) if reg.fwhm.any() else float("nan"),
        "std_sky_median": float(np.median(std_map)),
    }
    out["std_fwhm_over_sky"] = out["std_fwhm_median"] / out["std_sky_median"]
    return out


def z_score_stats(z) -> dict:
    """Summary of per-mode z-scores: RMS, max |z|, fractions with |z| <= 1, 2, 3 (finite values)."""
    z = np.asarray(z, np.float64).ravel()
    z = z[np.isfinite(z)]
    if z.size == 0:
        return {"rms": float("nan"), "max_abs": float("nan"), "within_1": float("nan"),
                "within_2": float("nan"), "within_3": float("nan"), "n": 0}
    a = np.abs(z)
    return {
        "rms": float(np.sqrt(np.mean(z**2))),
        "max_abs": float(a.max()),
        "within_1": float(np.mean(a <= 1)),
        "within_2": float(np.mean(a <= 2)),
        "within_3": float(np.mean(a <= 3)),
        "n": int(z.size),
    }
