"""The data-space path with a frame map: a stationary proxy factor and preconditioned CG (exact).

A file's ICRS coefficients always carry a frame map ``M = D_out A D_in``
(:class:`gcrsky.sphere.frames.FrameMap`: two Wigner rotations and annual aberration
``A ~ I + O(l |v|)``, ``|v| ~ 1e-4``, output degree ``lmax_out = lmax + pad``), which breaks the
stationary shortcut of :mod:`gcrsky.solvers.dataspace` (``lag_structure`` is None) and with it
the in-place set-up: D would cost ``~N_d^2 n`` flop and the rows' memory.

**The proxy.**  For a prior whose covariance is isotropic (``Var(a_l0) = C_l``,
``Var(Re a_lm) = Var(Im a_lm) = C_l / 2``: any ``C_l`` prior, :func:`gcrsky.model.isotropic_prior`)
a rotation keeps S: ``D_rot S D_rot^T = S``.  So with ``M0 = D_out D_in`` (``A`` replaced by the
embedding of ``l <= lmax`` in ``lmax_out``) ``X0_t S X0_t'^T = R Q(t) S_pad Q(t')^T R^T``: the
stationary form of the system *without* a frame map whose response is the file's truncated to the
columns with ``l <= lmax`` (in the realified, m-major layout of :mod:`gcrsky.sphere.modes` those
entries, in order, are the ``lmax`` layout).  :func:`stationary_proxy` builds that system (same
angles, noise, prior; frame None).  Its ``D0 = I + Y0 S Y0^T`` differs from the true
``D = I + Y S Y^T`` only through aberration (relative ``~ 2 lmax |v|``), so ``D0^-1`` is an excellent
preconditioner for D: it is factorised once by the existing stationary machinery (lag blocks by m,
the in-place host factor or the jnp Cholesky factor), and every ``D^-1 b`` (the Wiener filter, each
draw) is preconditioned CG with the *true* matrix-free ``D v = v + Y S Y^T v``
(:func:`pcg_solve`), batched over draws and channels with one iteration count per solve.

**Rigorous stop.**  For ``x ~ D^-1 b`` with residual ``r = b - D x`` the error ``e = x - x*`` of the
sky ``a = a_u + S Y^T x`` in posterior-sigma units is
``||S Y^T e||_P^2 = e^T Y S P S Y^T e = e^T (D - I) D e = r^T (I - D^-1) r <= ||r||_2^2``
(Woodbury: ``Y S P S Y^T = (D - I) D`` with ``P = S^-1 + Y^T Y``, and ``D >= I``).  So CG stops when
``||r||_2 <= tol`` (:class:`~gcrsky.solvers.DataSpaceOptions` ``tol``, posterior sigma) per solve, and
reports ``||r||_2`` of the true final residual as ``err_sigma`` (a bound) with its iteration count;
a solve that misses it within ``DataSpaceOptions.maxiter`` iterations is reported as not converged
(``Result.MAX_ITERATIONS``), never silently.

**Derivatives** are implicit against the true D (``jax.lax.custom_linear_solve`` with the
matrix-free product; the proxy's factor is held fixed: it changes the path, not the answer).

**What it does not give:** ``log det D`` (the evidence from such a state raises, naming the
alternative: :func:`gcrsky.inference.log_evidence_system`, which builds the exact D).
"""

from __future__ import annotations

import logging

import jax
import jax.numpy as jnp
import numpy as np

from ..model.operator import VisOperator, uses_mfactor
from ..model.system import LinearSystem
from ..sphere.frames import FrameMap, frame_lmax
from ..sphere.modes import mode_table
from ..sphere.rotation import wigner_nbytes
from .dataspace_large import dataspace_large_bytes
from .info import Result, SolveInfo, result_code
from .path import is_traced

__all__ = [
    "PROXY_ABERRATION_COPIES",
    "PROXY_FIXED_PARAM_VECTORS",
    "PROXY_ITERATIONS",
    "PROXY_WIGNER_COPIES",
    "anisotropy",
    "batched_pcg",
    "pcg_solve",
    "proxy_applies",
    "proxy_draw_bytes",
    "proxy_memory_bytes",
    "stationary_proxy",
    "truncation_index",
]

log = logging.getLogger(__name__)

