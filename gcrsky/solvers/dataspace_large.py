"""The data-space path when D fits in memory once but not twice (the in-place set-up).

Partial coverage of the HERA core (331 antennas compressed to 630 baselines, 8 h, 30
times) at lmax 300 has ``n = 90601`` parameters (a dense P would take 66 GB) and
``N_d = 2 Nt Nbl = 37800`` real data values: ``D = I + W^1/2 X S X^T W^1/2`` is 11.4 GB.
The standard set-up (:func:`gcrsky.solvers.dataspace.prepare_dataspace`) keeps D and its
factor (``4 x 8 N_d^2`` at its peak, 46 GB here) and builds D with one ``2 Nbl x 2 Nbl x n``
product per lag (``1.7e13`` flop here).  This set-up needs D once:

1. **Lag blocks by m** (:func:`lag_blocks_by_m`).  On the stationary shortcut
   (:func:`gcrsky.solvers.dataspace.lag_structure`: no frame map, S commuting with rotations
   about the pole) every block of D is ``W_t^1/2 G(theta_t - theta_t') W_t'^1/2`` with
   ``G(lag) = R_r S Q(lag) R_r^T`` (``R_r = [Re R; Im R]``).  A rotation about the pole is a
   phase per m, so ``G(lag) = sum_m cos(m lag) A_m + sin(m lag) B_m`` with the per-order Grams
   ``A_m = sum_l (Rs_re Rr_re^T + Rs_im Rr_im^T)`` and ``B_m = sum_l (Rs_im Rr_re^T - Rs_re Rr_im^T)``
   (``Rs = R_r S``; re / im: the columns of the Re / Im entries of ``(l, m)``).  Cost
   ``~8 (2 Nbl)^2 n`` for all Grams (``(lmax + 1)``-wide windows: twice the triangle's flops)
   plus ``4 k (2 Nbl)^2 (lmax + 1)`` for k lags, against ``2 k (2 Nbl)^2 n`` lag by lag
   (``~k / 8``-fold fewer: ~7x at 30 times).
2. **D filled on the host** (lower triangle, block row by block row) into one 64-byte-aligned
   NumPy buffer, **factorised in place** (:func:`gcrsky.solvers.blocked.blocked_cholesky`), and
   handed to JAX without a copy (``jax.device_put`` of an aligned C-contiguous array on the
   CPU; an unaligned one is copied at its first use, measured).
3. Every solve with D goes through the factor, differentiated implicitly against the
   matrix-free ``D v = v + Y S Y^T v`` (:func:`gcrsky.solvers.blocked.factor_solve`), so D
   itself is not kept: :class:`~gcrsky.solvers.dataspace.DataSpaceState` ``gram`` is None.

What it gives up: the set-up runs on concrete arrays (host orchestration; it cannot be traced
or differentiated as a whole, the Wiener filter and the draws it returns do differentiate as
the standard path's do, implicitly), and ``log det D`` from its factor has no derivative (a
gradient through it is NaN, never silently wrong; the evidence's own path,
:func:`gcrsky.solvers.dataspace.dataspace_evidence_parts`, builds D under the trace).
A device that holds ``2 x 8 N_d^2`` bytes is better served by the standard set-up.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import check_float64
from ..model.system import LinearSystem
from ..sphere.modes import lmax_from_nparams, n_alm
from .blocked import BLOCK, blocked_cholesky, blocked_cholesky_bytes

__all__ = [
    "HostFactor",
    "M_CHUNK",
    "aligned_empty",
    "dataspace_large_bytes",
    "factor_in_place",
    "fill_lower",
    "host_logdet",
    "lag_blocks_by_m",
    "logdet_no_grad",
]

#: Orders m whose Grams are formed before they are folded into the lag blocks (one GEMM over the
#: lags per chunk): ``2 M_CHUNK`` Grams of ``(2 Nbl)^2`` at a time.
M_CHUNK = 16


def _order_starts(lmax: int) -> tuple[np.ndarray, np.ndarray]:
    """Start of each order's Re entries and Im entries (m >= 1; m = 0 points at zero padding) in the
    realified vector, and each order's length ``lmax - m + 1``."""
    m = np.arange(lmax + 1)
    start_re = m * (2 * lmax + 1 - m) // 2 + m  # healpy index of (l = m, m)
    start_im = n_alm(lmax) + start_re - (lmax + 1)
    start_im[0] = (lmax + 1) ** 2  # the zero padding past the end
    return np.stack([start_re, start_im]), lmax + 1 - m


