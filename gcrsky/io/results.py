"""Run products on disk: ``results.h5`` (draws, Wiener filter, inputs) and strict JSON summaries.

``results.h5`` is written in three steps, so that a run can be killed at any point
and continued (``gcrsky run --resume``):

1. :func:`create_results_h5` (atomically: temporary name, then rename) writes the
   inputs, the Wiener filter, the run's settings and an empty, extendable ``draws``;
2. :func:`append_batch` appends one batch of draws at a time.  The file is opened,
   extended, flushed and closed for every batch, and the count of complete batches
   (attribute ``batches_complete``) is raised only after the batch's data are
   flushed; so between batches the file is closed and consistent, and a kill during a
   batch loses only that batch (rows beyond ``batches_complete`` are ignored by
   :func:`read_draws` and overwritten by the next :func:`append_batch`).  HDF5 is not
   journalled: a kill in the milliseconds of the append itself could in principle
   leave the file unreadable, which :func:`read_results_state` reports.  Others may
   read the file between batches; while one holds it open (HDF5's file lock) the
   append waits (``wait_s``);
3. :func:`finalize_results_h5` copies the file to a temporary name, adds the maps and
   z-scores, sets ``complete`` and renames it over the original.

:func:`write_results_h5` does the three in one call for draws already in memory.

Layout (``layout_version`` 2):

- ``draws`` ``(nfreq, ndraws, nparams)`` realified, K: chunked, extendable along
  ``ndraws``; only the first :attr:`ResultsState.ndraws_complete` rows count;
- ``draw_info/<field>`` ``(nfreq, ndraws)``: the :class:`~gcrsky.solvers.SolveInfo`
  of every draw (``iterations``, ``err_sigma``, ``rel_residual``, ``converged``,
  ``result``); ``wiener_info/<field>`` ``(nfreq,)`` that of the Wiener filter;
  ``batch_seconds`` ``(nbatches,)`` wall-clock seconds of each batch (the first of
  each process includes compilation); ``solver_rank`` ``(nfreq,)`` the rank the
  eigen path kept (when it ran);
- ``truth`` (if known), ``wiener_filter``, ``prior_mean``, ``prior_inv_var``
  ``(nfreq, nparams)``; ``modes/ell``, ``modes/m``, ``modes/is_imag`` ``(nparams,)``;
  ``freqs_hz``, ``lsts_rad``, ``antpairs``, ``data``, ``sigma``, ``weights``;
- after :func:`finalize_results_h5`: ``mode_z`` (if a truth is known) and the group
  ``maps`` (``truth``, ``mean``, ``std``, ``wiener``: HEALPix RING, float64, gzip):
  ``mean`` / ``std`` are the per-pixel mean and standard deviation over the draws,
  ``wiener`` the map of the Wiener filter (the exact posterior mean);
- attributes: ``units``, ``layout``, ``layout_version``, ``run_settings_json`` (what
  a resumed run must match), ``inputs_sha256`` (:func:`inputs_fingerprint`),
  ``nsamples``, ``batch``, ``n_batches``, ``batches_complete``, ``complete`` and
  whatever the caller adds (:func:`gcrsky.run.execute`: configuration,
  seed, method and its resolved options, key scheme, versions).
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import shutil
import time
from pathlib import Path
from typing import NamedTuple, Optional

import numpy as np

from ..base.memory import format_bytes
from ..base.solveinfo import SolveInfo
from .atomic import atomic_path, temporary_name

__all__ = [
    "LAYOUT_VERSION",
    "ResultsState",
    "StoredDraws",
    "append_batch",
    "clean_json",
    "create_results_h5",
    "finalize_results_h5",
    "inputs_fingerprint",
    "json_default",
    "read_draws",
    "read_results_state",
    "settings_json",
    "write_json",
    "write_results_h5",
]

#: The realified layout in words (stored as the ``layout`` attribute).
LAYOUT = "realified: [Re a_lm (l, m>=0) healpy order] ++ [Im a_lm (m>=1) healpy order]"
#: Units in words (stored as the ``units`` attribute).
UNITS = "coefficients and maps in K; data in K sr; freqs Hz; lsts rad"
#: Version of the layout described in the module doc (attribute ``layout_version``).
LAYOUT_VERSION = 2
#: Largest chunk of ``draws`` (bytes); a chunk is ``(nfreq, rows, nparams)``.
_CHUNK_BYTES = 4 << 20


class ResultsState(NamedTuple):
    """What a ``results.h5`` records about its run and how far it got (:func:`read_results_state`).

    Attributes:
        path: the file.
        settings: the run's settings (:func:`settings_json` decoded), or None if not recorded.
        nsamples, batch, n_batches: draws asked for, draws per batch, batches in all.
        batches_complete: batches whose draws are in the file.
        ndraws_complete: draws in the file, ``min(batches_complete * batch, nsamples)``.
        complete: the file was finalised (maps written; :func:`finalize_results_h5`).
        attrs: every attribute of the file.
    """

    path: Path
    settings: Optional[dict]
    nsamples: int
    batch: int
    n_batches: int
    batches_complete: int
    ndraws_complete: int
    complete: bool
    attrs: dict

    @property
    def draws_done(self) -> bool:
        """Every batch is in the file."""
        return self.batches_complete >= self.n_batches


class StoredDraws(NamedTuple):
    """The complete draws of a ``results.h5`` (:func:`read_draws`).

    Attributes:
        draws: ``(Nf, ndraws, n)`` realified, K.
        info: :class:`~gcrsky.solvers.SolveInfo` over ``(Nf, ndraws)``, or None if not recorded.
        batch_seconds: seconds of each batch.
        wiener_filter: ``(Nf, n)``.
        wiener_info: :class:`~gcrsky.solvers.SolveInfo` over ``(Nf,)``, or None.
        rank: ``(Nf,)`` rank kept by the eigen path, or None.
    """

    draws: np.ndarray
    info: Optional[SolveInfo]
    batch_seconds: list
    wiener_filter: np.ndarray
    wiener_info: Optional[SolveInfo]
    rank: Optional[np.ndarray]


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
    """Write ``obj`` as indented strict JSON (non-finite floats become ``null``), atomically."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        json.dump(clean_json(obj), fh, indent=2, default=json_default)
    return path


