"""Selections of a visibility file computed on its metadata: pyuvdata read keywords and their size.

Shared by the one-file reader (:mod:`gcrsky.io.observation`) and the many-file reader
(:mod:`gcrsky.io.manyfiles`): channels (indices and/or a range), times (JD and/or an LST
range), feed products, antennas and baselines, turned into ``UVData.from_file`` / ``select``
keywords (:func:`selection_kwargs`) whose size (:func:`estimate_bytes`) is checked before
anything is read.
"""

from __future__ import annotations

import numpy as np

__all__ = ["VIS_FORMATS", "estimate_bytes", "kept_times", "read_bytes", "selection_kwargs"]

#: Bytes per sample of a read (data complex128, flags, nsample float64) and of gcrsky's copies.
_BYTES_PER_SAMPLE = 16 + 1 + 8


# ---------------------------------------------------------------- selections


def _channel_selection(meta, freq_chans, freq_range_hz) -> dict:
    freqs = np.asarray(meta.freq_array, np.float64).reshape(-1)
    chans = np.arange(freqs.size)
    if freq_chans is not None:
        chans = np.asarray(freq_chans, np.int64).reshape(-1)
        if chans.size == 0 or chans.min() < 0 or chans.max() >= freqs.size:
            raise ValueError(f"freq_chans must index the file's {freqs.size} channels, got {freq_chans!r}")
        if np.unique(chans).size != chans.size:
            raise ValueError(f"freq_chans names a channel more than once ({freq_chans!r}): each channel is read once")
        chans = np.sort(chans)
    if freq_range_hz is not None:
        lo, hi = (float(x) for x in freq_range_hz)
        chans = chans[(freqs[chans] >= lo) & (freqs[chans] <= hi)]
        if chans.size == 0:
            raise ValueError(f"no channel in {lo / 1e6:g}-{hi / 1e6:g} MHz (the file has "
                             f"{freqs.min() / 1e6:g}-{freqs.max() / 1e6:g} MHz)")
    return {"freq_chans": chans} if not np.array_equal(chans, np.arange(freqs.size)) else {}


def kept_times(meta, times_jd, lst_range_hours) -> tuple[np.ndarray, np.ndarray]:
    """The file's unique times (JD, increasing) and which the selection keeps (bool); ``times_jd``
    absent from the file are not an error here (:func:`_time_selection` and the many-file reader say)."""
    tj = np.unique(np.asarray(meta.time_array))
    keep_t = np.ones(tj.size, bool)
    if times_jd is not None:
        keep_t &= np.isin(tj, np.atleast_1d(np.asarray(times_jd, np.float64)))
    if lst_range_hours is not None:
        lo, hi = (float(x) % 24.0 for x in lst_range_hours)
        lst_h = np.zeros(tj.size)
        ut, idx = np.unique(np.asarray(meta.time_array), return_index=True)
        lst_h[np.searchsorted(tj, ut)] = np.rad2deg(np.asarray(meta.lst_array)[idx]) / 15.0
        keep_t &= ((lst_h >= lo) & (lst_h <= hi)) if lo <= hi else ((lst_h >= lo) | (lst_h <= hi))
    return tj, keep_t


def _time_selection(meta, times_jd, lst_range_hours) -> dict:
    tj, keep_t = kept_times(meta, times_jd, lst_range_hours)
    if times_jd is not None:
        want = np.atleast_1d(np.asarray(times_jd, np.float64))
        missing = want[~np.isin(want, tj)]
        if missing.size:
            raise ValueError(f"times {missing[:3]} (JD) are not in the file")
    if not np.any(keep_t):
        raise ValueError("the time / LST selection leaves no integration")
    return {"times": tj[keep_t]} if not np.all(keep_t) else {}


def _pol_selection(meta, raw) -> dict:
    """``polarizations`` keyword for the raw feed products ``raw`` (None: every product in the file)."""
    from pyuvdata import utils

    file_pols = [int(p) for p in np.asarray(meta.polarization_array)]
    if raw is None:
        return {}
    missing = [r for r in raw if utils.polstr2num(r) not in file_pols]
    if missing:
        names = [utils.polnum2str(p) for p in file_pols]
        raise ValueError(f"the file holds polarisations {names}; pol needs {list(raw)} (missing {missing})")
    return {"polarizations": [int(utils.polstr2num(r)) for r in raw]} if len(raw) != len(file_pols) else {}


def _baseline_selection(meta, antennas, bls, autos) -> dict:
    kw: dict = {}
    if antennas is not None:
        kw["antenna_nums"] = _antenna_numbers(meta, antennas)
    if bls is not None:
        pairs = [tuple(int(x) for x in _antenna_numbers(meta, b)) for b in bls]
        if any(len(p) != 2 for p in pairs):
            raise ValueError("bls must be a sequence of antenna pairs (number or name each)")
        if autos:  # the radiometer noise needs the autos of every antenna involved
            pairs += [(a, a) for a in sorted({a for p in pairs for a in p})]
        kw["bls"] = sorted(set(pairs))
    return kw


def selection_kwargs(meta, *, freq_chans, freq_range_hz, times_jd, lst_range_hours, antennas, bls, raw, autos,
                      times=None):
    """pyuvdata ``select`` / ``read`` keywords for the selection (computed on the metadata); ``times``: the
    time keywords already computed (the many-file reader's, per file)."""
    t = _time_selection(meta, times_jd, lst_range_hours) if times is None else times
    return {**_channel_selection(meta, freq_chans, freq_range_hz), **t,
            **_pol_selection(meta, raw), **_baseline_selection(meta, antennas, bls, autos)}


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


def estimate_bytes(meta, kw) -> tuple[int, float]:
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


def read_bytes(nblts: int, nfreqs: int, npols: int) -> float:
    """Bytes a read of ``nblts`` rows of ``nfreqs`` channels and ``npols`` products holds (with gcrsky's copies)."""
    return float(nblts * nfreqs * npols) * _BYTES_PER_SAMPLE * 3


#: What a visibility file may be, for read errors.
VIS_FORMATS = "UVH5, UVFITS or Measurement Set (anything pyuvdata's UVData reads)"
