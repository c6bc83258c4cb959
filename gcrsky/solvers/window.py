"""The window preconditioner: P's data term with a Fejer-tapered time kernel, block-banded in m.

For partial coverage of the day the data term of P couples orders m, m' through the
*window kernel* of each baseline b (DESIGN.md section 12),

    K_b(D) = sum_t w_{t,b} exp(i D theta_t),   D = nu - mu,

(any weights: flags are zero weights).  Writing the visibility of baseline b at angle
theta as ``V_b(theta) = sum_{mu=-L..L} exp(i mu theta) u_{b,mu}`` with
``u_{b,mu} = sum_l gamma_{b,l,mu} at_{l,mu}`` (``at_{l,+-m} = re +- i im`` for m > 0,
``at_{l,0} = x_l0``; ``gamma_{l,m} = (R_re - i R_im) / 2``, ``gamma_{l,-m} =
(R_re + i R_im) / 2``, ``gamma_{l,0} = R_re(l, 0)``, with R_re / R_im the response's
columns of the Re / Im entries of (l, m)), the data term is exactly

    X^T W X = Re(J^H H J),  H_{(mu,l),(nu,l')} = sum_b K_b(nu - mu) conj(gamma_{b,l,mu}) gamma_{b,l',nu},

J the realified -> complex map.  The preconditioner replaces ``K_b(D)`` by
``K_b(D) phi(D)`` with the Fejer taper ``phi(D) = max(0, 1 - |D| / (B + 1))``.  The
Toeplitz matrices of ``K_b`` (a non-negative window) and of ``phi`` (the Fejer kernel,
>= 0) are positive semidefinite, so by the Schur product theorem

    M = Re(J^H H_B J) + S^-1

is symmetric positive definite for every bandwidth B >= 0 and proper prior.  Only
``|D| <= B`` survives, so M couples orders m, m' only for ``|m - m'| <= B`` (the
conjugate terms need ``m + m' <= B``, which implies it): block-banded in m.

Construction (:func:`window_preconditioner`): per order m and offset d = 0..B the
(padded) block of orders (m, m + d) is a weighted Gram of the response columns over
baselines, ``O(Nbl B n lmax)`` flop, never the dense n x n matrix.  The orders are then
grouped into *super-blocks* of G = max(1, min(B, lmax)) consecutive orders (each order
padded to ``nB = 2 lmax`` slots, identity on padding), which makes M block-tridiagonal;
a ``lax.scan`` block Cholesky factorises it and ``M^-1 r`` is a block forward / backward
substitution (:func:`window_solve`).

M <= P does *not* hold (the taper removes positive and negative parts alike), so CG's
usual stop ``sqrt(r^T M^-1 r) <= tol`` would not bound the error.  CG with this
preconditioner stops on ``sqrt(r^T S r)`` instead: ``P >= S^-1`` gives
``r^T P^-1 r <= r^T S r``, a rigorous bound on the error's P-norm
(:func:`gcrsky.solvers.preconditioners.stop_norm`).

Conventions: realified layout of :mod:`gcrsky.sphere.modes`; angles in radians; the
weights are ``system.inv_noise`` (per-component inverse noise variance, 1/Jy^2 if the
data are in Jy), so M has P's units.  Needs ``op.frame is None`` (the band structure
lives in the co-rotating frame of the response).

Measured (``benchmarks/window_pc.py``, 37-antenna hexagon): it helps only at large
coverage fractions.  It beats the prior-only preconditioner from ~8 h of the day (3-9x
at 16-20 h) and is worse than the prior alone below that (2 h: 340 vs 130 iterations at
lmax 16); it beats Nystrom (sketch 128) only where the data inform many more than 128
whitened directions (lmax 32 at 20 h: 222 vs 532; lmax 64 at 16 h: 946 vs 1713), not
at 8 h (lmax 64: 1060 vs 786).
"""

from __future__ import annotations

from functools import lru_cache, partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..model.system import LinearSystem
from ..sphere.modes import lmax_from_nparams, mode_table, order_slots

