"""The draws of a joint run: set-up once, then one batch at a time into ``results.h5``.

The path is chosen by size (:func:`gcrsky.solvers.plan.choose_path`; a resumed run keeps
the recorded one), set up once (:func:`gcrsky.inference.api.prepare`: P, its factor or
preconditioner, the Wiener filter), and the draws are made batch by batch with the
documented key scheme (:func:`draw_batch`, as :func:`gcrsky.inference.draw_batches`),
each batch appended to ``results.h5`` (:func:`gcrsky.io.append_batch`) as soon as it is
drawn; a resumed run starts at the first missing batch and so ends with exactly the
draws of an uninterrupted one.

Test hook: when the environment variable ``GCRSKY_TEST_KILL_AFTER_BATCH`` is ``k``
(or ``k:KILL``, ``k:TERM``, ``k:INT``), the process sends itself that signal (SIGKILL by
default) as soon as ``results.h5`` records ``k`` complete batches (an abrupt death, as a
killed job; a batch system's SIGTERM; Ctrl-C; ``tests/test_resume.py`` uses it).  It is
meant for tests only.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import time

import jax
import numpy as np

from ..inference.api import prepare
from ..inference.batches import KEY_SCHEME, batch_key
from ..inference.posterior import draw_exactly
from ..io.results import append_batch, create_results_h5, json_default, read_draws
from ..solvers.plan import choose_path
from .maps import parameter_frame
from .output import OpenRun
from .resume import options_from_json, options_json
from .stages import StageTimer, Watch
from .summary import versions

__all__ = ["append_batches", "append_chain_batch", "draw_batch", "joint_draws", "read_chain", "record_setup"]

log = logging.getLogger(__name__)

#: Environment variable of the kill test hook (module doc).
KILL_HOOK = "GCRSKY_TEST_KILL_AFTER_BATCH"


def draw_batch(key: jax.Array, prepared, b: int, batch: int, nsamples: int):
    """Batch ``b`` of the key scheme (:mod:`gcrsky.inference.batches`): host arrays.

    A full batch is drawn with ``fold_in(key, b)`` and truncated to the draws that
    exist (the last batch), exactly as :func:`gcrsky.inference.draw_batches` does.

    Returns:
        ``(draws (Nf, take, n), SolveInfo over (Nf, take))``, ``take = min(batch, nsamples - b * batch)``.
    """
    d, info = draw_exactly(batch_key(key, b), prepared, batch)
    d = np.asarray(jax.block_until_ready(d))
    take = min(batch, nsamples - b * batch)
    return d[:, :take], jax.tree_util.tree_map(lambda a: np.asarray(a)[:, :take], info.draws)


def kill_hook(complete: int) -> None:
    """The test hook of the module doc: signal this process once ``complete`` batches are in results.h5."""
    at = (os.environ.get(KILL_HOOK) or "").strip()
    if not at:
        return
    batches, _, name = at.partition(":")
    if int(batches) == complete:
        os.kill(os.getpid(), getattr(signal, f"SIG{name.strip().upper() or 'KILL'}", signal.SIGTERM))


def _results_attrs(prob, spec, settings, *, method, options, key_scheme) -> dict:
    """The attributes a run records in a new ``results.h5`` (``options``: a path's options object, or the
    JSON text of a path the registry does not list, e.g. a frequency-coupled run's)."""
    cfg = prob.config
    return {
        "config_json": json.dumps(cfg.to_dict() if cfg is not None else None, default=json_default),
        "sky_note": prob.sky_note,
        "gcrsky_version": versions()["gcrsky"],
        "seed": spec.draws.seed,
        "batch": spec.draws.batch,
        "method": method,
        "method_requested": settings["method"],
        "solver_options_json": options if isinstance(options, str) else options_json(options),
        "tol": spec.solver.tol,
        "scenario": spec.scenario or "",
        "key_scheme": key_scheme,
        "frame": parameter_frame(prob),
    }


def record_setup(prob, spec, run: OpenRun, a_wf, winfo, *, rank, method, options, key_scheme, per_draw=None,
                 arrays=None) -> None:
    """A new run: create ``results.h5`` with the set-up (Wiener filter, settings, chosen path).
    A resumed one: compare the set-up's Wiener filter with the recorded one (logged if it differs:
    the remaining draws will then not be bit-identical to an uninterrupted run's).  ``per_draw``, ``arrays``:
    further datasets of a new ``results.h5`` (:func:`gcrsky.io.create_results_h5`)."""
    if run.state is None:
        attrs = _results_attrs(prob, spec, run.settings, method=method, options=options, key_scheme=key_scheme)
        create_results_h5(run.h5, prob, a_wf, nsamples=spec.draws.nsamples, batch=spec.draws.batch,
                          settings=run.settings, wiener_info=winfo, rank=rank, attrs=attrs, per_draw=per_draw,
                          arrays=arrays)
        return
    recorded = read_draws(run.h5).wiener_filter
    if not np.array_equal(recorded, a_wf, equal_nan=True):
        log.warning("the resumed set-up's Wiener filter differs from the recorded one by up to %.3g K: the "
                    "remaining draws will not be bit-identical to an uninterrupted run's",
                    float(np.nanmax(np.abs(recorded - a_wf))))


def _setup(prob, spec, run: OpenRun):
    """Choose the path (``auto`` resolved here, so that the exact options are recorded; a resumed
    run keeps the recorded options), prepare it and record the set-up. Returns the prepared path."""
    d = spec.draws
    if run.state is None:
        options = choose_path(prob.system(), spec.solver.method, tol=spec.solver.tol, ndraws=d.batch)
    else:  # auto's CG is matrix-free, "cg"'s dense: the recorded options, not the name
        options = options_from_json(run.state.attrs["solver_options_json"])
    prepared = prepare(prob, options=options, ndraws=d.batch)
    a_wf = np.asarray(jax.block_until_ready(prepared.a_wf))
    record_setup(prob, spec, run, a_wf, prepared.wiener, rank=getattr(prepared, "kept", None),
                 method=prepared.method, options=options, key_scheme=KEY_SCHEME)
    return prepared


def joint_draws(prob, spec, run: OpenRun, st: StageTimer, watch: Watch) -> str:
    """The ``wiener`` stage and the draws of a joint run, from batch ``run.start``; returns the path that ran.

    Leaves the ``draws`` stage running (the caller stops it once it has read the draws back).
    """
    d = spec.draws
    st.start("wiener")  # set-up once: P, factor / preconditioner, Wiener filter (compile included)
    prepared = _setup(prob, spec, run) if run.start < d.n_batches else None
    method = prepared.method if prepared is not None else str(run.state.attrs["method"])
    st.stop()
    st.start("draws")
    key = jax.random.PRNGKey(d.seed)
    append_batches(run, d, watch, lambda b: draw_batch(key, prepared, b, d.batch, d.nsamples))
    return method


def append_batches(run: OpenRun, draws_spec, watch: Watch, draw_one) -> None:
    """Batches ``run.start`` to the last of ``draws_spec`` (:class:`~gcrsky.run.spec.Draws`), each drawn by
    ``draw_one(b) -> (draws (Nf, take, n), SolveInfo over (Nf, take))`` and appended to ``results.h5`` at
    once (timed; the kill test hook after each), with the caller's progress bar."""
    batches = range(run.start, draws_spec.n_batches)
    for b in watch.progress(batches) if watch.progress is not None else batches:
        t0 = time.perf_counter()
        draws, info = draw_one(b)
        kill_hook(append_batch(run.h5, b, draws, info, seconds=time.perf_counter() - t0))


def append_chain_batch(run: OpenRun, b: int, take: int, sky, info, extra: dict, state_arrays: dict, t0: float) -> None:
    """Append a Markov chain's batch ``b`` (its first ``take`` kept states) to ``run.h5``: the sky draws ``sky``
    (take+, Nf, n) and the sky steps' ``info`` (take+, Nf) moved to (Nf, take, ...), the per-draw datasets
    ``extra`` (already ``take`` rows), and the chain's state written over (``state_arrays``) before the batch
    counts, so a killed run resumes at the batch's end (:func:`gcrsky.io.append_batch`; ``t0`` the batch's start)."""
    draws = np.swapaxes(np.asarray(jax.block_until_ready(sky))[:take], 0, 1)
    info = jax.tree_util.tree_map(lambda a: np.swapaxes(np.asarray(a)[:take], 0, 1), info)
    kill_hook(append_batch(run.h5, b, draws, info, seconds=time.perf_counter() - t0, extra=extra,
                           replace=state_arrays))


def read_chain(h5, per_draw, fixed=(), optional=(), optional_per_draw=()) -> dict:
    """A chain's datasets in ``results.h5``: the kept rows of the ``per_draw`` ones and the whole ``fixed`` ones,
    each under its last path component; of the ``optional`` fixed ones and the ``optional_per_draw`` ones those
    present."""
    import h5py

    with h5py.File(h5, "r") as h:
        rows = int(h["draws"].shape[1]) if "draws" in h else 0
        out = {k.split("/")[-1]: h[k][:rows] for k in per_draw}
        out.update({k.split("/")[-1]: h[k][:rows] for k in optional_per_draw if k in h})
        out.update({k.split("/")[-1]: h[k][()] for k in fixed})
        out.update({k.split("/")[-1]: h[k][()] for k in optional if k in h})
    return out
