"""The paper's run: :func:`gcrsky.run.execute` with the paper's report hook (:func:`paper_hooks`).

The run itself (output directory, draws, maps, products, summary, resume) is the core's
:mod:`gcrsky.run`; the paper adds its metrics and figures through
:class:`~gcrsky.paper.report.PaperReport`.  A simulated configuration
(:class:`~gcrsky.sim.Config`) does not record its beam's FWHM, which the metrics need:
:func:`paper_hooks` measures it from the configuration's beam
(:func:`gcrsky.sim.beam_for_config`).

:func:`run_problem` is the former one-call form, kept for compatibility: it builds a
:class:`~gcrsky.run.RunSpec` from its keywords and returns the summary as a dict.
"""

from __future__ import annotations

import numpy as np

from ..instrument.beams import beam_fwhm_rad
from ..run import Draws, Independent, Joint, Output, RunSpec, Solver, Watch, execute
from ..sim.standard import beam_for_config
from ..solvers.options import DEFAULT_TOL
from .report import PaperReport

__all__ = ["paper_hooks", "run_problem", "simulated_fwhm_deg"]


def simulated_fwhm_deg(cfg, freqs_hz) -> tuple[float, ...]:
    """The FWHM (degrees) of a simulated configuration's beam at each frequency (Hz)."""
    return tuple(float(np.rad2deg(beam_fwhm_rad(beam_for_config(cfg), float(f)))) for f in np.asarray(freqs_hz))


def paper_hooks(prob) -> tuple[PaperReport]:
    """The paper's report hooks for a run of ``prob`` (simulated or read from a file)."""
    cfg = prob.config
    if cfg is None or getattr(cfg, "fwhm_deg", None) is not None:
        return (PaperReport(),)
    return (PaperReport(fwhm_deg=simulated_fwhm_deg(cfg, prob.freqs_hz)),)


def run_problem(prob, out, *, nsamples: int, seed: int, batch: int, method: str, plots: bool, build_s: float,
                tol: float = DEFAULT_TOL, argv=None, scenario_name: str | None = None, on_stage=None, progress=None,
                existing: str = "refuse", extra_settings: dict | None = None, compile_since=None,
                channels: str | None = None, channel_progress=None):
    """Compatibility form of :func:`gcrsky.run.execute` with :func:`paper_hooks`.

    The keywords are the fields of :class:`~gcrsky.run.RunSpec` (``Draws(nsamples, seed,
    batch)``, ``Solver(method, tol)``, ``Output(out, existing, plots)``, ``Independent(channels)`` unless None,
    ``scenario=scenario_name``, ``argv``, ``extra=extra_settings``) and of
    :class:`~gcrsky.run.Watch` (``on_stage``, ``progress``, ``channel_progress``).

    Returns:
        ``(summary.json's dict, RunProducts)``; ``(None, None)`` in a ``jax.distributed``
        process other than 0.
    """
    spec = RunSpec(Draws(nsamples, seed, batch), Output(out, existing, plots), Solver(method, tol),
                   Joint() if channels is None else Independent(channels), scenario=scenario_name, argv=argv,
                   extra=extra_settings)
    done = execute(prob, spec, hooks=paper_hooks(prob), watch=Watch(on_stage, progress, channel_progress),
                   build_s=build_s, compile_since=compile_since)
    if done is None:
        return None, None
    return done[0].to_json(), done[1]


#: Names this module held before the run moved to :mod:`gcrsky.run` (still importable from here, with a warning).
_MOVED = {name: "gcrsky.run" for name in (
    "EXISTING", "PRODUCT_FILES", "RESULTS_FILE", "RUN_FILES", "SUMMARY_FILE", "ResumeError",
    "RunExistsError", "RunProducts", "StageTimer", "check_output", "existing_run_files", "info_stats",
    "parameter_frame", "remove_run_files", "run_settings", "settings_differences", "solver_summary", "versions",
    "write_products")}
_MOVED["draw_batch"] = "gcrsky.run.draws"
_MOVED["FIGURE_FILES"] = "gcrsky.paper.report"


def __getattr__(name: str):
    if name in _MOVED:
        import importlib
        import warnings

        warnings.warn(f"gcrsky.paper.pipeline.{name} moved to {_MOVED[name]}.{name}", DeprecationWarning, stacklevel=2)
        return getattr(importlib.import_module(_MOVED[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
