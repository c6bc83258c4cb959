"""Run products on disk: ``results.h5`` (draws, Wiener filter, inputs) and strict JSON summaries.

``results.h5`` layout (what :func:`write_results_h5` writes; ``gcrsky run`` keeps it
stable):

- datasets ``draws`` ``(nfreq, ndraws, nparams)`` realified, K; ``truth`` (if known),
  ``wiener_filter``, ``prior_mean``, ``prior_inv_var`` ``(nfreq, nparams)``;
  ``modes/ell``, ``modes/m``, ``modes/is_imag`` ``(nparams,)``; ``freqs_hz``,
  ``lsts_rad``, ``antpairs``, ``data``, ``sigma``; optional ``mode_z`` and the
  group ``maps`` (``truth``, ``mean``, ``std``: HEALPix RING, float32, gzip);
- attributes: ``units``, ``layout`` and whatever the caller adds (configuration,
  seed, batch, method, key scheme, versions).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

__all__ = ["clean_json", "json_default", "write_json", "write_results_h5"]

#: The realified layout in words (stored as the ``layout`` attribute).
LAYOUT = "realified: [Re a_lm (l, m>=0) healpy order] ++ [Im a_lm (m>=1) healpy order]"
#: Units in words (stored as the ``units`` attribute).
UNITS = "coefficients and maps in K; data in K sr; freqs Hz; lsts rad"


def write_results_h5(
    path,
    problem,
    draws,
    wiener_filter,
    *,
    mode_z=None,
    maps: dict | None = None,
    attrs: dict | None = None,
) -> Path:
    """Write one run's arrays to ``path`` (HDF5; an existing file is replaced).

    Args:
        path: output file.
        problem: the :class:`~gcrsky.model.Problem` that was sampled (its truth, prior,
            modes, frequencies, LSTs, pairs, data and noise are stored).
        draws: (Nf, ndraws, n) realified draws, K.
        wiener_filter: (Nf, n) posterior mean, K.
        mode_z: optional (Nf, n) per-mode z-scores ``(mean - truth) / std``.
        maps: optional ``{"truth" | "mean" | "std": (Nf, Npix)}`` HEALPix RING maps, K.
        attrs: file attributes to add (strings or numbers).

    Returns:
        the path written.
    """
    import h5py

    path = Path(path)
    with h5py.File(path, "w") as h:
        for k, v in (attrs or {}).items():
            h.attrs[k] = v
        h.attrs["units"] = UNITS
        h.attrs["layout"] = LAYOUT
        ds = h.create_dataset("draws", data=np.asarray(draws))
        ds.attrs["shape"] = "(nfreq, ndraws, nparams)"
        if problem.a_true is not None:
            h["truth"] = np.asarray(problem.a_true)
        h["wiener_filter"] = np.asarray(wiener_filter)
        h["prior_mean"] = np.asarray(problem.prior.mean)
        h["prior_inv_var"] = np.asarray(problem.prior.inv_var)
        modes = problem.modes
        h["modes/ell"] = modes.ell
        h["modes/m"] = modes.m
        h["modes/is_imag"] = modes.is_imag
        h["freqs_hz"] = np.asarray(problem.freqs_hz)
        h["lsts_rad"] = np.asarray(problem.lsts_rad)
        h["antpairs"] = np.asarray(problem.antpairs)
        h["data"] = np.asarray(problem.data)
        h["sigma"] = np.asarray(problem.sigma)
        if mode_z is not None:
            h["mode_z"] = np.asarray(mode_z)
        if maps:
            g = h.create_group("maps")
            g.attrs["note"] = "HEALPix RING, equatorial, K; mean/std over the draws"
            for name, arr in maps.items():
                g.create_dataset(name, data=np.asarray(arr).astype(np.float32), compression="gzip",
                                 compression_opts=4)
    return path


def json_default(o):
    """``json.dump`` fallback: NumPy scalars and arrays as Python values, anything else as ``str``."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def clean_json(x):
    """Replace non-finite floats by None (recursively) so the result is strict JSON."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: clean_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [clean_json(v) for v in x]
    return x


def write_json(path, obj) -> Path:
    """Write ``obj`` as indented strict JSON (non-finite floats become ``null``)."""
    path = Path(path)
    with open(path, "w") as fh:
        json.dump(clean_json(obj), fh, indent=2, default=json_default)
    return path
