"""Truth skies for simulations: realified a_lm of the diffuse radio sky.

Two sources, both giving Stokes I in Kelvin (Rayleigh-Jeans brightness
temperature) expanded in Y_lm in the **equatorial (ICRS)** frame, packed in the
realified layout of :mod:`gcrsky.sphere.modes`:

* ``"gsm2016"`` -- pygdsm's GlobalSkyModel16 (Zheng et al. 2017), the paper's
  truth.  pygdsm downloads its component file (``gsm2016_components.h5``, via
  the astropy download cache) on first use; gcrsky never triggers that
  download, it only uses the file when it is already on disk
  (:func:`gsm2016_available`).
* ``"pyradiosky"`` -- the GSM map that pyradiosky ships
  (``pyradiosky/data/gsm_icrs.skyh5``: HEALPix nside 8, RING, ICRS, 10
  channels 50-150 MHz, K, Stokes I only non-zero).  Works offline.  It only
  carries l <= 2 nside = 16 reliably; l in (16, lmax] are filled with a
  Gaussian small-scale extension whose power spectrum continues the map's.

``source="auto"`` uses GSM2016 when its data are on disk, else falls back to
the pyradiosky map and says so (``SkyTruth.note`` and a logged warning).

Frequencies of order 100 MHz: Rayleigh-Jeans and CMB-thermodynamic kelvin
differ there by a factor 1 - (h nu / k T_cmb)^2 / 12 ~ 1 - 3e-7, i.e. not at
all for our purposes.
"""

from __future__ import annotations

import logging
import numbers
import os
import warnings
from typing import NamedTuple
from unittest import mock

import numpy as np

from ..model.gsmsky import gsm_source_maps, loglog_interp
from ..sphere.modes import n_params, realify, unrealify

__all__ = ["GSM_CL_TABLE_FREQS_HZ", "SkyTruth", "gsm2016_available", "gsm_cl_table", "sky_truth", "write_gsm_cl_table"]

logger = logging.getLogger(__name__)

#: Sources accepted by :func:`sky_truth`.
SOURCES = ("auto", "gsm2016", "pyradiosky")

#: GSM2016 frequency range accepted by pygdsm (Hz).
_GSM2016_FMIN_HZ = 10e6
_GSM2016_FMAX_HZ = 5e12

#: Relative slack when checking a frequency against the file's channel range
#: (the channel frequencies are not round numbers: 61.111... MHz).
_FREQ_RTOL = 1e-9


class SkyTruth(NamedTuple):
    """A truth sky in the realified spherical-harmonic layout.

    Attributes:
        alm: ``(nfreq, (lmax+1)**2)`` float64, realified coefficients (see
            :mod:`gcrsky.sphere.modes`) of Stokes I in kelvin (Rayleigh-Jeans),
            equatorial ICRS frame.  ``a_00 / sqrt(4 pi)`` is the sky mean.
        freqs_hz: ``(nfreq,)`` float64, frequencies in Hz.
        lmax: highest degree l.
        source: what was actually used, ``"gsm2016"`` or ``"pyradiosky-gsm"``.
        lmax_data: highest l taken from the map itself; l in
            ``(lmax_data, lmax]`` is the Gaussian extension (``== lmax`` when
            there is none).
        note: human-readable provenance, including why a fallback happened.
    """

    alm: np.ndarray
    freqs_hz: np.ndarray
    lmax: int
    source: str
    lmax_data: int
    note: str


# --------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------


def _check_lmax(lmax) -> int:
    if isinstance(lmax, bool) or not isinstance(lmax, numbers.Integral):
        raise ValueError(f"lmax must be a non-negative integer, got {lmax!r} ({type(lmax).__name__})")
    if lmax < 0:
        raise ValueError(f"lmax must be a non-negative integer, got {lmax!r}")
    return int(lmax)


def _check_freqs(freqs_hz) -> np.ndarray:
    try:
        f = np.asarray(freqs_hz, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"freqs_hz must be numeric frequencies in Hz, got {freqs_hz!r}") from err
    if f.ndim == 0:
        f = f.reshape(1)
    if f.ndim != 1:
        raise ValueError(f"freqs_hz must be 1-D (nfreq,), got shape {f.shape}")
    if f.size == 0:
        raise ValueError("freqs_hz is empty")
    if not np.all(np.isfinite(f)):
        raise ValueError(f"freqs_hz must be finite, got {f}")
    if np.any(f <= 0):
        raise ValueError(f"freqs_hz must be positive (Hz), got {f}")
    return f


