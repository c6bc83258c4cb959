"""The output directory of a run: its files, and whether a run may write there (refuse, overwrite, resume).

A directory that already holds a run's files (:data:`RUN_FILES`) is refused
(``existing="refuse"``: :class:`RunExistsError`), cleared (``"overwrite"``:
:func:`remove_run_files`) or continued (``"resume"``: the settings recorded in its
``results.h5`` must equal this run's, else :class:`~gcrsky.run.resume.ResumeError`).
Files of other names are never touched.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np

from ..base.memory import format_bytes
from ..io.atomic import is_temporary
from ..io.results import file_size_limit, read_results_state
from .resume import ResumeError, resumed_problem, settings_differences
from .summary import versions

__all__ = [
    "EXISTING",
    "BEAM_DIR",
    "GAIN_FILE",
    "PRODUCT_FILES",
    "RESULTS_FILE",
    "RUN_FILES",
    "SUMMARY_FILE",
    "OpenRun",
    "PostDrawError",
    "RunExistsError",
    "check_output",
    "check_out_dir",
    "clear_output",
    "existing_run_files",
    "open_run",
    "remove_run_files",
    "run_files",
    "temporaries",
]

log = logging.getLogger(__name__)

#: What a run may do with a directory that already holds a run's files.
EXISTING = ("refuse", "overwrite", "resume")

#: The appendable HDF5 file of a run (:mod:`gcrsky.io.results`).
RESULTS_FILE = "results.h5"
#: The run's summary (written last: its presence means the run finished).
SUMMARY_FILE = "summary.json"
#: The standard products: ``{key: file name}`` (:func:`gcrsky.run.products.write_products`).
PRODUCT_FILES = {
    "posterior_mean_fits": "posterior_mean.fits",
    "posterior_std_fits": "posterior_std.fits",
    "posterior_mean_alm": "posterior_mean_alm.fits",
    "posterior_mean_skyh5": "posterior_mean.skyh5",
}
#: The posterior-mean gains of a run that samples them (:func:`gcrsky.run.gains.write_gain_products`; the file
#: :class:`gcrsky.run.sampling.Gains` declares).
GAIN_FILE = "gains.calh5"
#: The directory of a beam run's posterior-mean beams, one UVBeam file per antenna (:mod:`gcrsky.run.beams`).
BEAM_DIR = "beams"
#: Every file the core writes into a run's directory, whatever it samples (the draw stages' files included).  A
#: report hook's files (:meth:`gcrsky.run.ReportHook.files`, e.g. the paper's figures) are passed as ``files`` to
#: the functions here: they are then part of the run's files, refused, overwritten and resumed with it.
RUN_FILES = (RESULTS_FILE, SUMMARY_FILE, *PRODUCT_FILES.values(), GAIN_FILE, BEAM_DIR)
_STAGE_FILES = (GAIN_FILE, BEAM_DIR)


def run_files(files: Sequence[str] = ()) -> tuple[str, ...]:
    """The core's run files (:data:`RUN_FILES`) with ``files`` (a report hook's) after the products."""
    core = tuple(f for f in RUN_FILES if f not in _STAGE_FILES)
    return (*core, *(f for f in files if f not in RUN_FILES), *_STAGE_FILES)


class RunExistsError(FileExistsError):
    """The output directory already holds a run's files (and neither resume nor overwrite was asked for).

    Attributes:
        out: the directory; files: the run files found in it.
    """

    def __init__(self, out, files, message: str | None = None):
        self.out, self.files = Path(out), list(files)
        super().__init__(message or (
            f"{out} already holds results of a run ({', '.join(self.files)}); resume it or overwrite it"
        ))


def check_out_dir(out) -> Path:
    """Make sure ``out`` is, or can be made, a directory this process can write; returns it.

    Created (with its parents) if missing; a probe file is written and removed, so a read-only
    directory or file system, a full disk or a quota is found before any work, not after the draws.

    Raises:
        NotADirectoryError: ``out``, or one of its parents, is a file.
        FileNotFoundError: ``out`` is a symbolic link to nothing.
        PermissionError, OSError: it cannot be created or written (the message names the path and says
            what to do).
    """
    out = Path(out)
    if out.is_symlink() and not out.exists():
        raise FileNotFoundError(f"--out {out} is a symbolic link to {os.readlink(out)}, which does not exist: create "
                                "the target directory or choose another --out")
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"--out {out} is a file, not a directory: choose another --out")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise NotADirectoryError(f"--out {out} cannot be created: {parent} is a file, not a directory")
            break
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".gcrsky-write-probe-{os.getpid()}"
        with open(probe, "wb") as fh:
            fh.write(b"\0" * 4096)
            fh.flush()
            os.fsync(fh.fileno())
        probe.unlink()
    except OSError as e:
        try:
            probe.unlink(missing_ok=True)
        except (OSError, UnboundLocalError):
            pass
        raise type(e)(e.errno, f"--out {out} cannot be written ({e.strerror or e}): choose a writable directory "
                               "with free space", str(out)) from e
    return out


class PostDrawError(RuntimeError):
    """A run failed after its draws were stored: ``results.h5`` keeps them, ``resume`` finishes the run.

    The maps, products, figures and summary are redone by a resumed run (the same settings,
    ``--resume``): it finds every batch drawn, skips the set-up and the draws, and writes
    what is missing.  Raised from the original error (``__cause__``).

    Attributes:
        out: the directory; stage: the stage that failed; ndraws: the draws kept.
    """

    def __init__(self, out, stage: str, ndraws: int, cause: BaseException):
        self.out, self.stage, self.ndraws = Path(out), stage, int(ndraws)
        super().__init__(
            f"the run failed after its draws, in stage {stage!r}: {type(cause).__name__}: {cause}. Its {ndraws} draws "
            f"are kept in {Path(out) / RESULTS_FILE}: remove the cause and run the same command with --resume to redo "
            "the maps, products, figures and summary from them (or --overwrite to start again)")


def existing_run_files(out, files: Sequence[str] = ()) -> list[str]:
    """The run files (:func:`run_files` of ``files``, a report hook's) present in ``out``, in that order."""
    out = Path(out)
    return [f for f in run_files(files) if (out / f).exists()]


def temporaries(out, files: Sequence[str] = ()) -> list[Path]:
    """Temporary files a killed writer of a run file (:func:`run_files` of ``files``) left in ``out``."""
    out = Path(out)
    if not out.is_dir():
        return []
    names = run_files(files)
    return [p for p in out.iterdir() if any(is_temporary(p, f) for f in names)]


def remove_run_files(out, files: Sequence[str] = ()) -> list[str]:
    """Delete the run files (:func:`run_files` of ``files``, a report hook's) in ``out`` and any temporary
    files a killed writer left.

    Nothing else in ``out`` is touched.  Returns the names removed.
    """
    out = Path(out)
    gone = []
    for f in existing_run_files(out, files):
        if f == BEAM_DIR and (out / f).is_dir():  # the one run file that is a directory (of files the run wrote)
            shutil.rmtree(out / f)
        else:
            (out / f).unlink()
        gone.append(f)
    for p in temporaries(out, files):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        gone.append(p.name)
    return gone


def check_output(out, settings: dict, existing: str = "refuse", files: Sequence[str] = ()):
    """Decide what a run with ``settings`` may do in ``out``; raises if it may not.

    Args:
        out: the output directory (need not exist).
        settings: this run's settings (:meth:`gcrsky.run.RunSpec.settings`).
        existing: ``"refuse"`` (a directory holding run files is an error),
            ``"overwrite"`` (it will be cleared) or ``"resume"`` (its run is continued).
        files: the report hooks' files (:meth:`gcrsky.run.ReportHook.files`), run files too.

    Returns:
        the :class:`gcrsky.io.ResultsState` to continue (``"resume"`` with a
        ``results.h5``), else None (a new run).

    Raises:
        RunExistsError: ``"refuse"`` and run files are present; or ``"resume"``, no
            ``results.h5`` but other run files.
        ResumeError: ``"resume"`` and the recorded run cannot be continued: its
            settings differ (:attr:`ResumeError.differences`), it records none (an older
            layout), or ``results.h5`` cannot be read.
    """
    if existing not in EXISTING:
        raise ValueError(f"existing must be one of {EXISTING}, got {existing!r}")
    out = Path(out)
    files = existing_run_files(out, files)
    if existing == "overwrite" or not files:
        return None
    if existing == "refuse":
        raise RunExistsError(out, files)
    h5 = out / RESULTS_FILE
    if not h5.exists():
        raise RunExistsError(out, files, f"{out} holds {', '.join(files)} but no {RESULTS_FILE}: nothing to resume "
                                         "from; overwrite it to start again")
    try:
        state = read_results_state(h5)
    except ValueError as e:
        raise ResumeError(out, f"cannot resume: {e}") from e
    if state.settings is None:
        raise ResumeError(out, f"cannot resume: {h5} records no run settings (written by an older gcrsky)")
    diffs = settings_differences(state.settings, settings)
    if diffs:
        what = "; ".join(f"{k}: recorded {a!r}, now {b!r}" for k, a, b in diffs)
        raise ResumeError(out, f"cannot resume the run in {out}: its settings differ: {what}", diffs)
    return state


def clear_output(out, existing: str, files: Sequence[str] = ()) -> None:
    """Make ``out`` ready for a run that :func:`check_output` allowed: cleared of run files (``files``: the
    report hooks') (``existing="overwrite"``) and of the temporaries a killed writer left."""
    out = Path(out)
    if existing == "overwrite":
        removed = remove_run_files(out, files)
        if removed:
            log.info("overwrite: removed %s from %s", ", ".join(removed), out)
    for p in temporaries(out, files):  # left by a killed writer
        p.unlink(missing_ok=True)


def draws_bytes(prob, nsamples: int) -> float:
    """Bytes the draws of a run take in ``results.h5``: ``Nf x nsamples x n`` float64."""
    return 8.0 * int(np.shape(prob.data)[0]) * int(nsamples) * int(prob.n)


def check_disk_space(out, nbytes: float) -> None:
    """Refuse a run whose draws cannot fit on the disk of ``out``, or in a file under ``ulimit -f`` (before the
    first draw; each batch is checked again as it is appended, :func:`gcrsky.io.results.check_room`).

    Raises:
        OSError: ``ENOSPC`` (the disk) or ``EFBIG`` (the file-size limit), naming the sizes and what to do.
    """
    free = shutil.disk_usage(out).free
    if nbytes > free:
        raise OSError(errno.ENOSPC, f"the draws need {format_bytes(nbytes)} but the disk of {out} has "
                                    f"{format_bytes(free)} free: fewer draws (--nsamples), or another --out", str(out))
    limit = file_size_limit()
    if nbytes > limit:
        raise OSError(errno.EFBIG, f"the draws need {format_bytes(nbytes)} in {RESULTS_FILE} but this process may "
                                   f"write files of at most {format_bytes(limit)} (ulimit -f): fewer draws "
                                   "(--nsamples), or raise the limit", str(out))


class OpenRun(NamedTuple):
    """An output directory a run may write to (:func:`open_run`).

    Attributes:
        out: the directory; h5: its ``results.h5``.
        settings: the run's settings (recorded in a new ``results.h5``).
        state: the recorded run to continue (:class:`gcrsky.io.ResultsState`), or None.
        start: the first batch to draw (0 for a new run).
        already_complete: a resumed run with every batch drawn and ``results.h5`` finished.
        before: the run files present before this run wrote anything.
        files: the report hooks' files (:meth:`gcrsky.run.ReportHook.files`), run files too.
        prob: the problem the run draws from: the caller's, or, resuming, the one with the recorded inputs.
    """

    out: Path
    h5: Path
    settings: dict
    state: Any
    start: int
    already_complete: bool
    before: frozenset
    files: tuple = ()
    prob: Any = None


def open_run(prob, spec, files: Sequence[str] = ()) -> OpenRun:
    """Check, prepare and describe ``spec.output.out`` for a run of ``prob``.

    The directory is created; a run in it is refused, cleared or continued as
    ``spec.output.existing`` says (:func:`check_output`; ``files``: the report hooks' files); a
    resumed run must have the same inputs and continues from the recorded ones
    (:func:`~gcrsky.run.resume.resumed_problem`: ``OpenRun.prob``).

    Raises:
        RunExistsError, ResumeError: as :func:`check_output` and ``resumed_problem``.
    """
    out = spec.output.out
    out.mkdir(parents=True, exist_ok=True)
    settings = spec.settings(prob.config)
    state = check_output(out, settings, spec.output.existing, files)
    check_disk_space(out, draws_bytes(prob, spec.draws.nsamples))
    clear_output(out, spec.output.existing, files)
    if state is not None:
        prob = resumed_problem(out, state, prob, versions()["gcrsky"], trust_recorded=spec.output.trust_recorded)
    start = 0 if state is None else state.batches_complete
    already_complete = state is not None and state.draws_done and state.complete
    return OpenRun(out, out / RESULTS_FILE, settings, state, start, already_complete,
                   frozenset(existing_run_files(out, files)), tuple(files), prob)
