"""Process-level runtime settings that the CLI and the test suite apply (never on import).

XLA's CPU backend can wedge its multi-threaded Eigen pool on large vmapped graphs:
the main thread waits in ``block_until_ready`` while every worker idles at 0% CPU
(seen here twice under load, in the vmapped CG loops; also reported upstream, e.g.
PyAutoFit#1530, where ``--xla_cpu_multi_thread_eigen=false`` removed it).  The
single-threaded Eigen path costs ~15% on matrix products; a hung job costs more.
"""

from __future__ import annotations

import os

__all__ = ["SAFE_XLA_FLAG", "use_safe_cpu_threading"]

SAFE_XLA_FLAG = "--xla_cpu_multi_thread_eigen=false"


def use_safe_cpu_threading() -> bool:
    """Add :data:`SAFE_XLA_FLAG` to ``XLA_FLAGS`` unless the user set that flag already.

    Must run before the first JAX computation (XLA reads the flags when its backend
    starts).  Set ``GCRSKY_FAST_THREADS=1`` to opt out.  Returns whether the flag is active.
    """
    if os.environ.get("GCRSKY_FAST_THREADS") == "1":
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_multi_thread_eigen" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " " + SAFE_XLA_FLAG).strip()
    return SAFE_XLA_FLAG in os.environ["XLA_FLAGS"]
