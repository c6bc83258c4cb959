"""Frequency channels beyond one device: one channel at a time, over devices and over processes.

The posterior factorises over frequency: P, the Wiener right-hand side and the GCR
fluctuation of channel f involve only channel f's response, data, noise and prior
(:func:`gcrsky.solvers.freq_slice` cuts that one-channel system out).  So a file with
many channels never needs its joint system in one solve: channels can be solved one at
a time (:func:`sample_channels`), split over the devices of a
:class:`jax.sharding.Mesh` (:func:`sample_channels_sharded`, each device running its own
channels with no communication) or over the processes of JAX's multi-host runtime
(:func:`distributed_channels`, after ``jax.distributed.initialize``), with the same
numbers however they are split.

Key scheme (:data:`CHANNEL_KEY_SCHEME`).  Channel ``f`` (its index in the *full*
channel list of the system, not its position in a subset or on a device) is sampled
with the key ``key_f = jax.random.fold_in(key, f)`` (:func:`channel_key`) on its
one-channel system ``freq_slice(system, f)``, with the path's own per-draw scheme from
there (draw ``i`` of a CG, Cholesky or data-space path uses
``jax.random.split(key_f, ndraws)[i]``; eigen and m-mode draw one normal array from
``key_f``).  With ``batch`` given, draws come in batches as in
:func:`gcrsky.inference.draw_batches`: batch ``b`` of channel ``f`` uses
``jax.random.fold_in(key_f, b)``.  Nothing in a channel's draws depends on the number of
channels, on which channels are computed together, on the device or process that
computes them, or on the padding below.  The joint scheme (``gcrsky.draw(key,
prepare(system), ndraws)``, one normal array of shape (Nf, n) per draw) gives
*different*, equally exact draws: its channel f depends on Nf, so it cannot be split.

Path.  :func:`resolve_channel_path` chooses the path once, host-side, for the
one-channel system (``method="auto"`` sizes it for one channel), and checks what a path
needs on the *whole* system (the CG preconditioner's ``"auto"`` is resolved on every
channel's prior; ``"mmode"`` needs :func:`gcrsky.solvers.mmode_check` to pass; the data
space needs a proper prior), so every channel runs the same compiled program.

Devices.  :func:`sample_channels_sharded` puts the per-channel arrays (response, data,
inverse noise, prior mean and inverse variance) on a 1-d mesh with axis ``"freq"``
(:data:`FREQ_AXIS`, :func:`channel_mesh`), everything else (angles, frame map)
replicated, and runs ``jax.shard_map``: each device runs prepare + draw on its own
channels, ``jax.lax.map`` over them (``vmap_channels`` at a time), with no collectives.
``jax.device_put`` needs the channel axis to be a multiple of the device count, so the
channel list is padded with copies of its last channel (a real, well-posed system), whose
results are computed and dropped: padding changes nothing about the real channels.
Results equal :func:`sample_channels` up to rounding: the per-channel program is the same
computation, compiled inside a ``lax.map`` body rather than on its own, and XLA may fuse
or order its sums differently.  Measured on 1 and 2 forced CPU devices against the loop:
Cholesky bitwise equal (3 channels at lmax 4; 16 channels at lmax 10, 200 draws); CG
bitwise equal at lmax 4, and 9.6e-13 relative (2 devices; 1 device bitwise) at lmax 10,
rounding amplified by the iterations.  The tests allow 1e-12 relative for the direct
paths and 1e-10 for CG.

Processes.  :func:`distributed_channels` gives process ``p`` of ``P`` the contiguous
block ``channel_blocks(Nc, P)[p]`` (sizes differ by at most one, earlier processes get
the extra ones), computes it with :func:`sample_channels` (or the sharded path over its
local devices), and gathers every block to every process with
:func:`jax.experimental.multihost_utils.process_allgather` (on CPU through JAX's gloo
collectives, ``jax_cpu_collectives_implementation = "gloo"``, JAX 0.10's default; see
:func:`init_distributed`).  Measured on a 2-core host: 2 processes on localhost give
bitwise the draws and Wiener filters of one process (Cholesky and CG; 3 channels at
lmax 4, 16 channels at lmax 6 and 10): each process runs the very per-channel programs
one process runs, and the gather moves bits.
"""

