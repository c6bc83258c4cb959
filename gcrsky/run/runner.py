"""One run from start to end: :func:`execute` (what ``gcrsky run`` and each scenario of the suite do).

1. :func:`~gcrsky.run.output.open_run`: the output directory is checked (refuse,
   overwrite or resume, :class:`~gcrsky.run.RunSpec`'s ``output.existing``);
2. the draws: the run's draw stage (``spec.sampling``, :mod:`gcrsky.run.sampling`), e.g.
   :func:`~gcrsky.run.draws.joint_draws` (set-up once, then batch by batch into ``results.h5``);
3. the maps (:func:`~gcrsky.run.maps.run_maps`) and the per-frequency metrics of the report
   hooks (:mod:`gcrsky.run.report`), then their figures;
4. the products (:func:`~gcrsky.run.products.write_products`), ``results.h5`` finished
   (:func:`gcrsky.io.finalize_results_h5`: maps and z-scores) and ``summary.json``
   (:class:`~gcrsky.run.summary.RunSummary`), with the posterior predictive check of the
   data (:func:`gcrsky.run.fit.goodness_of_fit`; a rejected fit is a warning).

Every file is written atomically; a resumed run writes only the files that are missing
and keeps the summary its run wrote.  A failure after the draws (steps 3 and 4) is a
:class:`~gcrsky.run.output.PostDrawError`: the draws stay in ``results.h5`` (not yet
finished), and a resumed run (same settings) skips the set-up and the draws and redoes
those steps.  Stage timings are recorded by a
:class:`~gcrsky.run.stages.StageTimer`, and the run's XLA compilation (seconds,
persistent-cache hits and misses) by :func:`gcrsky.parallel.compile_stats`; the caller
watches the stages and batches through a :class:`~gcrsky.run.stages.Watch`.  Nothing
here prints.
"""

from __future__ import annotations

import json
from typing import Sequence

import numpy as np

from ..io.results import finalize_results_h5, read_draws, read_results_state, write_json
from ..parallel.runtime import CompileStats, compile_cache_dir, compile_stats
from .fit import run_fit
from .lock import run_lock
from .maps import RunMaps, parameter_frame, run_maps, stored_maps
from .output import (
    PRODUCT_FILES,
    RESULTS_FILE,
    SUMMARY_FILE,
    OpenRun,
    PostDrawError,
    check_out_dir,
    existing_run_files,
    open_run,
)
from .products import write_products
from .report import ReportHook, RunView, collect_figures, collect_metrics, hook_files
from .spec import RunSpec
from .stages import StageTimer, Watch
from .summary import (
    COMPILE_NOTE,
    METRICS_NOTE,
    PRODUCTS_NOTE,
    TIMINGS_NOTE,
    RunProducts,
    RunSummary,
    first_data_channel,
    fixed_flux_scale,
    map_units,
    read_summary,
    shown_channel,
    solver_summary,
    versions,
)

__all__ = ["execute"]


def execute(prob, spec: RunSpec, *, hooks: Sequence[ReportHook] = (), watch: Watch | None = None,
            build_s: float = 0.0, compile_since: CompileStats | None = None
            ) -> tuple[RunSummary, RunProducts] | None:
    """Sample ``prob`` as ``spec`` says and write ``results.h5``, the products, figures and ``summary.json``.

    Args:
        prob: a :class:`~gcrsky.model.Problem` (with or without a truth and a configuration).
        spec: the :class:`~gcrsky.run.RunSpec`.
        hooks: report hooks (:class:`~gcrsky.run.report.ReportHook`), in order: extra
            metrics and figures (e.g. :func:`gcrsky.paper.pipeline.paper_hooks`); none: the
            draws, maps and products only.
        watch: how the caller follows the stages and batches (:class:`~gcrsky.run.stages.Watch`).
        build_s: seconds the caller spent building ``prob`` (recorded as stage ``build``).
        compile_since: the :func:`gcrsky.parallel.compile_stats` snapshot to count the run's
            compilation from (e.g. taken before building ``prob``); default: now.

    Returns:
        ``(RunSummary, RunProducts)``; None in a ``jax.distributed`` process other than 0
        (``spec.sampling`` ``Independent("processes")``), which computes its channels and writes nothing.

    Raises:
        RunExistsError, ResumeError: the output directory holds a run that this one may not
            touch or cannot continue (:func:`~gcrsky.run.output.check_output`).
        RunLockedError: another run is writing to the output directory (:func:`~gcrsky.run.lock.run_lock`,
            held from before the directory is looked at until the last file is written).
        PostDrawError: a stage after the draws failed (the draws are kept; resume finishes).
    """
    compile0 = compile_stats() if compile_since is None else compile_since
    watch = watch or Watch()
    if spec.sampling.elsewhere():
        spec.sampling.run_share(prob, spec, watch)
        return None
    check_out_dir(spec.output.out)  # a writable directory, before any work
    with run_lock(spec.output.out, spec.argv):  # one run per directory, from its first look to its last file
        return _execute_locked(prob, spec, hooks, watch, build_s, compile0)


