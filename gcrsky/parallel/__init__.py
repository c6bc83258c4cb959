"""More than one device: the baseline axis sharded with ``jax.sharding``, and XLA's CPU pool.

- ``sharding``: :func:`shard_system`: baselines padded and sharded over a mesh, identical results
- ``runtime``: XLA CPU-thread settings (the safe single-threaded Eigen pool, forced host devices sized so batched LAPACK cannot deadlock)
"""


from .runtime import (
    POOL_THREADS_PER_DEVICE,
    SAFE_XLA_FLAG,
    effective_pool_size,
    forced_device_count,
    host_devices_env,
    safe_pool_size,
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
    "POOL_THREADS_PER_DEVICE",
    "SAFE_XLA_FLAG",
    "baseline_mesh",
    "effective_pool_size",
    "forced_device_count",
    "host_devices_env",
    "pad_baselines",
    "safe_pool_size",
    "shard_system",
    "use_host_devices",
    "use_safe_cpu_threading",
]