#: Iterations per solve the planner's cost model assumes (measured 3-6 at lmax 8-20, tol 1e-6..1e-10;
#: the aberration's relative size grows like lmax, so a few more at lmax ~300).
PROXY_ITERATIONS = 10
#: Transient copies of the frame map's Wigner blocks (:func:`gcrsky.sphere.wigner_nbytes` bytes each) a batch of
#: products with the true D holds: the dots of :func:`gcrsky.sphere.rotate_euler` pack them (outside XLA's
#: buffers), a band cut to a smaller lmax is sliced.  Measured at lmax 200 (60 rows, 30 times, 2 and 10 draws):
#: XLA's temporaries and the process's peak beyond the factor's ~1.8 copies (margin: 3).
PROXY_WIGNER_COPIES = 3.0
#: Transient copies of the frame map's aberration blocks (``8 (lmax_out+1)^2 (lmax_in+1)`` bytes each): with
#: the Wigner copies above they bound XLA's fixed temporaries at lmax 12 as well (where they are ~3.3 Wigner copies).
PROXY_ABERRATION_COPIES = 2.0
#: Parameter-sized (``8 Nf n_resp``) temporaries a batch holds whatever its size (the rotations' (l, m) grids,
#: the Wiener parts): what dominates XLA's fixed temporaries at small lmax (~77 measured at lmax 12).
PROXY_FIXED_PARAM_VECTORS = 100.0
#: Parameter-sized (``8 Nf n_resp``) arrays per draw of a batch of products with the true D (the frame map's
#: complex (l, m) grids, the rotations' results, CG's products): XLA's memory analysis at lmax 40: ~22.
PROXY_PARAM_VECTORS = 24.0
#: Relative tolerance of the isotropy check of the prior's variances (per degree).
ISOTROPY_RTOL = 1e-12


def anisotropy(inv_var) -> str:
    """``""`` if the prior covariance is isotropic (``var * (1 if m == 0 else 2)`` the same for every
    entry of each degree l, every channel), else the first degree where it is not (host-side).

    Args:
        inv_var: (Nf, n) prior inverse variances (concrete), ``n = (lmax + 1)^2``.
    """
    iv = np.asarray(inv_var, np.float64)
    lmax = int(round(np.sqrt(iv.shape[-1]))) - 1
    if (lmax + 1) ** 2 != iv.shape[-1]:
        return f"{iv.shape[-1]} parameters is not (lmax + 1)^2"
    tab = mode_table(lmax)
    with np.errstate(divide="ignore", invalid="ignore"):
        cl = np.where(tab.m == 0, 1.0, 2.0) / iv  # C_l per entry, K^2
    ref = cl[:, tab.ell]  # the (l, m = 0) entry of each degree: the first lmax + 1 entries are m = 0, index l
    bad = ~(np.abs(cl - ref) <= ISOTROPY_RTOL * np.abs(ref))
    if bad.any():
        ell = int(tab.ell[np.argwhere(bad)[0, 1]])
        return f"the prior's variances at l = {ell} are not those of a C_l (Var(a_l0) = 2 Var(Re a_lm))"
    return ""


def truncation_index(lmax: int, lmax_out: int) -> np.ndarray:
    """Indices of the entries with ``l <= lmax`` in the realified ``lmax_out`` layout, in order: they are
    the ``lmax`` layout (m-major healpy order, Re then Im; :mod:`gcrsky.sphere.modes`)."""
    return np.flatnonzero(mode_table(lmax_out).ell <= lmax)


def proxy_applies(system: LinearSystem) -> str:
    """``""`` if :func:`stationary_proxy` gives a proxy for ``system``, else why not (host-side)."""
    op = system.op
    if op.frame is None:
        return "no frame map (the stationary shortcut itself applies)"
    if not isinstance(op.frame, FrameMap):
        return "the frame map is a dense matrix, not rotations and aberration"
    if is_traced((op.angles, op.response, system.prior.inv_var, system.inv_noise)):
        return "traced arrays (the proxy's factor is set up on concrete ones)"
    lin, lout = frame_lmax(op.frame)
    if system.prior.inv_var.shape[-1] != (lin + 1) ** 2 or op.response.shape[-1] != (lout + 1) ** 2:
        return "the response / prior sizes do not match the frame map's degrees"
    return anisotropy(system.prior.inv_var)