# --------------------------------------------------------------------------
# shared harmonic helpers
# --------------------------------------------------------------------------


def _map_to_alm(m: np.ndarray, lmax: int) -> np.ndarray:
    """HEALPix RING map ``(npix,)`` -> complex healpy-ordered alm up to ``lmax``.

    ``healpy.map2alm`` with 3 Jacobi iterations.  Pixel-weight quadrature
    (``use_pixel_weights=True``) would be slightly better for band-limited maps
    but healpy fetches the weight files from the internet (astropy download)
    when they are not installed, which must never happen here; ring weights
    are likewise external data.  Tested on simulated skies with a GSM-like
    spectrum, downgraded to nside 8: 3 iterations reduce the l = 2..4 error of
    plain quadrature by a factor ~2 and are no worse elsewhere.

    The monopole is then set to ``sqrt(4 pi) * mean(m)``.  HEALPix pixels have
    equal area, so for a map of pixel averages (how low-nside maps are made)
    the pixel mean is the *exact* sky integral, whatever the band limit.  The
    Jacobi iterations assume the map is band-limited to ``lmax``; the GSM at
    nside 8 is not (C_l at l ~ 20 is still ~5e3 K^2), and the iterations leak
    ~2.6e-4 of the monopole (0.3 K at 100 MHz) in from unresolved power.
    """
    import healpy as hp

    m = np.asarray(m, dtype=np.float64)
    alm = hp.map2alm(m, lmax=lmax, iter=3, use_weights=False, use_pixel_weights=False)
    alm = np.asarray(alm, dtype=np.complex128)
    alm[0] = np.sqrt(4.0 * np.pi) * m.mean()
    return alm


def _galactic_maps_to_equatorial_alm(maps: np.ndarray, lmax: int) -> np.ndarray:
    """Galactic RING maps ``(nfreq, npix)`` -> ICRS complex alm ``(nfreq, nalm)``.

    The rotation is applied to the coefficients (one Wigner-D rotation with the
    Euler angles of astropy's Galactic -> ICRS matrix, :mod:`gcrsky.sphere.frames`),
    exact to rounding and free of pixel interpolation.
    """
    from astropy.coordinates import ICRS, Galactic

    from ..sphere.frames import rotate_between_frames

    alm_g = np.stack([_map_to_alm(m, lmax) for m in np.atleast_2d(maps)])
    a_icrs = rotate_between_frames(realify(alm_g, lmax), Galactic(), ICRS())
    return np.asarray(unrealify(np.asarray(a_icrs), lmax), dtype=np.complex128)


def _realify_stack(alm: np.ndarray, lmax: int) -> np.ndarray:
    a = realify(np.ascontiguousarray(alm, dtype=np.complex128), lmax)
    assert a.shape[-1] == n_params(lmax)
    return np.ascontiguousarray(a, dtype=np.float64)


# --------------------------------------------------------------------------
# pyradiosky's shipped GSM map (read by gcrsky.model.gsmsky)
# --------------------------------------------------------------------------

_load_pyradiosky_gsm = gsm_source_maps
_loglog_interp = loglog_interp


def _fit_power_law(cl: np.ndarray, lmin: int, lmax: int) -> tuple[float, float]:
    """Fit ``C_l = A l^alpha`` over ``l in [lmin, lmax]`` (lmin >= 1).

    Weighted least squares in (log l, log C_l) with weights (2l+1)/2, the
    inverse variance of log C_l for a Gaussian field (Var C_l/C_l^2 = 2/(2l+1)).
    Returns ``(A, alpha)``.
    """
    ell = np.arange(lmin, lmax + 1)
    y = np.log(cl[ell])
    x = np.log(ell)
    w = (2 * ell + 1) / 2.0
    alpha, log_a = np.polyfit(x, y, 1, w=np.sqrt(w))
    return float(np.exp(log_a)), float(alpha)


def _extension_unit_normals(lmax_data: int, lmax: int, seed: int) -> np.ndarray:
    """Unit complex Gaussians ``z_lm`` in healpy order, zero for l <= lmax_data.

    ``z_l0 ~ N(0, 1)`` (real); for m > 0, Re and Im ~ N(0, 1/2), so
    ``E|z_lm|^2 = 1`` in both cases.  Drawn l by l in increasing order
    (Re for m = 0..l, then Im for m = 1..l), so for a fixed seed and
    ``lmax_data`` the coefficients at a given (l, m) do not depend on ``lmax``.
    """
    import healpy as hp

    rng = np.random.default_rng(seed)
    z = np.zeros(hp.Alm.getsize(lmax), dtype=np.complex128)
    for ell in range(lmax_data + 1, lmax + 1):
        re = rng.standard_normal(ell + 1)
        im = rng.standard_normal(ell)
        m = np.arange(ell + 1)
        idx = hp.Alm.getidx(lmax, ell, m)
        vals = re.astype(np.complex128)
        vals[1:] = (re[1:] + 1j * im) / np.sqrt(2.0)
        z[idx] = vals
    return z


