"""More than one device: the baseline axis sharded with ``jax.sharding``, and XLA's CPU pool.

- ``sharding``: :func:`shard_system`: baselines padded and sharded over a mesh, identical results
- ``channels``: frequency channels one at a time (:func:`sample_channels`), over a device mesh (:func:`sample_channels_sharded`) and over ``jax.distributed`` processes (:func:`distributed_channels`), with a per-channel key scheme that makes the split invisible
- ``mblocks``: the m-mode path's buckets of orders built, factorised and solved over several devices (:func:`prepare_mmode_on`, :func:`draw_mmode_on`) and ``jax.distributed`` processes (:func:`prepare_mmode_processes`), equal to one device
- ``rendezvous``: the ``jax.distributed`` processes meet on the coordinator's port before JAX starts (:func:`init_distributed` calls it), so that an unreachable coordinator or a process that never joins raises :class:`DistributedTimeoutError` instead of hanging and aborting
- ``runtime``: XLA CPU-thread settings (the safe single-threaded Eigen pool, forced host devices sized so batched LAPACK cannot deadlock); JAX's persistent compilation cache (:func:`use_compile_cache`, which the CLI calls and importing gcrsky never does) and the compile time and cache use of a run (:func:`compile_stats`)
"""


from .channels import (
    CHANNEL_KEY_SCHEME,
    DEFAULT_DIST_TIMEOUT,
    FREQ_AXIS,
    ChannelDraws,
    channel_blocks,
    channel_key,
    channel_mesh,
    distributed_channels,
    init_distributed,
    resolve_channel_path,
    sample_channels,
    sample_channels_sharded,
)
from .mblocks import (
    MModeSplitState,
    bucket_devices,
    draw_mmode_on,
    mmode_factor_on,
    prepare_mmode_on,
    prepare_mmode_processes,
    process_buckets,
)
from .rendezvous import DistributedInitError, DistributedTimeoutError
from .runtime import (
    COMPILE_CACHE_ENV,
    POOL_THREADS_PER_DEVICE,
    SAFE_XLA_FLAG,
    CompileStats,
    compile_cache_dir,
    compile_stats,
    default_compile_cache_dir,
    disable_compile_cache,
    effective_pool_size,
    forced_device_count,
    host_devices_env,
    safe_pool_size,
    use_compile_cache,
    use_host_devices,
    use_safe_cpu_threading,
)
from .sharding import (
    AXIS,
    baseline_mesh,
    pad_baselines,
    shard_system,
)

__all__ = [
    "AXIS",
    "MModeSplitState",
    "bucket_devices",
    "draw_mmode_on",
    "mmode_factor_on",
    "prepare_mmode_on",
    "prepare_mmode_processes",
    "process_buckets",
    "CHANNEL_KEY_SCHEME",
    "DEFAULT_DIST_TIMEOUT",
    "DistributedInitError",
    "DistributedTimeoutError",
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
    "COMPILE_CACHE_ENV",
    "POOL_THREADS_PER_DEVICE",
    "SAFE_XLA_FLAG",
    "CompileStats",
    "baseline_mesh",
    "compile_cache_dir",
    "compile_stats",
    "default_compile_cache_dir",
    "disable_compile_cache",
    "effective_pool_size",
    "forced_device_count",
    "host_devices_env",
    "pad_baselines",
    "safe_pool_size",
    "shard_system",
    "use_compile_cache",
    "use_host_devices",
    "use_safe_cpu_threading",
]