def stationary_proxy(system: LinearSystem) -> LinearSystem | None:
    """The stationary proxy of a system with a frame map (module docstring), or None where it does not apply.

    None (and why, in the debug log) when there is no frame map or it is not a
    :class:`~gcrsky.sphere.frames.FrameMap`, when arrays are traced, or when the prior is not
    isotropic per l (then ``D0`` would not be ``D`` up to aberration).

    Returns:
        the system with response ``R[..., idx]`` (Nf, Nbl, n) for the entries ``idx`` with
        ``l <= lmax`` (:func:`truncation_index`), the same angles, data, noise and prior, frame None.
    """
    why = proxy_applies(system)
    if why:
        log.debug("no stationary proxy: %s", why)
        return None
    op = system.op
    idx = truncation_index(*frame_lmax(op.frame))
    response = jnp.asarray(op.response)[..., jnp.asarray(idx)]
    return system._replace(op=VisOperator(response, op.angles, None))


# ---------------------------------------------------------------- preconditioned CG, batched


def _dot(u, v):
    return jnp.sum(u * v, axis=-1)


def _pcg_pass(matvec, precond, x, r, k0, thresh, maxiter):
    """One batched PCG pass from ``x`` with its true residual ``r``, lanes frozen once ``||r|| <= thresh``.

    Returns ``(k, iterations (batch), x, broke (batch))`` with ``k`` the loop's count (all lanes)."""
    z = precond(r)
    rz = _dot(r, z)
    active = jnp.sqrt(_dot(r, r)) > thresh
    zero = jnp.zeros(rz.shape, bool)
    init = (k0, jnp.zeros(rz.shape, jnp.int32), x, r, z, rz, active, zero)

    def cond(s):
        return (s[0] < maxiter) & jnp.any(s[6])

    def body(s):
        k, it, x, r, p, rz, active, broke = s
        Ap = matvec(p)
        pAp = _dot(p, Ap)
        bad = active & ~(pAp > 0)
        go = active & ~bad
        alpha = jnp.where(go, rz / jnp.where(go, pAp, 1.0), 0.0)[..., None]
        x = x + alpha * p
        r = r - alpha * Ap
        z = precond(r)
        rz_new = _dot(r, z)
        beta = (rz_new / jnp.where(rz == 0, 1.0, rz))[..., None]
        p = jnp.where(go[..., None], z + beta * p, p)
        rz = jnp.where(go, rz_new, rz)
        it = it + go.astype(jnp.int32)
        return k + 1, it, x, r, p, rz, go & (jnp.sqrt(_dot(r, r)) > thresh), broke | bad

    k, it, x, *_, broke = jax.lax.while_loop(cond, body, init)
    return k, it, x, broke


def batched_pcg(matvec, precond, b, *, tol: float, maxiter: int, rtol: float = 0.0):
    """Preconditioned CG for a batch of independent SPD systems; not differentiable itself (:func:`pcg_solve`).

    Each lane (every leading index of ``b``) stops when its residual's 2-norm
    ``||b - A x||_2 <= max(tol, rtol ||b||_2)``; after the loop CG restarts once from the true residual
    (residual replacement), so the reported residual is that of the returned x.  Products with A: the
    iterations, plus one true residual (plus one more only where the restart iterates).

    Args:
        matvec: x (..., N) -> A x, acting lane by lane (A block-diagonal over the lanes, SPD).
        precond: r (..., N) -> M^-1 r, lane by lane, SPD.
        b: (..., N) right-hand sides.
        tol: absolute threshold on ``||r||_2`` (posterior sigma for the data-space D, module docstring).
        maxiter: cap on the loop's iterations, both passes together.
        rtol: relative threshold (0: absolute only).

    Returns:
        ``(x (..., N), SolveInfo)`` with (...) fields: iterations (of the lane), ``err_sigma`` = the true
        ``||b - A x||_2``, ``rel_residual`` = that over ``||b||_2``, the result code.
    """
    thresh = jnp.maximum(tol, rtol * jnp.sqrt(_dot(b, b)))
    k, it1, x, broke1 = _pcg_pass(matvec, precond, jnp.zeros_like(b), b, jnp.asarray(0), thresh, maxiter)
    r = b - matvec(x)  # the true residual of the first pass's x
    _, it2, x2, broke2 = _pcg_pass(matvec, precond, x, r, k, thresh, maxiter)
    # the second pass usually stops at once (its true residual already meets the stop): then x and r are final
    # and no further product is needed; otherwise the true residual of its x (``cond``: one product or none)
    r = jax.lax.cond(jnp.any(it2 > 0), lambda: b - matvec(x2), lambda: r)
    x = x2
    err = jnp.sqrt(_dot(r, r))
    rel = err / jnp.maximum(jnp.sqrt(_dot(b, b)), jnp.finfo(b.dtype).tiny)
    finite = jnp.isfinite(err) & jnp.all(jnp.isfinite(x), axis=-1)
    code = result_code(err <= thresh, finite=finite, broke=broke1 | broke2)
    return x, SolveInfo(it1 + it2, err, rel, code == Result.SUCCESS, code)


