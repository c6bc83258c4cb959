"""Report hooks: what an application adds to a run after the draws (metrics, figures, warnings).

The run layer computes the maps (:mod:`gcrsky.run.maps`) and the per-frequency metrics it
knows (``freq_hz``); a :class:`ReportHook` adds more.  Hooks run in the order given, each
seeing the metrics of those before it (:attr:`RunView.per_freq`):

1. :meth:`ReportHook.metrics` (stage ``maps``): extra per-frequency metrics, one dict per
   channel, merged into ``summary.json``'s ``per_frequency`` (and ``metrics``, the first);
2. :meth:`ReportHook.figures` (stage ``plots``, only when the run draws figures): figure
   files written into the output directory and warnings for the terminal.

A hook declares the files it may write (:meth:`ReportHook.files`): they are run files
(:func:`gcrsky.run.output.run_files`), refused, overwritten and resumed with the run's own;
the core itself holds no figure names.

:mod:`gcrsky.paper.report` implements the paper's (beam-region metrics, truth metrics,
Figs. 3-7); a run without hooks writes the draws, the products and a summary without them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, NamedTuple, Protocol, Sequence, runtime_checkable

import numpy as np

from .maps import RunMaps

__all__ = ["FigureReport", "ReportHook", "RunView", "collect_figures", "collect_metrics", "hook_files"]


class RunView(NamedTuple):
    """What a report hook sees after the draws.

    Attributes:
        problem: the :class:`~gcrsky.model.Problem`.
        draws: ``(Nf, ndraws, n)`` realified draws, K.
        maps: :class:`~gcrsky.run.maps.RunMaps`.
        per_freq: the metrics so far, one dict per channel (read only).
        finite: every draw is finite.
        scenario: the run's scenario name, or None.
        shown: the channel the figures and the top-level metrics show (the first with data,
            :func:`gcrsky.run.summary.first_data_channel`).
        units: :func:`gcrsky.run.summary.map_units`'s block (None: K).
    """

    problem: Any
    draws: np.ndarray
    maps: RunMaps
    per_freq: Sequence[Mapping]
    finite: bool
    scenario: str | None
    shown: int = 0
    units: Mapping | None = None


class FigureReport(NamedTuple):
    """What :meth:`ReportHook.figures` did: ``names`` ``{key: file name}`` and ``warnings``."""

    names: dict
    warnings: list


@runtime_checkable
class ReportHook(Protocol):
    """Extra metrics and figures of a run; subclass it and override what you add (the defaults add nothing)."""

    def metrics(self, view: RunView) -> Sequence[Mapping]:
        """Extra metrics per frequency: a sequence of ``Nf`` dicts (JSON-able values)."""
        return [{} for _ in view.per_freq]

    def figures(self, view: RunView, out: Path, *, only_missing: bool) -> FigureReport:
        """Write figures into ``out`` (atomically; keep those present when ``only_missing``)."""
        return FigureReport({}, [])

    def files(self) -> Mapping[str, str]:
        """Every file :meth:`figures` may write: ``{key: file name}`` (the run's files with them)."""
        return {}


def hook_files(hooks: Sequence[ReportHook]) -> tuple[str, ...]:
    """The file names every hook may write (:meth:`ReportHook.files`), in order, each once."""
    return tuple(dict.fromkeys(f for hook in hooks for f in hook.files().values()))


def collect_metrics(view: RunView, hooks: Sequence[ReportHook]) -> list[dict]:
    """The per-frequency metrics: ``freq_hz`` then each hook's, merged in order.

    Raises:
        ValueError: a hook returned another number of channels than the problem has.
    """
    freqs = np.asarray(view.problem.freqs_hz)
    per_freq = [{"freq_hz": float(f)} for f in freqs]
    for hook in hooks:
        extra = list(hook.metrics(view._replace(per_freq=per_freq)))
        if len(extra) != len(per_freq):
            raise ValueError(f"report hook {type(hook).__name__} gave metrics of {len(extra)} channels, "
                             f"the problem has {len(per_freq)}")
        for m, e in zip(per_freq, extra):
            m.update(e)
    return per_freq


def collect_figures(view: RunView, hooks: Sequence[ReportHook], out: Path, *, only_missing: bool) -> FigureReport:
    """Every hook's figures and warnings, in order."""
    names: dict = {}
    warnings: list = []
    for hook in hooks:
        rep = hook.figures(view, Path(out), only_missing=only_missing)
        names.update(rep.names)
        warnings.extend(rep.warnings)
    return FigureReport(names, warnings)
