"""The m-mode exact path: block-by-block solves for uniform full-day coverage (DESIGN §4).

When every time sees the same noise and the rotation angles cover the day evenly,
the precision ``P`` is block-diagonal in the azimuthal order m.  This module checks
that structure cheaply, builds the m-blocks straight from the response (never
forming the dense ``n x n`` P) and solves / samples exactly block by block.

Derivation.  With time-constant noise ``W`` (per frequency, baseline) and the
realified rotation ``Q(t)`` (a 2x2 rotation by ``m t`` of each ``(Re a_lm, Im a_lm)``
pair; ``X_t = R Q(t)``), the data part of P is ``sum_t Q(t)^T A Q(t)`` with
``A = Re(R^H W R)``.  Write the 2x2 sub-block of A between orders m, m' as
``B = (aI + bJ) + (cK + dL)`` (J the 90-degree rotation; K, L the reflections):
``Q_m^T (aI + bJ) Q_m' = (aI + bJ) Q_{m'-m}`` and ``Q_m^T (cK + dL) Q_m' = (cK + dL) Q_{m+m'}``.
If ``sum_t exp(i k t) = 0`` for ``k = 1..2 lmax`` (equally spaced angles over 2 pi with
``Nt > 2 lmax``, any offset, any repetition) every term with ``m != m'`` and the
reflection part within ``m = m' > 0`` averages to zero, leaving

    P_m = Nt [[C, -D], [D, C]] + S_m^-1,
    C = (A_rr + A_ii) / 2,  D = (A_ir - A_ri) / 2   (m > 0);   P_0 = Nt A_rr + S_0^-1,

where ``A_rr = Re(R_re^H W R_re)``, ``A_ir = Re(R_im^H W R_re)`` etc. use only the
columns of R with order m.  Building all blocks costs ``O(Nf Nbl lmax^3)`` instead of
``O(Nf Nt Nbl lmax^4)`` for the dense P; factorising them ``O(Nf lmax^4)`` instead of
``O(Nf lmax^6)``.

Differentiation.  The Wiener filter differentiates implicitly against the true
(matrix-free) P (``jax.lax.custom_linear_solve``): its derivative is that of the true
posterior mean along any change of the system.  The draws and the evidence
differentiate natively through the block factors, which see the noise only through
its sum over times: exact along changes that keep the noise stationary (a noise scale,
any prior or response change), and the m-mode path does not apply anyway once the
noise varies in time.

Block layout (:func:`mmode_buckets`): block m has ``s_m`` real rows, ``lmax+1`` at m = 0
(``Re a_l0``) and ``2 (lmax-m+1)`` for m > 0 (``Re``, then ``Im a_lm``, l = m..lmax): all
blocks together hold ``~(4/3) lmax^3`` entries (2.9 GB at lmax 650).  Consecutive orders
whose half-size rounds up to the same multiple of ``MModeOptions.bucket`` (at most lmax+1)
form a bucket, one array (Nf, G, 2H, 2H): the blocks are padded only to their bucket's
size, with identity rows and columns (decoupled), so one batched Cholesky factorises a
bucket, and the shapes (one compile each) are as many as the buckets (21 at lmax 650 with
the default 32, padding 7.5 % of the entries).  Each bucket is built from its own columns
of R (never the whole padded response) and factorised before the next is built
(:func:`mmode_factor`); the draws and solves go bucket by bucket.  Memory and its estimate
before anything is built: :func:`mmode_memory`; measured in ``benchmarks/mmode_scale.py``.
"""

from __future__ import annotations

import functools
import itertools
from functools import lru_cache, partial
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import check_float64
from ..base.memory import format_bytes
from ..model.operator import MFACTOR_MIN_TIMES, MFACTOR_MIN_WORK, adjoint, n_in, uses_mfactor
from ..model.system import LinearSystem, data_apply, precision_apply, wiener_rhs
from ..sphere.modes import lmax_from_nparams, n_alm
from .info import DrawInfo, SolveInfo, direct_info, exact_info
from .options import MModeOptions
from .path import EvidenceParts, SolverPath, has_flat_prior, is_traced, quadratic_from_state

__all__ = [
    "PRODUCT_BYTES_PER_TIME_MODE",
    "PRODUCT_CHUNK_BYTES",
    "MModeBlocks",
    "MModeBuckets",
    "MModeCheck",
    "MModeMemory",
    "MModePath",
    "MModeState",
    "block_solve",
    "blocks_to_dense",
    "draw_mmode",
    "is_mmode_diagonal",
    "mmode_blocks",
    "mmode_buckets",
    "mmode_check",
    "mmode_factor",
    "mmode_memory",
    "mmode_wiener_and_draws",
    "prepare_mmode",
    "product_time_chunk",
]


