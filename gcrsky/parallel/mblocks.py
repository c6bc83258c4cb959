"""The m-mode path's blocks split over devices: each bucket of orders built, factorised and solved on its own.

Uniform full-day coverage makes P block-diagonal in m (:mod:`gcrsky.solvers.mmode`), and the
path stores its blocks by *buckets* of consecutive orders (:func:`gcrsky.solvers.mmode.mmode_buckets`).
The buckets share nothing but the response, so they split over devices without communication:
bucket ``i`` goes to ``devices[i % len(devices)]``, which receives a copy of the response, the
noise sums and the prior (each device gathers only its buckets' columns from it), builds and
factorises its blocks there (:func:`mmode_factor_on`), and keeps the factors.  The solves and the
draws run bucket by bucket on the devices that hold them, with the right-hand sides and the
normals cut from the same arrays as on one device and the results gathered back: the numbers are
those of :func:`gcrsky.solvers.mmode.prepare_mmode` / :func:`~gcrsky.solvers.mmode.draw_mmode` (the same
operations on the same inputs; tested equal to 1e-13 with 2 forced host devices in
``tests/test_parallel_mblocks.py``).

Over the processes of ``jax.distributed`` (:func:`prepare_mmode_processes`) the buckets go round
robin to the processes first (:func:`process_buckets`), then over each process's local devices; a
process keeps only its own factors, and the Wiener filter's pieces, its residual check and the draws'
pieces are summed over the processes (``process_allgather``; each entry is one process's number plus
zeros, so the results equal one process's: tested with 2 localhost processes).

The Wiener filter's right-hand side and its true-residual check (matrix-free products over every
time) run on the first device; shard the baselines (:func:`gcrsky.parallel.shard_system`) to split
those too.  Not traced as a whole (host orchestration over devices): :func:`prepare_mmode_on` takes
concrete arrays, and the state it returns is for :func:`draw_mmode_on`, not for the single-device
functions' jitted code.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import check_float64
from ..model.system import LinearSystem, precision_apply, wiener_rhs
from ..solvers.info import DrawInfo, SolveInfo, direct_info, exact_info
from ..solvers.mmode import (
    MModeBlocks,
    bucket_factor_jit,
    from_buckets,
    mmode_buckets,
    mmode_check,
    to_buckets,
    tri_solve,
)
from ..solvers.options import MModeOptions
from ..sphere.modes import lmax_from_nparams

__all__ = ["MModeSplitState", "bucket_devices", "draw_mmode_on", "mmode_factor_on", "prepare_mmode_on",
           "prepare_mmode_processes", "process_buckets"]


class MModeSplitState(NamedTuple):
    """The m-mode path set up over several devices (:func:`prepare_mmode_on`).

    Attributes:
        system: the linear system (on the first device).
        a_wf: (Nf, n) Wiener filter (first device).
        wiener: its SolveInfo (Nf,), from the true matrix-free residual.
        chol: :class:`~gcrsky.solvers.mmode.MModeBlocks` whose bucket ``i`` lives on ``devices[i % len(devices)]``.
        devices: the devices, in order.
    """

    system: LinearSystem
    a_wf: jax.Array
    wiener: SolveInfo
    chol: MModeBlocks
    devices: tuple


def bucket_devices(nbuckets: int, devices: Sequence) -> list:
    """The device of each bucket: round robin, ``devices[i % len(devices)]``."""
    devices = list(devices)
    if not devices:
        raise ValueError("bucket_devices needs at least one device")
    return [devices[i % len(devices)] for i in range(int(nbuckets))]


def mmode_factor_on(system: LinearSystem, devices: Sequence, bucket: int = MModeOptions.bucket,
                    owned: Sequence[int] | None = None) -> MModeBlocks:
    """:func:`gcrsky.solvers.mmode.mmode_factor` with bucket ``i`` built and factorised on ``devices[i % D]``.

    Every device gets one copy of the response ``(Nf, Nbl, n)``, the noise sums and the prior's inverse
    variances; the buckets are dispatched in turn (asynchronously, so the devices work at once).
    ``owned``: build only these buckets (the others are None: another process holds them,
    :func:`prepare_mmode_processes`); the k-th owned bucket goes to ``devices[k % D]``.
    """
    op = system.op
    if op.frame is not None:
        raise ValueError("the m-blocks need op.frame is None (a frame map couples m)")
    lay = mmode_buckets(lmax_from_nparams(op.response.shape[2]), bucket)
    owned = list(range(len(lay.gather))) if owned is None else [int(i) for i in owned]
    w = jnp.sum(system.inv_noise, axis=1)
    where = dict(zip(owned, bucket_devices(len(owned), devices)))
    inputs = {d: jax.device_put((op.response, w, system.prior.inv_var), d) for d in dict.fromkeys(where.values())}
    arrays = tuple(
        bucket_factor_jit(*inputs[where[i]], *jax.device_put((jnp.asarray(g), jnp.asarray(mk), jnp.asarray(sc)),
                                                               where[i])) if i in where else None
        for i, (g, mk, sc) in enumerate(zip(lay.gather, lay.mask, lay.scale)))
    return MModeBlocks(arrays, lay.lmax, lay.quantum)


@jax.jit
def _solve_bucket(L: jax.Array, g: jax.Array) -> jax.Array:
    return tri_solve(L, tri_solve(L, g[..., None], False), True)[..., 0]


def _block_solve_on(chol: MModeBlocks, b: jax.Array) -> jax.Array:
    """``P^-1 b`` (Nf, n) through factors that live on several devices; the result on b's device."""
    home = next(iter(b.devices()))

    def piece(L, g):  # zeros for a bucket another process holds
        if L is None:
            return jnp.zeros_like(g)
        return jax.device_put(_solve_bucket(L, jax.device_put(g, next(iter(L.devices())))), home)

    pieces = [piece(L, g) for L, g in zip(chol.arrays, to_buckets(b, chol.layout))]
    return from_buckets(pieces, chol.layout, jnp.zeros_like(b))


