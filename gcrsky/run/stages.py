"""The stages of a run, timed, and how a caller watches them (:class:`Watch`): nothing here prints.

A run's stages, in order: ``wiener`` (set-up: the path, P, its factor or preconditioner,
the Wiener filter), ``draws``, ``maps``, ``plots`` (only when figures are drawn) and
``write``; ``build`` is the caller's (the problem's construction).
"""

from __future__ import annotations

import logging
import time
from typing import Callable, Iterable, NamedTuple

__all__ = ["StageTimer", "Watch"]

log = logging.getLogger(__name__)


class Watch(NamedTuple):
    """How the caller follows a run (e.g. the CLI's progress bars); every field optional.

    Attributes:
        on_stage: called with ``(stage, "start" | "stop")`` around each stage.
        progress: wraps the iterable of draw batches (e.g. a tqdm bar).
        channel_progress: for an independent-channel run: ``total -> update``, called once;
            ``update(1)`` after each channel.
    """

    on_stage: Callable[[str, str], None] | None = None
    progress: Callable[[Iterable], Iterable] | None = None
    channel_progress: Callable[[int], Callable[[int], object]] | None = None


class StageTimer:
    """Wall-clock seconds of named stages; ``on_stage(name, "start" | "stop")`` is called around each."""

    def __init__(self, on_stage: Callable[[str, str], None] | None = None):
        self.times: dict[str, float] = {}
        self._on = on_stage
        self._name: str | None = None
        self._t0 = 0.0

    def start(self, name: str) -> None:
        self._name, self._t0 = name, time.perf_counter()
        log.info("stage %s ...", name)
        if self._on:
            self._on(name, "start")

    @property
    def current(self) -> str | None:
        """The stage running now (started, not yet stopped), or None."""
        return self._name

    def stop(self) -> None:
        dt = time.perf_counter() - self._t0
        self.times[self._name] = dt
        log.info("stage %s done in %.2f s", self._name, dt)
        if self._on:
            self._on(self._name, "stop")
        self._name = None
