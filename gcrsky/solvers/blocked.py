"""A blocked Cholesky factorisation in place, for SPD matrices that fit in memory once but not twice.

``jnp.linalg.cholesky`` (LAPACK ``potrf`` through XLA) returns its factor in a new buffer:
an ``N x N`` matrix needs at least ``2 x 8 N^2`` bytes at its peak (measured 2.2x with a
donated input at N = 12000, 3.2x without).  The data-space matrix of a HERA-core
partial-coverage run (331 antennas compressed to 630 baselines, 30 times: ``N_d = 37800``) is
11.4 GB: it fits in 16 GB once, not twice.  :func:`blocked_cholesky` factorises a host
(NumPy) array in its own buffer, right-looking by panels of ``block`` columns:

1. ``L_jj = chol(A_jj)`` of the ``b x b`` diagonal block (LAPACK ``dpotrf`` on a copy);
2. the panel below it, ``L_ij = A_ij L_jj^-T`` (``dtrsm``);
3. the trailing lower triangle, ``A_ik -= L_ij L_kj^T`` for ``j < k <= i``, one row chunk at a
   time (a GEMM per chunk: the temporaries are one chunk of rows, never the trailing matrix).

Only the lower triangle of the input is read; the result is lower triangular (its upper
triangle set to 0).  ``N^3 / 3`` flop, in GEMMs of ``block`` columns (multi-threaded BLAS where
the process allows it), and only small ``potrf`` calls: the multi-threaded OpenBLAS ``potrf``
that crashed above N = 14000 on the development host
(:data:`gcrsky.solvers.dense.OPENBLAS_SAFE_N`) never sees more than ``block``.  A JAX version
of the same panels (one jitted, donating step per panel) was measured first: XLA kept a copy
of the matrix (3.1 GB peak for a 1.15 GB matrix) and took 16x LAPACK's time, so this runs on
the host: it is the CPU's low-memory route; a device that holds ``2 x 8 N^2`` bytes uses
``jnp.linalg.cholesky``.

The factor goes to JAX without a copy where the platform allows (``jax.device_put`` of an
aligned C-contiguous array on the CPU backend).  Solves with it differentiate implicitly
against a matrix-free product (:func:`factor_solve`), so the matrix itself is not kept.
"""

from __future__ import annotations

import os

import jax
import numpy as np

__all__ = ["BLOCK", "THREADS_ENV", "blas_threads", "blocked_cholesky", "blocked_cholesky_bytes", "factor_solve",
           "triangular_solves"]

#: Default panel width (columns): a step's temporaries are ~3 x 8 x BLOCK x N bytes (~0.9 GB at N = 37800).
BLOCK = 1024
#: Environment variable: BLAS threads of :func:`blocked_cholesky` (default: the cores this process may use).
THREADS_ENV = "GCRSKY_BLAS_THREADS"