@partial(jax.jit, static_argnames=("tol",))
def _wiener_info(system: LinearSystem, a_wf: jax.Array, b: jax.Array, Pinv_r_dot: jax.Array, finite, tol: float):
    r = b - precision_apply(system, a_wf)
    err = jnp.sqrt(jnp.abs(Pinv_r_dot))
    rel = jnp.linalg.norm(r, axis=-1) / jnp.linalg.norm(b, axis=-1)
    return direct_info(err, rel, finite, tol)


def _sum_over_processes(x) -> jax.Array:
    """``x`` summed over the processes of ``jax.distributed`` (a collective; ``x`` itself with one process)."""
    if jax.process_count() == 1:
        return x
    from jax.experimental import multihost_utils

    home = next(iter(x.devices()))
    return jax.device_put(np.sum(np.asarray(multihost_utils.process_allgather(np.asarray(x))), axis=0), home)


def process_buckets(nbuckets: int, nprocesses: int, index: int) -> list[int]:
    """The buckets process ``index`` of ``nprocesses`` holds: round robin, ``i % nprocesses == index``."""
    if int(nprocesses) < 1 or not 0 <= int(index) < int(nprocesses):
        raise ValueError(f"process {index} of {nprocesses}: need 0 <= index < nprocesses")
    return [i for i in range(int(nbuckets)) if i % int(nprocesses) == int(index)]


def _prepare(system: LinearSystem, devices: tuple, options: MModeOptions, owned) -> MModeSplitState:
    """The set-up of :func:`prepare_mmode_on` / :func:`prepare_mmode_processes` for the buckets ``owned``
    (None: all); partial results summed over the processes."""
    check_float64(system.op.response, system.inv_noise)
    res = mmode_check(system, atol=options.atol, rtol=options.rtol)
    if not res.ok:
        raise ValueError(f"P is not block-diagonal in m: {res.reason}")
    system = jax.device_put(system, devices[0])
    L = mmode_factor_on(system, devices, options.bucket, owned)
    b = wiener_rhs(system)
    a_wf = _sum_over_processes(_block_solve_on(L, b))
    r = b - precision_apply(system, a_wf)
    dot = _sum_over_processes(jnp.sum(r * _block_solve_on(L, r), axis=-1))
    nf = system.prior.inv_var.shape[0]
    bad = [jax.device_put(~jnp.all(jnp.isfinite(a), axis=(1, 2, 3)), devices[0]) for a in L.arrays if a is not None]
    bad = _sum_over_processes(jnp.sum(jnp.stack(bad), axis=0, dtype=jnp.int32) if bad else jnp.zeros(nf, jnp.int32))
    info = _wiener_info(system, a_wf, b, dot, bad == 0, options.tol)
    return MModeSplitState(system, a_wf, info, L, devices)


