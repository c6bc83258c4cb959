"""Many visibility files read as one observation: a night of files, several nights, LST-binned files.

A HERA night is ~70 files of a few minutes each; LST-binned data come as many files too.
:func:`read_parts` reads each file's metadata, checks that the files share one array
(:func:`check_same_array`: telescope, site, the positions of the antennas they share,
channels, feed products, units; no integration in two files), computes each file's part of
the selection on its metadata (channels, products and antennas as for one file; the times
or LST range per file: a file with no selected integration is not read, and the notes say
so), checks the total size against the memory budget, then reads only those parts.
:func:`join_parts` joins them along pyuvdata's baseline-time axis (``UVData.fast_concat``)
so that the rest of the ingest sees one ``UVData`` whose times are the union of the files'.

Times may be far apart (several nights): the model uses each integration's LST and time, the
date only through them.  What needs adjacent integrations (the noise-excess check, the
``diff`` noise) pairs only integrations one integration time apart
(:func:`gcrsky.model.datachecks.adjacent_times`).

Calibration per file (one solutions file per data file) is applied to each part before the
join (:func:`gcrsky.io.calibration.read_calibrated_observation`).
"""

from __future__ import annotations

import logging
import os
from typing import NamedTuple

import numpy as np

from ..base.memory import check_memory, format_bytes
from .files import check_input_file, reading
from .selection import VIS_FORMATS, estimate_bytes, kept_times, selection_kwargs

__all__ = ["ARRAY_TOL_M", "FREQ_TOL_HZ", "FilePart", "check_same_array", "first_file", "join_parts", "read_parts",
           "source_name"]

log = logging.getLogger(__name__)

#: Two files hold the same antenna when their positions (ENU about each file's site) agree within this (m).
ARRAY_TOL_M = 0.01
#: Two files' sites agree within this (m).
SITE_TOL_M = 1.0
#: Two files' channels agree within this (Hz).
FREQ_TOL_HZ = 1.0


class FilePart(NamedTuple):
    """One file's part of the selection, read.

    Attributes:
        path: the file.
        uvd: its selected ``UVData``.
        selection: the pyuvdata read keywords used (JSON-friendly).
        times_jd: (Nt_file,) its integrations kept, JD increasing.
    """

    path: str
    uvd: object
    selection: dict
    times_jd: np.ndarray


def first_file(data):
    """The first of several files (whose header stands for all: :func:`check_same_array`), else ``data``."""
    return data[0] if isinstance(data, (list, tuple)) and data else data


def source_name(paths) -> str:
    """How an observation of ``paths`` names its source: the path, or the first and how many more."""
    paths = [str(p) for p in paths]
    return paths[0] if len(paths) == 1 else f"{paths[0]} and {len(paths) - 1} more file(s)"


def _metadata(path: str):
    from pyuvdata import UVData

    p = check_input_file(path, "visibility file", measurement_set=True)
    with reading(p, "a visibility file", VIS_FORMATS):
        return UVData.from_file(str(p), read_data=False)


def _mhz(f) -> str:
    return f"{f.size} channels, {f.min() / 1e6:.4f}-{f.max() / 1e6:.4f} MHz"


def _positions(meta) -> dict:
    enu = np.asarray(meta.telescope.get_enu_antpos(), np.float64)
    return {int(a): enu[k] for k, a in enumerate(meta.telescope.antenna_numbers)}


def check_same_array(metas, paths) -> None:
    """Refuse files that are not of one array and band (module docstring), naming the file and the field.

    Args:
        metas: the files' ``UVData`` metadata (``read_data=False``), in ``paths`` order.
        paths: the files.

    Raises:
        ValueError: a different telescope, site (> :data:`SITE_TOL_M`), antenna position of a shared
            antenna number (> :data:`ARRAY_TOL_M`), channel set (> :data:`FREQ_TOL_HZ`), feed
            products or units; no shared antenna; an integration in two files.
    """
    from pyuvdata.utils.pol import polnum2str

    ref, p0 = metas[0], paths[0]
    f0 = np.asarray(ref.freq_array, np.float64).ravel()
    pols0 = sorted(int(p) for p in np.asarray(ref.polarization_array))
    loc0 = ref.telescope.location
    pos0 = _positions(ref)
    for meta, path in zip(metas[1:], paths[1:]):
        head = f"{path} and {p0} are not of one array and band"
        if str(meta.telescope.name) != str(ref.telescope.name):
            raise ValueError(f"{head}: telescope {meta.telescope.name!r} against {ref.telescope.name!r}")
        loc = meta.telescope.location
        dist = float(np.sqrt(sum((getattr(loc, c) - getattr(loc0, c)).to_value("m") ** 2 for c in "xyz")))
        if dist > SITE_TOL_M:
            raise ValueError(f"{head}: their sites are {dist:.3g} m apart (telescope_location)")
        f = np.asarray(meta.freq_array, np.float64).ravel()
        if f.shape != f0.shape or np.max(np.abs(f - f0)) > FREQ_TOL_HZ:
            raise ValueError(f"{head}: the channels differ ({_mhz(f)} against {_mhz(f0)}); files of one run share "
                             "the file's channels (select the same channels in each before splitting)")
        pols = sorted(int(p) for p in np.asarray(meta.polarization_array))
        if pols != pols0:
            raise ValueError(f"{head}: the feed products differ ({[polnum2str(p) for p in pols]} against "
                             f"{[polnum2str(p) for p in pols0]})")
        if str(meta.vis_units) != str(ref.vis_units):
            raise ValueError(f"{head}: the units differ (vis_units {meta.vis_units!r} against {ref.vis_units!r})")
        pos = _positions(meta)
        shared = sorted(set(pos) & set(pos0))
        if not shared:
            raise ValueError(f"{head}: they share no antenna number")
        off = {a: float(np.linalg.norm(pos[a] - pos0[a])) for a in shared}
        worst = max(off, key=off.get)
        if off[worst] > ARRAY_TOL_M:
            raise ValueError(f"{head}: antenna {worst} is {off[worst]:.3g} m from its position in {p0} "
                             f"(antenna_positions; tolerance {ARRAY_TOL_M} m)")
    _refuse_shared_times(metas, paths)