from __future__ import annotations

import logging
import math
import time
import zlib
from collections.abc import Callable, Sequence
from functools import lru_cache
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ..inference.batches import batch_key
from ..inference.posterior import draw_exactly, prepare_system
from ..model.system import LinearSystem
from ..solvers.cg import freq_slice
from ..solvers.info import SolveInfo
from ..solvers.plan import choose_path
from ..solvers.registry import SolverOptions, path_of
from .rendezvous import DEFAULT_DIST_TIMEOUT, rendezvous
from .runtime import effective_pool_size, safe_pool_size

__all__ = [
    "CHANNEL_KEY_SCHEME",
    "DEFAULT_DIST_TIMEOUT",
    "FREQ_AXIS",
    "ChannelDraws",
    "channel_blocks",
    "channel_key",
    "channel_mesh",
    "distributed_channels",
    "init_distributed",
    "resolve_channel_path",
    "sample_channels",
    "sample_channels_sharded",
]

_log = logging.getLogger("gcrsky")

#: Name of the mesh axis the channels are split over.
FREQ_AXIS = "freq"

#: The per-channel key scheme in words (stored with results).
CHANNEL_KEY_SCHEME = (
    "channel f (index in the full channel list): key_f = jax.random.fold_in(key, f) on the one-channel "
    "system freq_slice(system, f); batch b of channel f: jax.random.fold_in(key_f, b); full batches, last truncated"
)

Progress = Callable[[int], object]


class ChannelDraws(NamedTuple):
    """Draws and Wiener filters of a set of channels (host NumPy arrays, channels in order).

    Attributes:
        draws: (Nc, ndraws, n) realified draws, channel ``channels[i]`` in row i.
        a_wf: (Nc, n) Wiener filter (posterior mean).
        wiener: :class:`~gcrsky.solvers.SolveInfo` of the Wiener solves, (Nc,) fields.
        info: :class:`~gcrsky.solvers.SolveInfo` of the draws, (Nc, ndraws) fields.
        channels: (Nc,) int, each row's index in the system's full channel list.
        seconds: (Nc,) wall-clock seconds per channel (the sharded path: its step's
            time divided by the step's channels; the first includes compilation).
    """

    draws: np.ndarray
    a_wf: np.ndarray
    wiener: SolveInfo
    info: SolveInfo
    channels: np.ndarray
    seconds: np.ndarray


def channel_key(key: jax.Array, f) -> jax.Array:
    """The key of channel ``f`` (index in the full channel list): ``jax.random.fold_in(key, f)``."""
    return jax.random.fold_in(key, f)


def _nchan(system: LinearSystem) -> int:
    return int(system.op.response.shape[0])


def _channel_list(system: LinearSystem, channels) -> np.ndarray:
    nf = _nchan(system)
    if channels is None:
        return np.arange(nf)
    ch = np.asarray(channels)
    if ch.ndim != 1 or ch.size == 0 or not np.issubdtype(ch.dtype, np.integer):
        raise ValueError(f"channels must be a non-empty 1-d sequence of integers, got {channels!r}")
    if ch.min() < 0 or ch.max() >= nf:
        raise ValueError(f"channels must lie in [0, {nf}), got {ch.min()}..{ch.max()}")
    return ch.astype(np.int64)


def _check_draw_args(ndraws, batch) -> tuple[int, int | None]:
    if int(ndraws) != ndraws or ndraws < 1:
        raise ValueError(f"ndraws must be a positive integer, got {ndraws!r}")
    if batch is not None and (int(batch) != batch or batch < 1):
        raise ValueError(f"batch must be a positive integer or None, got {batch!r}")
    return int(ndraws), (None if batch is None else int(batch))


