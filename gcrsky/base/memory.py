"""Memory budgets: how much a new allocation may use, and the error that refuses it.

Every path that allocates something large (the response, a dense P, the m-blocks,
CG work vectors) first compares its estimated size with :func:`available_memory_bytes`
through :func:`check_memory`, which raises :class:`InsufficientMemoryError` naming
the size and the alternative that would fit.
"""

from __future__ import annotations

import math
import os

import jax

__all__ = ["InsufficientMemoryError", "available_memory_bytes", "check_memory", "format_bytes"]


class InsufficientMemoryError(MemoryError):
    """A path would allocate more than the memory available; the message names the alternative."""


def format_bytes(n: float) -> str:
    """``1.5e9 -> '1.40 GiB'``."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.2f} {unit}"
    return f"{int(n)} B"


def available_memory_bytes(device=None) -> float:
    """Memory a new allocation can use on ``device`` (default: JAX's first device), bytes.

    Accelerators: ``bytes_limit - bytes_in_use`` from ``device.memory_stats()``.  CPU:
    ``MemAvailable`` from ``/proc/meminfo`` (Linux), else physical memory.  The
    environment variable ``GCRSKY_MEMORY_BUDGET_GB`` overrides both (e.g. on a shared
    node).
    """
    env = os.environ.get("GCRSKY_MEMORY_BUDGET_GB")
    if env:
        try:
            gib = float(env)
        except ValueError as e:
            raise ValueError(f"GCRSKY_MEMORY_BUDGET_GB must be a number of GiB, got {env!r}") from e
        if not (math.isfinite(gib) and gib > 0):
            raise ValueError(f"GCRSKY_MEMORY_BUDGET_GB must be a positive, finite number of GiB, got {env!r}")
        return gib * 2**30
    dev = device if device is not None else jax.devices()[0]
    if dev.platform != "cpu":
        stats = dev.memory_stats() or {}
        if "bytes_limit" in stats:
            return float(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def check_memory(nbytes: float, what: str, alternative: str, *, budget: float | None = None) -> None:
    """Raise :class:`InsufficientMemoryError` if ``nbytes`` exceeds the budget.

    Args:
        nbytes: the estimated allocation, bytes.
        what: what would be allocated (goes into the message).
        alternative: the path to use instead (goes into the message).
        budget: bytes available; default :func:`available_memory_bytes`.
    """
    avail = available_memory_bytes() if budget is None else float(budget)
    if nbytes > avail:
        raise InsufficientMemoryError(
            f"{what} needs ~{format_bytes(nbytes)} but only {format_bytes(avail)} is available; "
            f"{alternative}"
        )
