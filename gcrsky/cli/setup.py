"""Process settings of a command, before JAX's first computation: the safe CPU pool, float64, the compilation cache."""

from __future__ import annotations

import logging

__all__ = ["check_xla_can_start", "setup_compile_cache", "setup_jax", "setup_logging"]

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
    check_xla_can_start()
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


#: What the start-up probe runs: the CLI's imports, XLA's CPU client and one computation, the file and map libraries.
_PROBE = ("import gcrsky.cli, jax; jax.config.update('jax_enable_x64', True); import jax.numpy as jnp; "
          "jnp.ones(3).sum().block_until_ready(); import pyuvdata, healpy")


def check_xla_can_start() -> None:
    """Under a finite address-space limit (``ulimit -v``), check that XLA can start, in a child process.

    XLA reserves virtual memory for its thread pools when its client starts; under a tight ``ulimit -v``
    the thread creation fails and XLA aborts the process (``Check failed ... pthread_create() failed``,
    SIGABRT): no Python handler can turn that into a message.  So where the limit is finite (only then:
    it costs a process start, ~2 s) a child process with the same limit, environment and imports starts
    XLA first; if it dies, a :class:`MemoryError` says so (the CLI prints it, exit 2), and the parent
    starts its own client at once, in the same state the child had.  Measured on the 2-core machine:
    ``ulimit -v`` 2 GB aborted ``gcrsky run`` at XLA's start, 3 GB ran the default case.
    """
    import subprocess
    import sys

    from .errors import address_space_limit, under_address_limit

    if address_space_limit() is None:
        return
    try:
        child = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as e:  # a fork that fails under the limit says the same
        child = subprocess.CompletedProcess([], -1, "", str(e))
    if child.returncode != 0:
        last = next((ln for ln in child.stderr.splitlines() if "Check failed" in ln or "Error" in ln), "")
        raise under_address_limit("XLA cannot start" + (f" ({last.strip()[:160]})" if last else
                                                        f" (a test process ended with status {child.returncode})"))
    import jax

    jax.devices()  # the parent's client, now, as the child's started