def _refuse_shared_times(metas, paths) -> None:
    owner: dict = {}
    for meta, path in zip(metas, paths):
        for t in np.unique(np.asarray(meta.time_array, np.float64)):
            if float(t) in owner:
                raise ValueError(f"{path} and {owner[float(t)]} both hold the integration at JD {float(t):.6f}: a file "
                                 "given twice, or files that overlap (each integration must come from one file)")
            owner[float(t)] = path


def read_parts(paths, *, pol="pI", freq_chans=None, freq_range_hz=None, times_jd=None, lst_range_hours=None,
               antennas=None, bls=None, autos: bool = True,
               memory_budget: float | None = None) -> tuple[list[FilePart], list[str]]:
    """Read the selected part of every file in ``paths`` (module docstring): (parts, notes).

    Args: as :func:`gcrsky.io.read_observation` (``times_jd`` may name times of any file; each must
    be in one).  The notes name the files that hold no selected integration (not read).

    Raises:
        ValueError: files not of one array (:func:`check_same_array`), a selection no file satisfies,
            times in no file, a read the memory budget cannot hold.
    """
    from pyuvdata import UVData

    from .visdata import parse_products

    paths = [str(p) for p in paths]
    metas = [_metadata(p) for p in paths]
    check_same_array(metas, paths)
    if times_jd is not None:
        want = np.atleast_1d(np.asarray(times_jd, np.float64))
        have = np.concatenate([np.asarray(m.time_array, np.float64) for m in metas])
        missing = want[~np.isin(want, have)]
        if missing.size:
            raise ValueError(f"times {missing[:3]} (JD) are in none of the {len(paths)} files")
    raw = None if pol is None else parse_products(pol)[1]
    plans, notes, total, samples = [], [], 0.0, 0
    for meta, path in zip(metas, paths):
        tj, keep = kept_times(meta, times_jd, lst_range_hours)
        if not np.any(keep):
            notes.append(f"{path}: no integration in the time / LST selection: not read")
            continue
        times = {} if np.all(keep) else {"times": tj[keep]}
        try:
            kw = selection_kwargs(meta, freq_chans=freq_chans, freq_range_hz=freq_range_hz, times_jd=None,
                                   lst_range_hours=None, antennas=antennas, bls=bls, raw=raw, autos=autos,
                                   times=times)
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
        n, nbytes = estimate_bytes(meta, kw)
        samples, total = samples + n, total + nbytes
        plans.append((path, kw, tj[keep]))
    if not plans:
        raise ValueError(f"the time / LST selection leaves no integration in any of the {len(paths)} files")
    log.info("reading %d of %d files: %d samples selected (%s with gcrsky's copies)", len(plans), len(paths), samples,
             format_bytes(total))
    check_memory(total, f"reading {samples} visibility samples from {len(plans)} files",
                 "select fewer files, channels, times, antennas or baselines", budget=memory_budget)
    parts = []
    for path, kw, tj in plans:
        with reading(path, "a visibility file", VIS_FORMATS):
            uvd = UVData.from_file(path, **kw)
        sel = {k: (np.asarray(v).tolist() if not isinstance(v, list) else v) for k, v in kw.items()}
        parts.append(FilePart(path, uvd, sel, np.asarray(tj, np.float64)))
    for line in notes:
        log.warning(line)
    return parts, notes


def join_parts(parts: list[FilePart]):
    """One ``UVData`` of the parts' baseline-time rows, in the parts' order (pyuvdata ``fast_concat``).

    Raises:
        ValueError: pyuvdata refuses to join them (its words, with the files named).
    """
    if len(parts) == 1:
        return parts[0].uvd
    first, rest = parts[0].uvd, [p.uvd for p in parts[1:]]
    try:
        return first.fast_concat(rest, "blt", inplace=False)
    except (ValueError, AttributeError) as e:
        raise ValueError(f"pyuvdata cannot join {', '.join(os.path.basename(p.path) for p in parts)} along "
                         f"time: {e}") from None
