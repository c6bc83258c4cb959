"""Choosing a sampler path by problem size, and memory estimates before large allocations.

Between the normal operator (:mod:`gcrsky.normal`) and the samplers
(:mod:`gcrsky.sampler`, :mod:`gcrsky.mmode`): given a :class:`~gcrsky.normal.LinearSystem`
:func:`plan_sampler` picks the cheapest *exact* path and says why; every path that
allocates something large first checks it against the memory available
(:func:`check_memory`) and raises :class:`InsufficientMemoryError` naming the size
and the path that would fit.

Paths (all exact; they differ only in cost):

* ``"mmode"``: uniform full-day coverage with time-stationary noise and no frame map
  (:func:`gcrsky.mmode.mmode_check`): P is block-diagonal in m; blocks cost
  ``O(Nf Nbl lmax^3)`` to build and ``8 Nf (lmax+1) (2 lmax+2)^2`` bytes.
* ``"cholesky"``: dense ``P`` built once (``8 Nf Nt Nbl n^2`` flop, ``8 Nf n^2`` bytes,
  three times that with its factor and ``L^-T``), then each draw is a product with
  ``L^-T`` (``2 n^2`` flop).
* ``"eigh"``: like Cholesky, for a singular P (a flat prior, ``S^-1 = 0`` somewhere).
* ``"cg"`` matrix-free: never forms P; ``16 Nf Nt Nbl n`` flop per product, a rank-128
  Nystrom preconditioner (``8 Nf n 128`` bytes) for a proper prior, m-blocks for a
  flat one.

Rule of :func:`plan_sampler` (``method="auto"`` in :func:`gcrsky.prepare` /
:func:`gcrsky.sample`): m-mode when its check passes; else dense (Cholesky, or the
eigen sampler for a flat prior) when the dense P and its factor fit in
:data:`DENSE_MEMORY_FRACTION` of the available memory and ``n <= DENSE_MAX_N``; else
matrix-free CG.  The crossovers are measured in ``benchmarks/scale.py``: at lmax 50
(n = 2601) Cholesky set-up is 2-9 s and a draw 2-3 ms against 40-600 ms per draw for
matrix-free CG, so dense wins wherever it fits; ``DENSE_MAX_N`` = 12000 keeps the
``n^3 / 3`` factorisation under ~1 min on two cores.
"""

from __future__ import annotations

import logging
import os
from typing import NamedTuple

import jax
import numpy as np

from .normal import LinearSystem
from .operator import n_in

__all__ = [
    "InsufficientMemoryError",
    "SamplerPlan",
    "available_memory_bytes",
    "check_memory",
    "format_bytes",
    "path_memory_bytes",
    "plan_sampler",
    "DENSE_MAX_N",
    "DENSE_MEMORY_FRACTION",
]

log = logging.getLogger(__name__)

#: Largest n for which ``method="auto"`` forms and factorises the dense P.
DENSE_MAX_N = 12000
#: Fraction of the available memory the dense P and its factor may take under "auto".
DENSE_MEMORY_FRACTION = 0.5
#: Nystrom sketch rank used by the CG path (gcrsky.sampler default).
NYSTROM_RANK = 128


class InsufficientMemoryError(MemoryError):
    """A path would allocate more than the memory available; the message names the alternative."""


class SamplerPlan(NamedTuple):
    """What :func:`plan_sampler` chose.

    Attributes:
        method: ``"mmode"``, ``"cholesky"``, ``"eigh"`` or ``"cg"``.
        dense: for ``"cg"``: form the dense P (True) or run matrix-free (False).
        preconditioner: for ``"cg"``: ``"nystrom"`` or ``"mblock"``.
        memory_bytes: estimated peak of the path's large arrays.
        reason: one line saying why.
    """

    method: str
    dense: bool
    preconditioner: str
    memory_bytes: float
    reason: str


