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

Block layout: block m has size ``B = 2 (lmax+1)``; position ``p < lmax+1`` holds
``Re a_{l=p, m}``, ``p >= lmax+1`` holds ``Im a_{l=p-lmax-1, m}``.  Entries with
``l < m`` and the Im half of ``m = 0`` are padding: identity rows/columns, decoupled,
so one batched Cholesky factorises every block.
"""

from __future__ import annotations

from functools import lru_cache, partial
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import check_float64
from ..base.memory import format_bytes
from ..model.operator import n_in
from ..model.system import LinearSystem, precision_apply, wiener_rhs
from ..sphere.modes import lmax_from_nparams, mode_table, n_alm
from .info import DrawInfo, SolveInfo, direct_info, exact_info
from .options import MModeOptions
from .path import EvidenceParts, SolverPath, has_flat_prior, is_traced, quadratic_from_state

__all__ = [
    "MModeCheck",
    "MModeLayout",
    "MModePath",
    "MModeState",
    "block_solve",
    "blocks_to_dense",
    "draw_mmode",
    "is_mmode_diagonal",
    "mmode_blocks",
    "mmode_check",
    "mmode_layout",
    "mmode_wiener_and_draws",
    "prepare_mmode",
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


class MModeLayout(NamedTuple):
    """Index tables between the realified vector (n) and padded m-blocks (M = lmax+1, B = 2M).

    Attributes:
        gather: (M, B) realified index of each block entry (0 on padding).
        mask: (M, B) True on real entries.
        scatter: (n,) flat index ``m * B + p`` of every realified entry.
    """

    gather: np.ndarray
    mask: np.ndarray
    scatter: np.ndarray


@lru_cache(maxsize=32)
def mmode_layout(lmax: int) -> MModeLayout:
    """The block layout for ``lmax`` (see module docstring)."""
    tab = mode_table(lmax)
    M = lmax + 1
    B = 2 * M
    n = tab.m.size
    pos = np.where(tab.is_imag, M + tab.ell, tab.ell)
    scatter = tab.m * B + pos
    gather = np.zeros(M * B, np.int64)
    mask = np.zeros(M * B, bool)
    gather[scatter] = np.arange(n)
    mask[scatter] = True
    assert n_alm(lmax) + lmax * (lmax + 1) // 2 == n and mask.sum() == n
    return MModeLayout(gather.reshape(M, B), mask.reshape(M, B), scatter)


def _gather(x: jax.Array, lay: MModeLayout) -> jax.Array:
    """(..., n) -> (..., M, B) with zeros on padding."""
    return jnp.where(jnp.asarray(lay.mask), x[..., jnp.asarray(lay.gather)], 0)


def _scatter(y: jax.Array, lay: MModeLayout) -> jax.Array:
    """(..., M, B) -> (..., n)."""
    return y.reshape(y.shape[:-2] + (-1,))[..., jnp.asarray(lay.scatter)]


# ---------------------------------------------------------------- blocks


@jax.jit
def mmode_blocks(system: LinearSystem) -> jax.Array:
    """The m-blocks of P, (Nf, lmax+1, 2(lmax+1), 2(lmax+1)), identity on padding.

    Exact (equal to the dense :func:`gcrsky.model.precision_matrix` restricted to each m)
    only when :func:`mmode_check` passes; the time-constant noise enters as its sum over
    times (``Nt w``), so a derivative along a noise change that keeps it stationary
    (e.g. a noise scale) is exact.  Cost ``O(Nf Nbl lmax^3)``; never forms the dense P.
    """
    op = system.op
    if op.frame is not None:
        raise ValueError("mmode_blocks needs op.frame is None (a frame map couples m)")
    R = op.response  # (Nf, Nbl, n)
    n = R.shape[2]
    lmax = lmax_from_nparams(n)
    lay = mmode_layout(lmax)
    M = lmax + 1
    w = jnp.sum(system.inv_noise, axis=1)  # (Nf, Nbl): Nt w for time-constant noise
    G = _gather(R, lay)  # (Nf, Nbl, M, B) complex, zeros on padding
    Rre, Rim = G[..., :M], G[..., M:]

    def gram(X, Y):  # Re(X^H W Y) per m: (Nf, M, M[l], M[l'])
        return jnp.einsum("fbmi,fb,fbmj->fmij", jnp.conj(X), w, Y).real

    a_rr, a_ii, a_ir = gram(Rre, Rre), gram(Rim, Rim), gram(Rim, Rre)
    half = jnp.where(jnp.arange(M) == 0, 1.0, 0.5)[None, :, None, None]  # m = 0: no averaging
    C = half * (a_rr + a_ii)  # a_ii = 0 at m = 0
    D = 0.5 * (a_ir - jnp.swapaxes(a_ir, -1, -2))
    P = jnp.concatenate(
        [jnp.concatenate([C, -D], axis=-1), jnp.concatenate([D, C], axis=-1)], axis=-2
    )  # (Nf, M, B, B)
    mask = jnp.asarray(lay.mask)
    P = jnp.where(mask[:, :, None] & mask[:, None, :], P, 0.0)  # m = 0: drop the copy of C in the Im half
    diag = jnp.where(mask, _gather(system.prior.inv_var, lay), 1.0)  # identity on padding
    return P + diag[..., :, None] * jnp.eye(2 * M, dtype=P.dtype)


def blocks_to_dense(blocks: jax.Array) -> np.ndarray:
    """Assemble m-blocks (Nf, M, B, B) into the dense (Nf, n, n) realified matrix (tests)."""
    blocks = np.asarray(blocks)
    nf, M = blocks.shape[:2]
    lay = mmode_layout(M - 1)
    n = M * M
    out = np.zeros((nf, n, n), blocks.dtype)
    for m in range(M):
        sel = np.flatnonzero(lay.mask[m])
        idx = lay.gather[m, sel]
        out[:, idx[:, None], idx[None, :]] = blocks[:, m][:, sel[:, None], sel[None, :]]
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
        chol: (Nf, lmax+1, B, B) lower Cholesky factors of the blocks.
        options: the :class:`MModeOptions` (static).
    """

    system: LinearSystem
    a_wf: jax.Array
    wiener: SolveInfo
    chol: jax.Array
    options: MModeOptions = eqx.field(static=True, default=MModeOptions())

    method: ClassVar[str] = "mmode"