def _execute_locked(prob, spec: RunSpec, hooks, watch: Watch, build_s: float, compile0: CompileStats
                    ) -> tuple[RunSummary, RunProducts]:
    """:func:`execute` in process 0, holding the output directory's lock."""
    run = open_run(prob, spec, hook_files(hooks))
    prob = run.prob  # resuming: the recorded inputs (bit for bit the first batches' problem)
    st = StageTimer(watch.on_stage)
    st.times["build"] = build_s
    method = spec.sampling.run_draws(prob, spec, run, st, watch)  # leaves the "draws" stage running
    stored = read_draws(run.h5)
    st.stop()
    try:
        return _after_draws(prob, spec, run, st, stored, method, hooks, compile0)
    except Exception as err:  # the draws are safe in results.h5: say so, and how to finish
        raise PostDrawError(run.out, st.current or "fit", stored.draws.shape[1], err) from err


def _after_draws(prob, spec: RunSpec, run: OpenRun, st: StageTimer, stored, method: str, hooks,
                 compile0: CompileStats) -> tuple[RunSummary, RunProducts]:
    """Everything after the draws: maps, metrics, figures, fit, products, ``results.h5`` finished, summary."""
    solver, warnings = solver_summary(method, spec.solver.tol, stored.wiener_info, stored.info, None, prob.n,
                                      rank=stored.rank)
    if not np.isfinite(stored.draws).all():
        warnings.append(f"ERROR: {int((~np.isfinite(stored.draws)).sum())} non-finite values in the draws.")
    channels = spec.sampling.channels_block(prob, run.h5, warnings)
    view, figures = _report(prob, spec, run, stored, hooks, st, warnings)
    fit_prob = spec.sampling.fit_problem(prob, run.h5)
    gof = None if (run.out / SUMMARY_FILE).exists() else run_fit(fit_prob, stored.wiener_filter, warnings,
                                                                     rank=stored.rank)
    st.start("write")
    finalized = _write(prob, spec, run, stored, view.maps, method, channels, view.units)
    blocks = {} if (run.out / SUMMARY_FILE).exists() else spec.sampling.finish(prob, run.out, run.h5)
    for block in blocks.values():  # a stage's own warnings (e.g. a chain that has not mixed)
        warnings += (block or {}).get("warnings", [])
    st.stop()
    timings, compiled = _timings(st, stored, compile0)
    summary = _summary(prob, spec, run, view, solver, warnings, (timings, compiled), figures, method, gof, blocks,
                       channels)
    written = [f for f in existing_run_files(run.out, run.files)
               if f not in run.before or (f == RESULTS_FILE and finalized)]
    return summary, _products(prob, run, view, stored.draws, written)


def _report(prob, spec: RunSpec, run: OpenRun, stored, hooks, st: StageTimer, warnings: list
            ) -> tuple[RunView, dict]:
    """The ``maps`` stage (maps, the hooks' metrics) and the ``plots`` stage (the hooks' figures, whose
    warnings are added to ``warnings``). Returns the :class:`RunView` and ``{figure key: file name}``."""
    st.start("maps")
    maps = run_maps(prob, stored.draws, stored.wiener_filter,
                    maps=stored_maps(run.h5) if run.already_complete else None)
    units = map_units(prob, {"source": "inferred"} if spec.sampling.name == "amplitude" else None)
    view = RunView(prob, stored.draws, maps, [], bool(np.isfinite(stored.draws).all()), spec.scenario,
                   first_data_channel(prob), units)
    view = view._replace(per_freq=collect_metrics(view, hooks))
    st.stop()
    figures = {}
    if spec.output.plots:
        st.start("plots")
        figures, more = collect_figures(view, hooks, run.out, only_missing=True)
        warnings += more
        st.stop()
    return view, figures


