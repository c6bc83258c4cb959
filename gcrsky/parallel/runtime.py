"""Process-level runtime settings that the CLI and the test suite apply (never on import).

Two kinds: XLA's CPU thread pool (below), and JAX's persistent compilation cache with a
record of the compile time (:func:`use_compile_cache`, :func:`compile_stats`; see
"Compilation cache" at the end of this docstring).

XLA's CPU backend can wedge its multi-threaded Eigen pool on large vmapped graphs:
the main thread waits in ``block_until_ready`` while every worker idles at 0% CPU
(seen here twice under load, in the vmapped CG loops; also reported upstream, e.g.
PyAutoFit#1530, where ``--xla_cpu_multi_thread_eigen=false`` removed it).  The
single-threaded Eigen path costs ~15% on matrix products; a hung job costs more.

Forced host devices (``--xla_force_host_platform_device_count=N``, used to run the
sharded code of :mod:`gcrsky.parallel.sharding` on one CPU) need one more setting, because
of a deadlock in jaxlib 0.10's CPU LAPACK kernels that is independent of the flag
above:

* every batched LAPACK custom call (``jnp.linalg.cholesky``/``qr``/``svd``/``eigh``,
  ``solve_triangular``, ... on a batch of matrices, e.g. the Nystrom preconditioner's
  per-frequency QR, Cholesky, triangular solve and SVD) splits its batch into tasks on
  XLA's intra-op thread pool ("XLAEigen") and *blocks* its thread until they are done
  (``jax::ParallelBatchMap`` -> ``absl::BlockingCounter::Wait``);
* XLA's thunk executor runs independent thunks of a program on the same pool, so a
  LAPACK call often runs *on* a pool worker, and a replicated computation on N
  devices runs N such calls at once;
* the pool has ``max(PJRT_NPROC or the CPU count, N)`` threads: with N forced devices
  on N or fewer cores it has exactly N, and when the N devices' LAPACK calls each hold
  one worker, every worker waits for tasks that no thread is left to run.  The process
  then hangs at 0% CPU forever.

Measured on a 2-core host with 4 forced devices (the sharded CG check of
``tests/test_sharding.py``, Nystrom preconditioner): with XLA's default 4-thread
pool 3 of 6 runs hung (7 of 8 with ``OPENBLAS_NUM_THREADS=1``), every time with all
4 ``tf_XLAEigen`` threads in ``lapack_dgesdd_ffi -> ParallelBatchMap ->
BlockingCounter::Wait`` (gdb) and no thread in a collective; with a 16-thread pool
20 of 20 runs finished (37-78 s, the cores shared with other jobs).
:func:`host_devices_env` / :func:`use_host_devices` therefore size the pool
(``PJRT_NPROC``, read by XLA when it creates the CPU client) to
:data:`POOL_THREADS_PER_DEVICE` threads per device, so a deadlock would need that
many LAPACK calls blocked at once per device.  This is a workaround for jaxlib
0.10.x's parallel batch path; a jaxlib that runs the batch inline needs none.

One device is not immune: a program with independent batched LAPACK calls runs them
concurrently too, and the default pool has only the CPU count of threads.  Measured:
the Laplace Hessian of :func:`gcrsky.fit_hyperparameters` (forward-over-reverse
through Cholesky solves) hung on this 2-core host, both pool threads in
``TriMatrixEquationSolver -> ParallelBatchMap -> BlockingCounter::Wait`` (gdb).  So
:func:`use_safe_cpu_threading` sizes the pool for one device as well:
:func:`safe_pool_size` is ``max(CPU count, POOL_THREADS_PER_DEVICE * max(N, 2))``.

They also default ``OPENBLAS_NUM_THREADS`` to 1: the pool's LAPACK tasks call
multi-threaded OpenBLAS concurrently, which on few cores spins in
``exec_blas_async_wait`` (4 devices, an 8-thread pool, two replicated batched SVDs
of 4 x 120 x 60 a hundred times: not done after 60 s, 3 of 3, vs 4-5 s with one
OpenBLAS thread; jax-ml/jax#39292 reports the same oversubscription corrupting the
heap on many-core hosts).  One OpenBLAS thread is also what makes the dense Cholesky
of large P possible: multi-threaded ``dpotrf`` (scipy-openblas 0.3.30, which jaxlib's
CPU LAPACK kernels call) crashed with a segmentation fault from n = 16000 on this
2-core host (n = 14000 ran), in scipy as in JAX, while with one thread n = 16000 took
35 s and n = 22801 127 s (:data:`gcrsky.solvers.dense.OPENBLAS_SAFE_N`).  The setting
must precede the first import of scipy's LAPACK (gcrsky imports it lazily, so calling
:func:`use_safe_cpu_threading` right after ``import gcrsky`` is early enough).

Compiled programs and the kernel's map limit
--------------------------------------------
Each compiled XLA:CPU program JIT-links its code into ~27 memory mappings (measured with
jaxlib 0.10.2), held as long as JAX caches the program.  Linux allows a process at most
``vm.max_map_count`` mappings (65530 by default), so a process that compiles more than
~2400 distinct programs and keeps them (a long notebook session that varies shapes, a test
worker running hundreds of files) ends in an abort (LLVM cannot allocate a section) or a
segmentation fault inside ``backend_compile_and_load``.  ``jax.clear_caches()`` releases
them (the test suite does it after each file).  One ``gcrsky run`` compiles a few hundred.

Compilation cache
-----------------

Every new process compiles gcrsky's XLA programs again (8 s for the standard case's
Cholesky path on 2 cores, 15-20 s for the CG path), for work that then takes a fraction
of a second.  :func:`use_compile_cache` turns on JAX's persistent compilation cache
(``jax_compilation_cache_dir``), so that a later process loads the compiled programs
from disk instead.  The ``gcrsky`` command calls it (``--compile-cache DIR``,
``--no-compile-cache``); the library never does: a program that imports gcrsky decides.
The directory, unless given: ``$GCRSKY_COMPILE_CACHE`` (``off``, ``0``, ``none`` or
``false`` turn the cache off), else ``$JAX_COMPILATION_CACHE_DIR``, else
``$XDG_CACHE_HOME/gcrsky/jax`` or ``~/.cache/gcrsky/jax`` (:func:`default_compile_cache_dir`).

JAX 0.10's thresholds would skip most of gcrsky's programs: it writes only programs that
took at least ``jax_persistent_cache_min_compile_time_secs`` (default 1 s) to compile, and
a run's many small programs (``jnp.asarray``, PRNG, elementwise steps: about 3 s of the
standard case's 8 s) take less.  So :func:`use_compile_cache` lowers it to 0 by default and
lifts the entry-size floor (``jax_persistent_cache_min_entry_size_bytes = -1``); the whole
standard case is then 39 entries, about 0.4 MB.  The cache grows without bound (JAX's LRU
limit ``jax_compilation_cache_max_size`` needs the ``filelock`` package); delete the
directory to clear it.  Keys include the program, jaxlib's version, ``XLA_FLAGS`` and the
devices, so an upgrade or other flags simply miss.  XLA:CPU checks on load that the host
has the CPU features the program was compiled for and refuses an entry otherwise (then the
program is compiled again): a directory shared between different machines is safe, but
on some AVX-512 hosts jaxlib 0.10 refuses every entry (jax-ml/jax#38445), and the cache
never hits there.  As JAX's documentation warns, a compilation cache is trusted code: do
not share one with users you do not trust.

:func:`compile_stats` counts, from the first call on, what JAX reports through
``jax.monitoring``: the seconds of backend compilation (``/jax/core/compile/
backend_compile_duration``: XLA compiling a program, or loading it from the cache), of
tracing and of lowering to MLIR, and the persistent cache's hits, misses (programs
compiled while the cache was on) and writes.  ``gcrsky run`` records the difference over
a run in ``summary.json`` (``timings_s.compile_s``, ``cache_hits``, ``cache_misses``).
"""

