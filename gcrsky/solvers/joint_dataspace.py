"""Joint data-space samplers over channels for a frequency-coupled prior (DESIGN section 13).

The joint posterior of :mod:`gcrsky.solvers.joint` (prior ``a ~ N(a0, S)``, ``S = R (x) diag(c)``
on ``vec(a)``, channel-major) in data space, the joint form of :mod:`gcrsky.solvers.dataspace`.
With ``Y = W^1/2 X`` the whitened realified operator of every channel (rows as
:func:`gcrsky.solvers.dataspace.to_rows`: ``t 2 Nbl + p Nbl + b`` within a channel, channel-major
across channels) the data-space matrix

    D = I + Y S Y^T,      D[(nu, i), (nu', j)] = delta + R(nu, nu') (Y_nu diag(c) Y_nu'^T)[i, j],

couples the channels through the cross-channel blocks ``R(nu, nu') W_nu^1/2 X_nu diag(c) X_nu'^T
W_nu'^1/2``.  A flagged sample (``inv_noise`` 0) has zero rows of Y: its rows of D are identity rows,
decoupled, and it drops out of every product below (a fully flagged channel is all identity rows:
its posterior comes through R alone, inpainting).  With ``r~ = W^1/2 (d - X a0)`` (0 where flagged):

* Wiener filter ``a_wf = a0 + S Y^T D^-1 r~``;
* exact draws (Hoffman & Ribak, as :func:`gcrsky.solvers.dataspace.draw_dataspace`):
  ``delta = G w_a`` with ``G = L_R (x) diag(sqrt c)`` (``S = G G^T``), ``z ~ N(0, I)`` on the
  unflagged rows, ``a = a_wf + delta - S Y^T D^-1 (Y delta + z)``: exactly ``N(a_wf, P^-1)``;
* the joint log evidence ``-1/2 [r~^T D^-1 r~ + log det D + log det N + N_d log 2 pi]`` over the
  unflagged samples, the same quantity and normalisation as
  :func:`gcrsky.solvers.joint.joint_log_evidence_dense` (``r~^T D^-1 r~ = r^T W r - b'^T (a_wf - a0)``
  by Woodbury, ``log det D = log det M`` by the determinant lemma).

Two exact paths:

* dense (:func:`prepare_joint_dataspace`): ``D`` as one ``(Nf N_d, Nf N_d)`` Cholesky
  (``N_d = 2 Nt Nbl``), any coverage, noise and flags (and a frame map); ``Y`` is materialised
  ((Nf, N_d, n), ``8 Nf N_d n`` bytes) for the products.  Cost ``~(Nf N_d)^2 n`` flop for D,
  ``(Nf N_d)^3 / 3`` for its factor; memory ``~3 x 8 (Nf N_d)^2`` bytes plus a few copies of Y
  (:func:`joint_dataspace_bytes`).
* per m (:func:`prepare_joint_dataspace_mmode`), uniform full-day coverage with time-constant noise
  (:func:`gcrsky.solvers.mmode_check`; flagged *channels* are fine).  Then the unit vectors
  ``u_k(t) = exp(i k t) / sqrt(Nt)``, ``|k| <= lmax``, are orthonormal over the times, the model
  visibilities lie in their span, ``X_t a = sum_k exp(i k t) V_k`` with

      V_m = sum_l (R_re - i R_im)_lm alpha_lm / 2,   V_-m = sum_l (R_re + i R_im)_lm conj(alpha_lm) / 2
      (m > 0),   V_0 = sum_l R_re,l0 alpha_l0,

  (``alpha_lm = Re a_lm + i Im a_lm``; ``R_re``, ``R_im`` the response's columns of the Re and Im
  entries), and the data's projections ``d_k = u_k^H d`` are sufficient: the rest of the data is noise
  alone, independent of them (time-constant noise is white in time).  The real and imaginary parts
  of ``d_m`` and ``d_-m`` (``4 Nbl`` reals, ``2 Nbl`` at m = 0) depend only on the order-m
  coefficients, so D is block-diagonal in m with blocks of width ``Nf 4 Nbl``: all orders share one
  shape (m = 0 padded with identity rows), so one compiled build and factorisation serves every order.  The noise-only rest
  enters the evidence as ``r^T W r - |r~_proj|^2`` and adds nothing to ``log det D``.  Cost
  ``~(lmax+1) (Nf 4 Nbl)^2 2 (lmax+1)`` flop for the blocks, ``(lmax+1) (Nf 4 Nbl)^3 / 3`` for their
  factors, built and factorised one order at a time (``lax.map``); memory ``8 (lmax+1) (Nf 4 Nbl)^2``
  bytes for the factors (~1.5 times that at the set-up's peak, :func:`joint_dataspace_mmode_bytes`)
  plus the per-order rows ``8 (lmax+1) Nf 4 Nbl 2 (lmax+1)``.  Far smaller than the a-space joint
  m-blocks (``Nf 2 (lmax - m + 1)`` wide) when ``4 Nbl < 2 (lmax - m + 1)``: 64 channels at lmax 100
  with 6 baselines have blocks 1536 wide (a-space: 12928), set up in 48 s with a 3.6 GB peak on a
  loaded 2-core CPU (``benchmarks/joint_frequency.py``).

Differentiation: D and everything in it differentiate natively (the response, the noise, the prior's
hyperparameters through ``R`` and ``c``); on the dense path solves with D are differentiated implicitly
and ``log det D`` by ``tr(D^-1 dD)`` (:func:`gcrsky.solvers.dense.cholesky_solve`,
:func:`~gcrsky.solvers.dense.cholesky_logdet`), on the per-m path (which keeps only the blocks'
factors, to halve its memory) natively through the factors.  On the per-m path the noise enters
through its mean over times, so a derivative along a noise change that keeps it stationary is exact.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from ..base.memory import check_memory
from ..model.operator import apply, response_at
from ..sphere.modes import lmax_from_nparams
from .dataspace import DataSpacePath, to_rows
from .dense import cholesky_logdet, cholesky_solve
from .joint import (
    LOG_2PI,
    JointSystem,
    check_joint_system,
    data_system,
    direct_joint_draw,
    direct_joint_state,
    joint_evidence_terms,
)
from .mmode import mmode_buckets, mmode_check
from .options import MModeOptions
from .path import JointVariant, is_traced

__all__ = [
    "JointDataSpaceMState",
    "JointDataSpacePath",
    "JointDataSpaceState",
    "draw_joint_dataspace",
    "draw_joint_dataspace_mmode",
    "joint_dataspace_log_evidence",
    "joint_dataspace_log_evidence_mmode",
    "joint_dataspace_bytes",
    "joint_dataspace_matrix",
    "joint_dataspace_mmode_bytes",
    "prepare_joint_dataspace",
    "prepare_joint_dataspace_mmode",
    "whitened_solve_dataspace",
]


# ---------------------------------------------------------------- shared pieces


def _sqrt_w(w: jax.Array) -> jax.Array:
    """``W^1/2`` (same shape as ``w``), 0 where ``w == 0`` with a zero (not NaN) derivative there."""
    pos = w > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, w, 1.0)), 0.0)


def _s_apply(prior, v: jax.Array) -> jax.Array:
    """``S v = (R (x) diag(c)) v`` for v (..., Nf, n)."""
    return jnp.einsum("hf,...fk->...hk", prior.freq_cov, v) * prior.mode_var


def _g_apply(prior, w: jax.Array) -> jax.Array:
    """``G w = (L_R (x) diag(sqrt c)) w`` for w (..., Nf, n): a draw of ``N(0, S)`` from unit normals."""
    LR = jnp.linalg.cholesky(prior.freq_cov)
    return jnp.einsum("hf,...fk->...hk", LR, w) * jnp.sqrt(prior.mode_var)


def _residual(system: JointSystem) -> jax.Array:
    """``r = d - X a0`` (Nf, Nt, Nbl) complex, 0 on flagged samples (whatever the data hold there)."""
    r = system.data - apply(system.op, system.prior.mean)
    return jnp.where(system.inv_noise > 0, r, 0.0)


def _evidence(system: JointSystem, q, logdet_d):
    """``-1/2 [q + log det D + log det N + N_d log 2 pi]`` with the noise terms of all unflagged samples."""
    t = joint_evidence_terms(system)
    return -0.5 * (q + logdet_d + t["logdet_n"] + t["n_data"] * LOG_2PI)


# ---------------------------------------------------------------- dense


class JointDataSpaceState(eqx.Module):
    """The dense joint data-space path, factorised.

    Attributes:
        system: the :class:`~gcrsky.solvers.joint.JointSystem`.
        a_wf: (Nf, n) joint Wiener filter, Kelvin.
        gram: (Nf N_d, Nf N_d) ``D = I + Y S Y^T``, rows channel-major (``f N_d + i``).
        chol: its lower Cholesky factor.
        rows: (Nf, N_d, n) ``Y = W^1/2 X`` realified (0 on flagged rows).
    """

    system: JointSystem
    a_wf: jax.Array
    gram: jax.Array
    chol: jax.Array
    rows: jax.Array


def _rows(system: JointSystem) -> jax.Array:
    """``Y = W^1/2 X`` realified, (Nf, N_d, n), rows ``t 2 Nbl + p Nbl + b`` (:func:`to_rows`)."""
    op = system.op
    X = jax.vmap(lambda t: response_at(op, t), out_axes=1)(op.angles)  # (Nf, Nt, Nbl, n) complex
    sw = _sqrt_w(system.inv_noise)[..., None]  # (Nf, Nt, Nbl, 1)
    Y = jnp.stack([sw * X.real, sw * X.imag], axis=2)  # (Nf, Nt, 2, Nbl, n)
    nf, n = Y.shape[0], Y.shape[-1]
    return Y.reshape(nf, -1, n)


def _gram(prior, Y: jax.Array) -> jax.Array:
    """``I + Y S Y^T`` for rows Y (..., Nf, K, n), channel-major: (..., Nf K, Nf K)."""
    nf, k = Y.shape[-3], Y.shape[-2]
    G = jnp.einsum("...fak,...gbk->...fagb", Y * prior.mode_var, Y)
    D = (prior.freq_cov[:, None, :, None] * G).reshape(Y.shape[:-3] + (nf * k, nf * k))
    D = 0.5 * (D + jnp.swapaxes(D, -1, -2))  # exactly symmetric
    return D + jnp.eye(nf * k, dtype=D.dtype)


@jax.jit
def joint_dataspace_matrix(system: JointSystem) -> jax.Array:
    """The joint data-space matrix ``D = I + W^1/2 X S X^T W^1/2``, (Nf N_d, Nf N_d), channel-major
    (module docstring); identity rows and columns on flagged samples."""
    return _gram(system.prior, _rows(system))


@jax.jit
def _prepare_dense(system: JointSystem) -> JointDataSpaceState:
    Y = _rows(system)
    nf, nd, n = Y.shape
    D = _gram(system.prior, Y)
    L = jnp.linalg.cholesky(D)
    rt = to_rows(_sqrt_w(system.inv_noise) * _residual(system))  # (Nf, N_d)
    x = cholesky_solve(D, L, rt.reshape(-1)).reshape(nf, nd)
    a_wf = system.prior.mean + _s_apply(system.prior, jnp.einsum("fak,fa->fk", Y, x))
    return JointDataSpaceState(system, a_wf, D, L, Y)


def joint_dataspace_bytes(nf: int, nt: int, nbl: int, n: int) -> float:
    """Estimated peak bytes of the dense joint data-space set-up (float64): ``8 [3 (Nf N_d)^2 + 5 Nf N_d n]``
    (``N_d = 2 Nt Nbl``): D, its factor and one transient of the build; Y, the complex per-time response
    and the build's copies of them.  A bound on XLA's memory analysis of the set-up (measured 2.3 D + 4.0 Y
    by a fit over two shapes, lmax 10 and 20, 4 channels)."""
    nd = 2 * nt * nbl
    return 8.0 * (3.0 * (nf * nd) ** 2 + 5.0 * nf * nd * n)


def prepare_joint_dataspace(system: JointSystem, *, check: bool = True,
                            memory_budget: float | None = None) -> JointDataSpaceState:
    """Build and factorise the joint ``D`` and solve for the joint Wiener filter (dense; any coverage).

    Args:
        system: a :class:`~gcrsky.solvers.joint.JointSystem` (any coverage, noise, flags).
        check: :func:`~gcrsky.solvers.joint.check_joint_system` first, and that the set-up fits
            (:func:`joint_dataspace_bytes` against ``memory_budget``, default what is free); concrete
            arrays only.
        memory_budget: bytes the set-up may use (keyword).

    Returns:
        a :class:`JointDataSpaceState`.  Cost and memory: module docstring.  Under a trace a
        factorisation failure shows as NaN.

    Raises:
        ValueError: a bad concrete input (``check``).
        gcrsky.base.InsufficientMemoryError: the set-up would not fit (``check``).
    """
    if check and not is_traced(system):
        check_joint_system(system)
        nf, nt, nbl = (int(x) for x in system.data.shape)
        n = int(system.prior.mean.shape[-1])
        check_memory(joint_dataspace_bytes(nf, nt, nbl, n),
                     f"the dense joint data space (D: {nf * 2 * nt * nbl} square)",
                     "use prepare_joint_dataspace_mmode (full-day coverage) or the a-space joint paths "
                     "(gcrsky.solvers.joint), or fewer channels, times or baselines", budget=memory_budget)
    return _prepare_dense(system)


def _unit_normals(key, prior, ndraws):
    """``(w_a, k_n)``: unit normals (ndraws, Nf, n) for the prior part and the key of the noise part."""
    ka, kn = jax.random.split(key)
    return jax.random.normal(ka, (ndraws,) + prior.mean.shape, prior.mean.dtype), kn


@partial(jax.jit, static_argnames=("ndraws",))
def draw_joint_dataspace(key: jax.Array, state: JointDataSpaceState, ndraws: int) -> jax.Array:
    """``ndraws`` exact joint draws ``a_wf + delta - S Y^T D^-1 (Y delta + z)`` (ndraws, Nf, n).

    ``k_a, k_n = split(key)``: ``delta = G N(0, I)`` (ndraws, Nf, n) from ``k_a``, ``z ~ N(0, I)``
    (ndraws, Nf, N_d) from ``k_n``, zero on flagged rows.
    """
    system, Y = state.system, state.rows
    nf, nd, _ = Y.shape
    wa, kn = _unit_normals(key, system.prior, ndraws)
    delta = _g_apply(system.prior, wa)
    keep = to_rows(jnp.where(system.inv_noise > 0, 1.0 + 1.0j, 0.0)).astype(Y.dtype)
    z = keep * jax.random.normal(kn, (ndraws, nf, nd), Y.dtype)
    u = (jnp.einsum("fak,dfk->dfa", Y, delta) + z).reshape(ndraws, -1)
    x = jsl.cho_solve((state.chol, True), u.T).T.reshape(ndraws, nf, nd)
    return state.a_wf + delta - _s_apply(system.prior, jnp.einsum("fak,dfa->dfk", Y, x))


def joint_dataspace_log_evidence(state: JointSystem | JointDataSpaceState, *, check: bool = True) -> jax.Array:
    """The joint log evidence (scalar) on the dense data-space path (module docstring).

    Args:
        state: a :class:`~gcrsky.solvers.joint.JointSystem` (factorised here; checked on concrete
            arrays with ``check``) or a :class:`JointDataSpaceState`.

    Differentiable (``jax.grad``) in everything the system holds.
    """
    if isinstance(state, JointSystem):
        state = prepare_joint_dataspace(state, check=check)
    return _dense_evidence(state)


@jax.jit
def _dense_evidence(state: JointDataSpaceState) -> jax.Array:
    rt = to_rows(_sqrt_w(state.system.inv_noise) * _residual(state.system)).reshape(-1)
    q = jnp.dot(rt, cholesky_solve(state.gram, state.chol, rt))
    return _evidence(state.system, q, cholesky_logdet(state.gram, state.chol))


# ---------------------------------------------------------------- per m (uniform full-day coverage)


class JointDataSpaceMState(eqx.Module):
    """The per-m joint data-space path, factorised (module docstring).

    Attributes:
        system: the :class:`~gcrsky.solvers.joint.JointSystem`.
        a_wf: (Nf, n) joint Wiener filter, Kelvin.
        chol: (lmax+1, Nf 4 Nbl, Nf 4 Nbl) the lower Cholesky factors of the blocks ``D_m`` (the blocks
            themselves are not kept); rows ``f 4 Nbl + j``, ``j`` = ``p Nbl + b`` for the Re / Im part
            (p = 0 / 1) of ``d_m`` and ``(2 + p) Nbl + b`` of ``d_-m`` (identity rows at m = 0, and on
            flagged channels).
        rows: (lmax+1, Nf, 4 Nbl, 2 (lmax+1)) the whitened per-order operator ``W^1/2 Z_m``; columns
            as the single bucket of :func:`gcrsky.solvers.mmode.mmode_buckets` ``(lmax, lmax + 1)``
            (``Re a_{m+p, m}``, then ``Im a_{m+p, m}``; zero on padding).
        lmax: the band limit (static).
    """

    system: JointSystem
    a_wf: jax.Array
    chol: jax.Array
    rows: jax.Array
    lmax: int = eqx.field(static=True)


def _layout(lmax: int):
    """``(gather (M, 2M), mask (M, 2M), src, dst)`` of the one-bucket m layout (``M = lmax + 1``)."""
    lay = mmode_buckets(lmax, lmax + 1)
    assert len(lay.gather) == 1
    return lay.gather[0], lay.mask[0], lay.src[0], lay.dst[0]


def _to_orders(v: jax.Array, lmax: int) -> jax.Array:
    """(..., Nf, n) -> (..., M, Nf, 2M) per order, zeros on padding."""
    g, mk, _, _ = _layout(lmax)
    b = jnp.where(mk, v[..., g], 0.0)  # (..., Nf, M, 2M)
    return jnp.moveaxis(b, -3, -2)


def _from_orders(y: jax.Array, lmax: int) -> jax.Array:
    """(..., M, Nf, 2M) -> (..., Nf, n): the inverse of :func:`_to_orders` on the real entries."""
    _, _, src, dst = _layout(lmax)
    y = jnp.moveaxis(y, -3, -2)  # (..., Nf, M, 2M)
    flat = y.reshape(y.shape[:-2] + (-1,))[..., src]
    out = jnp.zeros(y.shape[:-2] + ((lmax + 1) ** 2,), y.dtype)
    return out.at[..., dst].set(flat)


def _order_rows(system: JointSystem, lmax: int) -> jax.Array:
    """``W^1/2 Z_m`` (M, Nf, 4 Nbl, 2M): the projected data ``[Re d_m, Im d_m, Re d_-m, Im d_-m]`` of
    every channel and baseline as a function of order m's coefficients (module docstring), times
    ``sqrt(Nt)`` (``d_k = u_k^H d = sqrt(Nt) V_k``) and the time-mean ``W^1/2``."""
    g, mk, _, _ = _layout(lmax)
    M = lmax + 1
    nt = system.op.angles.shape[0]
    Rg = jnp.where(mk, system.op.response[..., g], 0.0)  # (Nf, Nbl, M, 2M) complex
    Rre, Rim = Rg[..., :M], Rg[..., M:]  # columns of Re a_{m+p,m} and Im a_{m+p,m}
    m = np.arange(M)
    half = jnp.asarray(np.where(m == 0, 1.0, 0.5))[:, None]
    pos = jnp.asarray((m > 0).astype(float))[:, None]
    A = (Rre - 1j * Rim) * half  # V_m = A alpha
    B = (Rre + 1j * Rim) * half * pos  # V_-m = B conj(alpha); none at m = 0
    # (A_r + i A_i)(x + i y) and (B_r + i B_i)(x - i y), real and imaginary parts, columns [x, y]
    top_re = jnp.concatenate([A.real, -A.imag], axis=-1)
    top_im = jnp.concatenate([A.imag, A.real], axis=-1)
    bot_re = jnp.concatenate([B.real, B.imag], axis=-1)
    bot_im = jnp.concatenate([B.imag, -B.real], axis=-1)
    Z = jnp.stack([top_re, top_im, bot_re, bot_im], axis=1)  # (Nf, 4, Nbl, M, 2M)
    Z = jnp.where(mk, Z, 0.0)  # the Im half of m = 0 is padding
    sw = _sqrt_w(jnp.mean(system.inv_noise, axis=1))  # (Nf, Nbl): time-constant noise
    Z = Z * (np.sqrt(nt) * sw)[:, None, :, None, None]
    nf, nbl = sw.shape
    return jnp.moveaxis(Z.reshape(nf, 4 * nbl, M, 2 * M), 2, 0)  # (M, Nf, 4 Nbl, 2M)


def _projected_residual(system: JointSystem, lmax: int) -> jax.Array:
    """``W^1/2 [Re r_m, Im r_m, Re r_-m, Im r_-m]`` (M, Nf, 4 Nbl), ``r_k = u_k^H r``; 0 at -m for m = 0."""
    ang = system.op.angles
    nt = ang.shape[0]
    m = jnp.arange(lmax + 1, dtype=ang.dtype)
    ph = m[:, None] * ang[None, :]  # (M, Nt)
    r = _residual(system)
    rp = jnp.einsum("mt,ftb->mfb", jnp.exp(-1j * ph), r) / np.sqrt(nt)
    rn = jnp.einsum("mt,ftb->mfb", jnp.exp(1j * ph), r) / np.sqrt(nt)
    rn = rn * (m > 0)[:, None, None]
    sw = _sqrt_w(jnp.mean(system.inv_noise, axis=1))
    out = jnp.stack([rp.real, rp.imag, rn.real, rn.imag], axis=2) * sw[None, :, None, :]  # (M, Nf, 4, Nbl)
    return out.reshape(out.shape[0], out.shape[1], -1)


def _order_solve(L, b):
    """``D_m^-1 b`` per order by the factors L (M, K, K), b (M, K, B): one LAPACK solve per order."""
    return jax.lax.map(lambda lb: jsl.cho_solve((lb[0], True), lb[1]), (L, b))


@partial(jax.jit, static_argnames=("lmax",))
def _prepare_mmode(system: JointSystem, lmax: int) -> JointDataSpaceMState:
    Z = _order_rows(system, lmax)  # (M, Nf, 4 Nbl, 2M)
    M, nf, k, _ = Z.shape
    cb = _to_orders(system.prior.mode_var[None, :], lmax)[:, 0]  # (M, 2M), zeros on padding

    def block(zc):  # one order at a time: the build's transients are one block's, not all orders'
        return jnp.linalg.cholesky(_gram(system.prior._replace(mode_var=zc[1]), zc[0]))

    L = jax.lax.map(block, (Z, cb))  # only the factors are kept (D itself would double the memory)
    rt = _projected_residual(system, lmax).reshape(M, -1)
    x = _order_solve(L, rt[..., None])[..., 0].reshape(M, nf, k)
    a_wf = system.prior.mean + _s_apply(system.prior, _from_orders(jnp.einsum("mfak,mfa->mfk", Z, x), lmax))
    return JointDataSpaceMState(system, a_wf, L, Z, lmax)


def prepare_joint_dataspace_mmode(system: JointSystem, options: MModeOptions | None = None, *,
                                  check: bool = True, memory_budget: float | None = None) -> JointDataSpaceMState:
    """Build and factorise the per-m joint data-space blocks ``D_m`` and solve for the Wiener filter.

    Exact only for uniform full-day coverage with time-constant noise (flagged *channels*, all-zero
    ``inv_noise``, are fine; flagged samples within a channel are not): :func:`gcrsky.solvers.mmode_check`,
    checked here on concrete arrays (``check``; skipped under a trace).

    Args:
        system: a :class:`~gcrsky.solvers.joint.JointSystem` with ``op.frame is None``.
        options: :class:`~gcrsky.solvers.MModeOptions` (the check's tolerances).
        check: check the system, and that the set-up fits (:func:`joint_dataspace_mmode_bytes` against
            ``memory_budget``, default what is free); concrete arrays only.
        memory_budget: bytes the set-up may use (keyword).

    Returns:
        a :class:`JointDataSpaceMState`: ``lmax + 1`` blocks of width ``Nf 4 Nbl``.

    Raises:
        ValueError: a bad input, or the coverage or noise breaks the per-m structure (``check``).
        gcrsky.base.InsufficientMemoryError: the set-up would not fit (``check``).
    """
    options = options or MModeOptions()
    if system.op.frame is not None:
        raise ValueError("the per-m joint data-space path needs op.frame is None (a frame map couples m)")
    lmax = lmax_from_nparams(system.prior.mean.shape[-1])
    if check and not is_traced(system):
        check_joint_system(system)
        ok = mmode_check(data_system(system), atol=options.atol, rtol=options.rtol)
        if not ok:
            raise ValueError(f"the per-m joint data-space path (m-mode structure) does not apply: {ok.reason}")
        nf, _, nbl = (int(x) for x in system.data.shape)
        check_memory(joint_dataspace_mmode_bytes(nf, nbl, lmax),
                     f"the per-m joint data space ({lmax + 1} blocks of {4 * nf * nbl} square)",
                     "use fewer channels or baselines, or a lower lmax", budget=memory_budget)
    return _prepare_mmode(system, lmax)


@partial(jax.jit, static_argnames=("ndraws",))
def draw_joint_dataspace_mmode(key: jax.Array, state: JointDataSpaceMState, ndraws: int) -> jax.Array:
    """``ndraws`` exact joint draws (ndraws, Nf, n) on the per-m path, ``a_wf + delta - S Z^T D^-1 (Z delta + z)``.

    ``k_a, k_n = split(key)``: ``delta = G N(0, I)`` from ``k_a``, ``z ~ N(0, I)`` (ndraws, M, Nf 4 Nbl)
    from ``k_n`` (on identity rows z drops out: their columns of Z are zero).
    """
    system, Z, lmax = state.system, state.rows, state.lmax
    M, nf, k, _ = Z.shape
    wa, kn = _unit_normals(key, system.prior, ndraws)
    delta = _g_apply(system.prior, wa)  # (ndraws, Nf, n)
    z = jax.random.normal(kn, (ndraws, M, nf * k), Z.dtype)
    u = jnp.einsum("mfak,dmfk->dmfa", Z, _to_orders(delta, lmax)).reshape(ndraws, M, -1) + z
    x = jnp.moveaxis(_order_solve(state.chol, jnp.moveaxis(u, 0, -1)), -1, 0).reshape(ndraws, M, nf, k)
    corr = _s_apply(system.prior, _from_orders(jnp.einsum("mfak,dmfa->dmfk", Z, x), lmax))
    return state.a_wf + delta - corr


def joint_dataspace_log_evidence_mmode(state: JointSystem | JointDataSpaceMState, *,
                                       check: bool = True) -> jax.Array:
    """The joint log evidence (scalar) on the per-m path: the projected data's term through the blocks,
    plus the noise-only rest ``r^T W r - |W^1/2 r_proj|^2`` (module docstring).

    Args:
        state: a :class:`~gcrsky.solvers.joint.JointSystem` (factorised here, checked as in
            :func:`prepare_joint_dataspace_mmode`) or a :class:`JointDataSpaceMState`.

    Differentiable in the prior's hyperparameters and anything else that keeps the noise stationary.
    """
    if isinstance(state, JointSystem):
        state = prepare_joint_dataspace_mmode(state, check=check)
    return _mmode_evidence(state)


@jax.jit
def _mmode_evidence(state: JointDataSpaceMState) -> jax.Array:
    system = state.system
    M = state.lmax + 1
    rt = _projected_residual(system, state.lmax).reshape(M, -1)
    q_proj = jnp.sum(rt * _order_solve(state.chol, rt[..., None])[..., 0])
    rWr = joint_evidence_terms(system)["rWr"]
    q = rWr - jnp.sum(rt**2) + q_proj
    return _evidence(system, q, 2.0 * jnp.sum(jnp.log(jnp.diagonal(state.chol, axis1=-2, axis2=-1))))


def joint_dataspace_mmode_bytes(nf: int, nbl: int, lmax: int) -> float:
    """Estimated peak bytes of the per-m set-up (float64): the factors (``8 (lmax+1) (4 Nf Nbl)^2``), XLA's
    temporaries (half as much again, bounding XLA's memory analysis of the set-up: 0.48 x the factors
    at lmax 40, 16 channels, 6 baselines), one block's transients (``2 x 8 (4 Nf Nbl)^2``), and the
    per-order rows with their gathered complex response (``8 (lmax+1) 4 Nf Nbl 2 (lmax+1)`` each, about).
    Draws add ``~16 ndraws (lmax+1) 4 Nf Nbl``.  Not counted, as for every path: the process's fixed cost
    of compiling and running a program (~0.05-0.2 GB; the ``--quick`` benchmark's peak exceeds its estimate
    by 0.05 GB, the full one's is 0.46 GB below it)."""
    M, k = lmax + 1, 4 * nf * nbl
    return 8.0 * (1.5 * M + 2) * k * k + 2.0 * 8 * M * k * 2 * M


def _g_transpose(prior, v: jax.Array) -> jax.Array:
    """``G^T v`` for v (..., Nf, n)."""
    LR = jnp.linalg.cholesky(prior.freq_cov)
    return jnp.einsum("hf,...hk->...fk", LR, v * jnp.sqrt(prior.mode_var))


@jax.jit
def whitened_solve_dataspace(state: JointDataSpaceState | JointDataSpaceMState, v: jax.Array) -> jax.Array:
    """``M^-1 v`` for whitened vectors v (Nf, n), ``M = I + G^T X^T W X G``, by the data-space factor.

    Woodbury: ``M^-1 = I - G^T Y^T D^-1 Y G`` with ``D = I + Y S Y^T`` (``Y = W^1/2 X``; per order
    on the per-m path).  What :func:`gcrsky.solvers.joint.joint_wiener_info` needs to measure a
    Wiener filter's error in posterior sigma with the path's own factor.
    """
    prior = state.system.prior
    gv = _g_apply(prior, v)
    if isinstance(state, JointDataSpaceState):
        nf, nd = state.rows.shape[:2]
        u = jnp.einsum("fak,fk->fa", state.rows, gv).reshape(-1)
        x = jsl.cho_solve((state.chol, True), u).reshape(nf, nd)
        back = jnp.einsum("fak,fa->fk", state.rows, x)
    else:
        Z, lmax = state.rows, state.lmax
        M, nf, k, _ = Z.shape
        u = jnp.einsum("mfak,mfk->mfa", Z, _to_orders(gv, lmax)).reshape(M, nf * k, 1)
        x = _order_solve(state.chol, u).reshape(M, nf, k)
        back = _from_orders(jnp.einsum("mfak,mfa->mfk", Z, x), lmax)
    return v - _g_transpose(prior, back)


class JointDataSpacePath(DataSpacePath):
    """The data-space path (:class:`~gcrsky.solvers.dataspace.DataSpacePath`) with its joint flavour: dense
    over all channels' data (form ``"dense"``, :func:`prepare_joint_dataspace`) or per order of m for uniform
    full-day coverage (form ``"mmode"``, :func:`prepare_joint_dataspace_mmode`)."""

    joint = True

    def joint_variants(self, joint, full_day, requested):
        nf, nt, nbl = (int(x) for x in np.shape(joint.data))
        n = int(np.shape(joint.prior.mean)[1])
        if full_day:
            lmax = int(round(np.sqrt(n))) - 1
            return [JointVariant("mmode", joint_dataspace_mmode_bytes(nf, nbl, lmax), 4.0 * nf * nbl)]
        return [JointVariant("dense", joint_dataspace_bytes(nf, nt, nbl, n), 2.0 * nf * nt * nbl)]

    def joint_prepare(self, joint, tol, variant):
        inner = prepare_joint_dataspace_mmode(joint) if variant == "mmode" else prepare_joint_dataspace(joint)
        return direct_joint_state(self.name, variant, joint, inner, tol, whitened_solve_dataspace)

    def joint_draw(self, key, state, ndraws):
        draw = draw_joint_dataspace_mmode if state.variant == "mmode" else draw_joint_dataspace
        return direct_joint_draw(draw, key, state, ndraws)
