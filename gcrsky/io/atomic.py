"""Atomic file writes: write to a temporary name in the same directory, then rename.

A writer that is interrupted (an exception, a kill, a full disk) leaves the target
either as it was or complete, never half-written: the data go to a temporary file
``.NAME.tmp-PID-TOKEN.EXT`` beside the target (same directory, hence same file
system, so the final :func:`os.replace` is atomic on POSIX and Windows), which is
flushed to disk and renamed over the target only when the writer has finished.
On an exception the temporary file is removed; a hard kill can leave one behind
(hidden, recognisable by :func:`is_temporary`, never mistaken for a product).

The temporary name keeps the target's extension, so writers that choose a format
by extension (matplotlib's ``savefig``, healpy) behave as for the target.
"""

from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_path", "atomic_write_text", "is_temporary", "temporary_name"]

_TMP_TAG = ".tmp-"


def temporary_name(path) -> Path:
    """A fresh temporary path beside ``path``: ``.STEM.tmp-PID-TOKEN.EXT`` (``EXT`` = all of ``path``'s suffixes)."""
    path = Path(path)
    suffix = "".join(path.suffixes)
    stem = path.name[: len(path.name) - len(suffix)] if suffix else path.name
    return path.with_name(f".{stem}{_TMP_TAG}{os.getpid()}-{secrets.token_hex(4)}{suffix}")


def is_temporary(path, target=None) -> bool:
    """Whether ``path`` is a temporary file of :func:`atomic_path` (of ``target``, if given)."""
    name = Path(path).name
    if not (name.startswith(".") and _TMP_TAG in name):
        return False
    if target is None:
        return True
    t = Path(target).name
    suffix = "".join(Path(t).suffixes)
    stem = t[: len(t) - len(suffix)] if suffix else t
    return name.startswith(f".{stem}{_TMP_TAG}") and name.endswith(suffix)


def _fsync(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _fsync_dir(directory: Path) -> None:
    if os.name != "posix":
        return
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_path(path, *, fsync: bool = True) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path`` atomically.

    ::

        with atomic_path("out/map.fits") as tmp:
            healpy.write_map(tmp, m)   # tmp keeps the extension: .map.tmp-PID-TOKEN.fits

    The temporary file does not exist when the block starts (the writer creates it,
    with the usual permissions).  If the block raises, the temporary file is deleted
    and ``path`` is untouched (an existing file keeps its old content); if it returns
    without having created the file, that is an error.

    Args:
        path: the target file; its directory must exist.
        fsync: flush the file (and the directory entry) to disk before and after the
            rename, so the rename also survives a power cut, not only a killed process.
    """
    path = Path(path)
    tmp = temporary_name(path)
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f"the writer of {path} did not create its temporary file {tmp}")
        if fsync:
            _fsync(tmp)
        os.replace(tmp, path)
        if fsync:
            _fsync_dir(path.parent)
    except BaseException:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        raise


def atomic_write_text(path, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (:func:`atomic_path`); returns ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding=encoding) as fh:
            fh.write(text)
    return path