def format_bytes(n: float) -> str:
    """``1.5e9 -> '1.40 GiB'``."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.2f} {unit}"
    return f"{int(n)} B"


def available_memory_bytes(device=None) -> float:
    """Memory a new allocation can use on ``device`` (default: JAX's first device).

    Accelerators: ``bytes_limit - bytes_in_use`` from ``device.memory_stats()``.  CPU:
    ``MemAvailable`` from ``/proc/meminfo`` (Linux), else physical memory.  The
    environment variable ``GCRSKY_MEMORY_BUDGET_GB`` overrides both (e.g. on a shared
    node).
    """
    env = os.environ.get("GCRSKY_MEMORY_BUDGET_GB")
    if env:
        try:
            return float(env) * 2**30
        except ValueError as e:
            raise ValueError(f"GCRSKY_MEMORY_BUDGET_GB must be a number of GiB, got {env!r}") from e
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


def _sizes(system: LinearSystem) -> tuple[int, int, int, int]:
    nf, nbl, _ = system.op.response.shape
    return int(nf), int(system.data.shape[1]), int(nbl), int(n_in(system.op))


def path_memory_bytes(system: LinearSystem, method: str, *, dense: bool = True, ndraws: int = 1) -> float:
    """Estimated peak bytes of a path's large arrays (float64), beyond the system itself.

    Counts the dense P, its factor and inverse factor / eigenvectors (``8 Nf n^2`` each), the m-blocks,
    the Nystrom sketch and the per-draw CG work vectors (``~6 x 8 Nf ndraws n``).
    """
    nf, nt, nbl, n = _sizes(system)
    lmax = int(round(np.sqrt(n))) - 1
    vec = 6.0 * 8 * nf * max(1, ndraws) * n  # CG state per draw
    if method == "mmode":
        return 2.0 * 8 * nf * (lmax + 1) * (2 * lmax + 2) ** 2 + vec
    if method in ("cholesky", "eigh"):  # P, factor and L^-T (Cholesky) / P and eigenvectors, sqrt_cov (eigh)
        return 3.0 * 8 * nf * n * n + 8.0 * nf * max(1, ndraws) * n
    if method == "cg":
        sketch = max(3.0 * 8 * nf * n * min(n, NYSTROM_RANK), 8.0 * nf * (lmax + 1) * (2 * lmax + 2) ** 2)
        return (8.0 * nf * n * n if dense else 0.0) + sketch + vec
    raise ValueError(f"unknown method {method!r}")


def plan_sampler(system: LinearSystem, *, ndraws: int = 1, budget: float | None = None) -> SamplerPlan:
    """The cheapest exact path for ``system`` (host-side; call outside ``jit``).

    Args:
        system: the linear system (concrete arrays).
        ndraws: draws per batch (sizes the CG work vectors).
        budget: bytes available; default :func:`available_memory_bytes`.

    Returns:
        a :class:`SamplerPlan`; raises :class:`InsufficientMemoryError` if even the
        matrix-free path does not fit.
    """
    from .mmode import mmode_check

    avail = available_memory_bytes() if budget is None else float(budget)
    nf, nt, nbl, n = _sizes(system)
    flat = bool(np.any(np.asarray(system.prior.inv_var) <= 0))
    chk = mmode_check(system)
    if chk.ok and not flat:
        mem = path_memory_bytes(system, "mmode", ndraws=ndraws)
        if mem <= avail:
            return SamplerPlan("mmode", False, "", mem, "uniform full-day coverage, stationary noise: P is block-diagonal in m")
    dense_mem = path_memory_bytes(system, "cholesky", ndraws=ndraws)
    if n <= DENSE_MAX_N and dense_mem <= DENSE_MEMORY_FRACTION * avail:
        method = "eigh" if flat else "cholesky"
        why = (f"n = {n} <= {DENSE_MAX_N} and the dense P + factor ({format_bytes(dense_mem)}) fit in "
               f"{DENSE_MEMORY_FRACTION:.0%} of {format_bytes(avail)}")
        if flat:
            why += "; flat prior: eigen sampler (P may be singular)"
        if not chk.ok:
            why += f"; not m-mode: {chk.reason}"
        return SamplerPlan(method, True, "", dense_mem, why)
    pc = "mblock" if flat else "nystrom"
    mem = path_memory_bytes(system, "cg", dense=False, ndraws=ndraws)
    check_memory(mem, f"matrix-free CG ({ndraws} draws per batch, n = {n}, Nf = {nf})",
                 "draw in smaller batches (ndraws) or shard the baselines (gcrsky.sharding)", budget=avail)
    why = (f"dense P + factor would need {format_bytes(dense_mem)} (n = {n}); matrix-free CG, "
           f"{pc} preconditioner")
    return SamplerPlan("cg", False, pc, mem, why)