def settings_json(settings: dict) -> str:
    """The canonical JSON of a run's settings (sorted keys; tuples become lists), as stored and compared."""
    return json.dumps(clean_json(settings), sort_keys=True, default=json_default)


def inputs_fingerprint(problem) -> str:
    """SHA-256 (hex) of a problem's inputs: frequencies, LSTs, pairs, data, noise, weights and prior.

    Bit-exact: a resumed run must see exactly the inputs of the run it continues (the
    same configuration can give other data, e.g. when GSM2016's file appears on disk).
    """
    h = hashlib.sha256()
    arrays = (problem.freqs_hz, problem.lsts_rad, problem.antpairs, problem.data, problem.sigma, problem.weights,
              problem.prior.mean, problem.prior.inv_var)
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a))
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _info_fields(info) -> dict:
    return {k: np.asarray(getattr(info, k)) for k in SolveInfo._fields}


def create_results_h5(
    path,
    problem,
    wiener_filter,
    *,
    nsamples: int,
    batch: int,
    settings: dict | None = None,
    wiener_info: SolveInfo | None = None,
    rank=None,
    attrs: dict | None = None,
    per_draw: dict | None = None,
    arrays: dict | None = None,
) -> Path:
    """Start a ``results.h5`` for ``nsamples`` draws in batches of ``batch`` (atomically; replaces ``path``).

    Args:
        path: output file.
        problem: the :class:`~gcrsky.model.Problem` being sampled (its truth, prior,
            modes, frequencies, LSTs, pairs, data, noise and weights are stored).
        wiener_filter: ``(Nf, n)`` posterior mean, K.
        nsamples, batch: draws in all and per batch (``n_batches = ceil(nsamples / batch)``).
        settings: the run's settings (stored as ``run_settings_json``; what a resumed run must match).
        wiener_info: the Wiener solve's :class:`~gcrsky.solvers.SolveInfo` over ``(Nf,)``.
        rank: ``(Nf,)`` rank kept by the eigen path, if it ran.
        attrs: further file attributes (strings or numbers).
        per_draw: further datasets with one row per draw, ``{name: (tail shape, dtype, description)}``:
            created empty with shape ``(0, *tail)`` (attribute ``shape``: the description), filled by
            :func:`append_batch`'s ``extra`` (e.g. a gain run's ``gain_draws``).
        arrays: further datasets written once, ``{path: array}`` (e.g. ``"gains/units"``).

    Returns:
        the path written.
    """
    import h5py

    nsamples, batch = int(nsamples), int(batch)
    if nsamples < 1 or batch < 1:
        raise ValueError(f"nsamples and batch must be positive, got {nsamples}, {batch}")
    path = Path(path)
    wf = np.asarray(wiener_filter, np.float64)
    nf, n = wf.shape
    rows = max(1, min(batch, nsamples, _CHUNK_BYTES // (8 * nf * n)))
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h:
        for k, v in (attrs or {}).items():
            h.attrs[k] = v
        h.attrs["units"] = UNITS
        h.attrs["layout"] = LAYOUT
        h.attrs["layout_version"] = LAYOUT_VERSION
        if settings is not None:
            h.attrs["run_settings_json"] = settings_json(settings)
        h.attrs["inputs_sha256"] = inputs_fingerprint(problem)
        h.attrs["nsamples"] = nsamples
        h.attrs["batch"] = batch
        h.attrs["n_batches"] = -(-nsamples // batch)
        h.attrs["batches_complete"] = 0
        h.attrs["complete"] = False
        ds = h.create_dataset("draws", shape=(nf, 0, n), maxshape=(nf, None, n), chunks=(nf, rows, n), dtype="f8")
        ds.attrs["shape"] = "(nfreq, ndraws, nparams)"
        for k in SolveInfo._fields:
            h.create_dataset(f"draw_info/{k}", shape=(nf, 0), maxshape=(nf, None), chunks=(nf, max(rows, 64)),
                             dtype="i8" if k in ("iterations", "result") else ("?" if k == "converged" else "f8"))
        h.create_dataset("batch_seconds", shape=(0,), maxshape=(None,), chunks=(256,), dtype="f8")
        if problem.a_true is not None:
            h["truth"] = np.asarray(problem.a_true)
        h["wiener_filter"] = wf
        if wiener_info is not None:
            for k, v in _info_fields(wiener_info).items():
                h[f"wiener_info/{k}"] = v
        if rank is not None:
            h["solver_rank"] = np.asarray(rank)
        for name, (tail, dtype, what) in (per_draw or {}).items():
            tail = tuple(int(k) for k in tail)
            per = max(1, int(np.prod(tail)) * np.dtype(dtype).itemsize)
            ds = h.create_dataset(name, shape=(0, *tail), maxshape=(None, *tail), dtype=dtype,
                                  chunks=(max(1, min(batch, _CHUNK_BYTES // per)), *tail))
            ds.attrs["shape"] = what
        for name, value in (arrays or {}).items():
            h[name] = np.asarray(value)
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
        h["weights"] = np.asarray(problem.weights)
    return path


def _open_for_append(path, wait_s: float):
    """``h5py.File(path, "r+")``, waiting up to ``wait_s`` seconds while another process holds the file open
    (HDF5's file lock: e.g. someone reading ``results.h5`` between two batches)."""
    import h5py

    deadline = time.monotonic() + wait_s
    while True:
        try:
            return h5py.File(path, "r+")
        except OSError as e:
            if "lock" not in str(e).lower() or time.monotonic() > deadline:
                if "lock" in str(e).lower():
                    raise OSError(f"{path} is held open by another process (HDF5 file lock) for more than "
                                  f"{wait_s:g} s; close it there so the run can append its draws") from e
                raise
            time.sleep(0.25)


def file_size_limit() -> float:
    """The largest file this process may write (``ulimit -f``, ``RLIMIT_FSIZE``), bytes; inf if unlimited."""
    try:
        import resource
    except ImportError:  # not on POSIX
        return float("inf")
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return float("inf") if soft == resource.RLIM_INFINITY else float(soft)


def check_room(path, nbytes: float, what: str) -> None:
    """Refuse to write ``nbytes`` more into ``path`` when the disk or ``ulimit -f`` has no room for them.

    HDF5 left in the middle of a failed write cannot be closed cleanly (h5py raises
    ``RuntimeError`` on flush and close, and the process can then crash at exit), so a write
    that cannot fit is refused before it starts.

    Raises:
        OSError: ``ENOSPC`` (the disk) or ``EFBIG`` (the file-size limit), naming the sizes; the file
            is untouched, so what it holds (the batches written so far) is kept.
    """
    path = Path(path)
    size = path.stat().st_size if path.exists() else 0
    free = shutil.disk_usage(path.parent).free
    limit = file_size_limit()
    if nbytes > free:
        raise OSError(errno.ENOSPC, f"{what} needs ~{format_bytes(nbytes)} but the disk has {format_bytes(free)} free",
                      str(path))
    if size + nbytes > limit:
        raise OSError(errno.EFBIG, f"{what} would take the file to ~{format_bytes(size + nbytes)}, beyond this "
                                   f"process's file-size limit (ulimit -f) of {format_bytes(limit)}", str(path))


def append_batch(path, b: int, draws, info: SolveInfo | None = None, *, seconds: float | None = None,
                 wait_s: float = 120.0, extra: dict | None = None, replace: dict | None = None) -> int:
    """Append batch ``b`` (draws ``b * batch`` onwards) to a ``results.h5`` of :func:`create_results_h5`.

    ``b`` must be the file's ``batches_complete`` (batches are appended in order; rows a
    killed append left beyond it are overwritten).  The data are flushed before the count
    is raised, and the file is closed on return.

    Args:
        path: the file.
        b: batch index.
        draws: ``(Nf, take, n)`` the batch's draws, ``take = min(batch, nsamples - b * batch)``.
        info: the batch's :class:`~gcrsky.solvers.SolveInfo` over ``(Nf, take)`` (stored in ``draw_info``).
        seconds: the batch's wall-clock seconds (stored in ``batch_seconds``).
        wait_s: how long to wait while another process holds the file open (a reader
            between two batches), before raising ``OSError``.
        extra: ``{name: (take, ...) array}``: the batch's rows of the ``per_draw`` datasets of
            :func:`create_results_h5`.
        replace: ``{path: array}`` written over (or created): e.g. a Markov chain's state after
            the batch, so that a resumed run continues it; written before the count is raised.

    Returns:
        the number of complete batches now in the file (``b + 1``).
    """
    draws = np.asarray(draws, np.float64)
    check_room(path, 2 * draws.nbytes + sum(np.asarray(v).nbytes for v in (extra or {}).values()) + (1 << 20),
               f"batch {b} of draws")
    with _open_for_append(path, wait_s) as h:
        done, batch, nsamples = (int(h.attrs[k]) for k in ("batches_complete", "batch", "nsamples"))
        if b != done:
            raise ValueError(f"{path}: batch {b} cannot follow {done} complete batches (append them in order)")
        start = min(b * batch, nsamples)
        stop = min(start + batch, nsamples)
        ds = h["draws"]
        if draws.shape != (ds.shape[0], stop - start, ds.shape[2]):
            raise ValueError(f"batch {b} must have shape {(ds.shape[0], stop - start, ds.shape[2])}, got {draws.shape}")
        ds.resize(stop, axis=1)
        ds[:, start:stop] = draws
        if info is not None:
            for k, v in _info_fields(info).items():
                d = h[f"draw_info/{k}"]
                d.resize(stop, axis=1)
                d[:, start:stop] = v
        for name, value in (extra or {}).items():
            value = np.asarray(value)
            d = h[name]
            if value.shape != (stop - start, *d.shape[1:]):
                raise ValueError(f"batch {b} of {name} must have shape {(stop - start, *d.shape[1:])}, got {value.shape}")
            d.resize(stop, axis=0)
            d[start:stop] = value
        for name, value in (replace or {}).items():
            if name in h:
                del h[name]
            h[name] = np.asarray(value)
        bs = h["batch_seconds"]
        bs.resize(b + 1, axis=0)
        bs[b] = np.nan if seconds is None else float(seconds)
        h.flush()  # the batch's data reach the file before the count says they are there
        h.attrs["batches_complete"] = b + 1
        h.flush()
    return b + 1


def _attrs_dict(h) -> dict:
    out = {}
    for k, v in h.attrs.items():
        if isinstance(v, bytes):
            v = v.decode()
        elif isinstance(v, np.generic):
            v = v.item()
        out[k] = v
    return out


def read_results_state(path) -> ResultsState:
    """How far the run recorded in ``path`` got, and its settings.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file cannot be read as HDF5 (e.g. damaged by a kill during a
            write) or was not written by :func:`create_results_h5` (an older layout);
            the message says which.
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with h5py.File(path, "r") as h:
            attrs = _attrs_dict(h)
    except OSError as e:
        raise ValueError(f"{path} cannot be read as HDF5 ({e}); it may have been damaged while being written") from e
    missing = [k for k in ("nsamples", "batch", "n_batches", "batches_complete", "complete") if k not in attrs]
    if missing:
        raise ValueError(f"{path} does not record the progress of its run (no {', '.join(missing)}): "
                         f"written by an older gcrsky (layout_version {attrs.get('layout_version', 1)})")
    settings = json.loads(attrs["run_settings_json"]) if "run_settings_json" in attrs else None
    nsamples, batch, done = int(attrs["nsamples"]), int(attrs["batch"]), int(attrs["batches_complete"])
    return ResultsState(path, settings, nsamples, batch, int(attrs["n_batches"]), done,
                        min(done * batch, nsamples), bool(attrs["complete"]), attrs)


def read_draws(path) -> StoredDraws:
    """The complete draws of ``path`` (the first ``ndraws_complete``), their solve info and the Wiener filter."""
    import h5py

    state = read_results_state(path)
    rows = state.ndraws_complete
    with h5py.File(path, "r") as h:
        draws = h["draws"][:, :rows]
        info = None
        if "draw_info" in h:
            info = SolveInfo(**{k: h[f"draw_info/{k}"][:, :rows] for k in SolveInfo._fields})
        winfo = None
        if "wiener_info" in h:
            winfo = SolveInfo(**{k: h[f"wiener_info/{k}"][()] for k in SolveInfo._fields})
        seconds = [float(s) for s in h["batch_seconds"][: state.batches_complete]] if "batch_seconds" in h else []
        rank = h["solver_rank"][()] if "solver_rank" in h else None
        wf = h["wiener_filter"][()]
    return StoredDraws(draws, info, seconds, wf, winfo, rank)


def finalize_results_h5(path, *, mode_z=None, maps: dict | None = None, attrs: dict | None = None) -> Path:
    """Add the maps and z-scores to a ``results.h5`` whose draws are complete, and mark it ``complete``.

    The file is copied to a temporary name, extended there and renamed over ``path``
    (a kill leaves either the old or the finished file).  Rows of ``draws`` beyond the
    complete ones are dropped.

    Args:
        path: the file (every batch appended).
        mode_z: optional ``(Nf, n)`` per-mode z-scores ``(mean - truth) / std``.
        maps: optional ``{"truth" | "mean" | "std" | "wiener": (Nf, Npix)}`` HEALPix RING maps, K.
        attrs: further file attributes.

    Returns:
        the path written.
    """
    import h5py

    path = Path(path)
    state = read_results_state(path)
    if not state.draws_done:
        raise ValueError(f"{path}: {state.batches_complete} of {state.n_batches} batches; finish the draws first")
    rows = state.ndraws_complete
    with atomic_path(path) as tmp:
        with h5py.File(path, "r") as src, h5py.File(tmp, "w") as dst:
            for k, v in src.attrs.items():
                dst.attrs[k] = v
            for name in src:
                if name in ("maps", "mode_z"):
                    continue
                src.copy(src[name], dst, name=name)
            for name, ncols in (("draws", rows), *((f"draw_info/{k}", rows) for k in SolveInfo._fields)):
                if name in dst and dst[name].shape[1] != ncols:
                    dst[name].resize(ncols, axis=1)
            for k, v in (attrs or {}).items():
                dst.attrs[k] = v
            if mode_z is not None:
                dst["mode_z"] = np.asarray(mode_z)
            if maps:
                g = dst.create_group("maps")
                g.attrs["note"] = ("HEALPix RING, equatorial (the frame of the coefficients), K; mean/std: per-pixel "
                                   "mean and standard deviation (ddof 1) over the draws; wiener: the map of the Wiener "
                                   "filter (the exact posterior mean)")
                for name, arr in maps.items():
                    if arr is not None:
                        g.create_dataset(name, data=np.asarray(arr, np.float64), compression="gzip",
                                         compression_opts=4)
            dst.attrs["complete"] = True
    return path


def write_results_h5(
    path,
    problem,
    draws,
    wiener_filter,
    *,
    mode_z=None,
    maps: dict | None = None,
    attrs: dict | None = None,
    settings: dict | None = None,
    info: SolveInfo | None = None,
    wiener_info: SolveInfo | None = None,
) -> Path:
    """Write one run's arrays to ``path`` in one go (the layout of the module doc; replaces ``path`` atomically).

    Args:
        path: output file.
        problem: the :class:`~gcrsky.model.Problem` that was sampled.
        draws: ``(Nf, ndraws, n)`` realified draws, K (stored as one batch).
        wiener_filter: ``(Nf, n)`` posterior mean, K.
        mode_z: optional ``(Nf, n)`` per-mode z-scores ``(mean - truth) / std``.
        maps: optional ``{"truth" | "mean" | "std" | "wiener": (Nf, Npix)}`` HEALPix RING maps, K.
        attrs: file attributes to add (strings or numbers).
        settings: the run's settings (``run_settings_json``).
        info, wiener_info: :class:`~gcrsky.solvers.SolveInfo` of the draws ``(Nf, ndraws)`` and the Wiener filter.

    Returns:
        the path written.
    """
    path = Path(path)
    draws = np.asarray(draws, np.float64)
    staging = temporary_name(path)
    try:
        create_results_h5(staging, problem, wiener_filter, nsamples=draws.shape[1], batch=draws.shape[1],
                          settings=settings, wiener_info=wiener_info, attrs=attrs)
        append_batch(staging, 0, draws, info)
        finalize_results_h5(staging, mode_z=mode_z, maps=maps)
        os.replace(staging, path)
    finally:
        if staging.exists():
            staging.unlink()
    return path
