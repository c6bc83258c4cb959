"""One run per output directory: an exclusive lock on ``out`` for as long as a run writes there.

A run holds ``out/.gcrsky.lock`` (:data:`LOCK_FILE`) from before it looks at the
directory's files until its last file is written (:func:`run_lock`).  The file records the
owner (pid, host, start time in UTC, command line) so that a refused run can say who holds
the directory.  The exclusion itself is the kernel's: an ``fcntl.flock`` on the open lock
file, which the kernel drops when the owner exits in any way (also ``kill -9`` or a crash),
so a lock left behind by a dead run is *stale* and the next run takes it over (and logs
whose it was).  Where ``flock`` is not available (a platform without :mod:`fcntl`, a file
system that refuses it) the lock is an exclusively created file instead; a stale one is
recognised when its owner ran on this host and its pid no longer exists (a lock from
another host is then trusted: remove it by hand if that run is gone).

Another run of the same directory -- also ``--overwrite`` or ``--resume`` -- is refused with
:class:`RunLockedError` (a :class:`~gcrsky.run.output.RunExistsError`) before it reads,
removes or writes anything there.  A ``jax.distributed`` process other than 0 writes nothing
and takes no lock.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import socket
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from .output import RunExistsError

__all__ = ["LOCK_FILE", "RunLockedError", "check_unlocked", "lock_owner", "run_lock"]

log = logging.getLogger(__name__)

#: The lock file a run holds in its output directory (hidden; never a run file).
LOCK_FILE = ".gcrsky.lock"


class RunLockedError(RunExistsError):
    """Another run holds the output directory (:func:`run_lock`).

    Attributes:
        out: the directory; owner: what the holder recorded (``pid``, ``host``, ``started``
            (UTC, ISO 8601), ``argv``), empty if it could not be read.
    """

    def __init__(self, out, owner: dict | None):
        self.owner = dict(owner or {})
        super().__init__(out, [LOCK_FILE], f"{out} is in use by another gcrsky run ({describe_owner(self.owner)}); "
                                           "wait for it to finish, or choose another --out")


def describe_owner(owner: dict) -> str:
    """``pid P on host H since T: CMD`` of a lock's owner record (what is known of it)."""
    if not owner:
        return "owner unknown"
    text = f"pid {owner.get('pid', '?')} on host {owner.get('host', '?')}"
    if owner.get("started"):
        text += f" since {owner['started']}"
    if owner.get("argv"):
        text += ": gcrsky " + " ".join(str(a) for a in owner["argv"])
    return text


def _owner_record(argv) -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "argv": list(sys.argv[1:] if argv is None else argv)}


def _parse(text: str) -> dict:
    try:
        owner = json.loads(text)
    except ValueError:
        return {}
    return owner if isinstance(owner, dict) else {}


def _read(path: Path) -> dict:
    try:
        return _parse(path.read_text())
    except OSError:
        return {}


def _flock(fd: int) -> bool | None:
    """True: locked; False: another process holds it; None: ``flock`` is not available here."""
    try:
        import fcntl
    except ImportError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError as e:
        if e.errno in (errno.EAGAIN, errno.EACCES):
            return False
        return None  # ENOLCK, EINVAL, ...: the file system does not do flock
    return True


def _pid_alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, ValueError, TypeError, OverflowError):
        return True  # exists (another user's), or unreadable: do not take it
    return True


def _stale(owner: dict) -> bool:
    """Whether an exclusively created lock's owner is gone: it ran on this host and its pid is dead."""
    return bool(owner) and owner.get("host") == socket.gethostname() and not _pid_alive(owner.get("pid"))


@contextmanager
def _flock_lock(path: Path, out: Path, record: dict) -> Iterator[bool]:
    """Hold ``path`` by ``flock``; yields False (and holds nothing) where flock is unavailable."""
    while True:
        existed = path.exists()
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        got = _flock(fd)
        if got is None:
            os.close(fd)
            if not existed:  # the exclusive-create lock that follows must not find our empty file
                path.unlink(missing_ok=True)
            yield False
            return
        if not got:
            with os.fdopen(fd, "r") as fh:
                raise RunLockedError(out, _parse(fh.read()))
        try:  # the holder we waited on may have unlinked the file we opened: lock the one on disk
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        previous = _parse(os.pread(fd, 1 << 16, 0).decode(errors="replace"))
        if previous:
            log.warning("%s: took over a stale lock (its run is gone: %s)", out, describe_owner(previous))
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
        yield True
    finally:
        try:  # unlink while still holding the lock, then release it
            os.unlink(path)
        except FileNotFoundError:
            pass
        os.close(fd)


@contextmanager
def _exclusive_file_lock(path: Path, out: Path, record: dict) -> Iterator[None]:
    """Hold ``path`` by creating it exclusively (where ``flock`` is unavailable)."""
    for _ in range(3):
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            owner = _read(path)
            if not _stale(owner):
                raise RunLockedError(out, owner) from None
            log.warning("%s: took over a stale lock (its run is gone: %s)", out, describe_owner(owner))
            path.unlink(missing_ok=True)
            continue
        with os.fdopen(fd, "w") as fh:
            fh.write(json.dumps(record))
        break
    else:
        raise RunLockedError(out, _read(path))
    try:
        yield
    finally:
        if _read(path).get("pid") == record["pid"]:
            path.unlink(missing_ok=True)


@contextmanager
def run_lock(out, argv=None) -> Iterator[Path]:
    """Hold the exclusive lock of the output directory ``out`` (created if missing) for the block.

    Args:
        out: the run's output directory.
        argv: the command line to record (default ``sys.argv[1:]``).

    Yields:
        the lock file's path (``out/.gcrsky.lock``), removed when the block ends.

    Raises:
        RunLockedError: another live run holds ``out`` (its pid, host, start and command in
            the message); nothing in ``out`` was touched.
        OSError: ``out`` cannot be created or written (read-only, not a directory, ...).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / LOCK_FILE
    record = _owner_record(argv)
    with _flock_lock(path, out, record) as held:
        if held:
            yield path
            return
    with _exclusive_file_lock(path, out, record):
        yield path


def lock_owner(out) -> dict | None:
    """The owner record of a live lock on ``out`` (another run is writing there), else None.

    Takes and releases the lock to find out, so it never blocks; a stale lock reads as None.
    """
    out = Path(out)
    if not (out / LOCK_FILE).exists():
        return None
    try:
        with run_lock(out):
            return None
    except RunLockedError as e:
        return e.owner


def check_unlocked(out) -> None:
    """Raise :class:`RunLockedError` if a live run holds ``out`` (a cheap early check before expensive work;
    :func:`run_lock` is what excludes)."""
    owner = lock_owner(out)
    if owner is not None:
        raise RunLockedError(out, owner)