# ---------------------------------------------------------------- structural check


class MModeCheck(NamedTuple):
    """Result of :func:`mmode_check`: ``ok`` and, when not, the ``reason`` (else "")."""

    ok: bool
    reason: str

    def __bool__(self) -> bool:  # so ``if mmode_check(s):`` reads naturally
        return bool(self.ok)


def mmode_check(system: LinearSystem, *, atol: float = MModeOptions.atol, rtol: float = MModeOptions.rtol) -> MModeCheck:
    """Cheap structural test that P is exactly block-diagonal in m (host-side, O(Nt lmax + data size)).

    Conditions (sufficient, and the ones the derivation uses):

    * no frame map (``op.frame is None``): a frame map mixes m;
    * ``|sum_t exp(i k t)| <= atol * Nt`` for every ``k = 1 .. 2 lmax``: true for
      ``Nt > 2 lmax`` equally spaced angles covering exactly 2 pi (any offset, any
      equal repetition), false for partial coverage or aliasing ``Nt <= 2 lmax``;
    * inverse noise constant in time for each (frequency, baseline) to ``rtol`` of its
      maximum (flags, i.e. zero weights at some times, break it).

    Needs concrete arrays (call outside ``jit``).
    """
    op = system.op
    if op.frame is not None:
        return MModeCheck(False, "a frame map is set (op.frame is not None): it couples different m")
    n = n_in(op)
    lmax = lmax_from_nparams(n)
    angles = np.asarray(op.angles, np.float64)
    if angles.ndim != 1 or angles.size == 0:
        return MModeCheck(False, f"angles must be a non-empty 1-d array, got shape {angles.shape}")
    nt = angles.size
    if lmax > 0:
        k = np.arange(1, 2 * lmax + 1)
        s = np.abs(np.exp(1j * np.outer(k, angles)).sum(axis=1)) / nt
        worst = int(np.argmax(s))
        if s[worst] > atol:
            hint = f" (Nt = {nt} <= 2 lmax = {2 * lmax})" if nt <= 2 * lmax else ""
            return MModeCheck(
                False,
                "coverage is not uniform over the full day: |mean_t exp(i k t)| = "
                f"{s[worst]:.2e} at k = {k[worst]} > {atol:g}{hint}; need Nt > 2 lmax equally "
                "spaced angles covering 2 pi",
            )
    w = np.asarray(system.inv_noise)
    if w.ndim != 3 or w.shape[1] != nt:
        return MModeCheck(False, f"inv_noise has shape {w.shape}, expected (Nf, {nt}, Nbl)")
    scale = np.max(np.abs(w)) if w.size else 0.0
    dev = np.max(np.abs(w - w[:, :1, :])) if w.size else 0.0
    if dev > rtol * scale:
        return MModeCheck(
            False,
            f"inverse noise varies in time (max |w_t - w_0| = {dev:.2e} of max {scale:.2e}; "
            "flagged samples count as time-varying noise)",
        )
    return MModeCheck(True, "")


def is_mmode_diagonal(system: LinearSystem, **kw) -> bool:
    """``True`` if :func:`mmode_check` passes (P exactly block-diagonal in m)."""
    return mmode_check(system, **kw).ok


# ---------------------------------------------------------------- layout


