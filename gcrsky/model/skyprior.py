"""A prior for real data: the angular power spectrum of the Global Sky Model, shipped as a table.

Where no better prior is known, :func:`gsm_prior` gives the isotropic Gaussian prior
``a_lm ~ N(0, s C_l(nu))`` whose ``C_l`` is the angular power spectrum of the GSM (the
embedded map pyradiosky ships, ``gcrsky.sim``'s offline truth), scaled by ``s``.  It is
broad where the sky is bright (the monopole's variance is its own square, ~(4 pi)
T_mean^2) and knows the sky's steep spectrum in l, so the data, not the prior, decide
wherever they constrain the sky, and the unobserved sky is filled with the right power
but no structure (zero mean).

The table (``gsm_cl.json``: ``C_l`` for l <= 16 at 30-250 MHz: the map's own 10 channels,
50-150 MHz, and 14 channels of :func:`gcrsky.model.gsmsky.gsm_maps`' per-pixel power-law
extension below and above them) is computed by :func:`gcrsky.sim.sky.gsm_cl_table` and checked
against it by the tests; reading it needs only NumPy.  Accuracy (``tests/test_prior_band.py``):
between table channels the log-log interpolation is within 1.2 % of the C_l of the map at that
frequency (worst at the joins 47 and 155 MHz, < 1e-4 elsewhere); the extension itself, fitted
without the map's end channels, predicts their C_l to 2.4-4.3 % (one channel held out) and 6.1 %
(two held out, 22 MHz beyond the fit); far from 50-150 MHz (250 MHz) expect ~10 %.  A prior
variance needs its order of magnitude, not per cent.  Between channels ``C_l`` is interpolated
log-log in frequency (a power-law sky); beyond l = 16 each channel's spectrum is extended by
the power law ``C_l = A l^alpha`` fitted to l in [8, 16] (the map's nside 8 carries no
more).  Frequencies outside the table's 30-250 MHz are refused (no extrapolation).
"""

from __future__ import annotations

import functools
import json
from importlib.resources import files

import numpy as np

from .prior import Prior, isotropic_prior

__all__ = [
    "GSM_CL_FIT_RANGE",
    "GSM_MEAN_LMAX",
    "check_gsm_cl_frequencies",
    "gsm_cl",
    "gsm_cl_range_hz",
    "gsm_cl_source",
    "gsm_prior",
    "gsm_prior_mean",
]

#: Degrees over which the extension's power law is fitted.
GSM_CL_FIT_RANGE = (8, 16)

#: Highest degree of the GSM prior mean (:func:`gsm_prior_mean`): ``2 nside`` of the shipped nside-8 map.
GSM_MEAN_LMAX = 16


@functools.lru_cache(maxsize=1)
def _table():
    doc = json.loads(files("gcrsky.model").joinpath("gsm_cl.json").read_text())
    freqs = np.asarray(doc["freqs_hz"], np.float64)
    cl = np.asarray(doc["cl"], np.float64)
    freqs.setflags(write=False)
    cl.setflags(write=False)
    return freqs, cl, doc["source"]


def gsm_cl_source() -> str:
    """Where the shipped table comes from (for logs and run summaries)."""
    return _table()[2]


def gsm_cl_range_hz() -> tuple[float, float]:
    """``(lowest, highest)`` frequency of the shipped table, Hz (what :func:`gsm_cl` accepts)."""
    f = _table()[0]
    return float(f[0]), float(f[-1])


def check_gsm_cl_frequencies(freqs_hz) -> None:
    """Raise ``ValueError`` unless every frequency lies within the table's range (checked before any build)."""
    src_f = _table()[0]
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    lo, hi = src_f[0] * (1 - 1e-9), src_f[-1] * (1 + 1e-9)
    bad = freqs[(freqs < lo) | (freqs > hi)]
    if bad.size:
        raise ValueError(f"the GSM C_l table covers {src_f[0] / 1e6:g}-{src_f[-1] / 1e6:g} MHz; got "
                         f"{bad[0] / 1e6:g} MHz: select channels inside it (--freq-range) or give the prior's C_l "
                         "yourself (prior=... a C_l array or file)")


def gsm_cl(freqs_hz, lmax: int) -> np.ndarray:
    """The GSM's angular power spectrum at ``freqs_hz``: (Nf, lmax+1), K^2 (module docstring).

    Args:
        freqs_hz: (Nf,) frequencies in Hz, within the table's 30-250 MHz (:func:`gsm_cl_range_hz`).
        lmax: maximum degree (l > 16 from the per-channel power-law extension).

    Raises:
        ValueError: a frequency outside the table's range.
    """
    src_f, src_cl, _ = _table()
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    check_gsm_cl_frequencies(freqs)
    lt = src_cl.shape[1] - 1
    a, b = GSM_CL_FIT_RANGE
    ell = np.arange(a, b + 1, dtype=np.float64)
    ext_l = np.arange(lt + 1, max(lmax, lt) + 1, dtype=np.float64)
    full = []
    for row in src_cl:
        slope, icpt = np.polyfit(np.log(ell), np.log(row[a:b + 1]), 1)
        full.append(np.concatenate([row, np.exp(icpt) * ext_l**slope]))
    logc = np.log(np.asarray(full))  # (nchan, max(lmax, 16) + 1)
    logf = np.log(src_f)
    out = np.stack([np.interp(np.log(f), logf, logc[:, ell_i]) for f in freqs for ell_i in range(lmax + 1)])
    return np.exp(out.reshape(freqs.size, lmax + 1))


def gsm_prior(freqs_hz, lmax: int, *, scale: float = 1.0, mean=None) -> Prior:
    """The isotropic prior ``N(mean, scale * gsm_cl(freqs, lmax))`` (mean default 0): a :class:`Prior` (Nf, n)."""
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive finite number, got {scale!r}")
    return isotropic_prior(scale * gsm_cl(freqs_hz, lmax), (lmax + 1) ** 2, mean=mean)


def gsm_prior_mean(freqs_hz, lmax: int) -> np.ndarray:
    """The GSM's realified ICRS coefficients at ``freqs_hz``: (Nf, (lmax+1)^2), K (``--prior-mean gsm``).

    The map :func:`gcrsky.model.gsmsky.gsm_maps` gives (30-250 MHz; nside 8, ICRS) expanded by
    ``healpy.map2alm`` (3 iterations, no external weights) up to ``min(lmax, 16)``, the
    monopole set to ``sqrt(4 pi)`` x the pixel mean (exact for a map of pixel averages);
    degrees above 16 (:data:`GSM_MEAN_LMAX`, what the map carries) are 0: there the mean is
    the isotropic prior's, no structure.  A prior mean puts the GSM where the data say
    nothing (instead of a zero-mean sky that is ~70 % negative there).

    Raises:
        ValueError: a frequency outside 30-250 MHz.
    """
    import healpy as hp

    from ..sphere.modes import realify
    from .gsmsky import gsm_maps

    maps, _ = gsm_maps(freqs_hz)
    lm = min(int(lmax), GSM_MEAN_LMAX)
    out = np.zeros((maps.shape[0], hp.Alm.getsize(lmax)), np.complex128)
    ell, m = hp.Alm.getlm(lm)
    for k, mp in enumerate(maps):
        alm = hp.map2alm(mp, lmax=lm, iter=3, use_weights=False, use_pixel_weights=False)
        alm[0] = np.sqrt(4.0 * np.pi) * mp.mean()
        out[k, hp.Alm.getidx(lmax, ell, m)] = alm
    return np.asarray(realify(out, lmax), np.float64)