@partial(jax.jit, static_argnames=("m_chunk",))
def lag_blocks_by_m(system: LinearSystem, lags: jax.Array, m_chunk: int = M_CHUNK) -> jax.Array:
    """``G(lag) = R_r S Q(lag) R_r^T`` for every lag, by per-order Grams (module docstring).

    Args:
        system: no frame map; S commuting with rotations about the pole (equal prior variances for
            the Re and Im parts of every ``a_lm``), as :func:`gcrsky.solvers.dataspace.lag_structure`
            checks.
        lags: (k,) rotation-angle differences ``theta_t - theta_t'``, radians.
        m_chunk: orders per Gram chunk (memory ``2 m_chunk Nf (2 Nbl)^2`` float64).

    Returns:
        (k, Nf, 2 Nbl, 2 Nbl): rows and columns ``p Nbl + b`` (p = 0 real part, 1 imaginary part),
        equal to the lag-by-lag product of :func:`gcrsky.solvers.dataspace.dataspace_matrix`'s
        stationary shortcut to rounding.
    """
    R = system.op.response  # (Nf, Nbl, n)
    nf, nbl, n = R.shape
    lmax = lmax_from_nparams(n)
    width = lmax + 1
    Rr = jnp.concatenate([R.real, R.imag], axis=1)  # (Nf, 2 Nbl, n)
    pad = jnp.zeros((nf, 2 * nbl, width), Rr.dtype)
    Rr = jnp.concatenate([Rr, pad], axis=-1)
    Rs = jnp.concatenate([R.real, R.imag], axis=1) / system.prior.inv_var[:, None, :]
    Rs = jnp.concatenate([Rs, pad], axis=-1)
    starts, lengths = _order_starts(lmax)
    nchunk = -(-(lmax + 1) // m_chunk)
    orders = np.arange(nchunk * m_chunk)
    valid = orders <= lmax
    o = np.minimum(orders, lmax)
    st = jnp.asarray(np.where(valid, starts[:, o], (lmax + 1) ** 2).reshape(2, nchunk, m_chunk))
    ln = jnp.asarray(np.where(valid, lengths[o], 0).reshape(nchunk, m_chunk))
    ms = jnp.asarray(orders.reshape(nchunk, m_chunk), Rr.dtype)

    def window(X, s, length):
        cols = jax.lax.dynamic_slice_in_dim(X, s, width, axis=-1)
        return jnp.where(jnp.arange(width) < length, cols, 0.0)

    def grams(s_re, s_im, length):
        r_re, r_im = window(Rr, s_re, length), window(Rr, s_im, length)
        q_re, q_im = window(Rs, s_re, length), window(Rs, s_im, length)
        A = jnp.einsum("fak,fbk->fab", q_re, r_re) + jnp.einsum("fak,fbk->fab", q_im, r_im)
        B = jnp.einsum("fak,fbk->fab", q_im, r_re) - jnp.einsum("fak,fbk->fab", q_re, r_im)
        return A, B

    def body(G, c):
        A, B = jax.vmap(grams)(st[0, c], st[1, c], ln[c])  # (m_chunk, Nf, 2 Nbl, 2 Nbl) each
        ph = lags[:, None] * ms[c][None, :]  # (k, m_chunk)
        G = G + jnp.einsum("km,mfab->kfab", jnp.cos(ph), A) + jnp.einsum("km,mfab->kfab", jnp.sin(ph), B)
        return G, None

    G0 = jnp.zeros((lags.shape[0], nf, 2 * nbl, 2 * nbl), Rr.dtype)
    G, _ = jax.lax.scan(body, G0, jnp.arange(nchunk))
    return G


def aligned_empty(shape, align: int = 64) -> np.ndarray:
    """An uninitialised C-contiguous float64 array whose data start on an ``align``-byte boundary
    (so that ``jax.device_put`` on the CPU backend can use it without a copy)."""
    nbytes = int(np.prod(shape)) * 8
    buf = np.empty(nbytes + align, np.uint8)
    off = (-buf.ctypes.data) % align
    return buf[off : off + nbytes].view(np.float64).reshape(shape)


def fill_lower(G: np.ndarray, index: np.ndarray, sqrt_w_rows: np.ndarray, out: np.ndarray) -> np.ndarray:
    """The lower block triangle of ``D = I + W^1/2 [G(lag(t, t'))] W^1/2`` for one channel, in ``out``.

    Args:
        G: (k, B, B) lag blocks of this channel (``B = 2 Nbl``).
        index: (Nt, Nt) lag index of each pair of times.
        sqrt_w_rows: (N_d,) ``W^1/2`` in D's row layout.
        out: (N_d, N_d) float64 buffer; its block rows are written up to the diagonal block
            (the upper block triangle is left as it was: the factorisation never reads it).
    """
    nt = index.shape[0]
    B = G.shape[-1]
    for t in range(nt):
        rows = slice(t * B, (t + 1) * B)
        blk = G[index[t, : t + 1]]  # (t + 1, B, B)
        blk = np.moveaxis(blk, 0, 1).reshape(B, (t + 1) * B)
        out[rows, : (t + 1) * B] = sqrt_w_rows[rows, None] * blk * sqrt_w_rows[None, : (t + 1) * B]
    out[np.diag_indices(out.shape[0])] += 1.0
    return out


def dataspace_large_bytes(system: LinearSystem, nlags: int, ndraws: int = 1, block: int = BLOCK) -> float:
    """Estimated peak bytes of the in-place data-space set-up and ``ndraws`` draws (float64), beyond the system.

    The larger of its two phases, plus per draw ``~6`` vectors of ``N_d + n``:

    * building: first the lag blocks (``8 k Nf (2 Nbl)^2``) with the per-order Gram chunk (``4 M_CHUNK``
      blocks) and the response's padded real copies (``4 x 8 Nf 2 Nbl n``) while they form; then D
      (``8 Nf N_d^2``) filled from the lag blocks and their host copy (the larger of the two);
    * factorising: D and the blocked factorisation's temporaries
      (:func:`gcrsky.solvers.blocked.blocked_cholesky_bytes`).
    """
    nf, nt, nbl = (int(x) for x in system.data.shape)
    n = int(system.prior.mean.shape[-1])
    nd = 2 * nt * nbl
    B2 = 8.0 * (2 * nbl) ** 2
    D = nf * 8.0 * nd * nd
    lag = nlags * nf * B2
    grams = lag + 4.0 * M_CHUNK * nf * B2 + 4.0 * 8 * nf * 2 * nbl * (n + np.sqrt(n))  # before D exists
    build = max(grams, D + 2.0 * lag)  # D filled from the lag blocks and their host copy
    factor = D + (blocked_cholesky_bytes(nd, block) - 8.0 * nd * nd)
    return max(build, factor) + max(1, ndraws) * 6.0 * 8 * nf * (nd + n)


class HostFactor:
    """The in-place factor of D, kept on the host: (Nf, N_d, N_d) lower triangular NumPy array.

    XLA's CPU triangular solve takes a working copy of its matrix (measured: a temporary the size of the
    factor in every compiled solve, 11.4 GB at N_d = 37800), which the in-place set-up exists to avoid;
    so the solves with it run on the host (LAPACK ``dpotrs`` through SciPy, no copy) inside a
    ``jax.pure_callback``, linear and vmappable, differentiated implicitly by the caller
    (:func:`gcrsky.solvers.dataspace._d_solve`).  It enters PyTrees as static data (hashed by identity), so
    a state that holds it is still a PyTree jit and vmap accept; host-bound by design: a device that holds
    ``2 x 8 N_d^2`` bytes uses the standard set-up instead.

    Attributes:
        L: the factor (host array, written once, not to be modified).
        finite: (Nf,) bool, every entry of the channel's factor finite.
        logdet: (Nf,) ``log det D`` per channel (``2 sum log diag L``).
    """

    def __init__(self, L: np.ndarray):
        self.L = L
        diag = np.diagonal(L, axis1=-2, axis2=-1)
        self.finite = np.array([bool(np.all(np.isfinite(np.diagonal(Lf))) and np.isfinite(Lf.sum())) for Lf in L])
        self.logdet = 2.0 * np.sum(np.log(diag), axis=-1)

    @property
    def shape(self) -> tuple:
        return self.L.shape

    def __hash__(self) -> int:
        return id(self)

    def __eq__(self, other) -> bool:
        return self is other

    def _solve_host(self, r: np.ndarray) -> np.ndarray:
        import scipy.linalg as sla  # lazily: loading SciPy's OpenBLAS at `import gcrsky` would fix its thread count before use_safe_cpu_threading can

        r = np.asarray(r, np.float64)
        nf, nd = self.L.shape[0], self.L.shape[-1]
        flat = np.moveaxis(r.reshape((-1, nf, nd)), 0, -1)  # (Nf, N_d, k)
        # L[f].T is Fortran-ordered (no copy): the upper factor U = L^T with U^T U = D, as LAPACK's dpotrs
        # wants it (passing L itself, C-ordered, makes f2py copy the whole factor)
        out = np.stack([sla.cho_solve((self.L[f].T, False), flat[f], check_finite=False) for f in range(nf)])
        return np.moveaxis(out, -1, 0).reshape(r.shape)

    def solve(self, r: jax.Array) -> jax.Array:
        """``D^-1 r`` for r (..., Nf, N_d) through the host factor (a pure callback; not differentiable
        by itself: wrap it in ``lax.custom_linear_solve``)."""
        return jax.pure_callback(self._solve_host, jax.ShapeDtypeStruct(r.shape, r.dtype), r,
                                 vmap_method="expand_dims")


jax.tree_util.register_pytree_node(HostFactor, lambda h: ((), h), lambda h, _: h)


@jax.custom_jvp
def host_logdet(logdet: jax.Array, *depends_on) -> jax.Array:
    """``logdet`` (a constant from the host factor) with a NaN derivative along everything in ``depends_on``
    (the system's arrays D depends on): ``tr(D^-1 dD)`` is not available here, so a gradient through it is
    NaN, never silently zero."""
    return logdet


@host_logdet.defjvp
def _host_logdet_jvp(primals, tangents):
    logdet, *deps = primals
    _, *dts = tangents
    t = sum(jnp.sum(jnp.zeros_like(d) if isinstance(dt, jax.custom_derivatives.SymbolicZero) else dt)
            for d, dt in zip(deps, dts))
    return logdet, jnp.nan * t * jnp.ones_like(logdet)


@jax.custom_jvp
def logdet_no_grad(L: jax.Array) -> jax.Array:
    """``2 sum log diag L`` (...,) for a lower factor (..., N, N) whose matrix is not kept: its
    derivative (``tr(D^-1 dD)``) cannot be formed here, so any tangent through it is NaN."""
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), axis=-1)