def _tri(L, b, trans):
    return jax.scipy.linalg.solve_triangular(L, b, lower=True, trans=trans)


def _block_solve(chol: jax.Array, g: jax.Array) -> jax.Array:
    """Solve ``L L^T y = g`` for g (Nf, M, B, k)."""
    y = jax.vmap(jax.vmap(lambda l, v: _tri(l, v, "N")))(chol, g)
    return jax.vmap(jax.vmap(lambda l, v: _tri(l, v, "T")))(chol, y)


def block_solve(chol: jax.Array, b: jax.Array) -> jax.Array:
    """``P^-1 b`` through the factorised m-blocks: b (Nf, n) -> (Nf, n)."""
    lay = mmode_layout(chol.shape[1] - 1)
    return _scatter(_block_solve(chol, _gather(b, lay)[..., None])[..., 0], lay)


def _mmode_wiener(system: LinearSystem, L: jax.Array, options: MModeOptions):
    """``a_wf`` through the block factors, with its info from the *true* (matrix-free) residual."""
    b = wiener_rhs(system)  # (Nf, n), matrix-free O(Nt Nbl n)
    Lc = jax.lax.stop_gradient(L)
    # Implicit differentiation against the true (matrix-free) P: the derivative is that of
    # the true posterior mean, for any change of the system (the blocks' own derivative
    # would miss what a time-varying noise change adds off the block diagonal).
    solve = lambda mv, rhs: block_solve(Lc, rhs)  # noqa: E731
    a_wf = jax.lax.custom_linear_solve(lambda x: precision_apply(system, x), b, solve, symmetric=True)
    r = jax.lax.stop_gradient(b - precision_apply(system, a_wf))
    err = jnp.sqrt(jnp.abs(jnp.sum(r * block_solve(Lc, r), axis=-1)))
    finite = jnp.all(jnp.isfinite(Lc), axis=(1, 2, 3))
    rel = jnp.linalg.norm(r, axis=-1) / jnp.linalg.norm(jax.lax.stop_gradient(b), axis=-1)
    info = direct_info(err, rel, finite, options.tol)
    if options.throw:
        a_wf = eqx.error_if(a_wf, ~info.converged, "gcrsky m-mode: a block is not positive definite, or P is not "
                            "block-diagonal in m (the solve missed MModeOptions.tol against the true P)")
    return a_wf, info