from __future__ import annotations

import os
import re
import sys
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

__all__ = [
    "COMPILE_CACHE_ENV",
    "POOL_THREADS_PER_DEVICE",
    "SAFE_XLA_FLAG",
    "CompileStats",
    "compile_cache_dir",
    "compile_stats",
    "default_compile_cache_dir",
    "disable_compile_cache",
    "effective_pool_size",
    "forced_device_count",
    "host_devices_env",
    "safe_pool_size",
    "use_compile_cache",
    "use_host_devices",
    "use_safe_cpu_threading",
]

#: The XLA flag that keeps the CPU backend's Eigen pool single-threaded (see the module docstring).
SAFE_XLA_FLAG = "--xla_cpu_multi_thread_eigen=false"

#: Intra-op pool threads per forced host device (see the module docstring).  One
#: device's program can have more than one batched LAPACK call in flight (independent
#: branches run concurrently); 4 leaves room for that and costs only idle threads.
POOL_THREADS_PER_DEVICE = 4

_FORCE_FLAG = "--xla_force_host_platform_device_count"
_FORCE_RE = re.compile(r"--xla_force_host_platform_device_count=(\S*)")


def _cpu_count() -> int:
    """Schedulable CPUs, as XLA counts them when it sizes its pool (affinity-aware)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def forced_device_count(flags: str | None = None) -> int:
    """The host device count that ``XLA_FLAGS`` (or ``flags``) forces; 1 if none.

    The last occurrence wins, as in XLA's flag parser.  Raises ValueError for a value
    that is not a positive integer.
    """
    flags = os.environ.get("XLA_FLAGS", "") if flags is None else flags
    found = _FORCE_RE.findall(flags)
    if not found:
        return 1
    try:
        n = int(found[-1])
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"{_FORCE_FLAG} must be a positive integer, got {found[-1]!r}")
    return n


def safe_pool_size(n_devices: int) -> int:
    """XLA CPU intra-op pool size that keeps ``n_devices`` host devices deadlock-free.

    ``max(CPU count, POOL_THREADS_PER_DEVICE * max(n_devices, 2))``: room for that many
    batched LAPACK calls blocked at once (module docstring); idle threads cost nothing.
    """
    if int(n_devices) != n_devices or n_devices < 1:
        raise ValueError(f"n_devices must be a positive integer, got {n_devices}")
    return max(_cpu_count(), POOL_THREADS_PER_DEVICE * max(int(n_devices), 2))


def effective_pool_size(n_devices: int, environ: Mapping[str, str] | None = None) -> int:
    """The intra-op pool size XLA's CPU client picks for ``n_devices`` under ``environ``.

    ``max(PJRT_NPROC, or else NPROC, or else the CPU count; n_devices)``, XLA's own rule
    (``xla::DefaultThreadPoolSize``; the client never makes fewer threads than devices).
    Only meaningful for the environment the backend was started with.
    """
    env = os.environ if environ is None else environ
    size = _cpu_count()
    for key in ("PJRT_NPROC", "NPROC"):
        try:
            size = max(0, int(env[key]))
            break
        except (KeyError, ValueError):
            continue
    return max(size, int(n_devices))


def _pool_env(env: dict[str, str], n_devices: int) -> None:
    """Raise ``PJRT_NPROC`` to :func:`safe_pool_size` and default ``OPENBLAS_NUM_THREADS``."""
    want = safe_pool_size(n_devices)
    if effective_pool_size(n_devices, env) < want:  # only raised: a larger pool is kept
        env["PJRT_NPROC"] = str(want)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")


def host_devices_env(n_devices: int, environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """A copy of ``environ`` (default ``os.environ``) set up for ``n_devices`` host CPU devices.

    For a subprocess that runs sharded code on one CPU (``subprocess.run(..., env=...)``).
    ``XLA_FLAGS`` gets ``--xla_force_host_platform_device_count=n_devices`` (replacing any
    earlier count) and :data:`SAFE_XLA_FLAG` (unless ``xla_cpu_multi_thread_eigen`` is
    already set); ``PJRT_NPROC`` is raised to :func:`safe_pool_size` and
    ``OPENBLAS_NUM_THREADS`` defaults to 1 (module docstring: without them batched LAPACK
    calls deadlock on a 2-core host).
    """
    if int(n_devices) != n_devices or n_devices < 1:
        raise ValueError(f"n_devices must be a positive integer, got {n_devices}")
    env = dict(os.environ if environ is None else environ)
    flags = _FORCE_RE.sub("", env.get("XLA_FLAGS", "")).split()
    flags.append(f"{_FORCE_FLAG}={int(n_devices)}")
    if not any("xla_cpu_multi_thread_eigen" in f for f in flags):
        flags.append(SAFE_XLA_FLAG)
    env["XLA_FLAGS"] = " ".join(flags)
    _pool_env(env, int(n_devices))
    return env


def _backend_started() -> bool:
    xb = sys.modules.get("jax._src.xla_bridge")
    return bool(xb is not None and xb.backends_are_initialized())


def use_host_devices(n_devices: int) -> int:
    """Apply :func:`host_devices_env` to this process; returns the pool size it asks for.

    Must run before JAX starts its backend (XLA reads ``XLA_FLAGS`` and ``PJRT_NPROC``
    when it creates the CPU client), and ideally before NumPy/SciPy load OpenBLAS
    (``OPENBLAS_NUM_THREADS`` is read then).

    Raises:
        RuntimeError: if JAX's backend has already started.
    """
    if _backend_started():
        raise RuntimeError(
            "use_host_devices must run before JAX's first computation (its backend has already "
            "started, so the device count and the thread pool are fixed)"
        )
    env = host_devices_env(n_devices)
    for key in ("XLA_FLAGS", "PJRT_NPROC", "OPENBLAS_NUM_THREADS"):
        if key in env:
            os.environ[key] = env[key]
    return effective_pool_size(n_devices)


def use_safe_cpu_threading() -> bool:
    """Add :data:`SAFE_XLA_FLAG` to ``XLA_FLAGS`` unless the user set that flag already.

    Must run before the first JAX computation (XLA reads the flags when its backend
    starts).  Set ``GCRSKY_FAST_THREADS=1`` to opt out.  Returns whether the flag is active.

    It also sizes the intra-op pool (``PJRT_NPROC``, ``OPENBLAS_NUM_THREADS``) for the
    host devices ``XLA_FLAGS`` forces (one by default) as :func:`host_devices_env` does,
    opt-out or not: that one is a deadlock fix, not a speed trade-off.
    ``OPENBLAS_NUM_THREADS`` only takes effect if this runs before NumPy is imported.

    And it sets ``OMP_WAIT_POLICY=PASSIVE`` unless the user set a policy (read when an
    OpenMP runtime loads: before healpy is imported): healpy's spherical-harmonic
    transforms run OpenMP threads that, with the default active wait, spin at every
    barrier, and on a busy host (XLA's threads, other jobs) a descheduled thread stalls
    the others.  Measured on this 2-core machine at load ~4: 200 ``alm2map`` at lmax 12,
    nside 32 took 4.9 s with the default policy against 0.04 s passive (20 at lmax 50,
    nside 128: 0.52 s against 0.06 s); the "maps" stage of a 64-channel `gcrsky run --data` (lmax 12,
    200 draws) went from 44 s to 3.1 s.
    """
    env = dict(os.environ)
    _pool_env(env, forced_device_count())
    for key in ("PJRT_NPROC", "OPENBLAS_NUM_THREADS"):
        if key in env:
            os.environ[key] = env[key]
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if os.environ.get("GCRSKY_FAST_THREADS") == "1":
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_multi_thread_eigen" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " " + SAFE_XLA_FLAG).strip()
    return SAFE_XLA_FLAG in os.environ["XLA_FLAGS"]


# ---------------------------------------------------------------- the persistent compilation cache

#: Environment variable naming the compilation cache directory (or ``off``); see the module docstring.
COMPILE_CACHE_ENV = "GCRSKY_COMPILE_CACHE"
_OFF = frozenset({"off", "0", "none", "false", "no"})


def default_compile_cache_dir(environ: Mapping[str, str] | None = None) -> Path | None:
    """The compilation cache directory to use when none is given; None if the environment turns it off.

    ``$GCRSKY_COMPILE_CACHE`` (``off``, ``0``, ``none``, ``false`` or ``no``: None), else
    ``$JAX_COMPILATION_CACHE_DIR`` (JAX's own setting), else ``$XDG_CACHE_HOME/gcrsky/jax``,
    else ``~/.cache/gcrsky/jax``.  Empty values count as unset.
    """
    env = os.environ if environ is None else environ
    mine = env.get(COMPILE_CACHE_ENV, "").strip()
    if mine:
        return None if mine.lower() in _OFF else Path(mine).expanduser()
    jaxs = env.get("JAX_COMPILATION_CACHE_DIR", "").strip()
    if jaxs:
        return Path(jaxs).expanduser()
    xdg = env.get("XDG_CACHE_HOME", "").strip()
    base = Path(xdg).expanduser() if xdg else Path(env.get("HOME") or Path.home()).expanduser() / ".cache"
    return base / "gcrsky" / "jax"


def use_compile_cache(path=None, *, min_compile_time_s: float = 0.0) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``path``; returns the directory (None: turned off).

    Sets JAX's own configuration: ``jax_enable_compilation_cache``,
    ``jax_compilation_cache_dir``, ``jax_persistent_cache_min_compile_time_secs =
    min_compile_time_s`` (JAX's default of 1 s would skip most of gcrsky's programs) and
    ``jax_persistent_cache_min_entry_size_bytes = -1`` (no size floor).  Call it before the
    first computation: programs compiled earlier in the process are not written (JAX
    0.10 picks the new directory up for later ones).  Also starts :func:`compile_stats`.
    ``gcrsky run`` / ``gcrsky scenarios`` call it; importing gcrsky never does.

    Args:
        path: the directory (created if needed); None: :func:`default_compile_cache_dir`,
            which may say "off" (then the cache is turned off, as :func:`disable_compile_cache`).
        min_compile_time_s: programs that compiled faster are not written.

    Raises:
        OSError: the directory cannot be created.
    """
    import jax
    from jax.experimental.compilation_cache import compilation_cache as cc

    path = default_compile_cache_dir() if path is None else Path(path).expanduser()
    compile_stats()  # start counting
    if path is None:
        disable_compile_cache()
        return None
    path.mkdir(parents=True, exist_ok=True)
    path = path.resolve()
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    cc.reset_cache()  # a cache JAX already opened elsewhere in this process is dropped; the next compile opens this one
    return path


def disable_compile_cache() -> None:
    """Turn JAX's persistent compilation cache off for this process (``jax_enable_compilation_cache = False``),
    whatever directory JAX's configuration or environment names."""
    import jax
    from jax.experimental.compilation_cache import compilation_cache as cc

    jax.config.update("jax_enable_compilation_cache", False)
    cc.reset_cache()


def compile_cache_dir() -> Path | None:
    """The directory of JAX's persistent compilation cache as configured now, or None when it is off."""
    import jax

    path = jax.config.jax_compilation_cache_dir
    return Path(path) if path and jax.config.jax_enable_compilation_cache else None


class CompileStats(NamedTuple):
    """Compilation counted by :func:`compile_stats` (totals since counting started; ``b.since(a)`` for a span).

    Attributes:
        compile_s: seconds of backend compilation: XLA compiling programs, or loading
            them from the persistent cache (JAX's ``backend_compile_duration``).
        trace_s: seconds tracing Python functions to jaxprs.
        lower_s: seconds lowering jaxprs to MLIR (done again on a cache hit: the key is
            the lowered program).
        programs: backend compilations (each program once per process and shape).
        cache_hits: programs loaded from the persistent cache.
        cache_misses: programs compiled while the persistent cache was on.
        cache_writes: entries written to it.
    """

    compile_s: float = 0.0
    trace_s: float = 0.0
    lower_s: float = 0.0
    programs: int = 0
    cache_hits: int = 0
    cache_misses: int = 0
    cache_writes: int = 0

    def since(self, earlier: CompileStats) -> CompileStats:
        """What was counted between ``earlier`` and this snapshot."""
        return CompileStats(*(a - b for a, b in zip(self, earlier)))


# JAX 0.10's monitoring events (jax/_src/dispatch.py, compiler.py, compilation_cache.py).
_DURATIONS = {
    "/jax/core/compile/backend_compile_duration": "compile_s",
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
}
_REQUEST = "/jax/compilation_cache/compile_requests_use_cache"
_HIT = "/jax/compilation_cache/cache_hits"
_WRITE = "/jax/compilation_cache/cache_misses"  # JAX records it when it writes an entry
_counts: dict = {}
_watch_lock = threading.Lock()


def _on_duration(event: str, duration_secs: float, **kwargs) -> None:
    field = _DURATIONS.get(event)
    if field is not None:
        _counts[field] = _counts.get(field, 0.0) + float(duration_secs)
        if field == "compile_s":
            _counts["programs"] = _counts.get("programs", 0) + 1


def _on_event(event: str, **kwargs) -> None:
    if event == _REQUEST:
        if compile_cache_dir() is not None:  # JAX asks its cache even when no directory is set
            _counts["requests"] = _counts.get("requests", 0) + 1
    elif event == _HIT:
        _counts["cache_hits"] = _counts.get("cache_hits", 0) + 1
    elif event == _WRITE:
        _counts["cache_writes"] = _counts.get("cache_writes", 0) + 1


def compile_stats() -> CompileStats:
    """Totals of JAX's compilation in this process since the first call (which starts counting).

    Listens to ``jax.monitoring`` (see the module docstring); a snapshot, so a span is
    ``compile_stats().since(before)``.  Counting does not change what is compiled or cached.
    """
    with _watch_lock:
        if "watching" not in _counts:
            import jax.monitoring

            jax.monitoring.register_event_duration_secs_listener(_on_duration)
            jax.monitoring.register_event_listener(_on_event)
            _counts["watching"] = True
    c = dict(_counts)
    hits = int(c.get("cache_hits", 0))
    return CompileStats(
        compile_s=float(c.get("compile_s", 0.0)), trace_s=float(c.get("trace_s", 0.0)),
        lower_s=float(c.get("lower_s", 0.0)), programs=int(c.get("programs", 0)), cache_hits=hits,
        cache_misses=max(0, int(c.get("requests", 0)) - hits), cache_writes=int(c.get("cache_writes", 0)),
    )
