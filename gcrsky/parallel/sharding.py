"""Multi-device execution: shard the baseline axis of a :class:`LinearSystem`.

Every matrix-free product in gcrsky is a contraction over baselines (and times):
``apply`` computes ``V[f, t, b] = sum_k R[f, b, k] rot_t(a)_k`` (independent per
baseline) and ``adjoint`` sums ``conj(R[f, b, k]) v[f, t, b]`` over ``b``.  So
placing the response (axis 1), the data and the inverse noise (axis 2) on a 1-d
device mesh named ``"bl"`` and replicating everything of size O(n) (prior,
angles, frame map) is enough: ``jax.jit``'s automatic partitioning (GSPMD /
Shardy) then runs each device's baselines locally and combines the adjoint's
partial sums with one all-reduce per product.  No gcrsky function needs to change:
:func:`gcrsky.model.apply`, :func:`~gcrsky.model.adjoint`,
:func:`gcrsky.model.system.precision_apply`, :func:`~gcrsky.model.system.wiener_rhs` and
:func:`gcrsky.inference.sample_system` (CG, ``dense=False``) accept the sharded system
as is and return the same numbers as on one device, up to the order of the
floating-point sum over baselines (~1e-16 relative per product).

Usage:

    from gcrsky.parallel.runtime import use_host_devices
    use_host_devices(4)        # CPU only, before JAX's first computation (see below)
    mesh = baseline_mesh()                     # all devices
    sys_sh = shard_system(problem.system(), mesh)
    draws, info = sample_system(key, sys_sh, 16, dense=False, preconditioner="nystrom")

Several devices on one CPU (``--xla_force_host_platform_device_count``, for tests and
CI).  Set them up with :func:`gcrsky.parallel.use_host_devices` (this process, before
JAX starts) or :func:`gcrsky.parallel.runtime.host_devices_env` (a subprocess's environment),
not with ``XLA_FLAGS`` alone.  With jaxlib 0.10 a batched LAPACK call (the Nystrom
preconditioner's QR/Cholesky/SVD over frequencies, replicated, so every device runs
it) blocks a thread of XLA's intra-op pool while it waits for its own tasks on that
pool, and the pool has only ``max(cores, devices)`` threads: with N devices on <= N
cores every thread can end up waiting, a silent hang at 0% CPU (3 of 6 runs of the
4-device check on a 2-core host; not the collectives, which merely looked suspect).
The helpers raise the pool to :data:`gcrsky.parallel.runtime.POOL_THREADS_PER_DEVICE` threads
per device (``PJRT_NPROC``); see :mod:`gcrsky.parallel.runtime`.  :func:`baseline_mesh` warns
when the environment gives the pool fewer threads than that.

Processes.  The mesh may span ``jax.distributed`` processes (:func:`gcrsky.parallel.init_distributed`,
then ``baseline_mesh()`` over ``jax.devices()``, every process's devices): every process builds the
same system and :func:`shard_system` places only its own baselines (``jax.make_array_from_callback``),
so each process holds ``Nbl / P`` rows of the response, and the same jitted products and CG run as one
SPMD program, the adjoint's partial sums combined across processes.  Results that XLA keeps
replicated are read on any process; sharded ones through
:func:`jax.experimental.multihost_utils.process_allgather`.  Tested with two localhost processes
(``tests/test_sharding.py``): products, Wiener filter and draws equal one process's.

Padding.  ``jax.device_put`` needs the sharded axis to be a multiple of the device
count, so :func:`shard_system` appends ``(-Nbl) % ndev`` *dummy baselines* with zero
response, zero data and zero inverse noise.  A dummy baseline adds exactly zero to
``X^T W X`` and ``X^T W d`` (its model visibility is 0 and its weight is 0), so the
posterior, the Wiener filter and every deterministic product are unchanged (only the
summation order differs).  Two visible consequences:

* visibilities from ``apply(sharded.op, a)`` have ``Nbl_padded`` columns; the first
  ``Nbl`` are the real ones (``[..., :nbl]``), the rest are 0;
* the GCR fluctuation noise is drawn with shape ``(Nf, Nt, Nbl_padded)``, so a fixed
  key gives a *different, equally exact* realisation than on the unpadded system
  (the dummy baselines' noise is multiplied by ``sqrt(0)``, but the threefry stream
  depends on the array's shape).  Draws of the sharded system agree with draws of
  the same padded system on one device (:func:`pad_baselines`), which is what
  "identical to one device" means here; when ``Nbl`` is already a multiple of the
  device count nothing is padded and the draws match the unpadded system directly.
  (This relies on ``jax_threefry_partitionable``, default True since JAX 0.5, which
  makes random bits independent of the output's sharding.)

Caveats.  Only the baseline axis is split: the dense paths (``dense=True``,
``method="cholesky"``/``"eigh"``, the m-block preconditioner's (Nf, lmax+1, B, B)
blocks) reduce over baselines into an n x n matrix that XLA keeps replicated, so
they run, but every device then holds and factorises the whole P.  A frame map
(dense array or :class:`gcrsky.sphere.FrameMap`) is replicated: it acts on O(n)
vectors before and after the baseline contraction.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ..model.system import LinearSystem
from .runtime import effective_pool_size, safe_pool_size

__all__ = ["AXIS", "baseline_mesh", "pad_baselines", "shard_system"]

#: Name of the mesh axis the baselines are split over.
AXIS = "bl"


def baseline_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-d :class:`jax.sharding.Mesh` with axis ``"bl"`` over ``devices`` (default: all).

    Warns (RuntimeWarning) if the mesh has several CPU devices and the environment
    gives XLA's CPU thread pool fewer than :func:`gcrsky.parallel.runtime.safe_pool_size`
    threads: batched LAPACK calls can then deadlock (module docstring; fix with
    :func:`gcrsky.parallel.use_host_devices` before JAX starts).
    """
    devs = jax.devices() if devices is None else list(devices)
    if len(devs) == 0:
        raise ValueError("baseline_mesh needs at least one device")
    me = jax.process_index()  # the pool is per process: count this process's CPU devices
    ncpu = sum(d.platform == "cpu" and d.process_index == me for d in devs)
    if ncpu > 1:
        n_all = len(jax.local_devices(backend="cpu"))
        have, want = effective_pool_size(n_all), safe_pool_size(n_all)
        if have < want:
            warnings.warn(
                f"{n_all} CPU devices share an XLA thread pool of {have} threads (PJRT_NPROC / core "
                f"count); batched LAPACK calls (e.g. the Nystrom preconditioner) can deadlock it. "
                f"Call gcrsky.parallel.use_host_devices({n_all}) before JAX starts (wants >= {want}).",
                RuntimeWarning,
                stacklevel=2,
            )
    return Mesh(np.asarray(devs, dtype=object), (AXIS,))


