"""The prior stage of :func:`gcrsky.ingest.ingest`: the prior as given (a name, a C_l array or file, a map).

:func:`resolve_prior` turns :class:`~gcrsky.ingest.spec.PriorSpec`'s ``prior`` into a
:class:`~gcrsky.model.Prior` at the data's frequencies and ``lmax``; the mean it asks for
(``prior_mean``) is :func:`gcrsky.ingest.beamprior.apply_prior_mean`'s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.files import check_input_file, reading
from ..model.observed import default_prior
from ..model.prior import Prior, flat_prior, isotropic_prior
from ..model.skyprior import gsm_cl
from ..sphere.modes import n_params

__all__ = ["PRIOR_FORMATS", "fits_mean", "read_cl_file", "resolve_prior"]


def read_cl_file(path: Path, nf: int, lmax: int) -> np.ndarray:
    """(Nf, lmax+1) C_l from a ``.npy`` file or a text file (a column of l, then one column per frequency)."""
    arr = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, ndmin=2)
    arr = np.asarray(arr, np.float64)
    if arr.ndim == 1:
        arr = arr[None]
    if path.suffix != ".npy" and arr.shape[1] >= 2 and np.array_equal(arr[:, 0], np.arange(arr.shape[0])):
        arr = arr[:, 1:].T  # text: a column of l then one column per frequency
    if arr.shape[-1] < lmax + 1:
        raise ValueError(f"{path}: the C_l table stops at l = {arr.shape[-1] - 1}, lmax is {lmax}")
    arr = arr[..., : lmax + 1]
    if arr.shape[0] not in (1, nf):
        raise ValueError(f"{path}: {arr.shape[0]} spectra for {nf} frequencies")
    bad = ~np.isfinite(arr) | (arr < 0)
    if np.any(bad):
        k, ell = (int(x[0]) for x in np.nonzero(bad))
        raise ValueError(f"{path}: C_l must be finite and >= 0; spectrum {k} holds {float(arr[k, ell])} at l = {ell} "
                         f"({int(bad.sum())} such value(s) up to lmax {lmax})")
    return np.broadcast_to(arr, (nf, lmax + 1))


def fits_mean(path: Path, nf: int, lmax: int) -> np.ndarray:
    """Realified ICRS coefficients (Nf, n) from a HEALPix map or alm FITS file."""
    import healpy as hp

    from ..sphere.modes import realify

    try:
        alm = hp.read_alm(str(path), hdu=1)
        lmax_f = hp.Alm.getlmax(alm.size)
        cols = [alm]
        hdu = 2
        while True:
            try:
                cols.append(hp.read_alm(str(path), hdu=hdu))
                hdu += 1
            except (IndexError, OSError, ValueError):
                break
        out = np.zeros((len(cols), hp.Alm.getsize(lmax)), complex)
        ell, m = hp.Alm.getlm(min(lmax, lmax_f))
        for k, c in enumerate(cols):
            out[k, hp.Alm.getidx(lmax, ell, m)] = c[hp.Alm.getidx(lmax_f, ell, m)]
        a = realify(out, lmax)
    except Exception:  # noqa: BLE001 - not an alm file: read it as a map
        maps = np.atleast_2d(hp.read_map(str(path), field=None))
        a = realify(np.stack([hp.map2alm(m, lmax=lmax, iter=3) for m in maps]), lmax)
    if a.shape[0] not in (1, nf):
        raise ValueError(f"{path}: {a.shape[0]} columns for {nf} frequencies")
    return np.broadcast_to(a, (nf, n_params(lmax)))


#: What a prior file may be, for read errors.
PRIOR_FORMATS = "HEALPix map or alm FITS file, .npy or text C_l file"


def resolve_prior(prior, prior_scale, freqs, lmax) -> tuple[Prior, str]:
    """``(prior, description)``: the prior of :class:`~gcrsky.ingest.spec.PriorSpec`'s ``prior`` at ``lmax``.

    Args:
        prior: None / ``"gsm"``, ``"flat"``, a :class:`~gcrsky.model.Prior`, a C_l array or file,
            or a HEALPix map / alm FITS file (the mean; the GSM's C_l as its variance).
        prior_scale: factor on the variance.
        freqs: (Nf,) the data's frequencies, Hz.
        lmax: degree of the coefficients.
    """
    nf, n = freqs.size, n_params(lmax)
    if not (np.isfinite(prior_scale) and prior_scale > 0):
        raise ValueError(f"prior_scale must be a positive finite number, got {prior_scale!r}")
    if isinstance(prior, Prior):
        if np.shape(prior.mean) != (nf, n) or np.shape(prior.inv_var) != (nf, n):
            raise ValueError(f"the prior's arrays must be (Nf, n) = {(nf, n)}")
        return prior, "given (a Prior)"
    if prior is None or (isinstance(prior, str) and prior == "gsm"):
        return default_prior(freqs, lmax, prior_scale)
    if isinstance(prior, str) and prior == "flat":
        return flat_prior(nf, n), "flat (S^-1 = 0: the posterior may be improper where the data are blind)"
    if isinstance(prior, (str, Path)):
        if not Path(prior).exists():
            raise ValueError(f"prior {prior!r} is neither 'gsm', 'flat' nor an existing file")
        path = check_input_file(prior, "prior file")
        if path.suffix.lower() in (".fits", ".fit", ".fz") or path.name.endswith(".fits.gz"):
            with reading(path, "a prior (HEALPix map or alm FITS, ICRS, K)", PRIOR_FORMATS):
                mean = fits_mean(path, nf, lmax)
            cl = prior_scale * gsm_cl(freqs, lmax)
            return isotropic_prior(cl, n, mean=mean), (f"mean from {path} (HEALPix map or alm, ICRS), variance "
                                                       f"{prior_scale:g} x the GSM's C_l")
        with reading(path, "a prior's C_l (.npy, or text: l and C_l per frequency)", PRIOR_FORMATS):
            cl = prior_scale * read_cl_file(path, nf, lmax)
        return isotropic_prior(cl, n), f"isotropic, zero mean, C_l from {path} x {prior_scale:g}"
    cl = np.asarray(prior, np.float64)
    if cl.ndim not in (1, 2) or cl.shape[-1] != lmax + 1 or (cl.ndim == 2 and cl.shape[0] not in (1, nf)):
        raise ValueError(f"a C_l prior must be (lmax+1,) or (Nf, lmax+1) = {(nf, lmax + 1)}, got {cl.shape}")
    return isotropic_prior(prior_scale * np.broadcast_to(cl, (nf, lmax + 1)), n), \
        f"isotropic, zero mean, given C_l x {prior_scale:g}"