def _write(prob, spec: RunSpec, run: OpenRun, stored, maps: RunMaps, method: str, channels: dict,
           units: dict | None = None) -> bool:
    """The products (those missing), and ``results.h5`` finished unless it was (with the ``channels`` block as
    its attribute ``channels_json``); True if it was finished now."""
    write_products(run.out, wiener_filter=stored.wiener_filter, wiener_maps=maps.wiener_maps,
                   std_maps=maps.std_maps, freqs_hz=np.asarray(prob.freqs_hz), lmax=prob.lmax,
                   frame=parameter_frame(prob), ndraws=stored.draws.shape[1], method=method,
                   seed=spec.draws.seed, only_missing=True, units=units)
    if read_results_state(run.h5).complete:
        return False
    arrays = {"truth": maps.truth_maps, "mean": maps.mean_maps, "std": maps.std_maps, "wiener": maps.wiener_maps}
    finalize_results_h5(run.h5, mode_z=maps.mode_z, maps=arrays, attrs={"channels_json": json.dumps(channels)})
    return True


def _timings(st: StageTimer, stored, compile0: CompileStats) -> tuple[dict, dict]:
    """``summary.json``'s ``timings_s`` (the stages, their total, the batches, the compilation) and ``compile``."""
    timings = dict(st.times)
    timings["total"] = float(sum(v for v in st.times.values()))
    timings["draw_batches_s"] = stored.batch_seconds
    compiled = compile_stats().since(compile0)
    timings["compile_s"] = compiled.compile_s
    timings["cache_hits"] = compiled.cache_hits
    timings["cache_misses"] = compiled.cache_misses
    timings["note"] = TIMINGS_NOTE
    cache_dir = compile_cache_dir()
    return timings, {**compiled._asdict(), "cache_dir": None if cache_dir is None else str(cache_dir),
                     "note": COMPILE_NOTE}


def _summary(prob, spec: RunSpec, run: OpenRun, view: RunView, solver: dict, warnings: list,
             timings: tuple[dict, dict], figures: dict, method: str, gof: dict | None = None,
             blocks: dict | None = None, channels: dict | None = None) -> RunSummary:
    """The run's :class:`RunSummary`, written to ``summary.json`` (a resumed run keeps the one its run wrote)."""
    path = run.out / SUMMARY_FILE
    if path.exists():
        return read_summary(path)
    per_freq, maps, cfg = view.per_freq, view.maps, prob.config
    f0 = per_freq[view.shown]
    (timings, compiled), d = timings, spec.draws
    summary = RunSummary(
        frac_diff_centre_median=f0.get("frac_diff_centre_median"),
        frac_diff_fwhm_median=f0.get("frac_diff_fwhm_median"),
        metrics=dict(f0), metrics_note=METRICS_NOTE, per_frequency=per_freq,
        region=None if maps.centre_dec_deg is None else {
            "centre_dec_deg": maps.centre_dec_deg, "ra_range_deg": list(maps.ra_range_deg),
            "fwhm_deg": [m.get("fwhm_deg") for m in per_freq]},
        solver=solver, draws_finite=view.finite, warnings=warnings, timings_s=timings, compile=compiled,
        run={"nsamples": d.nsamples, "seed": d.seed, "batch": d.batch, "method": method, "scenario": spec.scenario,
             "argv": None if spec.argv is None else list(spec.argv),
             "resumed_at_batch": None if run.state is None else run.start, "frame": parameter_frame(prob)},
        figures=figures, products={**PRODUCT_FILES, "results": RESULTS_FILE}, products_note=PRODUCTS_NOTE,
        config=cfg.to_dict() if cfg is not None else None, sky_note=prob.sky_note, versions=versions(),
        exit_status=0 if view.finite else 1,
        data_checks=dict(getattr(cfg, "checks", None) or {}) or None,
        goodness_of_fit=gof,
        channels=channels,
        **{"flux_scale": fixed_flux_scale(prob), **(blocks or {})},
        shown_channel=shown_channel(prob, view.shown), units=dict(view.units or map_units(prob)),
    )
    write_json(path, summary.to_json())
    return summary


def _products(prob, run: OpenRun, view: RunView, draws: np.ndarray, written: list) -> RunProducts:
    """The shown channel's (:attr:`RunView.shown`: the first with data) maps, z-scores and draws, and what this
    call wrote."""
    maps, i = view.maps, view.shown
    return RunProducts(
        truth_map=None if maps.truth_maps is None else maps.truth_maps[i], mean_map=maps.mean_maps[i],
        std_map=maps.std_maps[i], z=None if maps.mode_z is None else maps.mode_z[i], draws=draws[i],
        truth=None if prob.a_true is None else np.asarray(prob.a_true)[i], modes=prob.modes,
        fwhm_deg=view.per_freq[i].get("fwhm_deg"), centre_dec_deg=maps.centre_dec_deg,
        ra_range_deg=maps.ra_range_deg, resumed_at_batch=None if run.state is None else run.start,
        written=written, already_complete=run.already_complete,
    )