class MModeBuckets(NamedTuple):
    """The bucketed block layout for ``lmax`` and a padding quantum ``q`` (module docstring).

    Order m's block has ``s_m`` real rows: ``lmax+1`` at m = 0 (``Re a_l0``), ``2 K_m`` for
    m > 0 (``Re`` then ``Im a_lm``, l = m..lmax, ``K_m = lmax+1-m``).  Its padded half-size is
    ``H_m = min(q ceil(K_m / q), lmax+1)`` (``K_0 = lmax+1``); consecutive orders sharing ``H``
    form one bucket, an array (Nf, G, 2H, 2H).  In a block, position ``p < H`` holds
    ``Re a_{l=m+p, m}`` and ``p >= H`` holds ``Im a_{l=m+p-H, m}``; entries with ``l > lmax``
    and the Im half of m = 0 are padding (identity rows and columns, decoupled).

    Attributes:
        lmax, quantum: what the layout was made for.
        orders: per bucket ``(m_first, m_end)`` (m_end exclusive).
        gather: per bucket (G, 2H) int64, the realified index of each entry (0 on padding).
        mask: per bucket (G, 2H) bool, True on real entries.
        scale: per bucket (G,) float64: 1 at m = 0, else 1/2 (the day average of a rotated pair).
        src: per bucket (n_b,) flat positions (in ``G * 2H``) of its real entries.
        dst: per bucket (n_b,) their realified indices (all buckets together: a permutation of n).
    """

    lmax: int
    quantum: int
    orders: tuple
    gather: tuple
    mask: tuple
    scale: tuple
    src: tuple
    dst: tuple

    @property
    def shapes(self) -> tuple:
        """``(G, 2H)`` per bucket: one compiled build, factor and solve per distinct shape."""
        return tuple(g.shape for g in self.gather)

    @property
    def padded_entries(self) -> int:
        """``sum_b G_b (2 H_b)^2``: the entries of all blocks as stored (per channel)."""
        return int(sum(g * s * s for g, s in self.shapes))

    @property
    def real_entries(self) -> int:
        """``sum_m s_m^2``: the entries of all blocks without padding (per channel)."""
        M = self.lmax + 1
        return M * M + sum(4 * k * k for k in range(1, M))

    @property
    def waste(self) -> float:
        """Fraction of the stored entries that are padding, relative to the real ones."""
        return self.padded_entries / self.real_entries - 1.0


