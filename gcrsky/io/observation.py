"""Reading a visibility file into an :class:`~gcrsky.io.Observation` (what the file says).

:func:`read_observation` reads any file ``UVData.from_file`` reads (UVH5; UVFITS,
Measurement Sets, MIRIAD where pyuvdata's optional readers are installed), or selects
from a ``UVData`` object, and arranges it on gcrsky's grids in gcrsky's conventions:

* Selections (frequency channels or range, times or LST range, antennas, baselines,
  including an arbitrary subset of pairs, feed products) are computed on the file's
  metadata and applied when reading, so pyuvdata reads only those parts of a UVH5 file;
  the size of the selection is checked against the free memory before anything is read
  (:func:`read_uvdata`).
* Baselines: pyuvdata's ``V_12 = <V_1^* V_2>`` with ``uvw = x_2 - x_1`` is gcrsky's
  ``(i, j)`` with baseline ``x_j - x_i``.  A row stored as ``(ant_2, ant_1)`` is
  conjugated into the canonical ``i < j`` (antennas indexed by increasing number), its
  feed product reversed (``xy`` <-> ``yx``, pyuvdata's ``conj_pol``), so any stored
  conjugation reads the same.  A pair or time absent from the file is an absent,
  flagged sample.  A sample stored twice is an error.
* Phase: drift-scan ("unprojected") data are kept as they are; a projected file is
  unprojected by pyuvdata (``UVData.unproject_phase``), and the Observation says so.
* Units and conventions are recorded, not converted (``"uncalib"`` reads; building a
  :class:`~gcrsky.model.Problem` in physical units refuses it).

Nothing here is physics: :func:`gcrsky.model.problem_from_observation` turns the
Observation into the inference problem.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np

from ..base.memory import check_memory, format_bytes
from .files import check_input_file, reading
from .selection import VIS_FORMATS, estimate_bytes, selection_kwargs
from .visdata import HISTORY_CHARS, Observation, parse_products

__all__ = ["read_observation", "read_uvdata"]

log = logging.getLogger(__name__)

def read_uvdata(data, *, pol="pI", freq_chans=None, freq_range_hz=None, times_jd=None, lst_range_hours=None,
                antennas=None, bls=None, autos: bool = True, memory_budget: float | None = None):
    """Read the selected part of a visibility file (or select from a ``UVData``): ``(UVData, source, selection)``.

    The selection is computed on the file's metadata (``read_data=False``), its size
    checked against the memory budget (:func:`gcrsky.base.check_memory`), then only it is
    read.  Arguments as :func:`read_observation` (``pol``: the modelled product(s), whose
    feed products are read, or None for every product); ``autos``: with ``bls``, keep
    the autocorrelations of the selected antennas too (the radiometer noise needs them).
    """
    from pyuvdata import UVData

    if isinstance(data, (list, tuple)) and len(data) == 1:
        data = data[0]
    if isinstance(data, (list, tuple)):  # several files: each read partially, then joined along time
        from .manyfiles import join_parts, read_parts, source_name

        parts, _ = read_parts(data, pol=pol, freq_chans=freq_chans,
                              freq_range_hz=freq_range_hz, times_jd=times_jd, lst_range_hours=lst_range_hours,
                              antennas=antennas, bls=bls, autos=autos, memory_budget=memory_budget)
        return join_parts(parts), source_name([p.path for p in parts]), many_selection(parts)
    raw = None if pol is None else parse_products(pol)[1]
    if isinstance(data, UVData):
        meta, source = data, "<UVData object>"
    else:
        path = check_input_file(data, "visibility file", measurement_set=True)
        with reading(path, "a visibility file", VIS_FORMATS):
            meta = UVData.from_file(str(path), read_data=False)
        source = str(path)
    kw = selection_kwargs(meta, freq_chans=freq_chans, freq_range_hz=freq_range_hz, times_jd=times_jd,
                           lst_range_hours=lst_range_hours, antennas=antennas, bls=bls, raw=raw, autos=autos)
    samples, nbytes = estimate_bytes(meta, kw)
    log.info("reading %s: %d samples selected (%s with gcrsky's copies)", source, samples, format_bytes(nbytes))
    check_memory(nbytes, f"reading {samples} visibility samples from {source}",
                 "select fewer channels, times, antennas or baselines", budget=memory_budget)
    if isinstance(data, UVData):
        uvd = data.select(**kw, inplace=False) if kw else data.copy()
    else:
        with reading(source, "a visibility file", VIS_FORMATS):
            uvd = UVData.from_file(source, **kw)
    selection = {k: (np.asarray(v).tolist() if not isinstance(v, list) else v) for k, v in kw.items()}
    return uvd, source, selection


def many_selection(parts) -> dict:
    """The selection record of several files' parts: the files read, each one's read keywords and
    integrations (JD; :func:`observation_of` tells each time's file from them)."""
    return {"files": [p.path for p in parts], "per_file": [p.selection for p in parts],
            "file_times_jd": [p.times_jd.tolist() for p in parts]}


def _time_files(selection: dict, times_jd) -> tuple[tuple, tuple]:
    """(files, index of each time's file) of a many-file selection; ``((), ())`` for one file."""
    if "file_times_jd" not in selection:
        return (), ()
    owner = {float(t): k for k, ts in enumerate(selection["file_times_jd"]) for t in ts}
    return tuple(selection["files"]), tuple(int(owner[float(t)]) for t in np.asarray(times_jd, np.float64))


# ---------------------------------------------------------------- arranging the samples


def unproject(uvd) -> tuple[str, list]:
    """Unproject a projected ``uvd`` in place: (phase type, notes)."""
    types = {int(k): v.get("cat_type") for k, v in uvd.phase_center_catalog.items()}
    used = {int(i) for i in np.unique(uvd.phase_center_id_array)}
    projected = [i for i in used if types.get(i) != "unprojected"]
    if not projected:
        return "unprojected", []
    uvd.unproject_phase()
    return "projected", [f"the file's data are phased to a phase centre (ids {projected}); unprojected them with "
                         f"pyuvdata to drift-scan data"]


class _Rows(NamedTuple):
    """Where each of the file's rows goes on gcrsky's grids."""

    antnums: np.ndarray  # (Nant,) antennas of the cross-correlations, increasing
    times_jd: np.ndarray  # (Nt,)
    tidx: np.ndarray  # (Nblts,) time index of each row
    ant_i: np.ndarray  # (Nblts,) antenna index of ant_1 (-1: not in a cross-correlation)
    swap: np.ndarray  # (Nblts,) the row is stored as (ant_2, ant_1)
    pairs: np.ndarray  # (Nbl, 2) antenna index pairs i < j
    cross: np.ndarray  # (Ncross,) rows of cross-correlations
    pidx: np.ndarray  # (Ncross,) their pair index
    auto: np.ndarray  # (Nauto,) rows of autocorrelations of the antennas in antnums


def _row_index(uvd) -> _Rows:
    a1, a2 = np.asarray(uvd.ant_1_array), np.asarray(uvd.ant_2_array)
    cross = a1 != a2
    if not np.any(cross):
        raise ValueError("the selection holds no cross-correlations")
    antnums = np.unique(np.concatenate([a1[cross], a2[cross]]))
    index = {int(a): k for k, a in enumerate(antnums)}
    times_jd, tidx = np.unique(np.asarray(uvd.time_array), return_inverse=True)
    tidx = tidx.reshape(-1)
    i = np.array([index.get(int(a), -1) for a in a1])
    j = np.array([index.get(int(b), -1) for b in a2])
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    pairs, pidx = np.unique(np.stack([lo[cross], hi[cross]], 1), axis=0, return_inverse=True)
    rows = _Rows(antnums, times_jd, tidx, i, cross & (i > j), pairs, np.flatnonzero(cross), pidx.reshape(-1),
                 np.flatnonzero(~cross & (i >= 0)))
    _refuse_duplicates(rows, a1, a2)
    n_other = int(np.sum(~cross & (i < 0)))
    if n_other:
        log.info("%d autocorrelation rows of antennas without cross-correlations are not used", n_other)
    return rows


def _refuse_duplicates(rows: _Rows, a1, a2) -> None:
    """A (time, pair) or (time, antenna) stored twice (e.g. in both orders) is an error, not a silent choice."""
    for what, sel, slot in (("baseline", rows.cross, rows.pidx), ("autocorrelation", rows.auto, rows.ant_i[rows.auto])):
        key = rows.tidx[sel] * (len(rows.pairs) + len(rows.antnums)) + slot
        uniq, first, counts = np.unique(key, return_index=True, return_counts=True)
        if np.any(counts > 1):
            r = sel[first[np.argmax(counts > 1)]]
            raise ValueError(f"the file holds the {what} ({int(a1[r])}, {int(a2[r])}) at time "
                             f"{float(np.asarray(rows.times_jd)[rows.tidx[r]])} JD more than once "
                             "(stored in both orders?): select one")


def _conjugate_sources(uvd, rows: _Rows) -> list[int]:
    """For each product, the product index whose conjugate a swapped row supplies (``xy`` for ``yx``)."""
    from pyuvdata.utils.pol import conj_pol, polnum2str

    pols = [int(p) for p in np.asarray(uvd.polarization_array)]
    out = []
    for p in pols:
        c = int(conj_pol(p))
        if c not in pols and np.any(rows.swap[rows.cross]):
            raise ValueError(f"rows stored as (ant_2, ant_1) give product {polnum2str(p)} as the conjugate of "
                             f"{polnum2str(c)}, which is not read: read both (or conjugate the file first)")
        out.append(pols.index(c) if c in pols else pols.index(p))
    return out


def _cross_grids(uvd, rows: _Rows) -> dict:
    """Cross-correlations on (Npols, Nf, Nt, Nbl) grids, conjugated into ``i < j``."""
    npol, nf = len(uvd.polarization_array), int(np.asarray(uvd.freq_array).size)
    shape = (npol, nf, rows.times_jd.size, rows.pairs.shape[0])
    vis, flags, nsamp = np.zeros(shape, np.complex128), np.ones(shape, bool), np.zeros(shape)  # absent: flagged
    data, flag, ns = np.asarray(uvd.data_array), np.asarray(uvd.flag_array, bool), np.asarray(uvd.nsample_array)
    r, t, b = rows.cross, rows.tidx[rows.cross], rows.pidx
    sw = rows.swap[r][:, None]
    for k, kc in enumerate(_conjugate_sources(uvd, rows)):
        vis[k][:, t, b] = np.where(sw, np.conj(data[r, :, kc]), data[r, :, k]).T
        flags[k][:, t, b] = np.where(sw, flag[r, :, kc], flag[r, :, k]).T
        nsamp[k][:, t, b] = np.where(sw, ns[r, :, kc], ns[r, :, k]).T
    present = np.zeros(shape[2:], bool)
    present[t, b] = True
    dt = np.zeros(shape[2:])
    dt[t, b] = np.asarray(uvd.integration_time, np.float64)[r]
    return {"vis": vis, "flags": flags, "nsamples": nsamp, "present": present, "integration_time_s": dt}


def _auto_grids(uvd, rows: _Rows) -> dict:
    """Autocorrelations on (Npols, Nf, Nt, Nant) grids."""
    npol, nf = len(uvd.polarization_array), int(np.asarray(uvd.freq_array).size)
    shape = (npol, nf, rows.times_jd.size, rows.antnums.size)
    autos, flags, nsamp = np.zeros(shape, np.complex128), np.ones(shape, bool), np.zeros(shape)
    r = rows.auto
    t, a = rows.tidx[r], rows.ant_i[r]
    autos[:, :, t, a] = np.transpose(np.asarray(uvd.data_array)[r], (2, 1, 0))
    flags[:, :, t, a] = np.transpose(np.asarray(uvd.flag_array, bool)[r], (2, 1, 0))
    nsamp[:, :, t, a] = np.transpose(np.asarray(uvd.nsample_array)[r], (2, 1, 0))
    present = np.zeros(shape[2:], bool)
    present[t, a] = True
    return {"autos": autos, "auto_flags": flags, "auto_nsamples": nsamp, "auto_present": present}


def _site_and_antennas(uvd, rows: _Rows, source: str = "the file") -> dict:
    from astropy.coordinates import EarthLocation

    tel = uvd.telescope
    loc = tel.location
    if not isinstance(loc, EarthLocation):
        raise ValueError(f"the telescope's location is a {type(loc).__name__}: gcrsky models observations from Earth")
    xyz = np.array([loc.x.to_value("m"), loc.y.to_value("m"), loc.z.to_value("m")], np.float64)
    if not np.all(np.isfinite(xyz)) or np.linalg.norm(xyz) < 6.0e6:
        raise ValueError(f"{source}: the telescope's location (telescope_location, ECEF {xyz.tolist()} m) is not a "
                         "place on the Earth's surface: fix the file's header")
    nums_all = [int(a) for a in tel.antenna_numbers]
    sel = [nums_all.index(int(a)) for a in rows.antnums]
    rel = np.asarray(tel.antenna_positions, np.float64)[sel]
    bad = ~np.all(np.isfinite(rel), axis=1)
    if np.any(bad):
        raise ValueError(f"{source}: the positions of antennas {rows.antnums[bad].tolist()} are not finite (the "
                         "telescope's antenna_positions): fix them, or leave those antennas out (--antennas)")
    return {
        "antenna_numbers": rows.antnums,
        "antenna_names": np.asarray(tel.antenna_names)[sel],
        "antpos_enu_m": np.asarray(tel.get_enu_antpos(), np.float64)[sel],
        "site_ecef_m": np.array([loc.x.to_value("m"), loc.y.to_value("m"), loc.z.to_value("m")], np.float64),
        "telescope_name": str(tel.name),
        "telescope_antenna_numbers": np.asarray(tel.antenna_numbers, np.int64),
        "telescope_antenna_names": np.asarray(tel.antenna_names),
        "x_orientation": tel.get_x_orientation_from_feeds(),
    }


def observation_of(uvd, *, source: str, selection: dict, phase_type: str, notes) -> Observation:
    """The Observation of an (unprojected, selected) ``UVData``."""
    rows = _row_index(uvd)
    files, time_file = _time_files(selection, rows.times_jd)
    lsts = np.zeros(rows.times_jd.size)
    lsts[rows.tidx] = np.asarray(uvd.lst_array, np.float64)
    freqs = np.asarray(uvd.freq_array, np.float64).reshape(-1)
    return Observation(
        **_cross_grids(uvd, rows), **_auto_grids(uvd, rows), **_site_and_antennas(uvd, rows, source),
        antpairs=rows.pairs, times_jd=rows.times_jd, lsts_rad=lsts, freqs_hz=freqs,
        channel_width_hz=np.broadcast_to(np.asarray(uvd.channel_width, np.float64).reshape(-1), freqs.shape),
        polarizations=np.asarray(uvd.polarization_array, np.int64), vis_units=str(uvd.vis_units),
        pol_convention=getattr(uvd, "pol_convention", None), phase_type=phase_type, source=source,
        history=str(uvd.history or "")[:HISTORY_CHARS], selection=selection, nblts_read=int(uvd.Nblts),
        notes=tuple(notes), files=files, time_file=time_file,
    )


def read_observation(
    data,
    *,
    pol=None,
    freq_chans=None,
    freq_range_hz=None,
    times_jd=None,
    lst_range_hours=None,
    antennas=None,
    bls=None,
    autos: bool = True,
    memory_budget: float | None = None,
) -> Observation:
    """Read a visibility file (or select from a ``UVData``) into an :class:`~gcrsky.io.Observation`.

    Args:
        data: a path to any file ``UVData.from_file`` reads, or a ``UVData`` object (not
            modified).
        pol: None (default: every feed product in the file), or the modelled product(s)
            (``"pI"``, ``"xx"``, ``"yy"``, ``("xx", "yy")`` or ``"xx,yy"``; the feed
            products they need are read, and must be in the file).
        freq_chans, freq_range_hz: channel indices, and/or a (lo, hi) range in Hz.
        times_jd, lst_range_hours: integration times (JD) to keep, and/or an LST range
            (hours; ``(22, 2)`` wraps through 0 h).
        antennas: antenna numbers or names to keep (pairs among them).
        bls: antenna pairs to keep (numbers or names), any subset.
        autos: with ``bls``, also keep the autocorrelations of their antennas.
        memory_budget: bytes the read may use (default: the free memory).

    Returns:
        the :class:`~gcrsky.io.Observation` (module docstring for the conventions).
    """
    uvd, source, selection = read_uvdata(
        data, pol=pol, freq_chans=freq_chans, freq_range_hz=freq_range_hz, times_jd=times_jd,
        lst_range_hours=lst_range_hours, antennas=antennas, bls=bls, autos=autos, memory_budget=memory_budget)
    phase_type, notes = unproject(uvd)
    for line in notes:
        log.info(line)
    return observation_of(uvd, source=source, selection=selection, phase_type=phase_type, notes=notes)
