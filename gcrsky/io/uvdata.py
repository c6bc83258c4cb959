"""Real observations in: a :class:`~gcrsky.model.Problem` from any file pyuvdata reads.

:func:`from_uvdata` turns a visibility file (UVH5; UVFITS, Measurement Sets, MIRIAD
where pyuvdata's optional readers are installed) or a ``UVData`` object into the
inference problem whose parameters are the ICRS coefficients of the sky (DESIGN
section 2, mode (b): the file's real observing times at the file's site).
:func:`inspect_uvdata` says what would be used without solving.

Conventions (pinned against pyuvdata's conventions page; ``docs/conventions.md``):

* Baselines: pyuvdata's ``V_12 = <V_1^* V_2>`` with ``uvw = x_2 - x_1`` is gcrsky's
  ``(i, j)`` with baseline ``x_j - x_i``.  A row stored as ``(ant_2, ant_1)`` is
  conjugated into the canonical ``i < j`` (antennas indexed by increasing number), so
  any stored conjugation reads the same.  Missing pairs or times are zero-weight samples.
* Phase: drift-scan ("unprojected") data are used as they are; a projected file is
  unprojected by pyuvdata (``UVData.unproject_phase``), and the log says so.
* Units: ``vis_units`` ``"Jy"`` are converted to K sr by Rayleigh-Jeans
  (:func:`gcrsky.base.kelvin_sr_to_jy`), ``"K str"`` are used as they are, ``"uncalib"``
  is refused.
* Polarisation: gcrsky models *I-equivalent* visibilities of an unpolarised sky,
  ``V = int K I e^{...}`` with the product's cross power beam ``K`` (``"xx"``: ``K_xx``;
  ``"pI"``: ``(K_xx + K_yy)/2``; :mod:`gcrsky.instrument.response`).  A file's
  ``pol_convention`` (pyuvdata; absent means ``"sum"``, what pyuvsim, matvis and
  hera_sim write) fixes the factor: under ``"sum"`` a feed sees half of Stokes I, so
  ``pol="xx"`` models ``2 V_xx`` and ``pol="pI"`` models ``V_xx + V_yy``; under
  ``"avg"`` ``V_xx`` and ``(V_xx + V_yy)/2``.  ``pol=("xx", "yy")`` fits both products
  as separate data of the same sky (better than pI when the feeds' beams differ).
  Feed ``x`` is pyuvdata's (the file's and the beam's ``x_orientation`` must agree).
* Noise (per component): by default the radiometer equation on the file's own
  autocorrelations, ``sigma^2_pq = |V_ii,pp V_jj,qq| / (2 dt dnu N)`` (``dt`` the
  integration time, ``dnu`` the channel width, ``N`` the nsample); ``noise="diff"``
  estimates a constant ``sigma`` per baseline, channel and product from time-adjacent
  differences (for files without autos; it includes any sky change between adjacent
  integrations, so it overestimates for long integrations on long baselines); or a
  given per-component ``sigma`` in the file's units.  Variances add as products are
  combined and scale with the convention's factor.
* Flags: a flagged sample, a zero nsample, a missing autocorrelation (radiometer
  noise) or a missing baseline gets weight 0; a non-finite unflagged sample is an error
  naming it.

Selections (frequency channels or range, times or LST range, antennas, baselines,
including an arbitrary subset of pairs) are applied when reading, so pyuvdata reads
only those parts of a UVH5 file; the size of the selection is checked against the free
memory before anything is read.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..base.memory import check_memory, format_bytes
from ..base.units import kelvin_sr_to_jy
from ..instrument.antennas import make_array
from ..instrument.response import response_matrix
from ..model.prior import Prior, flat_prior, isotropic_prior
from ..model.problem import Problem, assemble_problem, observation_geometry
from ..model.skyprior import gsm_cl, gsm_cl_source
from ..sphere.modes import n_params

__all__ = [
    "DataConfig",
    "POLS",
    "from_uvdata",
    "inspect_uvdata",
    "read_uvdata",
]

log = logging.getLogger(__name__)

#: The modelled products: name -> the raw feed products it combines.
POLS = {"pI": ("xx", "yy"), "xx": ("xx",), "yy": ("yy",)}
#: pyuvdata's polarisation numbers of the linear feed products.
_POLNUM = {"xx": -5, "yy": -6}
#: Bytes per sample of a read (data complex128, flags, nsample float64) and of gcrsky's copies.
_BYTES_PER_SAMPLE = 16 + 1 + 8


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """How a Problem was read from a file (recorded in ``Problem.config`` and the run's outputs).

    Attributes:
        source: the file's path (or ``"<UVData object>"``).
        pol: the modelled product(s), e.g. ``"pI"`` or ``("xx", "yy")``.
        lmax, nside: degree of the ICRS coefficients and HEALPix nside of the quadrature.
        beam: description of the beam model.
        prior: description of the prior.
        noise: ``"autos"``, ``"diff"`` or ``"given"``.
        selection: the selections applied when reading (JSON-friendly).
        conventions: what was read and converted (units, pol_convention, phase, ...).
        compressed: redundant baselines merged (exact).
        latitude_deg: the site's latitude (the beam centre of a zenith-pointing drift scan).
        lst_range_hours: (first, last) local sidereal time of the data, hours (last may
            exceed 24 when the data wrap through 0 h): the observed strip's RA range.
        fwhm_deg: (Nf,) FWHM of the first antenna's beam (feed x power), degrees.
    """

    source: str
    pol: Any
    lmax: int
    nside: int
    beam: str
    prior: str
    noise: str
    selection: dict
    conventions: dict
    compressed: bool
    latitude_deg: float
    lst_range_hours: tuple
    fwhm_deg: tuple

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["pol"] = list(self.pol) if isinstance(self.pol, tuple) else self.pol
        d["lst_range_hours"] = list(self.lst_range_hours)
        d["fwhm_deg"] = list(self.fwhm_deg)
        return d


# ---------------------------------------------------------------- reading


def _pol_rows(pol) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(modelled products, raw products needed) for ``pol`` (``"pI"``, ``"xx"``, ``"yy"`` or a tuple)."""
    if isinstance(pol, str):
        prods = tuple(p.strip() for p in pol.split(",")) if "," in pol else (pol,)
    else:
        prods = tuple(pol)
    bad = [p for p in prods if p not in POLS]
    if not prods or bad:
        raise ValueError(f"pol must be one of {sorted(POLS)} or a tuple of them (e.g. ('xx', 'yy')), got {pol!r}")
    if len(set(prods)) != len(prods):
        raise ValueError(f"pol names a product twice: {pol!r}")
    raw = tuple(dict.fromkeys(r for p in prods for r in POLS[p]))
    return prods, raw


def _selection_kwargs(meta, *, freq_chans, freq_range_hz, times_jd, lst_range_hours, antennas, bls, raw, autos):
    """pyuvdata ``select`` / ``read`` keywords for the selection (computed on the metadata)."""
    kw: dict = {}
    freqs = np.asarray(meta.freq_array, np.float64).reshape(-1)
    chans = np.arange(freqs.size)
    if freq_chans is not None:
        chans = np.asarray(freq_chans, np.int64).reshape(-1)
        if chans.size == 0 or chans.min() < 0 or chans.max() >= freqs.size:
            raise ValueError(f"freq_chans must index the file's {freqs.size} channels, got {freq_chans!r}")
    if freq_range_hz is not None:
        lo, hi = (float(x) for x in freq_range_hz)
        chans = chans[(freqs[chans] >= lo) & (freqs[chans] <= hi)]
        if chans.size == 0:
            raise ValueError(f"no channel in {lo / 1e6:g}-{hi / 1e6:g} MHz (the file has "
                             f"{freqs.min() / 1e6:g}-{freqs.max() / 1e6:g} MHz)")
    if chans.size != freqs.size:
        kw["freq_chans"] = chans
    tj = np.unique(np.asarray(meta.time_array))
    keep_t = np.ones(tj.size, bool)
    if times_jd is not None:
        want = np.atleast_1d(np.asarray(times_jd, np.float64))
        keep_t &= np.isin(tj, want)
        missing = want[~np.isin(want, tj)]
        if missing.size:
            raise ValueError(f"times {missing[:3]} (JD) are not in the file")
    if lst_range_hours is not None:
        lo, hi = (float(x) % 24.0 for x in lst_range_hours)
        lst_h = np.zeros(tj.size)
        ut, idx = np.unique(np.asarray(meta.time_array), return_index=True)
        lst_h[np.searchsorted(tj, ut)] = np.rad2deg(np.asarray(meta.lst_array)[idx]) / 15.0
        keep_t &= ((lst_h >= lo) & (lst_h <= hi)) if lo <= hi else ((lst_h >= lo) | (lst_h <= hi))
    if not np.any(keep_t):
        raise ValueError("the time / LST selection leaves no integration")
    if not np.all(keep_t):
        kw["times"] = tj[keep_t]
    file_pols = [int(p) for p in np.asarray(meta.polarization_array)]
    missing = [r for r in raw if _POLNUM[r] not in file_pols]
    if missing:
        from pyuvdata import utils

        names = [utils.polnum2str(p) for p in file_pols]
        raise ValueError(f"the file holds polarisations {names}; pol needs {list(raw)} (missing {missing})")
    if len(raw) != len(file_pols):
        kw["polarizations"] = [_POLNUM[r] for r in raw]
    if antennas is not None:
        nums = _antenna_numbers(meta, antennas)
        kw["antenna_nums"] = nums
    if bls is not None:
        pairs = [tuple(int(x) for x in _antenna_numbers(meta, b)) for b in bls]
        if any(len(p) != 2 for p in pairs):
            raise ValueError("bls must be a sequence of antenna pairs (number or name each)")
        if autos:  # the radiometer noise needs the autos of every antenna involved
            pairs += [(a, a) for a in sorted({a for p in pairs for a in p})]
        kw["bls"] = sorted(set(pairs))
    return kw


def _antenna_numbers(meta, ants) -> np.ndarray:
    """Antenna numbers of ``ants`` (numbers or names), checked against the file's telescope."""
    tel = meta.telescope
    names = [str(n) for n in tel.antenna_names]
    nums = [int(n) for n in tel.antenna_numbers]
    out = []
    for a in ants:
        if isinstance(a, (int, np.integer)):
            if int(a) not in nums:
                raise ValueError(f"antenna number {a} is not in the file")
            out.append(int(a))
        elif str(a) in names:
            out.append(nums[names.index(str(a))])
        else:
            raise ValueError(f"antenna {a!r} is neither a number nor a name in the file")
    return np.asarray(out, np.int64)


def _estimate_bytes(meta, kw) -> tuple[int, float]:
    """(samples, bytes) the read of the selection ``kw`` would hold (upper bound: all blts kept)."""
    nf = len(kw.get("freq_chans", np.arange(meta.Nfreqs)))
    npol = len(kw.get("polarizations", meta.polarization_array))
    tmask = np.isin(np.asarray(meta.time_array), kw["times"]) if "times" in kw else np.ones(meta.Nblts, bool)
    if "antenna_nums" in kw:
        sel = np.isin(meta.ant_1_array, kw["antenna_nums"]) & np.isin(meta.ant_2_array, kw["antenna_nums"])
        tmask &= sel
    if "bls" in kw:
        want = {tuple(p) for p in kw["bls"]} | {(p[1], p[0]) for p in kw["bls"]}
        tmask &= np.array([(int(a), int(b)) in want for a, b in zip(meta.ant_1_array, meta.ant_2_array)])
    samples = int(tmask.sum()) * nf * npol
    return samples, float(samples) * _BYTES_PER_SAMPLE * 3  # the read, and gcrsky's reordered copies


def read_uvdata(data, *, pol="pI", freq_chans=None, freq_range_hz=None, times_jd=None, lst_range_hours=None,
                antennas=None, bls=None, autos: bool = True, memory_budget: float | None = None):
    """Read the selected part of a visibility file (or select from a ``UVData``): ``(UVData, source, selection)``.

    The selection is computed on the file's metadata (``read_data=False``), its size
    checked against the memory budget (:func:`gcrsky.base.check_memory`), then only it is
    read.  Arguments as :func:`from_uvdata`; ``autos``: keep the autocorrelations of the
    selected antennas (the radiometer noise needs them).
    """
    from pyuvdata import UVData

    _, raw = _pol_rows(pol)
    if isinstance(data, UVData):
        meta, source = data, "<UVData object>"
    else:
        path = Path(data)
        if not path.exists():
            raise FileNotFoundError(f"no visibility file at {path}")
        meta, source = UVData.from_file(str(path), read_data=False), str(path)
    kw = _selection_kwargs(meta, freq_chans=freq_chans, freq_range_hz=freq_range_hz, times_jd=times_jd,
                           lst_range_hours=lst_range_hours, antennas=antennas, bls=bls, raw=raw, autos=autos)
    samples, nbytes = _estimate_bytes(meta, kw)
    log.info("reading %s: %d samples selected (%s with gcrsky's copies)", source, samples, format_bytes(nbytes))
    check_memory(nbytes, f"reading {samples} visibility samples from {source}",
                 "select fewer channels, times, antennas or baselines", budget=memory_budget)
    if isinstance(data, UVData):
        uvd = data.select(**kw, inplace=False) if kw else data.copy()
    else:
        uvd = UVData.from_file(source, **kw)
    selection = {k: (np.asarray(v).tolist() if not isinstance(v, list) else v) for k, v in kw.items()}
    return uvd, source, selection


# ---------------------------------------------------------------- arranging the samples


def _check_units_phase(uvd, log_lines: list) -> dict:
    units = str(uvd.vis_units)
    if units == "uncalib":
        raise ValueError("the file's visibilities are uncalibrated (vis_units 'uncalib'): gcrsky needs Jy or K str; "
                         "calibrate them first")
    if units not in ("Jy", "K str"):
        raise ValueError(f"unknown vis_units {units!r} (gcrsky reads 'Jy' and 'K str')")
    conv = getattr(uvd, "pol_convention", None)
    if conv not in (None, "sum", "avg"):
        raise ValueError(f"unknown pol_convention {conv!r} (pyuvdata's are 'sum' and 'avg')")
    types = {int(k): v.get("cat_type") for k, v in uvd.phase_center_catalog.items()}
    used = {int(i) for i in np.unique(uvd.phase_center_id_array)}
    projected = [i for i in used if types.get(i) != "unprojected"]
    phase = "unprojected (drift scan)"
    if projected:
        uvd.unproject_phase()
        phase = "projected in the file; unprojected by pyuvdata (UVData.unproject_phase)"
        log_lines.append(f"the file's data are phased to a phase centre (ids {projected}); unprojected them with "
                         f"pyuvdata to drift-scan data")
    return {"vis_units": units, "pol_convention": conv if conv is not None else "sum (absent in the file)",
            "phase": phase, "x_orientation": getattr(uvd.telescope, "x_orientation", None)}


class _Samples:
    """The file's samples arranged on (Nf, Nt, pair) grids per raw product, canonical ``i < j``."""

    def __init__(self, uvd, raw):
        self.freqs = np.asarray(uvd.freq_array, np.float64).reshape(-1)
        self.chan_width = np.broadcast_to(np.asarray(uvd.channel_width, np.float64).reshape(-1), self.freqs.shape)
        a1, a2 = np.asarray(uvd.ant_1_array), np.asarray(uvd.ant_2_array)
        cross = a1 != a2
        if not np.any(cross):
            raise ValueError("the selection holds no cross-correlations")
        self.antnums = np.unique(np.concatenate([a1[cross], a2[cross]]))
        index = {int(a): k for k, a in enumerate(self.antnums)}
        self.times_jd, tidx = np.unique(np.asarray(uvd.time_array), return_inverse=True)
        nf, nt, nant = self.freqs.size, self.times_jd.size, self.antnums.size
        i = np.array([index.get(int(a), -1) for a in a1])
        j = np.array([index.get(int(b), -1) for b in a2])
        swap = cross & (i > j)
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        self.pairs, pidx = np.unique(np.stack([lo[cross], hi[cross]], 1), axis=0, return_inverse=True)
        pidx = pidx.reshape(-1)
        nbl = self.pairs.shape[0]
        pol_index = {int(p): k for k, p in enumerate(np.asarray(uvd.polarization_array))}
        data = np.asarray(uvd.data_array)  # (Nblts, Nfreqs, Npols)
        flags = np.asarray(uvd.flag_array, bool)
        nsamp = np.asarray(uvd.nsample_array, np.float64)
        dt = np.asarray(uvd.integration_time, np.float64)
        rows = np.flatnonzero(cross)
        self.vis, self.flag, self.nsample = {}, {}, {}
        self.auto = {}
        self.dt = np.zeros((nt, nbl))
        self.dt[tidx[rows], pidx] = dt[rows]
        auto_rows = np.flatnonzero(~cross & (i >= 0))
        for r in raw:
            k = pol_index[_POLNUM[r]]
            v = np.zeros((nf, nt, nbl), np.complex128)
            f = np.ones((nf, nt, nbl), bool)  # missing samples stay flagged
            ns = np.zeros((nf, nt, nbl))
            d = data[rows, :, k]
            d = np.where(swap[rows][:, None], np.conj(d), d)
            v[:, tidx[rows], pidx] = d.T
            f[:, tidx[rows], pidx] = flags[rows, :, k].T
            ns[:, tidx[rows], pidx] = nsamp[rows, :, k].T
            self.vis[r], self.flag[r], self.nsample[r] = v, f, ns
            au = np.full((nf, nt, nant), np.nan)
            good = ~flags[auto_rows, :, k]
            au[:, tidx[auto_rows], i[auto_rows]] = np.where(good, np.abs(data[auto_rows, :, k].real), np.nan).T
            self.auto[r] = au
        self.n_autos = int(auto_rows.size)

    def radiometer_var(self, r):
        """Per-component variance from the autos: (Nf, Nt, Nbl), NaN where an auto is missing."""
        au = self.auto[r]
        ai, aj = au[:, :, self.pairs[:, 0]], au[:, :, self.pairs[:, 1]]
        with np.errstate(divide="ignore", invalid="ignore"):
            return ai * aj / (2.0 * self.dt[None] * self.chan_width[:, None, None] * self.nsample[r])

    def diff_var(self, r):
        """Per-component variance per (channel, baseline) from time-adjacent differences: (Nf, Nt, Nbl)."""
        v, ok = self.vis[r], ~self.flag[r] & (self.nsample[r] > 0)
        if v.shape[1] < 2:
            raise ValueError("noise='diff' needs at least two integrations")
        inv_n = np.where(ok, 1.0 / np.where(ok, self.nsample[r], 1.0), 0.0)
        pair_ok = ok[:, 1:] & ok[:, :-1]
        d2 = np.abs(v[:, 1:] - v[:, :-1]) ** 2 / (2.0 * (inv_n[:, 1:] + inv_n[:, :-1]) + ~pair_ok)
        cnt = pair_ok.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            s1 = np.where(cnt > 0, np.sum(np.where(pair_ok, d2, 0.0), axis=1) / cnt, np.nan)  # (Nf, Nbl): sigma_1^2
        return s1[:, None, :] * np.where(ok, inv_n, np.nan)


# ---------------------------------------------------------------- beams and priors


def _resolve_beams(beam, dish_diameter_m, meta_tel, antnums):
    """One beam object per used antenna (in ``antnums`` order) and a description."""
    from ..instrument.beams import gaussian_beam

    if beam is None and dish_diameter_m is None:
        raise ValueError("give the beam (a pyuvdata beam object or a beam file) or dish_diameter_m (a Gaussian beam "
                         "with the Airy FWHM of that dish)")
    if beam is not None and dish_diameter_m is not None:
        raise ValueError("give beam or dish_diameter_m, not both")
    if beam is None:
        b = gaussian_beam(float(dish_diameter_m))
        return [b] * len(antnums), f"Gaussian, Airy-matched FWHM of a {float(dish_diameter_m):g} m dish"
    from ..instrument.beams import load_beam as load
    if isinstance(beam, dict):
        names = [str(n) for n in meta_tel.antenna_names]
        nums = [int(n) for n in meta_tel.antenna_numbers]
        by_num = {}
        for key, b in beam.items():
            num = int(key) if isinstance(key, (int, np.integer)) else (
                nums[names.index(str(key))] if str(key) in names else None)
            if num is None:
                raise ValueError(f"beam key {key!r} is neither an antenna number nor a name in the file")
            by_num[num] = b
        missing = [int(a) for a in antnums if int(a) not in by_num]
        if missing:
            raise ValueError(f"no beam given for antennas {missing}")
        cache: dict = {}
        out = []
        for a in antnums:
            b = by_num[int(a)]
            key = id(b) if not isinstance(b, (str, Path)) else str(b)
            out.append(cache.setdefault(key, load(b)))
        return out, f"per antenna ({len(cache)} distinct beams)"
    if isinstance(beam, (list, tuple)):
        nums = [int(n) for n in meta_tel.antenna_numbers]
        if len(beam) != len(nums):
            raise ValueError(f"a beam list needs one beam per antenna of the file's telescope ({len(nums)}), "
                             f"in its antenna_numbers order; got {len(beam)} (or pass a dict number/name -> beam)")
        return _resolve_beams(dict(zip(nums, beam)), None, meta_tel, antnums)
    b = load(beam)
    return [b] * len(antnums), _describe_beam(beam, b)


def _describe_beam(arg, b) -> str:
    if isinstance(arg, (str, Path)):
        return f"file {arg}"
    return type(b).__name__


def _read_cl_file(path: Path, nf: int, lmax: int) -> np.ndarray:
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
    return np.broadcast_to(arr, (nf, lmax + 1))


def _fits_mean(path: Path, nf: int, lmax: int) -> np.ndarray:
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


def _resolve_prior(prior, prior_scale, freqs, lmax) -> tuple[Prior, str]:
    """The prior and its description (module docstring of :func:`from_uvdata`)."""
    nf, n = freqs.size, n_params(lmax)
    if not (np.isfinite(prior_scale) and prior_scale > 0):
        raise ValueError(f"prior_scale must be a positive finite number, got {prior_scale!r}")
    if isinstance(prior, Prior):
        if np.shape(prior.mean) != (nf, n) or np.shape(prior.inv_var) != (nf, n):
            raise ValueError(f"the prior's arrays must be (Nf, n) = {(nf, n)}")
        return prior, "given (a Prior)"
    if prior is None or (isinstance(prior, str) and prior == "gsm"):
        cl = prior_scale * gsm_cl(freqs, lmax)
        return isotropic_prior(cl, n), (f"isotropic, zero mean, C_l = {prior_scale:g} x the GSM's angular power "
                                        f"spectrum at the data's frequencies ({gsm_cl_source()})")
    if isinstance(prior, str) and prior == "flat":
        return flat_prior(nf, n), "flat (S^-1 = 0: the posterior may be improper where the data are blind)"
    if isinstance(prior, (str, Path)):
        path = Path(prior)
        if not path.exists():
            raise ValueError(f"prior {prior!r} is neither 'gsm', 'flat' nor an existing file")
        if path.suffix.lower() in (".fits", ".fit", ".fz") or path.name.endswith(".fits.gz"):
            mean = _fits_mean(path, nf, lmax)
            cl = prior_scale * gsm_cl(freqs, lmax)
            return isotropic_prior(cl, n, mean=mean), (f"mean from {path} (HEALPix map or alm, ICRS), variance "
                                                       f"{prior_scale:g} x the GSM's C_l")
        cl = prior_scale * _read_cl_file(path, nf, lmax)
        return isotropic_prior(cl, n), f"isotropic, zero mean, C_l from {path} x {prior_scale:g}"
    cl = np.asarray(prior, np.float64)
    if cl.ndim not in (1, 2) or cl.shape[-1] != lmax + 1 or (cl.ndim == 2 and cl.shape[0] not in (1, nf)):
        raise ValueError(f"a C_l prior must be (lmax+1,) or (Nf, lmax+1) = {(nf, lmax + 1)}, got {cl.shape}")
    return isotropic_prior(prior_scale * np.broadcast_to(cl, (nf, lmax + 1)), n), \
        f"isotropic, zero mean, given C_l x {prior_scale:g}"


# ---------------------------------------------------------------- the problem


def from_uvdata(
    data,
    *,
    lmax: int,
    nside: int,
    beam=None,
    dish_diameter_m: float | None = None,
    pol="pI",
    prior=None,
    prior_scale: float = 1.0,
    noise="autos",
    freq_chans=None,
    freq_range_hz=None,
    times_jd=None,
    lst_range_hours=None,
    antennas=None,
    bls=None,
    compress: bool = True,
    frame_pad: int = 4,
    memory_budget: float | None = None,
) -> Problem:
    """The inference problem of a visibility file: ICRS coefficients at ``lmax`` (module docstring).

    Args:
        data: a path to any file ``UVData.from_file`` reads, or a ``UVData`` object (not
            modified).
        lmax: maximum degree of the sky's ICRS coefficients.
        nside: HEALPix nside of the response quadrature.
        beam: a pyuvdata beam object (``UVBeam``, an ``AnalyticBeam`` such as
            ``GaussianBeam``, a ``BeamInterface``), a path to a beam file ``UVBeam`` reads
            (beamfits, CST, MWA), a dict from antenna numbers or names to beams, or a list
            of beams in the file's ``antenna_numbers`` order.
        dish_diameter_m: instead of ``beam``: a Gaussian beam with the Airy FWHM of that dish.
        pol: ``"pI"`` (pseudo-Stokes I, ``xx + yy``), ``"xx"``, ``"yy"``, or ``("xx", "yy")``
            (or ``"xx,yy"``: both products, separately, of the same sky).
        prior: ``None`` / ``"gsm"`` (isotropic, zero mean, C_l of the GSM at the data's
            frequencies, :func:`gcrsky.model.gsm_cl`), ``"flat"``, a
            :class:`~gcrsky.model.Prior`, a C_l array ((lmax+1,) or (Nf, lmax+1), K^2), a C_l
            file (``.npy``, or text with a column of l and one of C_l per frequency), or a
            HEALPix map / alm FITS file (ICRS, K; the prior's *mean*, with the GSM's C_l as
            its variance).
        prior_scale: factor on the prior variance.
        noise: ``"autos"`` (radiometer equation on the file's autocorrelations),
            ``"diff"`` (time-adjacent differences), or a per-component sigma (scalar or
            broadcastable to the file's (Nf, Nt, Nbl) grid), in the file's units, of each
            raw feed product.
        freq_chans, freq_range_hz: channel indices, and/or a (lo, hi) range in Hz.
        times_jd, lst_range_hours: integration times (JD) to keep, and/or an LST range
            (hours; ``(22, 2)`` wraps through 0 h).
        antennas: antenna numbers or names to keep (pairs among them).
        bls: antenna pairs to keep (numbers or names), any subset.
        compress: merge redundant baselines (exactly: only identical responses merge,
            :func:`gcrsky.compress_problem`).
        frame_pad: degree margin of the ICRS -> of-date frame map.
        memory_budget: bytes the read may use (default: the free memory).

    Returns:
        a :class:`~gcrsky.model.Problem` with ``pols`` recording each row's product and
        ``config`` a :class:`DataConfig`.
    """
    from astropy.time import Time

    from ..base.dtypes import require_x64

    require_x64("from_uvdata")
    prods, raw = _pol_rows(pol)
    noise_kind = noise if isinstance(noise, str) else "given"
    if noise_kind not in ("autos", "diff", "given"):
        raise ValueError(f"noise must be 'autos', 'diff' or a per-component sigma, got {noise!r}")
    uvd, source, selection = read_uvdata(
        data, pol=pol, freq_chans=freq_chans, freq_range_hz=freq_range_hz, times_jd=times_jd,
        lst_range_hours=lst_range_hours, antennas=antennas, bls=bls, autos=noise_kind == "autos",
        memory_budget=memory_budget)
    notes: list[str] = []
    conventions = _check_units_phase(uvd, notes)
    for line in notes:
        log.warning(line)
    smp = _Samples(uvd, raw)
    if noise_kind == "autos" and smp.n_autos == 0:
        raise ValueError("the file (selection) has no autocorrelations for the radiometer noise: pass noise='diff' "
                         "(time-adjacent differences) or a per-component sigma")
    nf, nt, nbl = smp.freqs.size, smp.times_jd.size, smp.pairs.shape[0]

    # noise per raw product, in the file's units
    var = {}
    for r in raw:
        if noise_kind == "autos":
            var[r] = smp.radiometer_var(r)
        elif noise_kind == "diff":
            var[r] = smp.diff_var(r)
        else:
            s = np.broadcast_to(np.asarray(noise, np.float64), (nf, nt, nbl))
            with np.errstate(divide="ignore"):
                var[r] = np.where(smp.nsample[r] > 0, s**2 / np.where(smp.nsample[r] > 0, smp.nsample[r], 1.0),
                                  np.nan)

    # combine into the modelled products, I-equivalent, K sr
    pol_conv = getattr(uvd, "pol_convention", None) or "sum"
    to_ksr = 1.0 / kelvin_sr_to_jy(smp.freqs) if conventions["vis_units"] == "Jy" else np.ones(nf)
    rows_d, rows_v, rows_ok, row_pols = [], [], [], []
    for p in prods:
        comps = POLS[p]
        if p == "pI":
            c = 1.0 if pol_conv == "sum" else 0.5
        else:
            c = 2.0 if pol_conv == "sum" else 1.0
        d = c * sum(smp.vis[r] for r in comps)
        v = c**2 * sum(var[r] for r in comps)
        ok = np.all([~smp.flag[r] & (smp.nsample[r] > 0) for r in comps], axis=0) & np.isfinite(v) & (v > 0)
        rows_d.append(d * to_ksr[:, None, None])
        rows_v.append(np.where(ok, v, 1.0) * to_ksr[:, None, None] ** 2)
        rows_ok.append(ok)
        row_pols += [p] * nbl
    data_k = np.concatenate(rows_d, axis=2)
    sigma = np.sqrt(np.concatenate(rows_v, axis=2))
    weights = np.concatenate(rows_ok, axis=2).astype(np.float64)
    pairs = np.concatenate([smp.pairs] * len(prods), axis=0)
    n_bad_noise = int(sum(np.sum(~np.isfinite(var[r]) & ~smp.flag[r]) for r in raw))
    if n_bad_noise:
        log.warning("%d unflagged samples have no noise estimate (a missing or flagged autocorrelation, or no "
                    "time-adjacent pair): weight 0", n_bad_noise)

    # the instrument and the geometry
    tel = uvd.telescope
    loc = tel.location
    enu_all = np.asarray(tel.get_enu_antpos(), np.float64)
    nums_all = [int(a) for a in tel.antenna_numbers]
    enu = enu_all[[nums_all.index(int(a)) for a in smp.antnums]]
    beams, beam_note = _resolve_beams(beam, dish_diameter_m, tel, smp.antnums)
    array = make_array(enu, float(loc.lat.deg), list(beams))
    times = Time(smp.times_jd, format="jd", scale="utc")
    geom = observation_geometry(array, lmax, times=times, location=loc, frame_pad=frame_pad)
    lst_ref = float(geom.lsts_rad[0])
    _check_beam_freqs(beams, smp.freqs)
    resp = _response(array, pairs, smp.freqs, geom.lmax_response, nside, lst_ref, row_pols)
    auto_pairs = np.stack([np.arange(len(smp.antnums))] * 2, 1)
    auto = _response(array, auto_pairs, smp.freqs, geom.lmax_response, nside, lst_ref,
                     [prods[0]] * auto_pairs.shape[0])
    prior_obj, prior_note = _resolve_prior(prior, prior_scale, smp.freqs, lmax)
    lst_h = np.unwrap(np.asarray(geom.lsts_rad, np.float64)) * 12.0 / np.pi
    lst_h = lst_h - 24.0 * np.floor(lst_h[0] / 24.0)
    fwhm = tuple(_fwhm_deg(beams[0], f) for f in smp.freqs)
    cfg = DataConfig(
        source=source, pol=prods[0] if len(prods) == 1 else prods, lmax=int(lmax), nside=int(nside), beam=beam_note,
        prior=prior_note, noise=noise_kind, selection=selection,
        conventions={**conventions, "factor": f"{'sum' if pol_conv == 'sum' else 'avg'} convention: modelled as "
                     + ", ".join(f"{p}" for p in prods) + " I-equivalent", "antenna_numbers":
                     [int(a) for a in smp.antnums]},
        compressed=False,
        latitude_deg=float(loc.lat.deg),
        lst_range_hours=(float(lst_h.min()), float(lst_h.max())),
        fwhm_deg=fwhm,
    )
    log.info("from_uvdata: %s; %d antennas, %d baselines x %d products, %d times, %d channels; prior: %s",
             source, len(smp.antnums), nbl, len(prods), nt, nf, prior_note)
    prob = assemble_problem(array, smp.freqs, geom, (resp, auto), lmax, nside, data_k, sigma, weights=weights,
                            prior=prior_obj, lst_ref_rad=lst_ref, config=cfg, pairs=pairs, pols=row_pols,
                            sky_note=f"data: {source}")
    if compress:
        prob = _compress(prob, array, cfg)
    return prob


def _fwhm_deg(beam, freq_hz) -> float:
    """FWHM of a beam (feed x power) in degrees, NaN where it does not fall to half above the horizon."""
    from ..instrument.beams import beam_fwhm_rad

    try:
        return float(np.rad2deg(beam_fwhm_rad(beam, float(freq_hz))))
    except ValueError:
        return float("nan")


def _check_beam_freqs(beams, freqs):
    """Refuse frequencies outside any beam's range (no extrapolation)."""
    from ..instrument.beams import check_beam_frequencies

    for b in {id(b): b for b in beams}.values():
        check_beam_frequencies(b, freqs)


def _response(array, pairs, freqs, lmax_resp, nside, lst_ref, pols):
    """The response rows of ``pairs`` for the products ``pols`` (one per row)."""
    return response_matrix(array, pairs, freqs, lmax_resp, nside, lst_ref_rad=lst_ref, pols=list(pols))


#: Response tolerance of the automatic compression: antenna positions read from a file go through ECEF
#: (6.4e6 m), so "redundant" baselines differ by ~1e-9 m and their responses by ~1e-9 relative (measured
#: 1.6e-9 at 102 MHz); merging within 1e-8 changes the model far below any noise or simulator agreement.
COMPRESS_RTOL = 1e-8


def _compress(prob, array, cfg):
    from ..model.compress import compress_problem

    try:
        out = compress_problem(prob, array, rtol=COMPRESS_RTOL)
    except ValueError as err:  # not exactly redundant (e.g. per-antenna beams): keep every baseline
        log.info("redundant compression skipped: %s", err)
        return prob
    if out.antpairs.shape[0] == prob.antpairs.shape[0]:
        return prob
    log.info("redundant compression: %d -> %d rows (responses equal to %g)", prob.antpairs.shape[0], out.antpairs.shape[0],
             COMPRESS_RTOL)
    return dataclasses.replace(out, config=dataclasses.replace(cfg, compressed=True))


# ---------------------------------------------------------------- inspect


def inspect_uvdata(path, *, pol="pI", lmax: int | None = None, nside: int | None = None, **selection) -> dict:
    """What :func:`from_uvdata` would use, without building the response or solving (a JSON-friendly dict).

    Reads the selection (so flags and autos are known) and reports the antennas,
    baselines (and unique ones), times and LST coverage, channels, products, units,
    conventions, the flagged fraction, a radiometer noise estimate from the autos (median
    per-component sigma of the modelled product, K sr) and the memory of the read and,
    with ``lmax`` (and ``nside``), of the dense posterior precision.
    """
    from ..instrument.redundancy import redundant_groups

    prods, raw = _pol_rows(pol)
    uvd, source, sel = read_uvdata(path, pol=pol, **selection)
    notes: list[str] = []
    conv = _check_units_phase(uvd, notes)
    smp = _Samples(uvd, raw)
    nf, nt, nbl = smp.freqs.size, smp.times_jd.size, smp.pairs.shape[0]
    enu_all = np.asarray(uvd.telescope.get_enu_antpos())
    nums_all = [int(a) for a in uvd.telescope.antenna_numbers]
    enu = enu_all[[nums_all.index(int(a)) for a in smp.antnums]]
    groups = redundant_groups(enu, smp.pairs)
    lsts = np.unique(np.asarray(uvd.lst_array))
    flagged = float(np.mean([np.mean(smp.flag[r] | (smp.nsample[r] <= 0)) for r in raw]))
    sig = None
    if smp.n_autos:
        to_ksr = 1.0 / kelvin_sr_to_jy(smp.freqs) if conv["vis_units"] == "Jy" else np.ones(nf)
        v = sum(smp.radiometer_var(r) for r in POLS[prods[0]])
        c = (1.0 if (getattr(uvd, "pol_convention", None) or "sum") == "sum" else 0.5) if prods[0] == "pI" else \
            (2.0 if (getattr(uvd, "pol_convention", None) or "sum") == "sum" else 1.0)
        with np.errstate(invalid="ignore"):
            sig = float(np.nanmedian(c * np.sqrt(v) * to_ksr[:, None, None]))
    out = {
        "source": source,
        "selection": sel,
        "antennas": [int(a) for a in smp.antnums],
        "n_antennas": int(smp.antnums.size),
        "n_baselines": nbl,
        "n_unique_baselines": groups.n_groups,
        "n_times": nt,
        "time_range_jd": [float(smp.times_jd.min()), float(smp.times_jd.max())],
        "lst_range_hours": [float(np.rad2deg(lsts.min()) / 15), float(np.rad2deg(lsts.max()) / 15)],
        "n_channels": nf,
        "freq_range_hz": [float(smp.freqs.min()), float(smp.freqs.max())],
        "channel_width_hz": float(np.median(smp.chan_width)),
        "file_polarizations": [str(p) for p in uvd.get_pols()],
        "modelled_products": list(prods),
        "conventions": conv,
        "notes": notes,
        "flagged_fraction": flagged,
        "has_autos": bool(smp.n_autos),
        "noise_sigma_median_k_sr": sig,
        "read_bytes": _estimate_bytes(uvd, {})[1],
        "site_lat_lon_deg": [float(uvd.telescope.location.lat.deg), float(uvd.telescope.location.lon.deg)],
    }
    if lmax is not None:
        n = n_params(lmax)
        out["n_params"] = n
        out["dense_precision_bytes"] = float(nf * n * n * 8)
        out["real_data_values"] = int(2 * groups.n_groups * nt * nf * len(prods))
        if nside is not None:
            out["response_bytes"] = float(nf * groups.n_groups * len(prods) * n_params(lmax + frame_pad_default())
                                          * 16)
    return out


def frame_pad_default() -> int:
    """The default degree margin of the frame map (:func:`from_uvdata`'s ``frame_pad``)."""
    return 4
