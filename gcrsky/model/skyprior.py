"""A prior for real data: the angular power spectrum of the Global Sky Model, shipped as a table.

Where no better prior is known, :func:`gsm_prior` gives the isotropic Gaussian prior
``a_lm ~ N(0, s C_l(nu))`` whose ``C_l`` is the angular power spectrum of the GSM (the
embedded map pyradiosky ships, ``gcrsky.sim``'s offline truth), scaled by ``s``.  It is
broad where the sky is bright (the monopole's variance is its own square, ~(4 pi)
T_mean^2) and knows the sky's steep spectrum in l, so the data, not the prior, decide
wherever they constrain the sky, and the unobserved sky is filled with the right power
but no structure (zero mean).

The table (``gsm_cl.json``: ``C_l`` for l <= 16 at the map's 10 channels, 50-150 MHz) is
computed by :func:`gcrsky.sim.sky.gsm_cl_table` from pyradiosky's map and checked against
it by the tests; reading it needs only NumPy.  Between channels ``C_l`` is interpolated
log-log in frequency (a power-law sky); beyond l = 16 each channel's spectrum is extended by
the power law ``C_l = A l^alpha`` fitted to l in [8, 16] (the map's nside 8 carries no
more).  Frequencies outside 50-150 MHz are refused (no extrapolation).
"""

from __future__ import annotations

import functools
import json
from importlib.resources import files

import numpy as np

from .prior import Prior, isotropic_prior

__all__ = ["GSM_CL_FIT_RANGE", "gsm_cl", "gsm_cl_source", "gsm_prior"]

#: Degrees over which the extension's power law is fitted.
GSM_CL_FIT_RANGE = (8, 16)


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


def gsm_cl(freqs_hz, lmax: int) -> np.ndarray:
    """The GSM's angular power spectrum at ``freqs_hz``: (Nf, lmax+1), K^2 (module docstring).

    Args:
        freqs_hz: (Nf,) frequencies in Hz, within the table's 50-150 MHz.
        lmax: maximum degree (l > 16 from the per-channel power-law extension).

    Raises:
        ValueError: a frequency outside the table's range.
    """
    src_f, src_cl, _ = _table()
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    lo, hi = src_f[0] * (1 - 1e-9), src_f[-1] * (1 + 1e-9)
    bad = freqs[(freqs < lo) | (freqs > hi)]
    if bad.size:
        raise ValueError(f"the GSM C_l table covers {src_f[0] / 1e6:g}-{src_f[-1] / 1e6:g} MHz; got "
                         f"{bad[0] / 1e6:g} MHz: give the prior's C_l yourself (prior=... a C_l array or file)")
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