def prepare_mmode_on(system: LinearSystem, devices: Sequence | None = None,
                     options: MModeOptions | None = None) -> MModeSplitState:
    """:func:`gcrsky.solvers.mmode.prepare_mmode` with the blocks split over ``devices`` (default: all local ones).

    Raises ``ValueError`` naming the reason unless :func:`gcrsky.solvers.mmode_check` passes.  The Wiener
    filter is ``P^-1 b`` through the factors (as on one device), judged by its true matrix-free residual.
    """
    options = MModeOptions() if options is None else options
    return _prepare(system, tuple(jax.local_devices() if devices is None else devices), options, None)


def prepare_mmode_processes(system: LinearSystem, options: MModeOptions | None = None,
                            devices: Sequence | None = None) -> MModeSplitState:
    """:func:`prepare_mmode_on` split over the processes of ``jax.distributed`` as well.

    Call it on every process with the same system (after :func:`gcrsky.parallel.init_distributed`).
    Process ``p`` of ``P`` builds and factorises the buckets :func:`process_buckets` gives it, over its
    ``devices`` (default: its local ones), and keeps them; the Wiener filter's pieces, its residual check
    and the finiteness flags are summed over the processes (``process_allgather``: every process ends
    with the whole Wiener filter and its info).  The buckets are disjoint, so each entry is one
    process's number plus zeros: equal to one process's result.  With one process it is
    :func:`prepare_mmode_on`.
    """
    options = MModeOptions() if options is None else options
    lay = mmode_buckets(lmax_from_nparams(system.op.response.shape[2]), options.bucket)
    owned = process_buckets(len(lay.gather), jax.process_count(), jax.process_index())
    return _prepare(system, tuple(jax.local_devices() if devices is None else devices), options, owned)


def draw_mmode_on(key: jax.Array, state: MModeSplitState, ndraws: int):
    """``ndraws`` exact draws ``a_wf + L_m^-T z``, each bucket's solve on its own device.

    The normals are :func:`gcrsky.solvers.mmode.draw_mmode`'s (one (Nf, sum_b G_b 2H_b, ndraws) array from
    ``key``, cut bucket by bucket), so the draws equal the single-device ones.  For a state of
    :func:`prepare_mmode_processes`, call it on every process: each solves its buckets and the pieces
    are summed over the processes (every process gets all draws).

    Returns:
        draws (Nf, ndraws, n) on the first device; a :class:`~gcrsky.solvers.DrawInfo`.
    """
    L, a_wf = state.chol, state.a_wf
    nf, n = a_wf.shape
    lay = L.layout
    home = state.devices[0]
    rows = [int(np.prod(np.shape(g))) for g in lay.gather]
    z = jax.device_put(jax.random.normal(key, (nf, sum(rows), ndraws), a_wf.dtype), home)
    out = jnp.zeros((nf, ndraws, n), a_wf.dtype)
    for Lb, g, start, size, src, dst in zip(L.arrays, lay.gather, np.cumsum([0, *rows]), rows, lay.src, lay.dst):
        if Lb is None:  # another process's bucket
            continue
        zb = jax.lax.slice_in_dim(z, int(start), int(start) + size, axis=1).reshape((nf,) + np.shape(g) + (ndraws,))
        delta = jax.device_put(_tri_t(Lb, jax.device_put(zb, next(iter(Lb.devices())))), home)
        out = out.at[..., dst].add(jnp.moveaxis(delta, -1, 1).reshape(nf, ndraws, -1)[..., src])
    out = a_wf[:, None, :] + _sum_over_processes(out)
    finite = jnp.all(jnp.isfinite(out), axis=-1)
    return out, DrawInfo(state.wiener, exact_info(state.wiener, finite, (nf, ndraws)), a_wf)


@jax.jit
def _tri_t(L: jax.Array, z: jax.Array) -> jax.Array:
    return tri_solve(L, z, True)