def resolve_channel_path(
    system: LinearSystem,
    method: str = "auto",
    *,
    options: SolverOptions | None = None,
    tol: float | None = None,
    ndraws: int = 1,
    memory_budget: float | None = None,
) -> SolverOptions:
    """One path's options for every channel of ``system`` (host-side, concrete arrays).

    :func:`gcrsky.solvers.choose_path` on the one-channel system ``freq_slice(system, 0)``
    (memory is checked for one channel and ``ndraws`` draws), then the whole-system
    checks that a one-channel choice cannot make, by the path
    (:meth:`gcrsky.solvers.SolverPath.resolve` on the whole system): CG's
    ``preconditioner="auto"`` is resolved on all channels' priors (m-blocks if any channel
    has a flat direction, :meth:`gcrsky.solvers.CGPath.resolve_channels`); ``"mmode"``
    requires :func:`gcrsky.solvers.mmode_check` on the whole system; ``"dataspace"`` a
    proper prior in every channel.
    """
    opts = choose_path(freq_slice(system, 0), method, options=options, tol=tol, ndraws=int(ndraws),
                       memory_budget=memory_budget)
    return path_of(opts).resolve_channels(system, opts, options)


def _draw_channel(key_f, state, ndraws: int, batch: int | None):
    """Draws of one prepared one-channel path by the key scheme; (1, ndraws, n), SolveInfo (1, ndraws)."""
    if batch is None:
        d, info = draw_exactly(key_f, state, ndraws)
        return d, info.draws
    nb = -(-ndraws // batch)
    parts = [draw_exactly(batch_key(key_f, b), state, batch) for b in range(nb)]
    d = jnp.concatenate([p[0] for p in parts], axis=1)[:, :ndraws]
    info = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a, axis=1)[:, :ndraws], *[p[1].draws for p in parts])
    return d, info


