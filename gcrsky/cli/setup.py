"""Process settings of a command, before JAX's first computation: the safe CPU pool, float64, the compilation cache."""

from __future__ import annotations

import logging

__all__ = ["setup_compile_cache", "setup_jax", "setup_logging"]

log = logging.getLogger("gcrsky.cli")


def setup_logging(verbose: int) -> None:
    """Log warnings, or info (``-v``) or debug (``-vv``), to stderr."""
    level = logging.WARNING - 10 * min(verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("gcrsky").setLevel(level)


def setup_jax(args=None):
    """Process settings before JAX's first computation: the safe CPU pool, float64, the compilation cache
    (and ``--devices`` host devices, ``jax.distributed``: the processes meet within ``--dist-timeout``
    seconds, else :class:`gcrsky.parallel.DistributedInitError`, which :func:`gcrsky.cli.main` turns into a
    message and exit status 4).

    Returns the :func:`gcrsky.parallel.compile_stats` snapshot to count the command's compilation from.
    """
    from ..parallel.runtime import compile_stats, use_host_devices, use_safe_cpu_threading

    if (getattr(args, "devices", None) or 1) > 1:
        use_host_devices(args.devices)  # CPU devices; on a GPU host the GPUs are the devices anyway
    use_safe_cpu_threading()  # before the first JAX computation (see gcrsky/parallel/runtime.py)
    import jax

    jax.config.update("jax_enable_x64", True)
    setup_compile_cache(args)
    if getattr(args, "coordinator", None):
        from ..parallel.channels import DEFAULT_DIST_TIMEOUT, init_distributed

        timeout = getattr(args, "dist_timeout", None) or DEFAULT_DIST_TIMEOUT
        init_distributed(args.coordinator, args.num_processes, args.process_id, timeout=timeout)
    return compile_stats()


def setup_compile_cache(args) -> None:
    """JAX's persistent compilation cache as the options (``--compile-cache``, ``--no-compile-cache``) ask."""
    from ..parallel.runtime import disable_compile_cache, use_compile_cache

    if args is not None and getattr(args, "no_compile_cache", False):
        disable_compile_cache()
        return
    want = getattr(args, "compile_cache", None)
    try:
        where = use_compile_cache(want)
    except OSError as e:  # e.g. a read-only home: run without the cache rather than fail
        log.warning("no compilation cache (%s); every program is compiled afresh", e)
        disable_compile_cache()
        return
    log.info("compilation cache: %s", where or "off")
