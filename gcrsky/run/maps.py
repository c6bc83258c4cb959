"""The maps of a run: truth, posterior mean and std over the draws, the Wiener filter; per-mode z-scores.

Maps are HEALPix RING ``(Nf, Npix)`` at the problem's ``nside``, in kelvin, in the frame
of the coefficients (:func:`parameter_frame`).  The observed strip (:func:`observed_region`)
is read from the problem's configuration when it records one (``latitude_deg`` and
``lst_range_hours``: a simulated :class:`~gcrsky.sim.Config` or a file's
:class:`~gcrsky.ingest.DataConfig`).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..sphere.maps import alm_to_map, posterior_maps

__all__ = ["RunMaps", "StoredMaps", "mode_z_scores", "observed_region", "parameter_frame", "run_maps", "stored_maps"]


class RunMaps(NamedTuple):
    """The maps of one run (:func:`run_maps`), each ``(Nf, Npix)`` in K.

    Attributes:
        truth_maps: the truth's maps, or None without a truth.
        mean_maps, std_maps: per-pixel mean and standard deviation (ddof 1) over the draws
            (NaN where a draw is not finite).
        wiener_maps: the Wiener filter's maps (the exact posterior mean).
        mode_z: ``(Nf, n)`` per-mode z-scores against the truth (:func:`mode_z_scores`), or None.
        centre_dec_deg, ra_range_deg: the observed strip (:func:`observed_region`), or None.
    """

    truth_maps: np.ndarray | None
    mean_maps: np.ndarray
    std_maps: np.ndarray
    wiener_maps: np.ndarray
    mode_z: np.ndarray | None
    centre_dec_deg: float | None
    ra_range_deg: tuple | None


def parameter_frame(prob) -> str:
    """The frame of ``prob``'s sky coefficients: ``"icrs"`` (real observing times) or
    ``"idealised"`` (the paper's idealised LSTs: the co-rotating equatorial frame)."""
    return "idealised" if prob.frame is None else "icrs"


def observed_region(config) -> tuple[float | None, tuple | None]:
    """``(centre_dec_deg, ra_range_deg)`` of a zenith-pointing drift scan: the site latitude and
    ``15 x`` the LST range (degrees); ``(None, None)`` without a configuration."""
    if config is None:
        return None, None
    lst = config.lst_range_hours
    return float(config.latitude_deg), (15.0 * lst[0], 15.0 * lst[1])


def mode_z_scores(draws, truth):
    """Per-mode ``z = (mean(draws) - truth) / std(draws)`` (the paper's Fig. 3).

    Args:
        draws: ``(..., ndraws, n)`` realified draws.
        truth: ``(..., n)`` true coefficients.

    Returns:
        ``(..., n)`` dimensionless (std with ddof = 1; NaN where the std is 0).
    """
    draws = np.asarray(draws, np.float64)
    truth = np.asarray(truth, np.float64)
    mean = draws.mean(axis=-2)
    std = draws.std(axis=-2, ddof=1) if draws.shape[-2] > 1 else np.zeros_like(mean)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (mean - truth) / std
    return np.where(std > 0, z, np.nan)


class StoredMaps(NamedTuple):
    """The maps a finished ``results.h5`` holds (:func:`stored_maps`), each ``(Nf, Npix)`` K or None if absent."""

    truth: np.ndarray | None = None
    mean: np.ndarray | None = None
    std: np.ndarray | None = None
    wiener: np.ndarray | None = None


def run_maps(prob, draws: np.ndarray, a_wf: np.ndarray, *, maps: StoredMaps | None = None) -> RunMaps:
    """Truth, posterior mean, std and Wiener maps of a run, its z-scores and observed strip.

    Args:
        prob: the :class:`~gcrsky.model.Problem` (``lmax``, ``nside``, ``a_true``, ``config``).
        draws: ``(Nf, ndraws, n)`` realified draws, K; non-finite draws give NaN mean and std maps.
        a_wf: ``(Nf, n)`` the Wiener filter, K.
        maps: the maps of these draws when already at hand (:class:`StoredMaps`, a finished
            ``results.h5``'s ``maps`` group, :func:`stored_maps`), not recomputed; None: none.
    """
    lmax, nside = prob.lmax, prob.nside
    truth = None if prob.a_true is None else np.asarray(prob.a_true)
    maps = maps or StoredMaps()
    truth_maps = None if truth is None else maps.truth
    if truth is not None and truth_maps is None:
        truth_maps = alm_to_map(truth, lmax, nside)
    wf_maps = maps.wiener if maps.wiener is not None else alm_to_map(a_wf, lmax, nside)
    if maps.mean is not None and maps.std is not None:
        mean_maps, std_maps = maps.mean, maps.std
    elif bool(np.isfinite(draws).all()):
        mean_maps, std_maps = posterior_maps(draws, lmax, nside)
    else:
        mean_maps = std_maps = np.full_like(wf_maps, np.nan)
    z = None if truth is None else mode_z_scores(draws, truth)  # (Nf, n)
    centre_dec, ra_range = observed_region(prob.config)
    return RunMaps(truth_maps, mean_maps, std_maps, wf_maps, z, centre_dec, ra_range)


def stored_maps(h5: Path) -> StoredMaps:
    """The ``maps`` group of a finished ``results.h5`` (:class:`StoredMaps`; each map None where absent)."""
    import h5py

    with h5py.File(h5, "r") as h:
        group = h["maps"] if "maps" in h else {}
        return StoredMaps(**{k: group[k][()] for k in StoredMaps._fields if k in group})