def _host(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


def sample_channels(
    key: jax.Array,
    system: LinearSystem,
    ndraws: int,
    method: str = "auto",
    *,
    options: SolverOptions | None = None,
    tol: float | None = None,
    memory_budget: float | None = None,
    batch: int | None = None,
    channels: Sequence[int] | None = None,
    progress: Progress | None = None,
) -> ChannelDraws:
    """Exact draws and Wiener filters, one channel at a time (host loop), by :data:`CHANNEL_KEY_SCHEME`.

    For each ``f`` in ``channels``: ``prepare_system(freq_slice(system, f), options=opts)``
    then draws with ``channel_key(key, f)``; ``opts`` from :func:`resolve_channel_path`
    (one compiled program serves every channel).  Memory: one channel's path at a time.

    Args:
        key: the run's PRNG key.
        system: the (Nf, ...) linear system (concrete arrays).
        ndraws: draws per channel.
        method, options, tol, memory_budget: the path, as for :func:`gcrsky.sample`.
        batch: draw in batches of this size (batch ``b`` keyed ``fold_in(key_f, b)``, as
            :func:`gcrsky.inference.draw_batches`); None: one call of ``ndraws``.
        channels: indices into the system's channels (default: all), in the order wanted.
        progress: called with 1 after each channel (e.g. a tqdm bar's ``update``); the
            library prints nothing.

    Returns:
        :class:`ChannelDraws` with rows in the order of ``channels``.
    """
    ndraws, batch = _check_draw_args(ndraws, batch)
    chans = _channel_list(system, channels)
    opts = resolve_channel_path(system, method, options=options, tol=tol, ndraws=batch or ndraws,
                                memory_budget=memory_budget)
    return _loop(key, system, ndraws, opts, batch, chans, progress)


def _loop(key, system, ndraws, opts, batch, chans, progress) -> ChannelDraws:
    draws, a_wf, winfo, dinfo, secs = [], [], [], [], []
    for f in chans:
        t0 = time.perf_counter()
        state = prepare_system(freq_slice(system, int(f)), options=opts)
        d, info = _draw_channel(channel_key(key, int(f)), state, ndraws, batch)
        d = np.asarray(jax.block_until_ready(d))
        draws.append(d[0])
        a_wf.append(np.asarray(state.a_wf)[0])
        winfo.append(_host(jax.tree_util.tree_map(lambda x: x[0], state.wiener)))
        dinfo.append(_host(jax.tree_util.tree_map(lambda x: x[0], info)))
        secs.append(time.perf_counter() - t0)
        _log.debug("channel %d: %.3f s", int(f), secs[-1])
        if progress is not None:
            progress(1)
    stack = lambda *a: np.stack(a)  # noqa: E731
    return ChannelDraws(np.stack(draws), np.stack(a_wf), jax.tree_util.tree_map(stack, *winfo),
                        jax.tree_util.tree_map(stack, *dinfo), chans, np.asarray(secs))


# ---------------------------------------------------------------- devices


def channel_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-d :class:`jax.sharding.Mesh` with axis ``"freq"`` over ``devices`` (default: this process's).

    Default ``jax.local_devices()``: in a multi-process run each process meshes its own
    devices (:func:`distributed_channels` splits channels between processes itself).
    Logs a warning when several CPU devices share an XLA pool smaller than
    :func:`gcrsky.parallel.runtime.safe_pool_size` (batched LAPACK can then deadlock; see
    :mod:`gcrsky.parallel.runtime`).
    """
    devs = jax.local_devices() if devices is None else list(devices)
    if len(devs) == 0:
        raise ValueError("channel_mesh needs at least one device")
    if sum(d.platform == "cpu" for d in devs) > 1:
        n_all = len(jax.local_devices(backend="cpu"))
        have, want = effective_pool_size(n_all), safe_pool_size(n_all)
        if have < want:
            _log.warning("%d CPU devices share an XLA thread pool of %d threads; batched LAPACK calls can "
                         "deadlock it. Call gcrsky.parallel.use_host_devices(%d) before JAX starts (wants >= %d).",
                         n_all, have, n_all, want)
    return Mesh(np.asarray(devs, dtype=object), (FREQ_AXIS,))


def _per_channel(system: LinearSystem):
    """The leaves with a leading channel axis (those :func:`freq_slice` cuts), in a fixed order."""
    return (system.op.response, system.data, system.inv_noise, system.prior.mean, system.prior.inv_var)


def _shared(system: LinearSystem):
    """Everything else (angles, frame map, any further fields), with the per-channel leaves set to None."""
    return (system.op._replace(response=None), system.prior._replace(mean=None, inv_var=None))


def _assemble(per, shared) -> LinearSystem:
    response, data, inv_noise, mean, inv_var = per
    op, prior = shared
    return LinearSystem(op=op._replace(response=response), data=data, inv_noise=inv_noise,
                        prior=prior._replace(mean=mean, inv_var=inv_var))


@lru_cache(maxsize=32)
def _sharded_program(mesh: Mesh, opts: SolverOptions, ndraws: int, batch: int | None, vmap_channels: int,
                     shared_def):
    """The jitted shard_map of prepare + draw over each device's channels (cached per configuration)."""

    def local(idx, key, per, shared):
        def one(args):
            f, per_f = args
            sys1 = _assemble(tuple(x[None] for x in per_f), shared)
            state = prepare_system(sys1, options=opts)
            d, dinfo = _draw_channel(channel_key(key, f), state, ndraws, batch)
            first = lambda t: jax.tree_util.tree_map(lambda x: x[0], t)  # noqa: E731
            return d[0], state.a_wf[0], first(state.wiener), first(dinfo)

        return jax.lax.map(one, (idx, per), batch_size=vmap_channels if vmap_channels > 1 else None)

    rep = jax.tree_util.tree_unflatten(shared_def, [P()] * shared_def.num_leaves)
    fn = jax.shard_map(local, mesh=mesh, in_specs=(P(FREQ_AXIS), P(), P(FREQ_AXIS), rep), out_specs=P(FREQ_AXIS),
                       check_vma=False)
    return jax.jit(fn)


def sample_channels_sharded(
    key: jax.Array,
    system: LinearSystem,
    ndraws: int,
    method: str = "auto",
    *,
    options: SolverOptions | None = None,
    tol: float | None = None,
    memory_budget: float | None = None,
    batch: int | None = None,
    channels: Sequence[int] | None = None,
    mesh: Mesh | None = None,
    step: int | None = None,
    vmap_channels: int = 1,
    progress: Progress | None = None,
) -> ChannelDraws:
    """As :func:`sample_channels`, with the channels split over the devices of ``mesh``.

    The channel list is padded to a multiple of ``ndev * step`` with copies of its last
    channel (computed, then dropped; module docstring) and run in steps of ``ndev *
    step`` channels: one jitted ``shard_map`` call per step, each device preparing and
    drawing its ``step`` channels one after another (``jax.lax.map``;
    ``vmap_channels > 1`` vectorises that many at a time, more memory, batched LAPACK).
    Same key scheme, same numbers as :func:`sample_channels` up to rounding.

    Args:
        key, system, ndraws, method, options, tol, memory_budget, batch, channels: as for
            :func:`sample_channels`.
        mesh: a 1-d mesh (default :func:`channel_mesh`: this process's devices).
        step: channels per device per call (default: all of them in one call).  A
            smaller step bounds memory and lets ``progress`` advance.
        vmap_channels: channels vectorised at once on a device (``lax.map``'s ``batch_size``).
        progress: called after each step with the number of real channels it finished.

    Returns:
        :class:`ChannelDraws` (host arrays, rows in the order of ``channels``).
    """
    ndraws, batch = _check_draw_args(ndraws, batch)
    chans = _channel_list(system, channels)
    mesh = channel_mesh() if mesh is None else mesh
    if not isinstance(mesh, Mesh) or len(mesh.axis_names) != 1:
        raise ValueError("sample_channels_sharded needs a 1-d jax.sharding.Mesh (channel_mesh())")
    if int(vmap_channels) != vmap_channels or vmap_channels < 1:
        raise ValueError(f"vmap_channels must be a positive integer, got {vmap_channels!r}")
    opts = resolve_channel_path(system, method, options=options, tol=tol, ndraws=batch or ndraws,
                                memory_budget=memory_budget)
    ndev = int(mesh.devices.size)
    nc = chans.size
    per_dev = -(-nc // ndev)
    step = per_dev if step is None else max(1, min(int(step), per_dev))
    width = ndev * step
    nsteps = -(-nc // width)
    padded = np.concatenate([chans, np.full(nsteps * width - nc, chans[-1], dtype=chans.dtype)])

    per_host = tuple(np.asarray(x) for x in _per_channel(system))
    shared = _shared(system)
    shared_leaves, shared_def = jax.tree_util.tree_flatten(shared)
    rep = NamedSharding(mesh, P())
    shared = jax.tree_util.tree_unflatten(shared_def, [jax.device_put(x, rep) for x in shared_leaves])
    split = NamedSharding(mesh, P(FREQ_AXIS))
    fn = _sharded_program(mesh, opts, ndraws, batch, int(vmap_channels), shared_def)
    key_rep = jax.device_put(key, rep)

    outs, secs = [], []
    for s in range(nsteps):
        t0 = time.perf_counter()
        idx = padded[s * width:(s + 1) * width]
        per = tuple(jax.device_put(x[idx], split) for x in per_host)
        out = fn(jax.device_put(idx.astype(np.int32), split), key_rep, per, shared)
        out = _host(jax.block_until_ready(out))
        real = min(width, nc - s * width)
        outs.append(jax.tree_util.tree_map(lambda x, r=real: x[:r], out))
        secs.extend([(time.perf_counter() - t0) / real] * real)
        if progress is not None:
            progress(real)
    cat = lambda *a: np.concatenate(a)  # noqa: E731
    d, a_wf, winfo, dinfo = jax.tree_util.tree_map(cat, *outs)
    return ChannelDraws(d, a_wf, winfo, dinfo, chans, np.asarray(secs))


# ---------------------------------------------------------------- processes


def init_distributed(coordinator_address: str, num_processes: int, process_id: int, *,
                     timeout: float | None = DEFAULT_DIST_TIMEOUT, **kwargs) -> None:
    """``jax.distributed.initialize`` for CPU processes (gloo collectives), before any JAX computation.

    Sets ``jax_cpu_collectives_implementation = "gloo"`` (JAX 0.10's default; set here so
    that an environment default cannot leave the CPU client without cross-process
    collectives, which :func:`distributed_channels` needs to gather), then calls
    ``jax.distributed.initialize(coordinator_address, num_processes, process_id, **kwargs)``.
    Process 0 hosts the coordinator at ``coordinator_address`` (``"host:port"``).

    Timeout.  JAX cannot fail a start cleanly: when its ``initialization_timeout``
    (default 300 s) passes with the coordinator unreachable or a peer missing, the C++
    client aborts the process (``LOG(QFATAL)``, a stack trace, no Python exception).
    So with ``timeout`` (seconds, default :data:`DEFAULT_DIST_TIMEOUT`) the processes
    first meet in :func:`gcrsky.parallel.rendezvous.rendezvous` (process 0 listens on
    the coordinator's port, the others connect and wait for its go-ahead), which raises
    :class:`~gcrsky.parallel.rendezvous.DistributedTimeoutError` (a ``TimeoutError`` and
    ``ConnectionError``) naming the address, the process id, the number of processes and
    the timeout when the coordinator cannot be reached or a process does not join within
    ``timeout`` seconds, before JAX is touched; a refused peer (another number of
    processes, a process id taken) or a port process 0 cannot listen on raises its base
    class :class:`~gcrsky.parallel.rendezvous.DistributedInitError`.  Every process
    must then call this function (with a timeout), as they all meet there.  JAX's own
    ``initialization_timeout`` is set to ``timeout`` too (rounded up to whole seconds;
    ``kwargs`` may override it), which bounds the wait should a process die between the
    rendezvous and JAX's registration (that one still aborts).  ``timeout=None`` skips
    the rendezvous: plain ``jax.distributed.initialize`` with ``kwargs``.
    """
    if timeout is not None:
        rendezvous(coordinator_address, num_processes, process_id, timeout,
                   bind_address=kwargs.get("coordinator_bind_address"))
        kwargs.setdefault("initialization_timeout", max(1, math.ceil(timeout)))
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=coordinator_address, num_processes=int(num_processes),
                               process_id=int(process_id), **kwargs)


def channel_blocks(nchannels: int, nprocesses: int) -> list[range]:
    """Contiguous positions ``[start, stop)`` of each process's channels; sizes differ by at most 1.

    Process ``p`` gets ``nchannels // nprocesses`` positions, plus one if ``p <
    nchannels % nprocesses``, in order.
    """
    if int(nprocesses) != nprocesses or nprocesses < 1:
        raise ValueError(f"nprocesses must be a positive integer, got {nprocesses!r}")
    if int(nchannels) != nchannels or nchannels < 0:
        raise ValueError(f"nchannels must be a non-negative integer, got {nchannels!r}")
    base, extra = divmod(int(nchannels), int(nprocesses))
    out, start = [], 0
    for p in range(int(nprocesses)):
        stop = start + base + (p < extra)
        out.append(range(start, stop))
        start = stop
    return out


def distributed_channels(
    key: jax.Array,
    system: LinearSystem,
    ndraws: int,
    method: str = "auto",
    *,
    options: SolverOptions | None = None,
    tol: float | None = None,
    memory_budget: float | None = None,
    batch: int | None = None,
    channels: Sequence[int] | None = None,
    sharded: bool = False,
    step: int | None = None,
    progress: Progress | None = None,
) -> ChannelDraws:
    """Channels split over the processes of ``jax.distributed``; every process gets all results.

    Call it on every process with the same arguments (every process holds the system,
    or at least the same arrays), after :func:`init_distributed` /
    ``jax.distributed.initialize``; with one process it is :func:`sample_channels`.
    Process ``p`` computes the contiguous block ``channel_blocks(Nc, P)[p]`` of
    ``channels`` by :data:`CHANNEL_KEY_SCHEME` (``sharded=True``: over its local devices
    with :func:`sample_channels_sharded`, else one at a time); the blocks are then
    padded to the largest block's size and gathered with
    :func:`jax.experimental.multihost_utils.process_allgather` (a collective: every
    process must call this function).  The path is resolved on each process and checked
    to be the same everywhere (``memory_budget=None`` measures each host's free memory,
    which may differ: pass a budget, or options, when processes run on different hosts).

    Args:
        key, system, ndraws, method, options, tol, memory_budget, batch, channels: as for
            :func:`sample_channels` (the same on every process).
        sharded: compute this process's block over its local devices
            (:func:`sample_channels_sharded`) instead of one channel at a time.
        step: channels per device per call when ``sharded``.
        progress: called as this process's channels finish (as in :func:`sample_channels`).

    Returns:
        :class:`ChannelDraws` of all ``channels`` (host arrays), identical on every process;
        ``seconds`` as measured by the process that computed each channel.

    Raises:
        ValueError: fewer channels than processes, or processes that resolved different paths.
    """
    from jax.experimental import multihost_utils

    ndraws, batch = _check_draw_args(ndraws, batch)
    chans = _channel_list(system, channels)
    nproc, pid = jax.process_count(), jax.process_index()
    if chans.size < nproc:
        raise ValueError(f"{chans.size} channels for {nproc} processes: every process needs at least one")
    opts = resolve_channel_path(system, method, options=options, tol=tol, ndraws=batch or ndraws,
                                memory_budget=memory_budget)
    if nproc > 1:
        sig = np.int64(zlib.crc32(repr(opts).encode()))
        sigs = np.asarray(multihost_utils.process_allgather(sig))
        if np.any(sigs != sigs[0]):
            raise ValueError(f"processes resolved different solver paths (this one: {opts!r}); pass method/options "
                             "and memory_budget explicitly")
    blocks = channel_blocks(chans.size, nproc)
    mine = chans[blocks[pid].start:blocks[pid].stop]
    _log.info("process %d of %d: channels %s", pid, nproc, f"{mine[0]}..{mine[-1]} ({mine.size})")
    if sharded:
        local = sample_channels_sharded(key, system, ndraws, options=opts, batch=batch, channels=mine, step=step,
                                        progress=progress)
    else:
        local = _loop(key, system, ndraws, opts, batch, mine, progress)
    if nproc == 1:
        return local
    bmax = max(len(b) for b in blocks)

    def pad(x):
        x = np.asarray(x)
        extra = bmax - x.shape[0]
        return x if extra == 0 else np.concatenate([x, np.repeat(x[-1:], extra, axis=0)])

    payload = jax.tree_util.tree_map(pad, tuple(local))
    gathered = multihost_utils.process_allgather(payload)  # every leaf (nproc, bmax, ...)
    out = jax.tree_util.tree_map(
        lambda g: np.concatenate([np.asarray(g)[p, :len(blocks[p])] for p in range(nproc)]), gathered)
    res = ChannelDraws(*out)
    if not np.array_equal(res.channels, chans):  # the gather's order is the process order
        raise RuntimeError(f"gathered channels {res.channels} differ from the requested {chans}")
    return res