def blas_threads() -> int:
    """BLAS threads for :func:`blocked_cholesky`: ``$GCRSKY_BLAS_THREADS``, else the cores this process may use."""
    env = os.environ.get(THREADS_ENV, "").strip()
    if env:
        try:
            k = int(env)
        except ValueError:
            raise ValueError(f"{THREADS_ENV} must be a positive integer, got {env!r}") from None
        if k < 1:
            raise ValueError(f"{THREADS_ENV} must be a positive integer, got {env!r}")
        return k
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _blas_limits(threads: int):
    """A context that runs BLAS with ``threads`` threads, whatever ``OPENBLAS_NUM_THREADS`` the process started
    with (threadpoolctl, imported here: it loads the BLAS libraries it controls)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=int(threads), user_api="blas")


def blocked_cholesky_bytes(n: int, block: int = BLOCK) -> float:
    """Peak bytes of :func:`blocked_cholesky` on an ``n x n`` float64 matrix: the matrix once, plus a
    step's temporaries (the panel below the diagonal block twice, one chunk's product)."""
    b = min(int(block), int(n))
    return 8.0 * n * n + 8.0 * (3.0 * n * b + 2.0 * b * b)


def blocked_cholesky(A: np.ndarray, block: int = BLOCK, threads: int | None = None) -> np.ndarray:
    """Lower Cholesky factor of SPD ``A`` (N, N) float64, computed **in A's buffer** (returns A).

    Its BLAS calls (GEMMs, ``dtrsm``, and ``potrf`` of at most ``block`` columns) run with ``threads``
    threads for their duration only (threadpoolctl): gcrsky's CPU set-up keeps ``OPENBLAS_NUM_THREADS=1``
    for the calls inside XLA's thread pool (:mod:`gcrsky.parallel.runtime`), but this runs on the host
    while XLA waits.  Measured N = 8000 on an idle 2-core host: 4.3 s with 1 thread, 2.7 s with 2.

    Args:
        A: writable, C-contiguous float64 NumPy array; only its lower triangle is read.
        block: panel width (columns per step).
        threads: BLAS threads; None: :func:`blas_threads`.

    Raises:
        ValueError: A is not square, float64 or C-contiguous, or not positive definite (naming
            the first panel whose diagonal block failed).
    """
    import scipy.linalg as sla  # lazily: SciPy's OpenBLAS loaded at `import gcrsky` would fix its thread count before use_safe_cpu_threading runs

    if not isinstance(A, np.ndarray) or A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"blocked_cholesky needs a square NumPy array (N, N), got {type(A).__name__} "
                         f"of shape {getattr(A, 'shape', None)}")
    if A.dtype != np.float64 or not A.flags.c_contiguous or not A.flags.writeable:
        raise ValueError(f"blocked_cholesky needs a writable C-contiguous float64 array, got {A.dtype}, "
                         f"C-contiguous {A.flags.c_contiguous}, writable {A.flags.writeable}")
    n = A.shape[0]
    block = max(1, min(int(block), n))
    with _blas_limits(blas_threads() if threads is None else threads):
        return _factor_panels(A, block, sla)


def _factor_panels(A: np.ndarray, block: int, sla) -> np.ndarray:
    """The right-looking panel loop of :func:`blocked_cholesky` (A checked, BLAS threads set)."""
    n = A.shape[0]
    for j0 in range(0, n, block):
        j1 = min(j0 + block, n)
        try:
            ljj = sla.cholesky(A[j0:j1, j0:j1], lower=True, check_finite=False)
        except np.linalg.LinAlgError as err:
            raise ValueError(f"the matrix is not positive definite (diagonal block of rows {j0}-{j1}: {err})") from None
        A[j0:j1, j0:j1] = ljj
        A[j0:j1, j1:] = 0.0
        if j1 == n:
            break
        # panel below: L_ij = A_ij L_jj^-T, i.e. solve L_jj X^T = A_ij^T
        panel = sla.solve_triangular(ljj, A[j1:, j0:j1].T, lower=True, check_finite=False).T
        A[j1:, j0:j1] = panel
        for i0 in range(j1, n, block):  # trailing lower triangle, a row chunk at a time
            i1 = min(i0 + block, n)
            A[i0:i1, j1:i1] -= panel[i0 - j1 : i1 - j1] @ panel[: i1 - j1].T
    return A


def triangular_solves(L: jax.Array, b: jax.Array) -> jax.Array:
    """``(L L^T)^-1 b`` for a lower factor L (N, N) and b (..., N): two triangular solves (JAX)."""
    B = b.reshape(-1, b.shape[-1]).T  # (N, k)
    y = jax.lax.linalg.triangular_solve(L, B, left_side=True, lower=True)
    x = jax.lax.linalg.triangular_solve(L, y, left_side=True, lower=True, transpose_a=True)
    return x.T.reshape(b.shape)


def factor_solve(matvec, L: jax.Array, b: jax.Array) -> jax.Array:
    """``A^-1 b`` (b (N,)) with A's lower factor L (N, N), differentiated implicitly against ``matvec``.

    ``lax.custom_linear_solve``: ``dx = A^-1 (db - dA x)``, where ``dA x`` comes from
    differentiating ``matvec`` (x -> A x, e.g. a matrix-free product), so A itself need not be
    stored; the factor is held fixed.
    """
    Lc = jax.lax.stop_gradient(L)
    return jax.lax.custom_linear_solve(matvec, b, lambda _, r: triangular_solves(Lc, r), symmetric=True)
