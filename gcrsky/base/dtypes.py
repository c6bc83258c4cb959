"""The dtype policy: gcrsky's linear algebra runs in float64 / complex128.

The normal equations reach condition numbers of ~1e9 (the standard case's
monopole prior variance is ~1e5 K^2 against a 0.25 K^2 floor), so single
precision loses the posterior's low-l modes.  Library paths that need float64
call :func:`check_float64` on their inputs and say so when handed float32;
entry points that create arrays call :func:`require_x64`.  The only float32
option is the CG preconditioner's storage (:class:`gcrsky.solvers.CGOptions`,
``pc_dtype``), measured to be safe in ``benchmarks/float32.py``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["check_float64", "require_x64"]


def require_x64(what: str = "gcrsky") -> None:
    """Raise ``RuntimeError`` unless JAX's 64-bit mode is on.

    Args:
        what: the caller, named in the message.
    """
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            f"{what} needs float64: call jax.config.update('jax_enable_x64', True) at start-up "
            "(before creating any JAX array); float32 loses the posterior's low-l modes"
        )


def check_float64(*arrays) -> None:
    """Raise ``TypeError`` if any floating (complex) array is not float64 (complex128).

    Works at trace time (only dtypes are inspected), so jitted functions call it on
    their inputs.
    """
    for x in arrays:
        dt = jnp.asarray(x).dtype if not hasattr(x, "dtype") else x.dtype
        if jnp.issubdtype(dt, jnp.floating) and dt != jnp.float64:
            raise TypeError(
                f"gcrsky's linear algebra needs float64 but got {dt}: enable x64 with "
                "jax.config.update('jax_enable_x64', True) before creating arrays"
            )
        if jnp.issubdtype(dt, jnp.complexfloating) and dt != jnp.complex128:
            raise TypeError(
                f"gcrsky's linear algebra needs complex128 but got {dt}: enable x64 with "
                "jax.config.update('jax_enable_x64', True) before creating arrays"
            )