@partial(jax.jit, static_argnames=("options",))
def _prepare(system: LinearSystem, options: MModeOptions) -> MModeState:
    L = jnp.linalg.cholesky(mmode_blocks(system))
    a_wf, info = _mmode_wiener(system, L, options)
    return MModeState(system, a_wf, info, L, options)


@jax.jit
def _condition(state: MModeState, data: jax.Array) -> MModeState:
    system = state.system._replace(data=jnp.asarray(data, state.system.data.dtype))
    a_wf, info = _mmode_wiener(system, state.chol, state.options)
    return MModeState(system, a_wf, info, state.chol, state.options)


def prepare_mmode(system: LinearSystem, options: MModeOptions | None = None, *, check: bool = True) -> MModeState:
    """Build and factorise the m-blocks and solve for the Wiener filter, once.

    Raises ``ValueError`` naming the reason unless :func:`mmode_check` passes with
    ``options``' tolerances.  ``check=False`` skips the check (it needs concrete
    arrays; inside ``jit`` it is skipped anyway).  Either way the Wiener solve is judged
    against the *true* (matrix-free) P: where P is not block-diagonal in m, its error
    exceeds ``options.tol`` and the solve (and every draw) is reported
    :data:`~gcrsky.solvers.Result.INACCURATE` (``options.throw``: an error), never
    converged.
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
    """``ndraws`` exact posterior draws ``a_wf + L_m^-T z`` block by block.

    Returns:
        draws (Nf, ndraws, n) in the realified layout; a :class:`~gcrsky.solvers.DrawInfo`
        (``wiener``, ``draws``: SolveInfo (Nf, ndraws), ``a_wf``) as :func:`gcrsky.draw`.
    """
    L, a_wf = prepared.chol, prepared.a_wf
    nf, M, B, _ = L.shape
    z = jax.random.normal(key, (nf, M, B, ndraws), a_wf.dtype)
    delta = jax.vmap(jax.vmap(lambda l, v: _tri(l, v, "T")))(L, z)  # (Nf, M, B, ndraws)
    lay = mmode_layout(M - 1)
    delta = _scatter(jnp.moveaxis(delta, -1, 1), lay)  # (Nf, ndraws, n)
    finite = jnp.all(jnp.isfinite(delta), axis=-1)
    return a_wf[:, None, :] + delta, DrawInfo(prepared.wiener, exact_info(prepared.wiener, finite, (nf, ndraws)), a_wf)


def mmode_wiener_and_draws(key: jax.Array, system: LinearSystem, ndraws: int, options: MModeOptions | None = None):
    """:func:`prepare_mmode` then :func:`draw_mmode`: (draws (Nf, ndraws, n), info)."""
    return draw_mmode(key, prepare_mmode(system, options), ndraws)


# ---------------------------------------------------------------- the path


def _mmode_evidence(state: MModeState, terms) -> EvidenceParts:
    diag = jnp.diagonal(state.chol, axis1=-2, axis2=-1)  # padding rows are identity: log 1 = 0
    logdet = 2.0 * jnp.sum(jnp.log(diag), axis=(1, 2)) - jnp.sum(jnp.log(state.system.prior.inv_var), axis=1)
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
        nf, n = int(system.data.shape[0]), n_in(system.op)
        lmax = lmax_from_nparams(n)
        return 2.0 * 8 * nf * (lmax + 1) * (2 * lmax + 2) ** 2 + 6.0 * 8 * nf * max(1, ndraws) * n

    def cost_flop(self, system, options, ndraws):
        nf, _, nbl = (int(x) for x in system.data.shape)
        B = 2 * (lmax_from_nparams(n_in(system.op)) + 1)
        blocks = B // 2 * (2.0 * nf * nbl * B * B + nf * B**3 / 3.0)
        return blocks + ndraws * nf * B // 2 * B * B

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