@lru_cache(maxsize=32)
def mmode_buckets(lmax: int, quantum: int = MModeOptions.bucket) -> MModeBuckets:
    """The bucketed block layout for ``lmax`` (see :class:`MModeBuckets`); host-side, cached."""
    M, nalm = lmax + 1, n_alm(lmax)
    K = np.array([M] + [M - m for m in range(1, M)])
    H = np.minimum(quantum * -(-K // quantum), M)
    edges = [0] + [m for m in range(1, M) if H[m] != H[m - 1]] + [M]
    out = {k: [] for k in ("orders", "gather", "mask", "scale", "src", "dst")}
    for m0, m1 in itertools.pairwise(edges):
        h = int(H[m0])
        gather = np.zeros((m1 - m0, 2 * h), np.int64)
        mask = np.zeros((m1 - m0, 2 * h), bool)
        for g, m in enumerate(range(m0, m1)):
            ls = np.arange(m, M)
            base = m * (2 * lmax + 1 - m) // 2  # healpy index of a_{l=m, m} minus m
            gather[g, ls - m], mask[g, ls - m] = base + ls, True
            if m > 0:
                gather[g, h + ls - m], mask[g, h + ls - m] = nalm + base + ls - M, True
        src = np.flatnonzero(mask.ravel())
        for k, v in zip(out, ((m0, m1), gather, mask, np.where(np.arange(m0, m1) == 0, 1.0, 0.5), src,
                              gather.ravel()[src])):
            out[k].append(v)
    assert np.array_equal(np.sort(np.concatenate(out["dst"])), np.arange(M * M))
    return MModeBuckets(lmax, quantum, *(tuple(v) for v in out.values()))


def to_buckets(x: jax.Array, lay: MModeBuckets) -> tuple:
    """(..., n) -> per bucket (..., G, 2H), zeros on padding."""
    return tuple(jnp.where(mk, x[..., g], 0) for g, mk in zip(lay.gather, lay.mask))


def from_buckets(ys, lay: MModeBuckets, out: jax.Array) -> jax.Array:
    """Per bucket (..., G, 2H) -> their real entries added into ``out`` (..., n)."""
    for y, src, dst in zip(ys, lay.src, lay.dst):
        out = out.at[..., dst].add(y.reshape(y.shape[:-2] + (-1,))[..., src])
    return out


# ---------------------------------------------------------------- blocks


class MModeBlocks(eqx.Module):
    """The m-blocks of P (or their lower Cholesky factors), bucket by bucket (:class:`MModeBuckets`).

    Attributes:
        arrays: per bucket (Nf, G, 2H, 2H) float64, identity on padding.
        lmax: the band limit (static).
        quantum: the layout's padding quantum (static).
    """

    arrays: tuple
    lmax: int = eqx.field(static=True)
    quantum: int = eqx.field(static=True)

    @property
    def layout(self) -> MModeBuckets:
        return mmode_buckets(self.lmax, self.quantum)

    @property
    def nbytes(self) -> int:
        """Bytes of all buckets together."""
        return int(sum(np.prod(a.shape) * a.dtype.itemsize for a in self.arrays))


def _bucket_blocks(R, w, inv_var, gather, mask, scale):
    """One bucket's blocks (Nf, G, S, S) from R (Nf, Nbl, n), ``w = Nt W`` (Nf, Nbl), ``S^-1`` (Nf, n).

    Gathers only this bucket's columns of R ((Nf, Nbl, G, S) complex; ``O(Nf Nbl G S)`` memory)
    and forms ``A = Re(R_m^H W R_m)`` per order, then ``Nt [[C, -D], [D, C]] + S_m^-1``.
    """
    S = gather.shape[1]
    H = S // 2
    X = jnp.where(mask, R[..., gather], 0)  # (Nf, Nbl, G, S) complex, zeros on padding
    Xr, Xi = X.real, X.imag
    wb = w[:, :, None, None]
    A = jnp.einsum("fbgi,fbgj->fgij", Xr, wb * Xr) + jnp.einsum("fbgi,fbgj->fgij", Xi, wb * Xi)
    a_rr, a_ii, a_ir = A[..., :H, :H], A[..., H:, H:], A[..., H:, :H]
    C = scale[None, :, None, None] * (a_rr + a_ii)  # a_ii = 0 at m = 0
    D = 0.5 * (a_ir - jnp.swapaxes(a_ir, -1, -2))
    P = jnp.concatenate([jnp.concatenate([C, -D], axis=-1), jnp.concatenate([D, C], axis=-1)], axis=-2)
    P = jnp.where(mask[:, :, None] & mask[:, None, :], P, 0.0)  # m = 0: drop the copy of C in the Im half
    diag = jnp.where(mask, inv_var[..., gather], 1.0)  # identity on padding
    return P + diag[..., :, None] * jnp.eye(S, dtype=P.dtype)


_bucket_blocks_jit = jax.jit(_bucket_blocks)
bucket_factor_jit = jax.jit(lambda *args: jnp.linalg.cholesky(_bucket_blocks(*args)))


def _per_bucket(fn, system: LinearSystem, quantum: int) -> MModeBlocks:
    """``fn`` (blocks or their factors) on every bucket in turn: one bucket's transients at a time."""
    op = system.op
    if op.frame is not None:
        raise ValueError("the m-blocks need op.frame is None (a frame map couples m)")
    R = op.response  # (Nf, Nbl, n)
    lmax = lmax_from_nparams(R.shape[2])
    lay = mmode_buckets(lmax, quantum)
    w = jnp.sum(system.inv_noise, axis=1)  # (Nf, Nbl): Nt w for time-constant noise
    arrays = tuple(fn(R, w, system.prior.inv_var, jnp.asarray(g), jnp.asarray(mk), jnp.asarray(sc))
                   for g, mk, sc in zip(lay.gather, lay.mask, lay.scale))
    return MModeBlocks(arrays, lmax, quantum)


def mmode_blocks(system: LinearSystem, bucket: int = MModeOptions.bucket) -> MModeBlocks:
    """The m-blocks of P by buckets (:class:`MModeBlocks`, :func:`mmode_buckets`), identity on padding.

    Exact (equal to the dense :func:`gcrsky.model.system.precision_matrix` restricted to each m)
    only when :func:`mmode_check` passes; the time-constant noise enters as its sum over
    times (``Nt w``), so a derivative along a noise change that keeps it stationary
    (e.g. a noise scale) is exact.  Cost ``O(Nf Nbl lmax^3)``; never forms the dense P nor
    the whole padded response (each bucket gathers its own columns of R).
    """
    return _per_bucket(_bucket_blocks_jit, system, bucket)


def mmode_factor(system: LinearSystem, bucket: int = MModeOptions.bucket) -> MModeBlocks:
    """The lower Cholesky factors of :func:`mmode_blocks`, built and factorised bucket by bucket
    (each bucket's unfactorised blocks are freed once factorised)."""
    return _per_bucket(bucket_factor_jit, system, bucket)


def blocks_to_dense(blocks: MModeBlocks) -> np.ndarray:
    """Assemble the buckets' blocks into the dense (Nf, n, n) realified matrix (tests)."""
    lay = blocks.layout
    M = blocks.lmax + 1
    arrays = [np.asarray(a) for a in blocks.arrays]
    out = np.zeros((arrays[0].shape[0], M * M, M * M), arrays[0].dtype)
    for a, gather, mask in zip(arrays, lay.gather, lay.mask):
        for g in range(gather.shape[0]):
            sel = np.flatnonzero(mask[g])
            idx = gather[g, sel]
            out[:, idx[:, None], idx[None, :]] = a[:, g][:, sel[:, None], sel[None, :]]
    return out


# ---------------------------------------------------------------- solve and sample


class MModeState(eqx.Module):
    """Factorised m-blocks and the Wiener filter: the m-mode path set up for many draws.

    Attributes:
        system: the linear system.
        a_wf: (Nf, n) Wiener filter.
        wiener: SolveInfo (Nf,) of the Wiener solve; ``err_sigma`` uses the *true*
            residual ``b - P a_wf`` (matrix-free P), so it also exposes any off-block
            part the structural check missed.
        chol: :class:`MModeBlocks` of the lower Cholesky factors, per bucket (Nf, G, 2H, 2H).
        options: the :class:`MModeOptions` (static).
    """

    system: LinearSystem
    a_wf: jax.Array
    wiener: SolveInfo
    chol: MModeBlocks
    options: MModeOptions = eqx.field(static=True, default=MModeOptions())

    method: ClassVar[str] = "mmode"


def tri_solve(L, b, trans: bool):
    """Batched ``L^-1 b`` (``L^-T b`` if ``trans``): L (..., S, S) lower, b (..., S, k).

    One LAPACK ``trsm`` per block (``lax.map`` over the batch): XLA's CPU lowering of a
    *batched* triangular solve is its own blocked expansion, measured 5x slower to run and
    slower to compile (32 blocks of 576, 200 right-hand sides: 1.0 s against 0.19 s).
    """
    batch = L.shape[:-2]
    flat = jax.lax.map(lambda lb: jax.lax.linalg.triangular_solve(lb[0], lb[1], left_side=True, lower=True,
                                                                   transpose_a=trans),
                       (L.reshape((-1,) + L.shape[-2:]), b.reshape((-1,) + b.shape[len(batch):])))
    return flat.reshape(b.shape)


def block_solve(chol: MModeBlocks, b: jax.Array) -> jax.Array:
    """``P^-1 b`` through the factorised m-blocks: b (Nf, n) -> (Nf, n)."""
    ys = tuple(tri_solve(L, tri_solve(L, g[..., None], False), True)[..., 0]
               for L, g in zip(chol.arrays, to_buckets(b, chol.layout)))
    return from_buckets(ys, chol.layout, jnp.zeros_like(b))


def _all_finite(blocks: MModeBlocks) -> jax.Array:
    """(Nf,) True where every bucket's entries are finite."""
    return functools.reduce(jnp.logical_and, [jnp.all(jnp.isfinite(a), axis=(1, 2, 3)) for a in blocks.arrays])


#: Bytes of the matrix-free products (per chunk of times) the Wiener filter may hold at once:
#: the products run over chunks of :func:`product_time_chunk` times (a sum over times, exact).
PRODUCT_CHUNK_BYTES = 2**30


def product_time_chunk(nf: int, nt: int, n: int, budget: float | None = None) -> int:
    """Times per chunk of the Wiener filter's products: ``Nt`` if all fit in ``budget`` bytes
    (default :data:`PRODUCT_CHUNK_BYTES`) at :data:`PRODUCT_BYTES_PER_TIME_MODE` per time and mode."""
    budget = PRODUCT_CHUNK_BYTES if budget is None else budget
    return int(max(1, min(nt, budget // (PRODUCT_BYTES_PER_TIME_MODE * nf * n))))


def _by_time_chunks(system: LinearSystem, fn, chunk: int) -> jax.Array:
    """``sum_c fn(system restricted to chunk c of times)`` (Nf, n), by ``lax.scan`` over chunks.

    Exact for any ``fn`` that is a sum over times (``X^T W d``, ``X^T W X a``): the last chunk
    is padded with zero weight, zero data and angle 0, which add nothing.  ``chunk >= Nt``:
    ``fn(system)`` itself.
    """
    nt = system.op.angles.shape[0]
    if chunk >= nt:
        return fn(system)
    nc = -(-nt // chunk)

    def split(x, axis):  # (..., Nt, ...) -> (nc, ..., chunk, ...), zero-padded
        x = jnp.pad(x, [(0, nc * chunk - nt) if i == axis else (0, 0) for i in range(x.ndim)])
        return jnp.moveaxis(x.reshape(x.shape[:axis] + (nc, chunk) + x.shape[axis + 1:]), axis, 0)

    def body(acc, c):
        ang, d, w = c
        return acc + fn(system._replace(op=system.op._replace(angles=ang), data=d, inv_noise=w)), None

    xs = (split(system.op.angles, 0), split(system.data, 1), split(system.inv_noise, 1))
    return jax.lax.scan(body, jnp.zeros(system.prior.inv_var.shape, system.prior.inv_var.dtype), xs)[0]


def _mmode_wiener(system: LinearSystem, L: MModeBlocks, options: MModeOptions, chunk: int):
    """``a_wf`` through the block factors, with its info from the *true* (matrix-free) residual.

    ``b`` and ``P x`` are the matrix-free :func:`~gcrsky.model.system.wiener_rhs` and
    :func:`~gcrsky.model.system.precision_apply` (``O(Nf Nt Nbl n)`` flop); where ``chunk < Nt``, their
    data parts are summed over chunks of ``chunk`` times (:func:`_by_time_chunks`) so that they
    hold ``O(Nf chunk n)`` memory.
    """
    prior = system.prior
    if chunk >= system.op.angles.shape[0]:
        b, P = wiener_rhs(system), partial(precision_apply, system)
    else:
        b = _by_time_chunks(system, lambda s: adjoint(s.op, s.inv_noise * s.data), chunk) + prior.inv_var * prior.mean
        P = lambda x: _by_time_chunks(system, lambda s: data_apply(s, x), chunk) + prior.inv_var * x
    Lc = jax.lax.stop_gradient(L)
    # Implicit differentiation against the true (matrix-free) P: the derivative is that of
    # the true posterior mean, for any change of the system (the blocks' own derivative
    # would miss what a time-varying noise change adds off the block diagonal).
    solve = lambda mv, rhs: block_solve(Lc, rhs)
    a_wf = jax.lax.custom_linear_solve(P, b, solve, symmetric=True)
    r = jax.lax.stop_gradient(b - P(a_wf))
    err = jnp.sqrt(jnp.abs(jnp.sum(r * block_solve(Lc, r), axis=-1)))
    rel = jnp.linalg.norm(r, axis=-1) / jnp.linalg.norm(jax.lax.stop_gradient(b), axis=-1)
    info = direct_info(err, rel, _all_finite(Lc), options.tol)
    if options.throw:
        a_wf = eqx.error_if(a_wf, ~info.converged, "gcrsky m-mode: a block is not positive definite, or P is not "
                            "block-diagonal in m (the solve missed MModeOptions.tol against the true P)")
    return a_wf, info


def _chunk_of(system: LinearSystem) -> int:
    """All times at once on the m-factorised products (their memory does not grow with ``Nt n``); else
    :func:`product_time_chunk`."""
    nf, nt, _ = system.data.shape
    if uses_mfactor(system.op):
        return int(nt)
    return product_time_chunk(int(nf), int(nt), int(system.prior.inv_var.shape[1]))


_mmode_wiener_jit = partial(jax.jit, static_argnames=("options", "chunk"))(_mmode_wiener)


def _prepare(system: LinearSystem, options: MModeOptions) -> MModeState:
    L = mmode_factor(system, options.bucket)  # bucket by bucket (one bucket's transients at a time)
    a_wf, info = _mmode_wiener_jit(system, L, options, _chunk_of(system))
    return MModeState(system, a_wf, info, L, options)


@jax.jit
def _condition(state: MModeState, data: jax.Array) -> MModeState:
    system = state.system._replace(data=jnp.asarray(data, state.system.data.dtype))
    a_wf, info = _mmode_wiener(system, state.chol, state.options, _chunk_of(system))
    return MModeState(system, a_wf, info, state.chol, state.options)


def prepare_mmode(system: LinearSystem, options: MModeOptions | None = None, *, check: bool = True) -> MModeState:
    """Build and factorise the m-blocks (bucket by bucket) and solve for the Wiener filter, once.

    Raises ``ValueError`` naming the reason unless :func:`mmode_check` passes with
    ``options``' tolerances.  ``check=False`` skips the check (it needs concrete
    arrays; inside ``jit`` it is skipped anyway).  Either way the Wiener solve is judged
    against the *true* (matrix-free) P: where P is not block-diagonal in m, its error
    exceeds ``options.tol`` and the solve (and every draw) is reported
    :data:`~gcrsky.solvers.Result.INACCURATE` (``options.throw``: an error), never
    converged.  Memory: :func:`mmode_memory`.
    """
    options = MModeOptions() if options is None else options
    if not isinstance(options, MModeOptions):
        raise TypeError(f"the m-mode path takes MModeOptions, got {type(options).__name__}")
    check_float64(system.op.response, system.inv_noise)
    if check and not is_traced(system):
        res = mmode_check(system, atol=options.atol, rtol=options.rtol)
        if not res.ok:
            raise ValueError(f"P is not block-diagonal in m: {res.reason}")
    return _prepare(system, options)


@partial(jax.jit, static_argnames=("ndraws",))
def draw_mmode(key: jax.Array, prepared: MModeState, ndraws: int):
    """``ndraws`` exact posterior draws ``a_wf + L_m^-T z`` bucket by bucket (batched triangular solves).

    The normals are one (Nf, sum_b G_b 2H_b, ndraws) array from ``key``, bucket b taking its
    ``G_b 2H_b`` rows in turn (one random-number program: one per bucket took most of the
    compile); each bucket's solve is added into the output in turn.

    Returns:
        draws (Nf, ndraws, n) in the realified layout; a :class:`~gcrsky.solvers.DrawInfo`
        (``wiener``, ``draws``: SolveInfo (Nf, ndraws), ``a_wf``) as :func:`gcrsky.draw`.
    """
    L, a_wf = prepared.chol, prepared.a_wf
    nf, n = a_wf.shape
    lay = L.layout
    rows = [Lb.shape[1] * Lb.shape[2] for Lb in L.arrays]
    z = jax.random.normal(key, (nf, sum(rows), ndraws), a_wf.dtype)
    out = jnp.broadcast_to(a_wf[:, None, :], (nf, ndraws, n))
    for Lb, start, size, src, dst in zip(L.arrays, np.cumsum([0, *rows]), rows, lay.src, lay.dst):
        zb = jax.lax.slice_in_dim(z, int(start), int(start) + size, axis=1).reshape(Lb.shape[:3] + (ndraws,))
        delta = jnp.moveaxis(tri_solve(Lb, zb, True), -1, 1)  # (Nf, ndraws, G, 2H)
        out = out.at[..., dst].add(delta.reshape(nf, ndraws, -1)[..., src])
    finite = jnp.all(jnp.isfinite(out), axis=-1)
    return out, DrawInfo(prepared.wiener, exact_info(prepared.wiener, finite, (nf, ndraws)), a_wf)


def mmode_wiener_and_draws(key: jax.Array, system: LinearSystem, ndraws: int, options: MModeOptions | None = None):
    """:func:`prepare_mmode` then :func:`draw_mmode`: (draws (Nf, ndraws, n), info)."""
    return draw_mmode(key, prepare_mmode(system, options), ndraws)


# ---------------------------------------------------------------- memory


#: Bytes per time and mode of today's matrix-free products (``wiener_rhs``, ``precision_apply``):
#: measured 6.2 x 8 for one right-hand side over all times (lmax 300, Nt 601, 630 baselines) and
#: 9.9 x 8 for the Wiener step over chunks of 211 times (lmax 300, 165 baselines): the rotated
#: copies (Nf, Nt, n) of :func:`gcrsky.model.operator.apply` / ``adjoint``, their complex casts.
PRODUCT_BYTES_PER_TIME_MODE = 12 * 8


class MModeMemory(NamedTuple):
    """Estimated bytes of the m-mode path beyond the system (:func:`mmode_memory`).

    Attributes:
        factors: the Cholesky factors of all buckets (kept in the state).
        build: the largest bucket's transients while it is built and factorised (its
            columns of R, real and imaginary parts, their weighted copies, the blocks).
        products: the matrix-free products of the Wiener filter and its residual check
            (:data:`PRODUCT_BYTES_PER_TIME_MODE` per time and mode, over chunks of
            :func:`product_time_chunk` times).
        draws: ``ndraws`` draws: the output (Nf, ndraws, n) and its update, all normals, one
            bucket's solve.
    """

    factors: float
    build: float
    products: float
    draws: float

    @property
    def peak(self) -> float:
        """All four summed.  The stages follow one another, but the measured peaks exceed the
        factors plus the largest stage (by 0.8 GB at lmax 400: what the allocator keeps from one
        stage to the next, XLA's own buffers), so they are not assumed to reuse each other's memory."""
        return self.factors + self.build + self.products + self.draws


def mmode_memory(nf: int, nbl: int, nt: int, lmax: int, ndraws: int = 1,
                 bucket: int = MModeOptions.bucket) -> MModeMemory:
    """Estimate the m-mode path's memory (bytes, float64) from sizes alone, before building anything.

    ``system bytes + mmode_memory(...).peak`` bounds the process's peak (``ru_maxrss``, less
    the runtime's own ~0.5 GB) of :func:`prepare_mmode` plus :func:`draw_mmode`
    (``benchmarks/mmode_scale.py`` measures both).
    """
    lay = mmode_buckets(lmax, bucket)
    n = (lmax + 1) ** 2
    factors = 8.0 * nf * lay.padded_entries
    build = max(8.0 * nf * (8 * nbl * g * s + 5 * g * s * s) for g, s in lay.shapes)
    if nt >= MFACTOR_MIN_TIMES and nt * nbl * n >= MFACTOR_MIN_WORK:  # m-factorised products (all times at once):
        # one order's window of R (complex, and its cotangent), U and W per order, the visibilities, a few vectors
        products = 8.0 * nf * (8 * nbl * (lmax + 1) + 8 * nbl * (lmax + 1) + 4 * nt * nbl + 6 * n)
    else:
        products = float(PRODUCT_BYTES_PER_TIME_MODE) * nf * product_time_chunk(nf, nt, n) * n
    gs = max(g * s for g, s in lay.shapes)
    draws = 8.0 * nf * max(1, ndraws) * (2 * n + sum(g * s for g, s in lay.shapes) + 3 * gs)
    return MModeMemory(factors, build, products, draws)


# ---------------------------------------------------------------- the path


def _mmode_evidence(state: MModeState, terms) -> EvidenceParts:
    # padding rows are identity: log 1 = 0
    logdet_p = sum(jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), axis=(1, 2)) for L in state.chol.arrays)
    logdet = 2.0 * logdet_p - jnp.sum(jnp.log(state.system.prior.inv_var), axis=1)
    chi2 = terms["rWr"] - quadratic_from_state(state, terms["b_res"])
    return EvidenceParts(chi2, logdet, jnp.zeros(logdet.shape), state.wiener)


class MModePath(SolverPath):
    """Block-by-block exact solves for uniform full-day coverage (:func:`prepare_mmode`)."""

    name = "mmode"
    options_type = MModeOptions
    state_type = MModeState

    def check(self, system, options):
        return mmode_check(system, atol=options.atol, rtol=options.rtol).reason

    def resolve(self, system, options):
        if not is_traced(system):
            why = self.check(system, options)
            if why:
                raise ValueError(f"method='mmode' needs P block-diagonal in m, but {why}; use method='auto'")
        return options

    def memory_bytes(self, system, options, ndraws=1):
        """:func:`mmode_memory`'s peak: the factors, the build, the products and the draws."""
        nf, nt, nbl = (int(x) for x in system.data.shape)
        lmax = lmax_from_nparams(n_in(system.op))
        return mmode_memory(nf, nbl, nt, lmax, ndraws, options.bucket).peak

    def cost_flop(self, system, options, ndraws):
        """Blocks (``4 Nbl S^2`` per order), factors (``S^3 / 3``), draws (``S^2`` per order and draw),
        ``S = 2H`` each bucket's padded size; the matrix-free products of the Wiener filter are
        left out, as in the other direct paths."""
        nf, _, nbl = (int(x) for x in system.data.shape)
        lay = mmode_buckets(lmax_from_nparams(n_in(system.op)), options.bucket)
        return float(nf * sum(g * (4.0 * nbl * s * s + s**3 / 3.0 + ndraws * s * s) for g, s in lay.shapes))

    def auto_limits(self, system, options, budget, ndraws):
        if has_flat_prior(system):
            return "a flat prior direction: blocks may be singular"
        mem = self.memory_bytes(system, options, ndraws)
        return "" if mem <= budget else f"its blocks need {format_bytes(mem)}, more than {format_bytes(budget)}"

    def describe(self, system, options, memory):
        return "uniform full-day coverage, stationary noise: P is block-diagonal in m"

    def prepare(self, system, options):
        return prepare_mmode(system, options)

    def draw(self, key, state, ndraws):
        return draw_mmode(key, state, ndraws)

    def condition(self, state, data):
        return _condition(state, data)

    def evidence_parts(self, system, options, terms, *, slq=None, key=None):
        return _mmode_evidence(prepare_mmode(system, options), terms)

    def state_evidence_parts(self, state, terms, *, slq=None, key=None):
        return _mmode_evidence(state, terms)
