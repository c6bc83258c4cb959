"""Matrix-free CG for the joint system over channels (frequency-coupled prior, DESIGN section 13).

The system is that of :mod:`gcrsky.solvers.joint`, in its prior-whitened form

    M = I + G^T blockdiag_nu(H_nu) G,     G = L_R (x) diag(sqrt c),     H_nu = X_nu^T W_nu X_nu,

solved for ``u`` with ``a = a0 + G u`` (Wiener filter: right-hand side ``G^T b'``; draws: the GCR
right-hand sides ``G^T (b' + X^T W^1/2 w_d) + w_a`` exactly as :func:`gcrsky.solvers.joint.draw_joint_dense`
builds them from its key).  ``M u`` costs one :func:`gcrsky.model.operator.apply` and one
:func:`~gcrsky.model.operator.adjoint` over all channels (each channel through its own response) and two
``Nf x Nf`` products with ``L_R``: ``blockdiag(H)`` and ``M`` are never formed.

Stopping rule (rigorous).  ``M >= I`` (its data part is positive semi-definite), so ``M^-1 <= I`` and for the
true residual ``r = M (u* - u)``

    ||a - a*||_P^2 = (u - u*)^T G^T P G (u - u*) = (u - u*)^T M (u - u*) = r^T M^-1 r <= r^T r,

since ``G^T P G = M``.  CG therefore stops on the plain 2-norm of the whitened residual,
``||r||_2 <= tol``: an upper bound on the error's P-norm, which bounds every linear functional's error
in units of its posterior standard deviation (``|v^T (a - a*)| <= sqrt(v^T P^-1 v) ||a - a*||_P``).  It
holds whatever the preconditioner; the m-block and per-mode preconditioners have no ``M_pc <= M`` on
partial coverage, so ``r^T M_pc^-1 r`` would bound nothing there.  The Nystrom sketch never exceeds the
matrix it approximates (``I <= M_pc <= M``), so with it CG stops on ``sqrt(r^T M_pc^-1 r)``, also a bound
(``r^T M_pc^-1 r >= r^T M^-1 r``) and tighter than ``||r||_2``.  ``SolveInfo.converged`` (and
``err_sigma``) is this measured bound against ``tol`` on the true residual after CG's residual restart
(:func:`gcrsky.solvers.cg.pcg`).

Preconditioners.  Built per channel and per m, from the full-day m-mode approximation of each channel's
data term (:func:`gcrsky.solvers.mmode.mmode_blocks`: ``H_nu``'s m-blocks with the noise summed over the
observed times, the m-mode path's formula; exact for uniform full-day coverage):

* ``"mblock"``: for each m, the block of ``M`` restricted to order m, ``I + G_m^T blockdiag_nu(H_nu,m) G_m``
  of width ``Nf s_m``, Cholesky-factorised (the joint m-mode path's factor; bucketed as
  :class:`gcrsky.solvers.mmode.MModeBuckets`).  Memory ``8 Nf^2 sum_m s_m^2 ~ 11 Nf^2 lmax^3`` bytes,
  set-up ``O(Nf^3 lmax^4)``.  For uniform full-day coverage it is ``M`` itself (one CG step).
* ``"mode"``: the cheaper per-mode blocks ``I + c_k L_R^T diag_nu(H_nu,kk) L_R``, (n, Nf, Nf): ``M``'s
  diagonal in the mode, exact in the frequency coupling.  Memory ``8 n Nf^2``, set-up ``O(n Nf^3)``.

and, because neither helps on partial coverage (below):

* ``"nystrom"``: a rank-``sketch_size`` randomized Nystrom sketch of the whitened data part ``M - I``
  over all channels together (``sketch_size`` products with ``M``, the stable construction of
  :func:`gcrsky.solvers.preconditioners.nystrom_preconditioner`), ``M_pc = I + U diag(lam) U^T``;
  memory ``8 Nf n k`` bytes.
* ``"none"``: the identity (``M``'s eigenvalues are >= 1 already).

Measured iterations to ``tol = 1e-8``, Wiener filter / the most of 4 draws (all converged), with the
log-frequency kernel (A 1.2, beta -2.5, xi 0.06, nugget 1e-2), 4 channels 100-112 MHz with channel 2
flagged, noise sigma 2e-3, the 10-antenna hexagon; full day = Nt angles equally spaced over 2 pi, 8 h =
Nt angles over a third of the day; Nystrom with the default ``sketch_size`` 128 (Nystrom stops on its
tighter norm, the others on ``||r||_2``):

======================  =====  ==========  ===========  =========  =========
lmax, Nbl, Nt           cover  none        mode         mblock     nystrom
======================  =====  ==========  ===========  =========  =========
6, 12, 16               24 h   57 / 60     98 / 102     1 / 1      1 / 1
6, 12, 16               8 h    63 / 65     150 / 159    118 / 119  1 / 1
12, 30, 32              24 h   186 / 195   290 / 310    1 / 1      53 / 53
12, 30, 32              8 h    214 / 222   461 / 493    342 / 362  3 / 3
20, 45, 48              24 h   433 / 432   944 / 1008   1 / 1      259 / 261
20, 45, 48              8 h    541 / 565   1544 / 1639  776 / 826  32 / 32
======================  =====  ==========  ===========  =========  =========

(Measured by building these systems as ``tests/test_joint_cg.py`` does, response at nside 32 below lmax 16
and 64 above, and reading ``prepare_joint_cg(system, JointCGOptions(tol=1e-8, preconditioner=kind))
.wiener.iterations`` and ``draw_joint_cg(PRNGKey(0), state, 4)[1].draws.iterations``.)  The
m-blocks are exact on the full day and lose to no preconditioner on 8 h (1.4-1.9x the iterations): the
data of a third of the day constrain the sky seen, not every m evenly, and a preconditioner
block-diagonal in m cannot say so (the *exact* m-diagonal blocks of the 8 h ``H_nu``, built per time,
measured the same: 115, 338, 791 Wiener iterations).  The per-mode blocks lose everywhere.  With 256
directions the Nystrom sketch needs 1 / 1 / 3 iterations at lmax 6 / 12 / 20 on 8 h.

Default (``"auto"``): ``"mblock"`` on uniform full-day coverage (:func:`gcrsky.solvers.mmode.mmode_check`
on concrete arrays) while its factors need at most :data:`MBLOCK_MAX_BYTES`, as it is ``M`` there (but
the exact :func:`gcrsky.solvers.joint.prepare_joint_mmode` is then the better path); ``"nystrom"``
everywhere else and under a trace, since it needs by far the fewest iterations on partial coverage.

Differentiation: the solves go through :func:`gcrsky.solvers.cg.cg_solve` (``jax.lax.custom_linear_solve``):
``jax.grad`` of the Wiener filter in anything the system holds (the prior's hyperparameters) follows the
implicit rule without differentiating the iterations; the preconditioner is held constant.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.operator import adjoint, apply
from .cg import CGPath, cg_solve
from .info import DrawInfo, SolveInfo
from .joint import (
    JointState,
    JointSystem,
    bucket_scales,
    bucket_solve,
    check_joint_system,
    color_apply,
    color_buckets,
    data_system,
    joint_evidence_terms,
    joint_noise_terms,
    prior_whitening,
    whiten_apply,
    whiten_buckets,
)
from .mmode import mmode_blocks, mmode_buckets, mmode_check
from .options import CGOptions, MModeOptions
from .path import is_traced

__all__ = [
    "MBLOCK_MAX_BYTES",
    "JointCGOptions",
    "JointCGPath",
    "JointCGState",
    "JointMBlockPreconditioner",
    "JointModePreconditioner",
    "JointNystromPreconditioner",
    "draw_joint_cg",
    "joint_matvec",
    "joint_precondition",
    "joint_preconditioner",
    "prepare_joint_cg",
    "wiener_joint_cg",
]

#: ``"auto"`` takes the m-block preconditioner while its factors need at most this many bytes.
MBLOCK_MAX_BYTES = 2 * 1024**3

KINDS = ("auto", "mblock", "mode", "nystrom", "none")


@dataclasses.dataclass(frozen=True)
class JointCGOptions:
    """Options of the joint CG (hashable: a static argument of the jitted functions).

    Attributes:
        tol: stop when the whitened residual's 2-norm ``||r||_2 <= tol`` (with ``"nystrom"``:
            ``sqrt(r^T M_pc^-1 r) <= tol``, tighter): a rigorous bound on the error's P-norm,
            posterior-sigma units (module docstring).
        maxiter: cap on iterations per solve (both passes of the residual restart together).
        preconditioner: ``"auto"``, ``"mblock"``, ``"mode"``, ``"nystrom"`` or ``"none"`` (module docstring).
        bucket: padding quantum of the m-block layout (:class:`gcrsky.solvers.MModeOptions`).
        sketch_size: rank of the ``"nystrom"`` sketch (clipped to ``Nf n``).
        throw: raise (``equinox.error_if``) when a solve did not converge.
    """

    tol: float = 1e-8
    maxiter: int = 2000
    preconditioner: Literal["auto", "mblock", "mode", "nystrom", "none"] = "auto"
    bucket: int = MModeOptions.bucket
    sketch_size: int = 128
    throw: bool = False

    def __post_init__(self):
        if self.preconditioner not in KINDS:
            raise ValueError(f"preconditioner must be one of {KINDS}, got {self.preconditioner!r}")
        if not (isinstance(self.tol, (int, float)) and np.isfinite(self.tol) and self.tol > 0):
            raise ValueError(f"tol must be a positive finite number, got {self.tol!r}")
        for name in ("maxiter", "bucket", "sketch_size"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if not isinstance(self.throw, bool):
            raise ValueError(f"throw must be True or False, got {self.throw!r}")


# ---------------------------------------------------------------- the operator


def joint_matvec(system: JointSystem, chol_r: jax.Array, sqrt_c: jax.Array, u: jax.Array) -> jax.Array:
    """``M u = u + G^T blockdiag_nu(H_nu) G u`` for u (Nf, n), matrix-free.

    Args:
        system: the :class:`~gcrsky.solvers.joint.JointSystem` (its operator and ``inv_noise``).
        chol_r: (Nf, Nf) lower Cholesky factor of ``R``; sqrt_c: (n,) ``sqrt(mode_var)``.
        u: (Nf, n) whitened vector.

    Cost: one operator product and its adjoint over all channels, ``O(Nf Nt Nbl n)``.
    """
    a = color_apply(chol_r, sqrt_c, u)
    return u + whiten_apply(chol_r, sqrt_c, adjoint(system.op, system.inv_noise * apply(system.op, a)))


# ---------------------------------------------------------------- preconditioners


class JointMBlockPreconditioner(eqx.Module):
    """Cholesky factors of ``M``'s m-blocks (full-day approximation), per bucket (G, Nf S, Nf S).

    Attributes:
        chol: per bucket of :func:`gcrsky.solvers.mmode.mmode_buckets`, lower factors, index
            ``f S + i`` within a block (identity on padding).
        lmax, quantum: the layout (static).
    """

    chol: tuple
    lmax: int = eqx.field(static=True)
    quantum: int = eqx.field(static=True)


class JointModePreconditioner(NamedTuple):
    """Cholesky factors (n, Nf, Nf) of the per-mode blocks ``I + c_k L_R^T diag_nu(H_nu,kk) L_R``."""

    chol: jax.Array


class JointNystromPreconditioner(NamedTuple):
    """A rank-k Nystrom sketch ``K ~ U diag(lam) U^T`` of the whitened data part ``K = M - I``.

    Attributes:
        U: (Nf n, k) orthonormal columns (channel-major ``f n + k``); lam: (k,) eigenvalues >= 0.
    """

    U: jax.Array
    lam: jax.Array


def _nystrom(system: JointSystem, chol_r, sqrt_c, k: int, key=None) -> JointNystromPreconditioner:
    """The stable randomized Nystrom sketch (Frangella, Tropp & Udell 2023) of ``M - I`` with k products."""
    nf, n = system.prior.mean.shape
    key = jax.random.PRNGKey(0) if key is None else key
    om = jnp.linalg.qr(jax.random.normal(key, (nf * n, k), chol_r.dtype))[0]

    def data_part(v):
        u = v.reshape(nf, n)
        return (joint_matvec(system, chol_r, sqrt_c, u) - u).reshape(-1)

    Y = jax.lax.map(data_part, om.T, batch_size=min(8, k)).T  # (Nf n, k)
    nu = jnp.finfo(Y.dtype).eps * jnp.linalg.norm(Y)
    Yn = Y + nu * om
    C = jnp.linalg.cholesky(om.T @ Yn)
    B = jax.scipy.linalg.solve_triangular(C, Yn.T, lower=True).T
    U, sv, _ = jnp.linalg.svd(B, full_matrices=False)
    return JointNystromPreconditioner(U, jnp.maximum(sv**2 - nu, 0.0))


def _whitened_mblocks(system: JointSystem, chol_r, sqrt_c, quantum: int):
    """Per bucket (G, Nf S, Nf S): ``I + G_m^T blockdiag(H_nu,m) G_m`` (padding decoupled), and the layout."""
    nf = chol_r.shape[0]
    blocks = mmode_blocks(data_system(system), quantum)  # (Nf, G, S, S) H_nu's m-blocks, identity on padding
    lay = blocks.layout
    out = []
    for Hd, s in zip(blocks.arrays, bucket_scales(sqrt_c, lay)):
        G, S = s.shape
        Hs = Hd * s[None, :, :, None] * s[None, :, None, :]  # padding rows and columns now 0
        M = jnp.einsum("hf,hk,hgij->gfikj", chol_r, chol_r, Hs).reshape(G, nf * S, nf * S)
        out.append(M + jnp.eye(nf * S, dtype=M.dtype))
    return tuple(out), blocks


def joint_preconditioner(system: JointSystem, kind: str = "mblock", quantum: int = MModeOptions.bucket,
                         sketch_size: int = 128):
    """Build the named preconditioner of ``M`` (module docstring).

    Args:
        system: a :class:`~gcrsky.solvers.joint.JointSystem` (``op.frame is None`` for ``"mblock"`` and ``"mode"``).
        kind: ``"mblock"``, ``"mode"``, ``"nystrom"`` or ``"none"``.
        quantum: the m-block layout's padding quantum.
        sketch_size: the Nystrom sketch's rank (clipped to ``Nf n``).

    Returns:
        a :class:`JointMBlockPreconditioner`, :class:`JointModePreconditioner`,
        :class:`JointNystromPreconditioner` or None.

    Raises:
        ValueError: an unknown ``kind``, or a frame map with ``"mblock"`` / ``"mode"`` (it couples the orders m).
    """
    nf, n = system.prior.mean.shape
    if kind not in KINDS[1:]:
        raise ValueError(f"unknown joint preconditioner {kind!r}; expected one of {KINDS[1:]}")
    if kind == "none":
        return None
    if kind == "nystrom":
        return _nystrom(system, *prior_whitening(system.prior), min(int(sketch_size), nf * n))
    if system.op.frame is not None:
        raise ValueError("the joint m-block and mode preconditioners need op.frame is None (a frame map couples m); "
                         "use 'nystrom' or 'none'")
    chol_r, sqrt_c = prior_whitening(system.prior)
    if kind == "mblock":
        Ms, blocks = _whitened_mblocks(system, chol_r, sqrt_c, quantum)
        return JointMBlockPreconditioner(tuple(jnp.linalg.cholesky(M) for M in Ms), blocks.lmax, quantum)
    # "mode": the diagonal of each H_nu (from the same m-blocks), then per mode an Nf x Nf block
    blocks = mmode_blocks(data_system(system), quantum)
    lay = blocks.layout
    diag = jnp.zeros((nf, n), chol_r.dtype)
    for Hd, src, dst in zip(blocks.arrays, lay.src, lay.dst):
        d = jnp.diagonal(Hd, axis1=-2, axis2=-1)  # (Nf, G, S)
        diag = diag.at[:, dst].add(d.reshape(nf, -1)[:, src])
    B = jnp.einsum("hf,hk,hg->kfg", chol_r, diag * sqrt_c**2, chol_r) + jnp.eye(nf, dtype=diag.dtype)
    return JointModePreconditioner(jnp.linalg.cholesky(B))


def joint_precondition(pc, r: jax.Array) -> jax.Array:
    """``M_pc^-1 r`` for r (Nf, n) with a preconditioner of :func:`joint_preconditioner` (None: identity)."""
    if pc is None:
        return r
    nf, n = r.shape
    if isinstance(pc, JointNystromPreconditioner):
        v = r.reshape(-1)
        c = pc.U.T @ v
        return (pc.U @ (c / (pc.lam + 1.0)) + v - pc.U @ c).reshape(nf, n)
    if isinstance(pc, JointModePreconditioner):
        x = jax.vmap(lambda L, b: jax.scipy.linalg.cho_solve((L, True), b))(pc.chol, r.T)  # (n, Nf)
        return x.T
    lay = mmode_buckets(pc.lmax, pc.quantum)
    one = jnp.eye(nf, dtype=r.dtype)
    scb = bucket_scales(jnp.ones((n,), r.dtype), lay)
    us = bucket_solve(pc.chol, whiten_buckets(one, scb, r, lay))
    return color_buckets(one, scb, us, lay, nf, n)


# ---------------------------------------------------------------- solves


def _solve(system: JointSystem, chol_r, sqrt_c, pc, y, options: JointCGOptions):
    """``M^-1 y`` for y (Nf, n) or (B, Nf, n) by preconditioned CG (vmapped over B), implicit derivative."""
    pc = jax.lax.stop_gradient(pc)  # changes the path, not the answer
    cgo = CGOptions(tol=options.tol, maxiter=options.maxiter)

    # the Nystrom sketch never exceeds M (M_pc <= M): r^T M_pc^-1 r bounds the error's P-norm and is tighter
    # than ||r||^2 (M_pc >= I); with the others only the 2-norm is a bound
    stop = None if isinstance(pc, JointNystromPreconditioner) else (lambda r: jnp.vdot(r, r).real)

    def one(b):
        return cg_solve(lambda u: joint_matvec(system, chol_r, sqrt_c, u), lambda r: joint_precondition(pc, r), b,
                        jnp.zeros_like(b), cgo, stop=stop)

    u, info = one(y) if y.ndim == 2 else jax.vmap(one)(y)
    if options.throw:
        u = eqx.error_if(u, ~info.converged, "gcrsky joint CG: a solve did not converge (JointCGOptions(throw=True))")
    return u, info


class JointCGState(eqx.Module):
    """The joint CG path set up for many draws (a PyTree).

    Attributes:
        system: the :class:`~gcrsky.solvers.joint.JointSystem`.
        a_wf: (Nf, n) joint Wiener filter, Kelvin.
        wiener: :class:`~gcrsky.solvers.SolveInfo` of its solve (scalar fields; ``err_sigma`` the
            bound on the error's P-norm: ``||r||_2``, or ``sqrt(r^T M_pc^-1 r)`` with ``"nystrom"``).
        pc: the preconditioner (:func:`joint_preconditioner`), or None.
        chol_r: (Nf, Nf) lower Cholesky factor of ``R``; sqrt_c: (n,) ``sqrt(mode_var)``.
        terms: :func:`gcrsky.solvers.joint.joint_evidence_terms`.
        options: the :class:`JointCGOptions` (static; ``preconditioner`` resolved).
    """

    system: JointSystem
    a_wf: jax.Array
    wiener: SolveInfo
    pc: object
    chol_r: jax.Array
    sqrt_c: jax.Array
    terms: dict
    options: JointCGOptions = eqx.field(static=True)


def _resolve(system: JointSystem, options: JointCGOptions | None) -> JointCGOptions:
    """``options`` with ``preconditioner="auto"`` made concrete (module docstring), checked against the system."""
    options = JointCGOptions() if options is None else options
    if not isinstance(options, JointCGOptions):
        raise ValueError(f"the joint CG takes JointCGOptions, got {type(options).__name__}")
    kind = options.preconditioner
    if kind == "auto":
        nf, n = system.prior.mean.shape
        fits = 8 * nf * nf * mmode_buckets(int(round(np.sqrt(n))) - 1, options.bucket).padded_entries
        kind = "nystrom"
        if system.op.frame is None and fits <= MBLOCK_MAX_BYTES and not is_traced(system):
            kind = "mblock" if mmode_check(data_system(system)) else "nystrom"
    if kind in ("mblock", "mode") and system.op.frame is not None:
        raise ValueError("the joint m-block and mode preconditioners need op.frame is None; "
                         "use JointCGOptions(preconditioner='nystrom')")
    return dataclasses.replace(options, preconditioner=kind)


@partial(jax.jit, static_argnames=("options",))
def _prepare(system: JointSystem, options: JointCGOptions) -> JointCGState:
    chol_r, sqrt_c = prior_whitening(system.prior)
    pc = joint_preconditioner(system, options.preconditioner, options.bucket, options.sketch_size)
    terms = joint_evidence_terms(system)
    u, info = _solve(system, chol_r, sqrt_c, pc, whiten_apply(chol_r, sqrt_c, terms["b_res"]), options)
    a_wf = system.prior.mean + color_apply(chol_r, sqrt_c, u)
    return JointCGState(system, a_wf, info, pc, chol_r, sqrt_c, terms, options)


def prepare_joint_cg(system: JointSystem, options: JointCGOptions | None = None, *,
                     check: bool = True) -> JointCGState:
    """Build the preconditioner and solve the joint Wiener filter by CG (started at the prior mean).

    Args:
        system: a :class:`~gcrsky.solvers.joint.JointSystem` (any coverage, noise and flags; ``op.frame``
            None unless ``preconditioner="none"``).
        options: :class:`JointCGOptions` (default: ``tol=1e-8``, ``"auto"`` preconditioner).
        check: :func:`gcrsky.solvers.joint.check_joint_system` first (concrete arrays only).

    Returns:
        a :class:`JointCGState`; ``state.wiener.converged`` says whether the measured bound met ``tol``.

    Raises:
        ValueError: a bad concrete input or option.
    """
    if check:
        check_joint_system(system)
    return _prepare(system, _resolve(system, options))


def wiener_joint_cg(system: JointSystem, options: JointCGOptions | None = None, *, check: bool = True):
    """The joint Wiener filter by CG: ``(a_wf (Nf, n), SolveInfo)`` (scalar fields).

    Differentiable (``jax.grad``, implicitly through ``jax.lax.custom_linear_solve``) in everything the
    system holds, e.g. the prior's hyperparameters; usable under ``jit`` (``check`` is skipped on a trace).
    """
    state = prepare_joint_cg(system, options, check=check)
    return state.a_wf, state.wiener


@partial(jax.jit, static_argnames=("ndraws",))
def draw_joint_cg(key: jax.Array, state: JointCGState, ndraws: int):
    """``ndraws`` exact joint posterior draws by the GCR equation, solved by CG, vmapped over the draws.

    The noise terms are those of :func:`gcrsky.solvers.joint.draw_joint_dense` for the same key, so the
    two paths' draws agree to the solves' tolerance.

    Returns:
        draws (ndraws, Nf, n); a :class:`~gcrsky.solvers.DrawInfo` with ``wiener`` (scalar fields)
        and ``draws`` (fields (ndraws,)), ``a_wf``.
    """
    system = state.system
    xw, wa = joint_noise_terms(key, system, ndraws)
    y = whiten_apply(state.chol_r, state.sqrt_c, state.terms["b_res"] + xw) + wa
    u, info = _solve(system, state.chol_r, state.sqrt_c, state.pc, y, state.options)
    return system.prior.mean + color_apply(state.chol_r, state.sqrt_c, u), DrawInfo(state.wiener, info, state.a_wf)


class JointCGPath(CGPath):
    """The CG path (:class:`~gcrsky.solvers.cg.CGPath`) with its joint flavour: matrix-free CG on the
    whitened joint precision (:func:`prepare_joint_cg`, form ``"cg"``); its solves report their own bounds."""

    joint = True

    def joint_prepare(self, joint, tol, variant):
        inner = prepare_joint_cg(joint, JointCGOptions(tol=tol))
        nf = int(np.shape(jax.block_until_ready(inner.a_wf))[0])
        # one joint solve: its bound is the same for every channel
        wiener = jax.tree_util.tree_map(lambda v: np.broadcast_to(np.asarray(v), (nf,)).copy(), inner.wiener)
        return JointState(self.name, variant, inner, wiener)

    def joint_draw(self, key, state, ndraws):
        x, solved = jax.block_until_ready(draw_joint_cg(key, state.inner, ndraws))
        x = np.moveaxis(np.asarray(x), 0, 1)  # (Nf, ndraws, n)
        # CG's per-draw bound, the same for every channel
        draws = jax.tree_util.tree_map(lambda v: np.broadcast_to(np.asarray(v), x.shape[:2]).copy(), solved.draws)
        return x, DrawInfo(state.wiener, draws, np.asarray(state.a_wf))