__all__ = [
    "WINDOW_AUTO_MAX",
    "WINDOW_AUTO_THRESHOLD",
    "WINDOW_TRACED_BANDWIDTH",
    "WindowPreconditioner",
    "auto_bandwidth",
    "fejer_taper",
    "resolve_bandwidth",
    "window_blocks",
    "window_data_matrix",
    "window_flop",
    "window_kernel",
    "window_memory_bytes",
    "window_preconditioner",
    "window_solve",
]

#: :func:`auto_bandwidth`: the kernel's relative size below which lags are dropped.  Small,
#: because the data term dominates the prior by orders of magnitude at useful SNR: in
#: ``benchmarks/window_pc.py`` the iterations fell with B up to 8 at every coverage, also
#: at 16 h where ``|K(D)| / K(0)`` is below 0.1 beyond D = 2 (0.1 chose B = 2: 259
#: iterations against 177 at B = 8, lmax 16).
WINDOW_AUTO_THRESHOLD = 0.01
#: :func:`auto_bandwidth`: the largest bandwidth it returns.
WINDOW_AUTO_MAX = 8
#: Bandwidth used for ``"auto"`` when the weights are traced (unknown values): what the rule
#: gives for any partial coverage.
WINDOW_TRACED_BANDWIDTH = WINDOW_AUTO_MAX


class WindowPreconditioner(NamedTuple):
    """Block Cholesky factor of the block-tridiagonal window matrix M (per frequency).

    With ``nS`` super-blocks of ``N = G nB`` slots (G orders, each padded to
    ``nB = 2 lmax`` slots; ``nB = 1`` at lmax 0):

    Attributes:
        chol: (Nf, nS, N, N) lower Cholesky factors ``L_j`` of the diagonal super-blocks
            of the Schur complements (identity on padding slots).
        low: (Nf, nS-1, N, N) off-diagonal factors ``E_j = C_j L_j^-T``, C_j the block of
            M in rows of super-block j+1 and columns of super-block j.
        idx: (nS, N) realified index held by each slot (0 on padding).
        mask: (nS, N) True on real slots.
        svar: (Nf, n) prior variance ``S`` (diagonal), the weight of CG's rigorous stop
            ``sqrt(r^T S r)`` and the bound ``lambda_max(M^-1) <= max S``.
    """

    chol: jax.Array
    low: jax.Array
    idx: jax.Array
    mask: jax.Array
    svar: jax.Array


# ------------------------------------------------------------------ layout




def _group(lmax: int, bandwidth: int) -> tuple[int, int]:
    """``(Bm, G)``: the band in m (``min(B, lmax)``) and the orders per super-block."""
    bm = min(int(bandwidth), lmax)
    return bm, max(1, bm)