def _sky_pyradiosky(freqs: np.ndarray, lmax: int, extend_seed: int) -> SkyTruth:
    import healpy as hp

    src_freqs, src_maps, nside, path = _load_pyradiosky_gsm()
    maps = _loglog_interp(src_freqs, src_maps, freqs)

    lmax_data = min(lmax, 2 * nside)
    alm_data = np.stack([_map_to_alm(m, lmax_data) for m in maps])  # (nfreq, nalm(lmax_data))

    alm = np.zeros((freqs.size, hp.Alm.getsize(lmax)), dtype=np.complex128)
    ell_d, m_d = hp.Alm.getlm(lmax_data)
    alm[:, hp.Alm.getidx(lmax, ell_d, m_d)] = alm_data

    note = (
        f"pyradiosky GSM map {path} (nside {nside}, RING, ICRS, K, "
        f"{src_freqs.size} channels {src_freqs[0] / 1e6:.2f}-{src_freqs[-1] / 1e6:.2f} MHz), "
        f"per-pixel log-log interpolation in frequency, Stokes I; "
        f"l <= {lmax_data} from map2alm(iter=3) with monopole = sqrt(4 pi) x pixel mean"
    )
    if lmax > lmax_data:
        lo = max(lmax_data // 2, 1)
        z = _extension_unit_normals(lmax_data, lmax, extend_seed)
        ell_all = hp.Alm.getlm(lmax)[0]
        ext = ell_all > lmax_data
        alphas = []
        for k in range(freqs.size):
            cl = hp.alm2cl(alm_data[k])
            amp, alpha = _fit_power_law(cl, lo, lmax_data)
            alphas.append(alpha)
            alm[k, ext] = np.sqrt(amp * ell_all[ext].astype(np.float64) ** alpha) * z[ext]
        note += (
            f"; l in ({lmax_data}, {lmax}] is a Gaussian extension with C_l = A l^alpha fitted "
            f"per frequency over l in [{lo}, {lmax_data}] (alpha {min(alphas):.3f}..{max(alphas):.3f}), "
            f"the same unit draws at every frequency (seed {extend_seed})"
        )
    return SkyTruth(
        alm=_realify_stack(alm, lmax),
        freqs_hz=freqs.copy(),
        lmax=lmax,
        source="pyradiosky-gsm",
        lmax_data=lmax_data,
        note=note,
    )


# --------------------------------------------------------------------------
# GSM2016 through pygdsm
# --------------------------------------------------------------------------


def _gsm2016_urls() -> list[str]:
    try:
        from pygdsm.component_data import GSM2016_DATA_URL
    except Exception:  # pygdsm not installed or broken
        return []
    return [GSM2016_DATA_URL] if isinstance(GSM2016_DATA_URL, str) else list(GSM2016_DATA_URL)


def _gsm2016_cached_path() -> str | None:
    """Path of pygdsm's GSM2016 component file in the astropy cache, or None.

    pygdsm (component_data.download_from_url_list) fetches its data with
    ``astropy.utils.data.download_file(url, cache=True)`` from a list of
    mirror URLs; the file lives in astropy's download cache keyed by URL.
    Here we only *look up* that cache (a local operation), never download.
    """
    urls = _gsm2016_urls()
    if not urls:
        return None
    try:
        from astropy.utils.data import cache_contents
    except Exception:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # CacheMissingWarning when the cache dir does not exist
        try:
            contents = cache_contents()
        except Exception:
            return None
    for url in urls:
        p = contents.get(url)
        if p and os.path.isfile(p):
            return p
    return None


def gsm2016_available() -> bool:
    """True only if pygdsm is installed and its GSM2016 data file is already on disk.

    Never attempts a download.
    """
    return _gsm2016_cached_path() is not None


def _gsm2016_missing_message() -> str:
    urls = _gsm2016_urls()
    if not urls:
        return "GSM2016 needs pygdsm, which is not installed (pip install pygdsm)."
    return (
        "GSM2016 data (gsm2016_components.h5, ~0.5 GB) are not in the astropy download cache and "
        "gcrsky does not download them. On a machine with internet run "
        "`python -c 'import pygdsm; pygdsm.GlobalSkyModel16()'`; or fetch the file from "
        f"{urls[0]} and register it with "
        f"`astropy.utils.data.import_file_to_cache({urls[0]!r}, '/path/to/gsm2016_components.h5')`."
    )


def _gsm2016_galactic_maps(freqs: np.ndarray, path: str) -> np.ndarray:
    """GSM2016 Stokes I, K (Rayleigh-Jeans), galactic RING maps ``(nfreq, npix)``, nside 1024."""
    import pygdsm.gsm16 as g16

    # pygdsm's constructor walks its URL list through astropy's download_file;
    # if only a later mirror is cached it would first try the network for the
    # earlier one.  Hand it the cached path directly instead.
    with mock.patch.object(g16, "download_from_url_list", lambda urls: path):
        gsm = g16.GlobalSkyModel16(freq_unit="Hz", data_unit="TRJ", resolution="hi", include_cmb=False)
    maps = np.asarray(gsm.generate(freqs), dtype=np.float64)
    return np.atleast_2d(maps)


def _sky_gsm2016(freqs: np.ndarray, lmax: int) -> SkyTruth:
    import healpy as hp

    path = _gsm2016_cached_path()
    if path is None:
        raise RuntimeError(_gsm2016_missing_message())
    bad = (freqs < _GSM2016_FMIN_HZ) | (freqs > _GSM2016_FMAX_HZ)
    if np.any(bad):
        raise ValueError(
            f"frequencies {freqs[bad]} Hz are outside GSM2016's range "
            f"[{_GSM2016_FMIN_HZ:g}, {_GSM2016_FMAX_HZ:g}] Hz"
        )
    maps = _gsm2016_galactic_maps(freqs, path)
    nside = hp.npix2nside(maps.shape[-1])
    if lmax > 2 * nside:
        logger.warning("lmax=%d exceeds 2*nside=%d of the GSM2016 maps; high l are unreliable", lmax, 2 * nside)
    alm = _galactic_maps_to_equatorial_alm(maps, lmax)
    note = (
        f"GSM2016 (pygdsm, {path}), TRJ kelvin without CMB, nside {nside} galactic maps, "
        f"map2alm(iter=3) to lmax {lmax} with monopole = sqrt(4 pi) x pixel mean, "
        "rotated galactic -> equatorial in harmonic space"
    )
    return SkyTruth(
        alm=_realify_stack(alm, lmax),
        freqs_hz=freqs.copy(),
        lmax=lmax,
        source="gsm2016",
        lmax_data=lmax,
        note=note,
    )


# --------------------------------------------------------------------------
# public entry point
# --------------------------------------------------------------------------


def sky_truth(freqs_hz, lmax: int, *, source: str = "auto", extend_seed: int = 2024) -> SkyTruth:
    """Truth sky a_lm at the given frequencies.

    Args:
        freqs_hz: ``(nfreq,)`` positive finite frequencies in Hz (a scalar is
            treated as one frequency).
        lmax: highest degree, non-negative integer.
        source: ``"auto"`` (GSM2016 if its data are on disk, else the
            pyradiosky map), ``"gsm2016"`` or ``"pyradiosky"``.
        extend_seed: seed of ``numpy.random.default_rng`` for the Gaussian
            small-scale extension (pyradiosky source only, l > lmax_data).

    Returns:
        :class:`SkyTruth` with ``alm`` of shape ``(nfreq, (lmax+1)**2)``:
        realified Stokes I coefficients in kelvin (Rayleigh-Jeans), equatorial
        ICRS frame.

    The pyradiosky map has nside 8.  Only l <= lmax_data = min(lmax, 2 nside)
    (= 16) are taken from it: above ~2 nside the HEALPix ring quadrature is
    unreliable (the 768 pixels cannot constrain the (l+1)^2 coefficients, and
    aliasing of unresolved power dominates).  For l in (lmax_data, lmax] a
    Gaussian realisation continues the map: per frequency, C_l = A l^alpha is
    fitted to the map's C_l over l in [lmax_data // 2, lmax_data], and
    a_lm = sqrt(C_l(nu)) z_lm with the *same* unit draws z_lm at every
    frequency (spectrally smooth; deterministic for a given seed).

    Raises:
        ValueError: bad ``lmax``, ``freqs_hz`` or ``source``, or frequencies
            outside the chosen source's range (pyradiosky: 50-150 MHz).
        RuntimeError: ``source="gsm2016"`` and its data are not on disk.
    """
    lmax = _check_lmax(lmax)
    freqs = _check_freqs(freqs_hz)
    if not isinstance(source, str) or source.lower() not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
    source = source.lower()
    if isinstance(extend_seed, bool) or not isinstance(extend_seed, numbers.Integral):
        raise ValueError(f"extend_seed must be an integer, got {extend_seed!r}")

    if source == "gsm2016":
        return _sky_gsm2016(freqs, lmax)
    if source == "pyradiosky":
        return _sky_pyradiosky(freqs, lmax, extend_seed)

    # auto
    if gsm2016_available():
        try:
            return _sky_gsm2016(freqs, lmax)
        except (OSError, RuntimeError) as err:
            reason = f"GSM2016 data are on disk but could not be used ({type(err).__name__}: {err})"
    else:
        reason = "GSM2016 data are not on disk (pygdsm would have to download them)"
    logger.warning("sky_truth: falling back to pyradiosky's nside-8 GSM map: %s", reason)
    try:
        truth = _sky_pyradiosky(freqs, lmax, extend_seed)
    except ValueError as err:
        raise ValueError(f"{err} (fell back to the pyradiosky map because {reason})") from err
    return truth._replace(note=f"FALLBACK from GSM2016: {reason}. " + truth.note)


#: Channels (Hz) of the shipped C_l table (``gcrsky/model/gsm_cl.json``): the map's own ten 50-150 MHz, and
#: 30-45 MHz and 160-250 MHz (5 and 10 MHz apart) from :func:`gcrsky.model.gsmsky.gsm_maps`' per-pixel power laws.
GSM_CL_TABLE_FREQS_HZ = tuple([30e6, 35e6, 40e6, 45e6] + list(np.linspace(50e6, 150e6, 10))
                              + [1e6 * f for f in range(160, 251, 10)])


def gsm_cl_table(lmax: int = 16, freqs_hz=None) -> tuple[np.ndarray, np.ndarray]:
    """Angular power spectra of pyradiosky's shipped GSM map, over 30-250 MHz.

    The source of the table :func:`gcrsky.model.gsm_cl` interpolates (``gcrsky/model/gsm_cl.json``,
    regenerated with ``python -c "from gcrsky.sim.sky import write_gsm_cl_table; write_gsm_cl_table()"``):
    ``healpy.alm2cl`` of the map's coefficients (``map2alm(iter=3)``, monopole ``sqrt(4 pi)`` x
    the pixel mean, as the truth sky uses) up to ``lmax`` (at most ``2 nside`` = 16), of the map
    :func:`gcrsky.model.gsmsky.gsm_maps` gives at each frequency (the shipped channels as they are,
    per-pixel power laws outside 50-150 MHz).

    Args:
        lmax: maximum degree (<= 16).
        freqs_hz: (Nf,) frequencies within 30-250 MHz (default :data:`GSM_CL_TABLE_FREQS_HZ`).

    Returns:
        ``(freqs_hz (Nf,), cl (Nf, lmax+1) K^2)``.
    """
    import healpy as hp

    from ..model.gsmsky import gsm_maps

    freqs = np.asarray(GSM_CL_TABLE_FREQS_HZ if freqs_hz is None else freqs_hz, np.float64).reshape(-1)
    maps, nside = gsm_maps(freqs)
    if lmax > 2 * nside:
        raise ValueError(f"the shipped map (nside {nside}) carries l <= {2 * nside}, asked for {lmax}")
    return freqs, np.stack([hp.alm2cl(_map_to_alm(m, lmax)) for m in maps])


def write_gsm_cl_table(path=None) -> str:
    """Write :func:`gsm_cl_table` to the package's ``gcrsky/model/gsm_cl.json`` (or ``path``)."""
    import json
    from pathlib import Path

    freqs, cl = gsm_cl_table()
    path = Path(path) if path is not None else Path(__file__).parents[1] / "model" / "gsm_cl.json"
    doc = {
        "source": f"pyradiosky {gsm_source_maps()[3].rsplit('/', 1)[-1]} (nside 8, ICRS, K; 30-250 MHz, per-pixel "
                  "power laws outside its 50-150 MHz): healpy alm2cl of map2alm(iter=3), gcrsky.sim.sky.gsm_cl_table",
        "units": "K^2",
        "freqs_hz": [float(f) for f in freqs],
        "cl": [[float(x) for x in row] for row in cl],
    }
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return str(path)
