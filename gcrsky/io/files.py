"""Input files checked before they are read, and read errors that name the file.

A file a user passes (visibilities, a beam, a prior, calibration solutions) is checked to
exist, to be a regular, non-empty file (or, where the format is a directory, a directory of
that format), and a reader's failure on it -- h5py's "file signature not found" on a
corrupt file, "truncated file" on a partly copied one, pyuvdata's missing header on a
bit-flipped one, astropy's "Empty or corrupt FITS file" -- becomes a :class:`ValueError`
naming the file, what it was read as and the reader's own words, instead of a traceback
from deep inside the reader.
"""

from __future__ import annotations

import glob
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["READ_ERRORS", "VIS_SUFFIXES", "check_input_file", "expand_data_paths", "reading"]

#: What readers raise on a file that is not what it claims (corrupt, truncated, another format); HDF5 raises
#: ``RuntimeError`` for a damaged symbol table ("Unable to get group info (bad symbol table node signature)").
READ_ERRORS = (OSError, KeyError, AttributeError, ValueError, TypeError, IndexError, EOFError, RuntimeError)


def _is_measurement_set(path: Path) -> bool:
    return (path / "table.dat").is_file()


#: Suffixes of the visibility files a directory given as ``--data`` contributes (a Measurement Set is a
#: directory holding ``table.dat``).
VIS_SUFFIXES = (".uvh5", ".h5", ".hdf5", ".uvfits", ".fits", ".ms")


def _has_glob(text: str) -> bool:
    return any(c in text for c in "*?[")


def _expand_one(item) -> list[str]:
    path = Path(item)
    if not path.exists() and _has_glob(str(item)):
        found = sorted(glob.glob(str(item)))
        if not found:
            raise FileNotFoundError(f"no visibility file matches {item!r}")
        return [p for f in found for p in _expand_one(f)]
    if path.is_dir() and not _is_measurement_set(path):
        found = sorted(str(p) for p in path.iterdir() if p.suffix.lower() in VIS_SUFFIXES
                       and (p.is_file() or _is_measurement_set(p)))
        if not found:
            raise FileNotFoundError(f"the directory {path} holds no visibility file (suffixes "
                                    f"{', '.join(VIS_SUFFIXES)})")
        return found
    return [str(item)]


def expand_data_paths(data) -> list[str]:
    """The visibility files ``data`` names, in order: a path, a glob pattern, a directory, or a list of them.

    A glob (``"night/zen.*.uvh5"``) gives its matches sorted by name; a directory (not a Measurement
    Set) gives its files whose suffix is in :data:`VIS_SUFFIXES`, sorted; a list keeps its order with
    each entry expanded so.  Each file is then checked (:func:`check_input_file`).

    Raises:
        FileNotFoundError: a pattern or directory that matches nothing, a path that does not exist.
        ValueError: the same file named twice (a night's file given twice would count its data twice),
            an empty list, or an entry that is not a readable file.
    """
    items = [data] if isinstance(data, (str, os.PathLike)) else list(data)
    if not items:
        raise ValueError("no visibility file given (an empty list)")
    paths = [p for item in items for p in _expand_one(item)]
    seen: dict = {}
    for p in paths:
        key = os.path.realpath(p)
        if key in seen:
            raise ValueError(f"the visibility file {p} is given twice ({seen[key]} and {p}): its data would count "
                             "twice")
        seen[key] = p
        check_input_file(p, "visibility file", measurement_set=True)
    return paths


def check_input_file(path, what: str, *, measurement_set: bool = False) -> Path:
    """``path`` as a :class:`~pathlib.Path`, checked to be a readable input file.

    Args:
        path: the file.
        what: what it should be, for the messages (``"visibility file"``, ``"beam file"``, ...).
        measurement_set: a directory holding ``table.dat`` (a CASA Measurement Set) is accepted.

    Raises:
        FileNotFoundError: nothing at ``path`` (a dangling symbolic link says so).
        ValueError: a directory (other than a Measurement Set where accepted), an empty file, or a
            file that cannot be opened for reading.
    """
    path = Path(path)
    if not path.exists():
        if path.is_symlink():
            raise FileNotFoundError(f"{what} {path} is a symbolic link to {os.readlink(path)}, which does not exist")
        raise FileNotFoundError(f"no {what} at {path}")
    if path.is_dir():
        if measurement_set and _is_measurement_set(path):
            return path
        hint = " (a Measurement Set is a directory holding table.dat)" if measurement_set else ""
        raise ValueError(f"{path} is a directory, not a {what}{hint}")
    if not path.is_file():
        raise ValueError(f"{path} is not a regular file (a device, socket or pipe), not a {what}")
    try:
        size = path.stat().st_size
        with open(path, "rb"):
            pass
    except OSError as e:
        raise ValueError(f"{what} {path} cannot be opened: {e.strerror or e}") from None
    if size == 0:
        raise ValueError(f"{what} {path} is empty (0 bytes)")
    return path


@contextmanager
def reading(path, what: str, formats: str) -> Iterator[None]:
    """Turn a reader's failure on ``path`` into a :class:`ValueError` naming the file.

    Args:
        path: the file being read.
        what: what it was read as (``"a visibility file"``).
        formats: what it should be (``"UVH5, UVFITS or a Measurement Set"``), for the message.

    Raises:
        ValueError: ``"{path} cannot be read as {what} ({Error}: {reader's message}); is it a complete
        {formats}?"``, chained to the reader's exception (``gcrsky -v`` shows it).
    """
    try:
        yield
    except READ_ERRORS as e:
        if isinstance(e, (FileNotFoundError, MemoryError)):
            raise
        detail = str(e).strip() or type(e).__name__
        raise ValueError(f"{path} cannot be read as {what} ({type(e).__name__}: {detail}); is it a complete, "
                         f"uncorrupted {formats}?") from e