@logdet_no_grad.defjvp
def _logdet_no_grad_jvp(primals, tangents):
    (L,), (dL,) = primals, tangents
    out = logdet_no_grad(L)
    return out, jnp.nan * jnp.sum(dL, axis=(-2, -1))  # linear in dL: NaN in forward and reverse mode


def factor_in_place(system: LinearSystem, G: jax.Array, index: np.ndarray, sqrt_w_rows: np.ndarray,
                    block: int = BLOCK) -> HostFactor:
    """D filled for every channel into one aligned host buffer, the lag blocks dropped, then factorised
    channel by channel in place; the factor (Nf, N_d, N_d) as a :class:`HostFactor` around that buffer.

    ``G`` is consumed: pass it as a temporary (the caller's reference keeps its memory alive).  Raises
    ``ValueError`` naming the channel if D is not positive definite (it is ``I +`` a PSD matrix, so only
    non-finite or negative inputs do that).
    """
    check_float64(system.op.response, system.inv_noise)
    nf = G.shape[1]
    nd = sqrt_w_rows.shape[-1]
    out = aligned_empty((nf, nd, nd))
    Gh = np.asarray(G)
    del G
    for f in range(nf):
        fill_lower(Gh[:, f], index, sqrt_w_rows[f], out[f])
    del Gh
    for f in range(nf):
        try:
            blocked_cholesky(out[f], block)
        except ValueError as err:
            raise ValueError(f"data space, channel {f}: {err}") from None
    return HostFactor(out)