def _pad_axis(x, axis: int, extra: int):
    if extra == 0:
        return x
    widths = [(0, 0)] * x.ndim
    widths[axis] = (0, extra)
    return jnp.pad(jnp.asarray(x), widths)


def pad_baselines(system: LinearSystem, multiple: int) -> LinearSystem:
    """Append zero-response, zero-data, zero-weight baselines up to a multiple of ``multiple``.

    Exact: a dummy baseline contributes nothing to the precision or the right-hand
    sides (see the module docstring).  Returns ``system`` itself if no padding is needed.
    """
    if int(multiple) != multiple or multiple < 1:
        raise ValueError(f"multiple must be a positive integer, got {multiple}")
    nbl = system.op.response.shape[1]
    if system.data.shape[2] != nbl or system.inv_noise.shape[2] != nbl:
        raise ValueError(
            f"response has {nbl} baselines but data {system.data.shape} / inv_noise "
            f"{system.inv_noise.shape} do not (expected (Nf, Nt, {nbl}))"
        )
    extra = (-nbl) % int(multiple)
    if extra == 0:
        return system
    op = system.op._replace(response=_pad_axis(system.op.response, 1, extra))
    return system._replace(
        op=op, data=_pad_axis(system.data, 2, extra), inv_noise=_pad_axis(system.inv_noise, 2, extra)
    )


def _place(x, sharding: NamedSharding):
    """``x`` placed with ``sharding``: ``jax.device_put`` where this process addresses every device of the
    mesh, else (a mesh over ``jax.distributed`` processes) each process places only its own shards from its
    own full copy of ``x`` (:func:`jax.make_array_from_callback`; every process must pass the same ``x``)."""
    if sharding.is_fully_addressable:
        return jax.device_put(x, sharding)
    host = np.asarray(x)
    return jax.make_array_from_callback(host.shape, sharding, lambda idx: host[idx])


def _replicate(tree, mesh: Mesh):
    rep = NamedSharding(mesh, P())
    return jax.tree_util.tree_map(
        lambda x: _place(x, rep) if isinstance(x, (np.ndarray, jax.Array)) else x, tree
    )


def shard_system(system: LinearSystem, mesh: Mesh) -> LinearSystem:
    """Place ``system`` on ``mesh`` with its baseline axis split over the mesh's one axis.

    * ``op.response`` (Nf, Nbl, n): ``P(None, axis)``;
    * ``data``, ``inv_noise`` (Nf, Nt, Nbl): ``P(None, None, axis)``;
    * ``op.angles``, ``op.frame`` and the prior: replicated.

    The baseline axis is first padded to a multiple of the device count with dummy
    baselines (zero response and weight: exact, see the module docstring), so the
    result may have more baselines than ``system``.

    Raises:
        ValueError: if ``mesh`` is not 1-d.
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a jax.sharding.Mesh, got {type(mesh).__name__}")
    if len(mesh.axis_names) != 1:
        raise ValueError(
            f"shard_system needs a 1-d mesh (one axis for the baselines), got axes {mesh.axis_names} "
            f"of shape {tuple(mesh.devices.shape)}; use baseline_mesh()"
        )
    (axis,) = mesh.axis_names
    system = pad_baselines(system, mesh.devices.size)
    resp_sh = NamedSharding(mesh, P(None, axis))
    vis_sh = NamedSharding(mesh, P(None, None, axis))
    op = system.op._replace(
        response=_place(system.op.response, resp_sh),
        angles=_replicate(system.op.angles, mesh),
        frame=_replicate(system.op.frame, mesh),
    )
    return LinearSystem(
        op=op,
        data=_place(system.data, vis_sh),
        inv_noise=_place(system.inv_noise, vis_sh),
        prior=_replicate(system.prior, mesh),
    )
