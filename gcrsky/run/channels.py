"""The draws of an independent-channel run (``RunSpec.channels``): one at a time, over devices or processes.

Channels are independent systems; :mod:`gcrsky.parallel.channels` solves them with its own
key scheme (:data:`~gcrsky.parallel.channels.CHANNEL_KEY_SCHEME`: other, equally exact
draws than a joint run's, the same however the channels are split).  The set-up and draws
of every channel run before ``results.h5`` is written (its batches are then appended at
once), so a killed channel run resumes by recomputing the channels; the draws are the same.
With ``"processes"``, every ``jax.distributed`` process computes its share and only
process 0 writes (:func:`worker_channels` is the others' part).
"""

from __future__ import annotations

import time

import jax
import numpy as np

from ..io.results import append_batch
from ..parallel.channels import (
    CHANNEL_KEY_SCHEME,
    distributed_channels,
    resolve_channel_path,
    sample_channels,
    sample_channels_sharded,
)
from ..solvers.registry import method_of
from .draws import kill_hook, record_setup
from .output import OpenRun
from .resume import options_from_json
from .stages import StageTimer, Watch

__all__ = ["channel_draws", "sample_by_channel", "worker_channels"]


def sample_by_channel(mode: str, key, system, nsamples: int, options, batch: int, update):
    """All channels of ``system`` by :data:`~gcrsky.parallel.channels.CHANNEL_KEY_SCHEME`.

    Args:
        mode: ``"loop"``, ``"devices"`` or ``"processes"`` (``RunSpec.channels``).
        key: ``PRNGKey(seed)``; system: the :class:`~gcrsky.model.LinearSystem`.
        nsamples, batch: the draws; options: the resolved solver options.
        update: called with 1 after each channel, or None.

    Returns:
        :class:`~gcrsky.parallel.channels.ChannelDraws` (host arrays).
    """
    kw = dict(options=options, batch=batch, progress=update)
    if mode == "loop":
        return sample_channels(key, system, nsamples, **kw)
    if mode == "devices":
        return sample_channels_sharded(key, system, nsamples, **kw)
    return distributed_channels(key, system, nsamples, sharded=len(jax.local_devices()) > 1, **kw)


def _updater(watch: Watch, nchan: int):
    return None if watch.channel_progress is None else watch.channel_progress(nchan)


def worker_channels(prob, spec, watch: Watch) -> None:
    """A ``jax.distributed`` process other than 0: its share of the channels, gathered to process 0."""
    system = prob.system()
    d = spec.draws
    options = resolve_channel_path(system, spec.solver.method, tol=spec.solver.tol, ndraws=d.batch)
    sample_by_channel("processes", jax.random.PRNGKey(d.seed), system, d.nsamples, options, d.batch,
                      _updater(watch, prob.data.shape[0]))


def channel_draws(prob, spec, run: OpenRun, st: StageTimer, watch: Watch) -> str:
    """The ``wiener`` stage and the draws of an independent-channel run; returns the path that ran.

    Every channel is prepared and drawn, then ``results.h5`` is created (or, resumed,
    its Wiener filter compared) and the batches from ``run.start`` appended.  Leaves the
    ``draws`` stage running (the caller stops it).
    """
    system = prob.system()
    d = spec.draws
    st.start("wiener")  # only the path here: the channels' set-up runs with their draws
    if run.state is None:
        options = resolve_channel_path(system, spec.solver.method, tol=spec.solver.tol, ndraws=d.batch)
    else:
        options = options_from_json(run.state.attrs["solver_options_json"])
    st.stop()
    st.start("draws")
    if run.start >= d.n_batches:
        return str(run.state.attrs["method"])
    t0 = time.perf_counter()
    res = sample_by_channel(spec.channels, jax.random.PRNGKey(d.seed), system, d.nsamples, options, d.batch,
                            _updater(watch, prob.data.shape[0]))
    per_batch = (time.perf_counter() - t0) / d.n_batches
    chosen = method_of(options)
    record_setup(prob, spec, run, res.a_wf, res.wiener, rank=None, method=chosen, options=options,
                 key_scheme=CHANNEL_KEY_SCHEME)
    for b in range(run.start, d.n_batches):
        sl = slice(b * d.batch, min((b + 1) * d.batch, d.nsamples))
        info = jax.tree_util.tree_map(lambda a: np.asarray(a)[:, sl], res.info)
        kill_hook(append_batch(run.h5, b, res.draws[:, sl], info, seconds=per_batch))
    return chosen
