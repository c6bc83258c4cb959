"""More than one device: the baseline axis sharded with ``jax.sharding``, and XLA's CPU pool.

- ``sharding``: :func:`shard_system`: baselines padded and sharded over a mesh, identical results
- ``channels``: frequency channels one at a time (:func:`sample_channels`), over a device mesh (:func:`sample_channels_sharded`) and over ``jax.distributed`` processes (:func:`distributed_channels`), with a per-channel key scheme that makes the split invisible
- ``mblocks``: the m-mode path's buckets of orders built, factorised and solved over several devices (:func:`prepare_mmode_on`, :func:`draw_mmode_on`) and ``jax.distributed`` processes (:func:`prepare_mmode_processes`), equal to one device
- ``rendezvous``: the ``jax.distributed`` processes meet on the coordinator's port before JAX starts (:func:`init_distributed` calls it), so that an unreachable coordinator or a process that never joins raises :class:`DistributedTimeoutError` instead of hanging and aborting
- ``runtime``: XLA CPU-thread settings (the safe single-threaded Eigen pool, forced host devices sized so batched LAPACK cannot deadlock); JAX's persistent compilation cache (:func:`use_compile_cache`, which the CLI calls and importing gcrsky never does) and the compile time and cache use of a run (:func:`compile_stats`)
"""


from .channels import (
    CHANNEL_KEY_SCHEME,
    ChannelDraws,
    channel_key,
    channel_mesh,
    distributed_channels,
    init_distributed,
    sample_channels,
    sample_channels_sharded,
)
from .mblocks import MModeSplitState, draw_mmode_on, prepare_mmode_on, prepare_mmode_processes
from .rendezvous import DistributedInitError, DistributedTimeoutError
from .runtime import (
    CompileStats,
    compile_stats,
    disable_compile_cache,
    use_compile_cache,
    use_host_devices,
    use_safe_cpu_threading,
)
from .sharding import baseline_mesh, shard_system

__all__ = [
    "MModeSplitState",
    "draw_mmode_on",
    "prepare_mmode_on",
    "prepare_mmode_processes",
    "CHANNEL_KEY_SCHEME",
    "DistributedInitError",
    "DistributedTimeoutError",
    "ChannelDraws",
    "channel_key",
    "channel_mesh",
    "distributed_channels",
    "init_distributed",
    "sample_channels",
    "sample_channels_sharded",
    "CompileStats",
    "baseline_mesh",
    "compile_stats",
    "disable_compile_cache",
    "shard_system",
    "use_compile_cache",
    "use_host_devices",
    "use_safe_cpu_threading",
]
