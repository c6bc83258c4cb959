"""Fitting a run in memory: all channels at once, or one channel at a time (issue 39).

A run whose channels are independent (:class:`~gcrsky.run.sampling.Joint`, ``method="auto"``) is
planned for every channel at once by :func:`gcrsky.solvers.plan.plan_sampler`.  Where that joint
plan does not fit, or fits only as matrix-free CG while one channel fits a direct path (dense
Cholesky, data space, m-mode: exact in a fixed number of operations, where CG iterates), the run
goes one channel at a time (``Independent("loop")``, as ``--by-channel``): the memory of one
channel's set-up, not of all of them.  Where even one channel does not fit, the refusal names the
command line's own options (:data:`CLI_MEMORY_OPTIONS`), before anything large is allocated.

The choice follows the memory free when the run starts: a run resumed on a machine with much less
(or more) memory free may choose the other way, and is then refused as a run with other settings.
"""

from __future__ import annotations

import dataclasses
import logging

from ..base.memory import InsufficientMemoryError, available_memory_bytes, format_bytes
from ..solvers.cg import freq_slice
from ..solvers.plan import plan_sampler
from .sampling import Independent, Joint

__all__ = ["CLI_MEMORY_OPTIONS", "MemoryPlan", "fit_in_memory"]

log = logging.getLogger(__name__)

#: What a user of ``gcrsky run`` can change when a run does not fit.
CLI_MEMORY_OPTIONS = ("--batch N (fewer draws at once), --by-channel (one channel at a time), --lmax L (a lower band "
                      "limit), or fewer channels (--freq-range, --chans), times (--lst-range) or antennas (--antennas)")


@dataclasses.dataclass(frozen=True)
class MemoryPlan:
    """What :func:`fit_in_memory` decided.

    Attributes:
        spec: the run's :class:`~gcrsky.run.spec.RunSpec` (its sampling ``Independent("loop")`` where the
            channels go one at a time, else unchanged).
        note: one line for the terminal and the summary saying why, or None where nothing changed.
        joint: the joint plan's path and estimated bytes (``(method, bytes)``), or None where it does not fit.
        per_channel: the one-channel plan's ``(method, bytes)``, or None where it was not needed.
    """

    spec: object
    note: str | None = None
    joint: tuple[str, float] | None = None
    per_channel: tuple[str, float] | None = None


def fit_in_memory(prob, spec, *, budget: float | None = None) -> MemoryPlan:
    """All channels at once where that fits a direct path, else one channel at a time (module doc).

    Only a :class:`~gcrsky.run.sampling.Joint` run with ``method="auto"`` and more than one channel is
    changed; a path or a draw stage the user chose is left as given (its own checks refuse it).

    Args:
        prob: the :class:`~gcrsky.model.Problem` (concrete arrays).
        spec: the :class:`~gcrsky.run.spec.RunSpec`.
        budget: bytes available (default :func:`gcrsky.base.available_memory_bytes`).

    Raises:
        InsufficientMemoryError: not even one channel's set-up fits; the message names
            :data:`CLI_MEMORY_OPTIONS`.
    """
    if not isinstance(spec.sampling, Joint) or spec.solver.method != "auto":
        return MemoryPlan(spec)
    system = prob.system()
    nf = int(system.data.shape[0])
    avail = available_memory_bytes() if budget is None else float(budget)
    batch = spec.draws.batch
    try:
        joint = plan_sampler(system, ndraws=batch, budget=avail)
    except InsufficientMemoryError as e:
        joint, why = None, str(e)
    if nf == 1 or (joint is not None and joint.method != "cg"):
        if joint is None:
            raise InsufficientMemoryError(f"{why}; {CLI_MEMORY_OPTIONS}")
        return MemoryPlan(spec, joint=(joint.method, joint.memory_bytes))
    try:
        one = plan_sampler(freq_slice(system, 0), ndraws=batch, budget=avail)
    except InsufficientMemoryError as e:
        raise InsufficientMemoryError(f"not even one channel fits: {e}; {CLI_MEMORY_OPTIONS}") from e
    if joint is not None and one.method == "cg":
        return MemoryPlan(spec, joint=(joint.method, joint.memory_bytes))  # CG either way: all channels at once
    all_at_once = (f"all {nf} channels at once would need matrix-free CG (~{format_bytes(joint.memory_bytes)})"
                   if joint is not None else f"all {nf} channels at once do not fit ({why})")
    note = (f"one channel at a time (as --by-channel): {one.method} per channel needs ~{format_bytes(one.memory_bytes)} "
            f"of {format_bytes(avail)} free, where {all_at_once}")
    log.info("memory plan: %s", note)
    return MemoryPlan(dataclasses.replace(spec, sampling=Independent("loop")), note,
                      None if joint is None else (joint.method, joint.memory_bytes), (one.method, one.memory_bytes))