@lru_cache(maxsize=32)
def _super_tables(lmax: int, bandwidth: int):
    """Static gather tables of the super-block assembly (all small: (nS, G, G)).

    Returns ``(slot_idx, slot_mask, diag, off)``: slots (nS, G nB) and for the diagonal
    (nS, G, G) and sub-diagonal (nS-1, G, G) super-blocks the tuples
    ``(order, offset, transpose, valid)``: block (a, c) of super-block j is
    ``Q[order, offset]`` (transposed where ``transpose``), zero where not ``valid``.
    """
    bm, g = _group(lmax, bandwidth)
    ns = -(-(lmax + 1) // g)
    idx, mask = order_slots(lmax)
    nb = idx.shape[1]
    orders = np.arange(ns * g).reshape(ns, g)
    ok = orders <= lmax
    oc = np.minimum(orders, lmax)
    slot_idx = np.where(ok[..., None], idx[oc], 0).reshape(ns, g * nb)
    slot_mask = (ok[..., None] & mask[oc]).reshape(ns, g * nb)
    a, c = np.meshgrid(np.arange(g), np.arange(g), indexing="ij")
    j = np.arange(ns)[:, None, None]
    d_ord = j * g + np.minimum(a, c)
    d_off = np.abs(c - a) + 0 * j
    d_tr = (c < a) + 0 * j
    d_ok = (d_off <= bm) & (j * g + np.maximum(a, c) <= lmax)
    jo = np.arange(ns - 1)[:, None, None]
    o_ord = jo * g + c  # columns: super-block j, rows: j + 1
    o_off = g + a - c + 0 * jo
    o_ok = (o_off <= bm) & ((jo + 1) * g + a <= lmax)
    o_tr = np.ones_like(o_ok)
    cl = lambda o, d: (np.minimum(o, lmax), np.clip(d, 0, bm))  # noqa: E731
    return (slot_idx, slot_mask, (*cl(d_ord, d_off), d_tr.astype(bool), d_ok),
            (*cl(o_ord, o_off), o_tr.astype(bool), o_ok))


# ------------------------------------------------------------------ the kernel


def window_kernel(angles: jax.Array, inv_noise: jax.Array, dmax: int) -> jax.Array:
    """``K_b(D) = sum_t w_{t,b} exp(i D theta_t)`` for D = -dmax..dmax.

    Args:
        angles: (Nt,) rotation angles, radians.
        inv_noise: (Nf, Nt, Nbl) weights (any, >= 0; flags are zeros).
        dmax: the largest lag.

    Returns:
        (Nf, Nbl, 2 dmax + 1) complex; entry ``D + dmax`` holds lag D.
    """
    d = jnp.arange(-dmax, dmax + 1, dtype=angles.dtype)
    ph = jnp.exp(1j * angles[:, None] * d[None, :])  # (Nt, 2dmax+1)
    return jnp.einsum("ftb,td->fbd", inv_noise.astype(angles.dtype), ph)


def fejer_taper(d, bandwidth: int):
    """The Fejer taper ``max(0, 1 - |D| / (B + 1))`` (NumPy or JAX array of lags D)."""
    xp = jnp if isinstance(d, jax.Array) else np
    return xp.clip(1.0 - xp.abs(d) / (bandwidth + 1.0), 0.0, None)


def auto_bandwidth(angles, inv_noise, lmax: int, *, threshold: float = WINDOW_AUTO_THRESHOLD,
                   bmax: int = WINDOW_AUTO_MAX) -> int:
    """The ``"auto"`` bandwidth: the last lag where the window still matters, host-side.

    Rule: with ``k(D) = sum_b K_b(0) |K_b(D)| / K_b(0) / sum_b K_b(0)`` (the baselines'
    relative kernels averaged with their total weight), B is the largest lag
    ``1 <= D <= 2 lmax`` with ``k(D) > threshold``, capped at ``bmax`` (0 if none:
    full uniform coverage, where ``K_b`` is a delta).  A window covering a fraction f of
    the day has ``k(D) ~ |sinc(pi f D)|``, so B grows like 1/(pi f threshold) until the
    cap: with the default threshold 0.01 that is the cap (8) for any partial coverage,
    and less only where the kernel is (nearly) a delta (uniform full-day coverage).
    Concrete arrays only (NumPy).

    Args:
        angles: (Nt,) radians; inv_noise: (Nf, Nt, Nbl) weights; lmax: the band limit.
    """
    th = np.asarray(angles, float)
    w = np.asarray(inv_noise, float)
    d = np.arange(0, 2 * lmax + 1)
    k = np.abs(np.einsum("ftb,td->fbd", w, np.exp(1j * th[:, None] * d[None, :])))  # (Nf, Nbl, D)
    k0 = k[..., :1]
    tot = np.maximum(k0.sum(axis=1), np.finfo(float).tiny)
    rel = (k * (k0 > 0)).sum(axis=1) / tot  # (Nf, D): weighted mean of |K(D)| / K(0)
    big = np.flatnonzero(np.max(rel[:, 1:], axis=0) > threshold)
    return int(min(bmax, big[-1] + 1)) if big.size else 0


def resolve_bandwidth(system: LinearSystem, bandwidth) -> int:
    """An integer bandwidth: ``bandwidth`` itself, or :func:`auto_bandwidth` for ``"auto"``.

    Under a trace (weights unknown) ``"auto"`` is :data:`WINDOW_TRACED_BANDWIDTH`.
    """
    if bandwidth != "auto":
        if isinstance(bandwidth, bool) or not isinstance(bandwidth, (int, np.integer)) or bandwidth < 0:
            raise ValueError(f"bandwidth must be 'auto' or an integer >= 0, got {bandwidth!r}")
        return int(bandwidth)
    lmax = lmax_from_nparams(system.op.response.shape[-1])
    if isinstance(system.inv_noise, jax.core.Tracer) or isinstance(system.op.angles, jax.core.Tracer):
        return WINDOW_TRACED_BANDWIDTH
    return auto_bandwidth(system.op.angles, system.inv_noise, lmax)


# ------------------------------------------------------------------ the banded matrix


def _columns(response: jax.Array, lmax: int) -> jax.Array:
    """The coefficient of each realified entry in ``u_{b,+m}`` and ``u_{b,-m}``, by order.

    Returns (Nf, lmax+1, 2, Nbl, nB) complex: ``[:, m, 0]`` the ``+m`` and ``[:, m, 1]``
    the ``-m`` coefficients of the slots of order m (zero on padding, and for ``-m`` at
    m = 0, which has one term only).
    """
    tab = mode_table(lmax)
    nalm = (lmax + 1) * (lmax + 2) // 2
    k = np.arange(tab.m.size)
    partner = np.where(tab.m == 0, k, np.where(tab.is_imag, k - nalm + lmax + 1, k + nalm - lmax - 1))
    re_col = np.where(tab.is_imag, partner, k)
    im_col = np.where(tab.is_imag, k, partner)
    rre, rim = response[..., re_col], response[..., im_col]  # (Nf, Nbl, n)
    m0 = jnp.asarray(tab.m == 0)
    imag = jnp.asarray(tab.is_imag)
    plus = jnp.where(m0, rre, 0.5 * (rre - 1j * rim)) * jnp.where(imag, 1j, 1.0)
    minus = jnp.where(m0, 0.0, 0.5 * (rre + 1j * rim) * jnp.where(imag, -1j, 1.0))
    idx, mask = order_slots(lmax)
    c = jnp.stack([plus, minus], axis=1)[..., idx] * jnp.asarray(mask)  # (Nf, 2, Nbl, L+1, nB)
    return jnp.moveaxis(c, 3, 1)


@partial(jax.jit, static_argnames=("bandwidth", "taper"))
def window_blocks(system: LinearSystem, bandwidth: int, taper: bool = True) -> jax.Array:
    """The band of the (data part of the) window matrix, order pair by order pair.

    ``Q[f, m, d]`` is the (nB, nB) block of rows of order m and columns of order m + d
    (slots of :func:`order_slots`; zero where m + d > lmax), d = 0..min(B, lmax).
    With ``taper=False`` the kernel is cut at ``|D| <= B`` without the Fejer weights
    (not positive definite in general: for tests, where ``B >= 2 lmax`` gives the exact
    data term of P).  Cost ``~32 Nf Nbl (lmax+1) (B+1) nB^2`` flop; memory
    ``8 Nf (lmax+1) (B+1) nB^2`` bytes.

    Returns:
        (Nf, lmax+1, min(B, lmax)+1, nB, nB) float.
    """
    op = system.op
    if op.frame is not None:
        raise ValueError("the window preconditioner needs op.frame None (the band lives in the response's frame)")
    lmax = lmax_from_nparams(op.response.shape[-1])
    bm, _ = _group(lmax, bandwidth)
    dmax = 2 * lmax + bm
    lags = np.arange(-dmax, dmax + 1)
    keep = np.abs(lags) <= bandwidth
    phi = fejer_taper(lags, bandwidth) if taper else keep.astype(float)
    K = window_kernel(op.angles, system.inv_noise, dmax) * jnp.asarray(phi * keep)  # (Nf, Nbl, 2dmax+1)
    cols = _columns(op.response, lmax)
    cpad = jnp.pad(cols, ((0, 0), (0, bm), (0, 0), (0, 0), (0, 0)))
    sgn = np.array([1, -1])
    dd = np.arange(bm + 1)

    def one(m):
        a = cpad[:, m]  # (Nf, 2, Nbl, nB)
        nb_ = jax.lax.dynamic_slice_in_dim(cpad, m, bm + 1, axis=1)  # (Nf, d, 2, Nbl, nB)
        lag = sgn[None, None, :] * (m + dd[:, None, None]) - sgn[None, :, None] * m  # (d, s, s')
        kmat = K[:, :, lag + dmax]  # (Nf, Nbl, d, s, s')
        z = jnp.einsum("fbdst,fdtbj->fdsbj", kmat, nb_)
        return jnp.einsum("fsbi,fdsbj->fdij", a.real, z.real) + jnp.einsum("fsbi,fdsbj->fdij", a.imag, z.imag)

    q = jnp.moveaxis(jax.lax.map(one, jnp.arange(lmax + 1)), 0, 1)  # (Nf, L+1, d, nB, nB)
    q0 = q[:, :, 0]
    return q.at[:, :, 0].set(0.5 * (q0 + jnp.swapaxes(q0, -1, -2)))  # exactly symmetric diagonal blocks


def window_data_matrix(system: LinearSystem, bandwidth: int, taper: bool = True) -> jax.Array:
    """The dense (Nf, n, n) data part of M (tests and diagnostics only: n^2 memory)."""
    lmax = lmax_from_nparams(system.op.response.shape[-1])
    q = window_blocks(system, bandwidth, taper)
    idx, mask = order_slots(lmax)
    nf, n = q.shape[0], (lmax + 1) ** 2
    out = jnp.zeros((nf, n, n), q.dtype)
    for m in range(lmax + 1):
        for d in range(q.shape[2]):
            if m + d > lmax:
                continue
            r, c = idx[m][mask[m]], idx[m + d][mask[m + d]]
            blk = q[:, m, d][:, mask[m]][:, :, mask[m + d]]
            out = out.at[:, r[:, None], c[None, :]].set(blk)
            out = out.at[:, c[:, None], r[None, :]].set(jnp.swapaxes(blk, 1, 2))
    return out


# ------------------------------------------------------------------ factor and solve


def _assemble(q: jax.Array, sinv: jax.Array, lmax: int, bandwidth: int):
    """Diagonal (Nf, nS, N, N) and sub-diagonal (Nf, nS-1, N, N) super-blocks of M."""
    slot_idx, slot_mask, diag, off = _super_tables(lmax, bandwidth)
    nf, _, _, nb, _ = q.shape

    def gather(tab):
        order, offset, tr, ok = tab
        blk = q[:, order, offset]  # (Nf, nS', G, G, nB, nB)
        blk = jnp.where(tr[..., None, None], jnp.swapaxes(blk, -1, -2), blk) * ok[..., None, None]
        ns_, g = order.shape[0], order.shape[1]
        return jnp.moveaxis(blk, 4, 3).reshape(nf, ns_, g * nb, g * nb)

    dblk = gather(diag)
    fm = jnp.asarray(slot_mask, q.dtype)
    dvals = sinv[:, slot_idx] * fm + (1.0 - fm)  # prior on real slots, identity on padding
    dblk = dblk + jax.vmap(jax.vmap(jnp.diag))(dvals)
    return dblk, gather(off)


def _block_cholesky(dblk: jax.Array, cblk: jax.Array):
    """Block Cholesky of a block-tridiagonal SPD matrix (one frequency), by ``lax.scan``.

    Args:
        dblk: (nS, N, N) diagonal blocks; cblk: (nS-1, N, N) blocks (j+1, j).

    Returns:
        ``(L, E)``: (nS, N, N) lower factors, (nS-1, N, N) ``E_j = C_j L_j^-T``.
    """
    tri = jax.scipy.linalg.solve_triangular
    l0 = jnp.linalg.cholesky(dblk[0])

    def step(lprev, dc):
        d, c = dc
        e = tri(lprev, c.T, lower=True).T
        lj = jnp.linalg.cholesky(d - e @ e.T)
        return lj, (lj, e)

    _, (ls, es) = jax.lax.scan(step, l0, (dblk[1:], cblk))
    return jnp.concatenate([l0[None], ls], axis=0), es


@partial(jax.jit, static_argnames=("bandwidth",))
def window_preconditioner(system: LinearSystem, bandwidth: int) -> WindowPreconditioner:
    """Build the window preconditioner of bandwidth B (an integer >= 0; resolve ``"auto"`` first).

    Needs a proper prior (``S^-1 > 0``) and ``op.frame is None``.  Cost
    :func:`window_flop`, memory :func:`window_memory_bytes`.
    """
    lmax = lmax_from_nparams(system.op.response.shape[-1])
    q = window_blocks(system, bandwidth, True)
    dblk, cblk = _assemble(q, system.prior.inv_var, lmax, bandwidth)
    ls, es = jax.vmap(_block_cholesky)(dblk, cblk)
    slot_idx, slot_mask, _, _ = _super_tables(lmax, bandwidth)
    return WindowPreconditioner(ls, es, jnp.asarray(slot_idx), jnp.asarray(slot_mask), 1.0 / system.prior.inv_var)


def window_solve(pc: WindowPreconditioner, f, r: jax.Array) -> jax.Array:
    """``M_f^-1 r`` for r (n,): block forward then backward substitution (two scans)."""
    tri = jax.scipy.linalg.solve_triangular
    L, E = pc.chol[f], pc.low[f]
    g = jnp.where(pc.mask, r[pc.idx], 0.0).astype(L.dtype)  # (nS, N)
    z0 = tri(L[0], g[0], lower=True)

    def fwd(zprev, x):
        lj, e, gj = x
        z = tri(lj, gj - e @ zprev, lower=True)
        return z, z

    _, zs = jax.lax.scan(fwd, z0, (L[1:], E, g[1:]))
    z = jnp.concatenate([z0[None], zs], axis=0)
    ylast = tri(L[-1], z[-1], lower=True, trans="T")

    def bwd(ynext, x):
        lj, e, zj = x
        y = tri(lj, zj - e.T @ ynext, lower=True, trans="T")
        return y, y

    _, ys = jax.lax.scan(bwd, ylast, (L[:-1], E, z[:-1]), reverse=True)
    y = jnp.concatenate([ys, ylast[None]], axis=0)
    return jnp.zeros(r.shape, y.dtype).at[pc.idx].add(jnp.where(pc.mask, y, 0.0))


# ------------------------------------------------------------------ estimates


def _sizes(lmax: int, bandwidth: int):
    bm, g = _group(lmax, bandwidth)
    ns = -(-(lmax + 1) // g)
    nb = order_slots(lmax)[0].shape[1]
    return bm, g, ns, nb, g * nb


def window_memory_bytes(lmax: int, bandwidth: int, nbl: int, nf: int = 1) -> dict:
    """Bytes of the window preconditioner (float64), by part.

    Returns a dict: ``"factor"`` the stored ``L`` and ``E`` (``8 Nf (2 nS - 1) N^2``),
    ``"band"`` the order-pair blocks Q (``8 Nf (lmax+1)(Bm+1) nB^2``), ``"assembly"``
    the super-blocks before factorisation (as ``"factor"``), ``"columns"`` the response
    columns by order (``32 Nf (lmax+1) Nbl nB``), and ``"peak"`` their sum (an upper
    bound on the build's live arrays).
    """
    bm, _, ns, nb, n_sb = _sizes(lmax, bandwidth)
    factor = 8.0 * nf * (2 * ns - 1) * n_sb**2
    band = 8.0 * nf * (lmax + 1) * (bm + 1) * nb**2
    cols = 32.0 * nf * (lmax + 1) * nbl * nb
    return {"factor": factor, "band": band, "assembly": factor, "columns": cols,
            "peak": 2 * factor + band + cols}


def window_flop(lmax: int, bandwidth: int, nbl: int, nf: int = 1) -> dict:
    """Floating-point operations of the window preconditioner, by part.

    Returns a dict: ``"band"`` the weighted Grams (``16 Nf Nbl (lmax+1)(Bm+1) nB^2``:
    two real products over 2 Nbl per block), ``"factor"`` the block Cholesky
    (``~(7/3) Nf nS N^3``), ``"apply"`` one ``M^-1 r`` (``~6 Nf nS N^2``).
    """
    bm, _, ns, nb, n_sb = _sizes(lmax, bandwidth)
    return {"band": 16.0 * nf * nbl * (lmax + 1) * (bm + 1) * nb**2,
            "factor": nf * ns * (7.0 / 3.0) * n_sb**3,
            "apply": 6.0 * nf * ns * n_sb**2}