def pcg_solve(matvec, precond, b, *, tol: float, maxiter: int):
    """``A^-1 b`` by :func:`batched_pcg`, differentiated implicitly against ``matvec``
    (``jax.lax.custom_linear_solve``, symmetric: ``dx = A^-1 (db - dA x)``).

    The forward solve stops at ``tol`` (absolute, 2-norm per lane); the cotangent solve of reverse mode
    at ``tol`` relative to its right-hand side.  ``precond`` must not carry derivatives (close over
    ``stop_gradient``-ed arrays): it changes the path, not the answer.

    Returns:
        ``(x like b, SolveInfo)`` of the forward solve (not differentiated).
    """

    def solve(mv, rhs):
        return batched_pcg(mv, precond, rhs, tol=tol, maxiter=maxiter)

    def transpose_solve(mv, rhs):
        return batched_pcg(mv, precond, rhs, tol=0.0, maxiter=maxiter, rtol=tol)

    x, info = jax.lax.custom_linear_solve(matvec, b, solve, transpose_solve, symmetric=True, has_aux=True)
    return x, jax.tree_util.tree_map(jax.lax.stop_gradient, info)


# ---------------------------------------------------------------- sizes


def proxy_draw_bytes(system: LinearSystem, ndraws: int = 1) -> float:
    """Per-batch bytes of the proxy's CG solves, beyond the factor: per draw ~10 data-space vectors
    (``8 Nf N_d`` each: x, r, z, p, A p, the batch's right-hand side and temporaries),
    :data:`PROXY_PARAM_VECTORS` parameter-sized ones (``8 Nf n_resp``) and, where the operator
    is not m-factorised (:func:`gcrsky.model.operator.uses_mfactor`), its rotated copies
    (``2 x 8 Nf Nt n_resp``); plus transient copies of the frame map's Wigner and aberration blocks
    (:data:`PROXY_WIGNER_COPIES`, :data:`PROXY_ABERRATION_COPIES`; the system holds one more of each) and
    :data:`PROXY_FIXED_PARAM_VECTORS` parameter-sized ones."""
    nf, nt, nbl = (int(x) for x in system.data.shape)
    n = int(system.prior.mean.shape[-1])
    n_resp = int(system.op.response.shape[-1])
    blocks = getattr(system.op.frame, "blocks", None)
    fixed = 0.0 if blocks is None else PROXY_WIGNER_COPIES * wigner_nbytes(blocks)
    ab = getattr(system.op.frame, "aberration", None)
    fixed += 0.0 if ab is None else PROXY_ABERRATION_COPIES * 8.0 * float(np.prod(ab.shape))
    fixed += PROXY_FIXED_PARAM_VECTORS * 8 * nf * max(n, n_resp)
    per_draw = 10.0 * 8 * nf * 2 * nt * nbl + PROXY_PARAM_VECTORS * 8 * nf * max(n, n_resp)
    if not uses_mfactor(system.op):
        per_draw += 2.0 * 8 * nf * nt * n_resp
    return fixed + max(1, ndraws) * per_draw


def proxy_memory_bytes(system: LinearSystem, nlags: int, ndraws: int = 1, in_place: bool = True) -> float:
    """Estimated peak bytes of the proxy set-up and a batch of ``ndraws`` CG draws (float64): the in-place
    factor's set-up (:func:`gcrsky.solvers.dataspace_large.dataspace_large_bytes` of the proxy: D0 once), or
    with ``in_place=False`` the jnp factor's (D0, its factor and a transient copy, ``3 x 8 Nf N_d^2``, plus
    the lag blocks), then :func:`proxy_draw_bytes`.  No rows and no exact D are ever formed."""
    nf, nt, nbl = (int(x) for x in system.data.shape)
    nd = 2 * nt * nbl
    if in_place:
        setup = dataspace_large_bytes(system, nlags, 1) - 6.0 * 8 * nf * (nd + int(system.prior.mean.shape[-1]))
    else:
        setup = 3.0 * 8 * nf * nd * nd + 2.0 * 8 * nlags * nf * (2 * nbl) ** 2
    return setup + proxy_draw_bytes(system, ndraws)
