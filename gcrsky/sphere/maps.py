"""HEALPix maps of realified coefficients: synthesis and posterior mean / std maps.

Maps are HEALPix RING-ordered, in the frame of the coefficients (equatorial:
ICRS for real observing times, the co-rotating frame of the paper's idealised
LSTs), in the coefficients' units (kelvin).  healpy is imported when a map is
made (it imports matplotlib when present, which ``import gcrsky`` must not).
"""

from __future__ import annotations

import numpy as np

from .modes import lmax_from_nparams, unrealify

__all__ = ["alm_to_map", "posterior_maps"]


def alm_to_map(a, lmax: int, nside: int) -> np.ndarray:
    """Realified ``(..., n)`` -> HEALPix RING maps ``(..., 12 nside^2)`` (healpy alm2map).

    The map lives in the frame of the coefficients (equatorial for gcrsky).
    """
    import healpy as hp

    a = np.asarray(a, dtype=np.float64)
    alm = unrealify(a, lmax)
    flat = alm.reshape(-1, alm.shape[-1])
    maps = np.stack([hp.alm2map(x, nside, lmax=lmax) for x in flat])
    return maps.reshape(a.shape[:-1] + (hp.nside2npix(nside),))


def posterior_maps(draws, lmax: int | None = None, nside: int = 128, chunk: int = 32):
    """Posterior mean and standard-deviation maps from realified draws.

    The std map is the per-pixel standard deviation of the draws' maps (ddof = 1;
    0 for a single draw), accumulated over chunks of ``chunk`` draws so memory
    stays at ``chunk`` maps.

    Args:
        draws: realified coefficients, ``(..., ndraws, n)`` with ``n = (lmax+1)**2``
            (e.g. ``(Nf, ndraws, n)`` from :func:`gcrsky.sample`), Kelvin.
        lmax: maximum degree (inferred from ``n`` if omitted).
        nside: HEALPix resolution of the output maps.
        chunk: draws converted to maps at a time.

    Returns:
        ``(mean_map, std_map)``, each ``(..., 12 nside^2)``, Kelvin.
    """
    draws = np.asarray(draws, np.float64)
    if draws.ndim < 2:
        raise ValueError(f"draws must be (..., ndraws, n), got shape {draws.shape}")
    if lmax is None:
        lmax = lmax_from_nparams(draws.shape[-1])
    lead, (nd, n) = draws.shape[:-2], draws.shape[-2:]
    flat = draws.reshape((-1, nd, n))
    npix = 12 * int(nside) ** 2
    means = np.empty((flat.shape[0], npix))
    stds = np.empty((flat.shape[0], npix))
    for f, d in enumerate(flat):
        mean_a = d.mean(axis=0)
        means[f] = alm_to_map(mean_a, lmax, nside)
        ss = np.zeros(npix)
        for s in range(0, nd, chunk):
            dev = alm_to_map(d[s : s + chunk] - mean_a, lmax, nside)  # maps are linear in a
            ss += np.einsum("ij,ij->j", dev, dev)
        stds[f] = np.sqrt(ss / max(nd - 1, 1))
    return means.reshape(lead + (npix,)), stds.reshape(lead + (npix,))
