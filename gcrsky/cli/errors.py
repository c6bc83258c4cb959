"""What the command prints for an error the user can fix: one message naming the cause, exit status 2.

A bad file, option or path, a full disk or too little memory is a *user error*: the command
prints ``gcrsky CMD: error: ...`` (what is wrong, where, and what to do) and returns
:data:`EXIT_USAGE`, with the traceback only under ``-v``.  Anything else is a bug and keeps
its traceback.
"""

from __future__ import annotations

import errno
import sys
import traceback

__all__ = ["EXIT_USAGE", "USER_ERRORS", "address_space_limit", "error_message", "out_of_memory", "report_user_error",
           "under_address_limit"]

#: Exit status of a user error (as argparse's for bad arguments).
EXIT_USAGE = 2

#: The exceptions that mean the input, an option, a path, the disk or the memory is at fault.
USER_ERRORS = (ValueError, OSError, MemoryError)

_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
_DENIED = (errno.EACCES, errno.EPERM, errno.EROFS)


def _full_disk(e: BaseException) -> bool:
    text = str(e)
    return getattr(e, "errno", None) in _FULL or "No space left" in text or "File too large" in text or (
        "Disk quota" in text)


def address_space_limit() -> int | None:
    """The process's address-space limit (``ulimit -v``) in bytes, or None where there is none."""
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    return None if soft == resource.RLIM_INFINITY else int(soft)


def under_address_limit(what: str) -> MemoryError:
    """The message of a failure caused by a tight ``ulimit -v`` (``what`` failed): the limit and the remedy."""
    soft = address_space_limit() or 0
    return MemoryError(
        f"{what} under this shell's address-space limit (ulimit -v {soft // 1024} KiB = {soft / 2**30:.1f} GiB): "
        "XLA's thread pools and the shared libraries gcrsky loads need more virtual memory than that; raise the "
        "limit (ulimit -v unlimited, or at least ~4 GiB), or bound resident memory instead (e.g. systemd-run "
        "--user -p MemoryMax=8G gcrsky ..., and GCRSKY_MEMORY_BUDGET_GB)")


def _blames_address_limit(e: BaseException) -> bool:
    """A failure to load a library or map memory, while a ``ulimit -v`` is set: the limit is the likely cause."""
    if address_space_limit() is None:
        return False
    text = str(e)
    return isinstance(e, MemoryError) and "ulimit" not in text or getattr(e, "errno", None) == errno.ENOMEM or (
        isinstance(e, OSError) and ("shared object" in text or "failed to map" in text or "cannot allocate" in
                                    text.lower()))


def error_message(e: BaseException) -> str:
    """The one-paragraph message of a user error (:data:`USER_ERRORS`): the cause, the path, what to do."""
    if _blames_address_limit(e):
        return f"{under_address_limit(type(e).__name__ + ': ' + str(e))}"
    if isinstance(e, OSError):
        where = f" {e.filename}" if getattr(e, "filename", None) else ""
        what = e.strerror or str(e)
        if _full_disk(e):
            if "--" in what:  # the message already says what to do (e.g. the draws' size checked up front)
                return f"no space left on the device of{where}: {what}"
            return (f"no space left writing{where or ' the output'} ({what}): free some space or choose another "
                    "--out; the batches of draws already written are kept, and --resume continues the run")
        if getattr(e, "errno", None) in _DENIED:
            return f"cannot write{where} ({what}): choose a directory you can write (--out)"
        if where and e.strerror and e.strerror not in str(e.filename):
            return f"{e.filename}: {what}"
        return str(e)
    if isinstance(e, MemoryError):
        from ..run.memoryplan import CLI_MEMORY_OPTIONS

        what = str(e) or "out of memory"
        return what if "--" in what else f"{what}; on the command line: {CLI_MEMORY_OPTIONS}"
    return str(e)


def out_of_memory(e: BaseException) -> MemoryError | None:
    """XLA's out-of-memory error (``RESOURCE_EXHAUSTED`` / ``Out of memory allocating N bytes``) as a
    :class:`MemoryError` saying so and what to change (the traceback stays under ``-v``); None for any other."""
    text = str(e)
    if type(e).__name__ != "JaxRuntimeError" or not ("RESOURCE_EXHAUSTED" in text or "Out of memory" in text):
        return None
    import re

    size = re.search(r"allocating (\d+) bytes", text)
    from ..base.memory import format_bytes

    got = f" (an allocation of {format_bytes(float(size.group(1)))})" if size else ""
    err = MemoryError(f"the device ran out of memory{got}, past gcrsky's own estimates (please report it)")
    err.__cause__ = e
    return err


def report_user_error(e: BaseException, command: str, verbose: int) -> int:
    """Print the message of a user error to stderr (the traceback too under ``-v``); :data:`EXIT_USAGE`."""
    if verbose:
        traceback.print_exception(e)
    print(f"gcrsky {command}: error: {error_message(e)}"
          + ("" if verbose else "  (-v shows where it happened)"), file=sys.stderr)
    return EXIT_USAGE
