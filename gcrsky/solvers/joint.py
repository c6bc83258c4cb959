"""Exact joint samplers over channels for a frequency-coupled prior (DESIGN section 13).

With a separable prior ``a ~ N(a0, S)``, ``S = R (x) diag(c)``
(:class:`gcrsky.model.spectral.FrequencyPrior`; on ``vec(a)``, channel-major index ``f n + k``)
the joint posterior precision over all channels is

    P = blockdiag_nu(H_nu) + R^-1 (x) diag(c)^-1,     H_nu = X_nu^T W_nu X_nu,

of size ``Nf n``.  The channels are coupled only through the prior.  Everything here works in
the prior-whitened form: with ``G = L_R (x) diag(c)^1/2`` (``R = L_R L_R^T``, so ``S = G G^T``)

    P = G^-T M G^-1,    M = I + G^T blockdiag(H) G,

so only the Cholesky factor of ``R`` is needed (never ``R^-1``: a nearly singular ``R``, e.g. a
smooth kernel over close channels, costs no accuracy), and ``log det M = log det S + log det P``.

* Wiener filter: ``a_wf = a0 + G M^-1 G^T b'`` with ``b' = X^T W (d - X a0)``.
* Draws (the GCR equation ``P a = b + X^T W^1/2 w_d + S^-1/2 w_a`` with unit normal ``w_d``,
  ``w_a`` and the square root ``S^-1/2 = G^-T``):
  ``a = a0 + G M^-1 (G^T (b' + X^T W^1/2 w_d) + w_a)``, exactly ``N(a_wf, P^-1)``.
* Log evidence of all channels together (the normalised density of the real and imaginary
  parts of every unflagged sample under ``d ~ N(X a0, N + X S X^T)``, constants included, as
  :mod:`gcrsky.inference.evidence`): ``-1/2 [r^T W r - b'^T (a_wf - a0) + log det M +
  log det N + N_d log 2 pi]``: one scalar, since the channels are not independent.

Two exact paths:

* dense (:func:`prepare_joint_dense`): ``M`` as one ``(Nf n, Nf n)`` Cholesky; the data part
  ``H_nu`` from :func:`gcrsky.model.system.precision_data_matrix`; any coverage and noise; cost
  ``O(Nf^3 n^3)`` flop, ``O(Nf^2 n^2)`` memory;
* m-mode (:func:`prepare_joint_mmode`, uniform full-day coverage, :func:`gcrsky.solvers.mmode_check`):
  ``H_nu`` is block-diagonal in m (:func:`gcrsky.solvers.mmode.mmode_blocks`), and so is the prior
  coupling (it is diagonal in the mode), so ``M`` is block-diagonal in m with blocks of size
  ``Nf s_m`` (``s_m = 2 (lmax - m + 1)``, ``lmax + 1`` at m = 0), stored per bucket of the
  m-mode layout (:class:`gcrsky.solvers.mmode.MModeBuckets`, padding decoupled).  Cost
  ``O(Nf^3 lmax^4)``.

A flagged channel (``inv_noise`` all 0) has ``H_nu = 0``: its posterior comes through ``R``
alone (inpainting), and it adds no data to the evidence.

Everything is a pure function of its PyTree inputs and differentiates with ``jax.grad``
(the Cholesky factorisations natively), in the prior's hyperparameters in particular.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from ..model.operator import VisOperator, adjoint, apply
from ..model.prior import Prior
from ..model.spectral import FrequencyPrior
from ..model.system import (
    LinearSystem,
    check_system,
    fluctuation_rhs,
    precision_data_matrix,
    precision_matrix_by_time,
)
from ..sphere.modes import lmax_from_nparams
from .dense import CholeskyPath
from .info import DrawInfo, SolveInfo, direct_info, exact_info
from .mmode import MModePath, mmode_blocks, mmode_buckets, mmode_check
from .options import MModeOptions
from .path import JointVariant, is_traced

__all__ = [
    "JointCholeskyPath",
    "JointDenseState",
    "JointMModePath",
    "JointMModeState",
    "JointState",
    "JointSystem",
    "check_joint_system",
    "direct_joint_draw",
    "direct_joint_state",
    "joint_dense_bytes",
    "joint_mmode_bytes",
    "data_system",
    "draw_joint_dense",
    "draw_joint_mmode",
    "joint_evidence_terms",
    "joint_wiener_info",
    "joint_log_evidence_dense",
    "joint_log_evidence_mmode",
    "joint_precision_matrix",
    "prepare_joint_dense",
    "prepare_joint_mmode",
    "whitened_solve",
]

LOG_2PI = float(np.log(2 * np.pi))

#: Bytes per entry of the dense joint path's working set: M and its factor in float64, with slack.
_DENSE_BYTES = 3 * 8


class JointState(NamedTuple):
    """A path's joint flavour, prepared (:meth:`gcrsky.solvers.path.SolverPath.joint_prepare`).

    Attributes:
        method: the path's name (:data:`gcrsky.solvers.registry.PATHS`).
        variant: the form that was prepared (e.g. ``"dense"``, ``"mmode"``).
        inner: the form's own state (:class:`JointDenseState`, :class:`JointMModeState`, ...).
        wiener: the Wiener filter's measured :class:`SolveInfo`, (Nf,) host fields.
    """

    method: str
    variant: str
    inner: object
    wiener: SolveInfo

    @property
    def a_wf(self) -> jax.Array:
        """The joint Wiener filter (Nf, n), Kelvin."""
        return self.inner.a_wf


def direct_joint_state(method: str, variant: str, joint: JointSystem, inner, tol: float, solve) -> JointState:
    """A direct joint form's :class:`JointState`: its Wiener filter's accuracy measured from the true
    residual (:func:`joint_wiener_info`, through ``solve(inner, v)``, the whitened ``M^-1``)."""
    a_wf = np.asarray(jax.block_until_ready(inner.a_wf))
    winfo = jax.tree_util.tree_map(np.asarray, joint_wiener_info(joint, a_wf, tol, solve=partial(solve, inner)))
    return JointState(method, variant, inner, winfo)


def direct_joint_draw(draw, key: jax.Array, state: JointState, ndraws: int) -> tuple[np.ndarray, DrawInfo]:
    """``draw(key, inner, ndraws)`` ((ndraws, Nf, n)) as (Nf, ndraws, n) host draws with the exact
    factor's :class:`DrawInfo` (the Wiener filter's accuracy, ``NONFINITE`` where a draw is not finite)."""
    x = np.moveaxis(np.asarray(jax.block_until_ready(draw(key, state.inner, ndraws))), 0, 1)
    draws = jax.tree_util.tree_map(np.asarray, exact_info(state.wiener, np.isfinite(x).all(axis=-1), x.shape[:2]))
    return x, DrawInfo(state.wiener, draws, np.asarray(state.a_wf))


def joint_dense_bytes(nf: int, n: int) -> float:
    """Estimated peak bytes of the dense a-space joint path (its ``(Nf n)^2`` factor and working set)."""
    return _DENSE_BYTES * float(nf * n) ** 2 + 8.0 * nf * n * n


def joint_mmode_bytes(nf: int, n: int, lmax: int) -> float:
    """Estimated peak bytes of the a-space joint path per order (blocks ``Nf s_m`` wide, ``s_m = 2 (lmax - m + 1)``)."""
    s = 2 * (lmax + 1 - np.arange(lmax + 1))
    return float(np.sum(2 * 8.0 * (nf * s) ** 2)) + 8.0 * nf * n * n


class JointSystem(NamedTuple):
    """The linear system of all channels under a frequency-coupled prior.

    Attributes:
        op: the visibility operator (response (Nf, Nbl, n), angles (Nt,)).
        data: (Nf, Nt, Nbl) complex visibilities, Kelvin-equivalent units of the response.
        inv_noise: (Nf, Nt, Nbl) per-component inverse noise variance (0 = flagged).
        prior: :class:`~gcrsky.model.spectral.FrequencyPrior` (mean (Nf, n), mode_var (n,),
            freq_cov (Nf, Nf)).
    """

    op: VisOperator
    data: jax.Array
    inv_noise: jax.Array
    prior: FrequencyPrior


def data_system(system: JointSystem) -> LinearSystem:
    """The per-channel :class:`~gcrsky.model.LinearSystem` of the data alone (flat prior, ``S^-1 = 0``,
    mean the joint prior's): its precision is ``blockdiag_nu(H_nu)``."""
    mean = system.prior.mean
    return LinearSystem(system.op, system.data, system.inv_noise, Prior(mean, jnp.zeros_like(mean)))


def check_joint_system(system: JointSystem) -> JointSystem:
    """Check a concrete :class:`JointSystem` on the host; raise ``ValueError`` naming what is wrong.

    The data, noise, operator and prior mean as :func:`gcrsky.model.check_system`; ``mode_var``
    (n,) finite and positive; ``freq_cov`` (Nf, Nf) finite and symmetric (to 1e-12 of its
    largest entry) with a positive Cholesky factor.  Traced systems pass unchecked.

    Returns:
        the system, unchanged.
    """
    if is_traced(system):
        return system
    check_system(data_system(system))
    nf, n = np.shape(system.prior.mean)
    c = np.asarray(system.prior.mode_var)
    if c.shape != (n,) or not np.all(np.isfinite(c) & (c > 0)):
        raise ValueError(f"prior.mode_var must be (n,) = ({n},), finite and positive; got shape {c.shape}")
    R = np.asarray(system.prior.freq_cov)
    if R.shape != (nf, nf):
        raise ValueError(f"prior.freq_cov has shape {R.shape}, expected (Nf, Nf) = {(nf, nf)}")
    if not np.all(np.isfinite(R)) or np.abs(R - R.T).max() > 1e-12 * np.abs(R).max():
        raise ValueError("prior.freq_cov must be finite and symmetric")
    try:
        np.linalg.cholesky(R)
    except np.linalg.LinAlgError:
        raise ValueError("prior.freq_cov is not positive definite in float64: give it a nugget "
                         "(gcrsky.model.spectral, e.g. a rank-K spectral basis needs one)") from None
    return system


def joint_evidence_terms(system: JointSystem) -> dict:
    """The solve-free terms of the joint log evidence (scalars, summed over channels), and ``b'``.

    Returns:
        ``{"rWr": r^T W r, "b_res": b' = X^T W r (Nf, n), "logdet_n": log det N,
        "n_data": N_d}`` with ``r = d - X a0`` over the unflagged samples.
    """
    w = system.inv_noise
    kept = w > 0
    safe = jnp.where(kept, w, 1.0)
    r = jnp.where(kept, system.data - apply(system.op, system.prior.mean), 0.0)
    return {
        "rWr": jnp.sum(w * (r.real**2 + r.imag**2)),
        "b_res": adjoint(system.op, w * r),
        "logdet_n": -2.0 * jnp.sum(jnp.where(kept, jnp.log(safe), 0.0)),
        "n_data": 2.0 * jnp.sum(kept),
    }


def prior_whitening(prior: FrequencyPrior):
    """``(L_R (Nf, Nf), sqrt(c) (n,))``: ``G = L_R (x) diag(sqrt c)``."""
    return jnp.linalg.cholesky(prior.freq_cov), jnp.sqrt(prior.mode_var)


def color_apply(LR, sc, u):
    """``G u`` for u (..., Nf, n)."""
    return jnp.einsum("hf,...fk->...hk", LR, u) * sc


def whiten_apply(LR, sc, v):
    """``G^T v`` for v (..., Nf, n)."""
    return jnp.einsum("hf,...hk->...fk", LR, v * sc)


def _data_precision(system: LinearSystem) -> jax.Array:
    """``H_nu`` (Nf, n, n) for any coverage (the m-ordered build; by times when Nt <= 2)."""
    if system.op.angles.shape[0] <= 2:
        return precision_matrix_by_time(system)
    return precision_data_matrix(system.op, system.inv_noise)


def joint_precision_matrix(system: JointSystem) -> jax.Array:
    """The dense joint precision ``blockdiag_nu(H_nu) + R^-1 (x) diag(c)^-1``, (Nf n, Nf n), channel-major.

    For inspection and tests (the samplers never form ``R^-1``).
    """
    H = _data_precision(data_system(system))
    nf, n = H.shape[0], H.shape[1]
    Rinv = jnp.linalg.inv(system.prior.freq_cov)
    P = jnp.kron(Rinv, jnp.diag(1.0 / system.prior.mode_var))
    idx = jnp.arange(nf)
    blocks = jnp.zeros((nf, n, nf, n), H.dtype).at[idx, :, idx, :].set(H)
    return P + blocks.reshape(nf * n, nf * n)


class JointDenseState(eqx.Module):
    """The dense joint path, factorised: Wiener filter, factors and evidence terms.

    Attributes:
        system: the :class:`JointSystem`.
        a_wf: (Nf, n) joint Wiener filter (posterior mean), Kelvin.
        chol: (Nf n, Nf n) lower Cholesky factor of the whitened precision ``M``.
        chol_r: (Nf, Nf) lower Cholesky factor of ``R``.
        sqrt_c: (n,) ``sqrt(mode_var)``.
        terms: :func:`joint_evidence_terms`.
    """

    system: JointSystem
    a_wf: jax.Array
    chol: jax.Array
    chol_r: jax.Array
    sqrt_c: jax.Array
    terms: dict


def prepare_joint_dense(system: JointSystem, *, check: bool = True) -> JointDenseState:
    """Factorise the joint whitened precision ``M = I + G^T blockdiag(H) G`` and solve the Wiener filter.

    Args:
        system: a :class:`JointSystem` (any coverage, noise and flags).
        check: :func:`check_joint_system` first (concrete arrays only; skipped under a trace).

    Returns:
        a :class:`JointDenseState`.  Cost ``O(Nf^3 n^3)``; under a trace a factorisation failure
        (``R`` not positive definite in float64) shows as NaN (check ``jnp.isfinite(state.a_wf)``).

    Raises:
        ValueError: a bad concrete input (``check``).
    """
    if check:
        check_joint_system(system)
    return _prepare_dense(system)


@jax.jit
def _prepare_dense(system: JointSystem) -> JointDenseState:
    LR, sc = prior_whitening(system.prior)
    H = _data_precision(data_system(system))
    nf, n = H.shape[0], H.shape[1]
    Hs = H * sc[None, :, None] * sc[None, None, :]
    M = jnp.einsum("hf,hg,hkj->fkgj", LR, LR, Hs).reshape(nf * n, nf * n) + jnp.eye(nf * n, dtype=H.dtype)
    L = jnp.linalg.cholesky(M)
    terms = joint_evidence_terms(system)
    u = jsl.cho_solve((L, True), whiten_apply(LR, sc, terms["b_res"]).reshape(-1)).reshape(nf, n)
    a_wf = system.prior.mean + color_apply(LR, sc, u)
    return JointDenseState(system, a_wf, L, LR, sc, terms)


def joint_noise_terms(key, system: JointSystem, ndraws: int):
    """``(X^T W^1/2 w_d, w_a)`` for ``ndraws`` draws: (ndraws, Nf, n) each."""
    ds = data_system(system)
    kd, ka = jax.random.split(key)
    xw = jax.vmap(lambda k: fluctuation_rhs(k, ds))(jax.random.split(kd, ndraws))  # S^-1 = 0: data part only
    wa = jax.random.normal(ka, (ndraws,) + system.prior.mean.shape, system.prior.mean.dtype)
    return xw, wa


@partial(jax.jit, static_argnames=("ndraws",))
def draw_joint_dense(key: jax.Array, state: JointDenseState, ndraws: int) -> jax.Array:
    """``ndraws`` exact joint posterior draws (ndraws, Nf, n) by the GCR equation (module docstring)."""
    xw, wa = joint_noise_terms(key, state.system, ndraws)
    LR, sc = state.chol_r, state.sqrt_c
    y = whiten_apply(LR, sc, state.terms["b_res"] + xw) + wa
    nf, n = state.a_wf.shape
    u = jax.vmap(lambda v: jsl.cho_solve((state.chol, True), v.reshape(-1)).reshape(nf, n))(y)
    return state.system.prior.mean + color_apply(LR, sc, u)


def _evidence(state, logdet_m):
    t = state.terms
    chi2 = t["rWr"] - jnp.sum(t["b_res"] * (state.a_wf - state.system.prior.mean))
    return -0.5 * (chi2 + logdet_m + t["logdet_n"] + t["n_data"] * LOG_2PI)


def joint_log_evidence_dense(state: JointSystem | JointDenseState, *, check: bool = True) -> jax.Array:
    """The joint log evidence ``log p(d)`` of all channels (a scalar; module docstring).

    Args:
        state: a :class:`JointSystem` (factorised here, checked on concrete arrays with ``check``)
            or a :class:`JointDenseState`.

    Differentiable (``jax.grad``) in everything the system holds, e.g. the prior's hyperparameters.
    """
    if isinstance(state, JointSystem):
        state = prepare_joint_dense(state, check=check)
    return _evidence(state, 2.0 * jnp.sum(jnp.log(jnp.diagonal(state.chol))))


def joint_wiener_info(system: JointSystem, a_wf: jax.Array, tol: float, *, solve=None) -> SolveInfo:
    """The measured accuracy of a joint Wiener filter, from its true residual computed matrix-free.

    With ``delta = a_wf - a0`` and ``u = G^-1 delta`` the whitened solve is ``M u = y``,
    ``y = G^T b'``; its true residual ``r = y - u - G^T blockdiag(H) delta`` is computed with
    the operator's products (``H delta = X^T W X delta``), independently of the factor that
    produced ``a_wf``.  The error's M-norm (the error in posterior sigma) is
    ``sqrt(r^T M^-1 r)``: with ``solve`` (``v -> M^-1 v`` by the path's factor:
    :func:`whitened_solve`, :func:`gcrsky.solvers.joint_dataspace.whitened_solve_dataspace`)
    as every direct path measures its solves (:func:`gcrsky.solvers.info.direct_info`); without, the bound
    ``||r||_2`` (``M >= I``), which rounding in ``H delta`` dominates when the data are
    much more precise than the prior (it grows like ``eps ||M|| ||u||``).

    Args:
        system: the :class:`JointSystem`; a_wf: (Nf, n) its Wiener filter, Kelvin.
        tol: the accuracy asked for, posterior sigma.
        solve: ``M^-1`` by the path's factor, a function of (Nf, n) whitened vectors, or None (keyword).

    Returns:
        a :class:`~gcrsky.solvers.SolveInfo` with (Nf,) fields (the joint solve's figures,
        the same for every channel: the channels are solved together).
    """
    LR, sc = prior_whitening(system.prior)
    delta = jnp.asarray(a_wf) - system.prior.mean
    b_res = joint_evidence_terms(system)["b_res"]
    h_delta = adjoint(system.op, system.inv_noise * apply(system.op, delta))
    u = jsl.solve_triangular(LR, (delta / sc).reshape(delta.shape[0], -1), lower=True)
    y = whiten_apply(LR, sc, b_res)
    r = y - u - whiten_apply(LR, sc, h_delta)
    if solve is None:
        err = jnp.linalg.norm(r)
    else:
        err = jnp.sqrt(jnp.maximum(jnp.sum(r * solve(r)), 0.0))
    rel = jnp.linalg.norm(r) / jnp.maximum(jnp.linalg.norm(y), jnp.finfo(r.dtype).tiny)
    nf = delta.shape[0]
    finite = jnp.all(jnp.isfinite(delta))
    return direct_info(jnp.full((nf,), err), jnp.full((nf,), rel), jnp.full((nf,), finite), tol)


def whitened_solve(state, v: jax.Array) -> jax.Array:
    """``M^-1 v`` for whitened vectors v (Nf, n) with a factorised joint path's factor.

    Args:
        state: a :class:`JointDenseState` or :class:`JointMModeState`.
        v: (Nf, n) in the prior-whitened coordinates ``u = G^-1 (a - a0)``.
    """
    nf, n = state.a_wf.shape
    if isinstance(state, JointDenseState):
        return jsl.cho_solve((state.chol, True), v.reshape(-1)).reshape(nf, n)
    lay = mmode_buckets(state.lmax, state.quantum)
    eye, ones = jnp.eye(nf, dtype=v.dtype), bucket_scales(jnp.ones(n, v.dtype), lay)
    us = bucket_solve(state.chol, whiten_buckets(eye, ones, v, lay))
    return color_buckets(eye, ones, us, lay, nf, n)


# ---------------------------------------------------------------- m-mode


class JointMModeState(eqx.Module):
    """The joint m-mode path, factorised.

    Attributes:
        system: the :class:`JointSystem`.
        a_wf: (Nf, n) joint Wiener filter, Kelvin.
        chol: per bucket of :func:`gcrsky.solvers.mmode.mmode_buckets`, (G, Nf S, Nf S) lower
            Cholesky factors of the whitened blocks ``M_m`` (index ``f S + i``; identity on padding).
        chol_r: (Nf, Nf) lower Cholesky factor of ``R``.
        sqrt_c: (n,) ``sqrt(mode_var)``.
        terms: :func:`joint_evidence_terms`.
        lmax: band limit (static).
        quantum: the bucket layout's padding quantum (static).
    """

    system: JointSystem
    a_wf: jax.Array
    chol: tuple
    chol_r: jax.Array
    sqrt_c: jax.Array
    terms: dict
    lmax: int = eqx.field(static=True)
    quantum: int = eqx.field(static=True)


def bucket_scales(sc, lay):
    """Per bucket (G, S): ``sqrt c`` on real entries, 0 on padding."""
    return tuple(jnp.where(mk, sc[g], 0.0) for g, mk in zip(lay.gather, lay.mask))


def whiten_buckets(LR, scb, v, lay):
    """``G^T v`` for v (..., Nf, n), per bucket (..., G, Nf S)."""
    out = []
    for g, mk, s in zip(lay.gather, lay.mask, scb):
        vb = jnp.where(mk, v[..., g], 0.0)  # (..., Nf, G, S)
        y = jnp.einsum("hf,...hgi->...gfi", LR, vb) * s[:, None, :]
        out.append(y.reshape(y.shape[:-2] + (-1,)))
    return tuple(out)


def color_buckets(LR, scb, us, lay, nf, n):
    """``G u`` from per bucket u (..., G, Nf S) to (..., Nf, n)."""
    out = None
    for u, s, src, dst in zip(us, scb, lay.src, lay.dst):
        u = u.reshape(u.shape[:-1] + (nf, -1))  # (..., G, Nf, S)
        x = jnp.einsum("hf,...gfi->...hgi", LR, u * s[:, None, :])  # (..., Nf, G, S)
        x = x.reshape(x.shape[:-2] + (-1,))[..., src]
        if out is None:
            out = jnp.zeros(x.shape[:-1] + (n,), x.dtype)
        out = out.at[..., dst].add(x)
    return out


def bucket_solve(chols, ys):
    """``M_m^-1 y`` per bucket: chols (G, K, K), ys (..., G, K)."""
    out = []
    for L, y in zip(chols, ys):
        lead, (G, K) = y.shape[:-2], y.shape[-2:]
        yy = jnp.moveaxis(y.reshape((-1, G, K)), 0, -1)  # (G, K, B)
        x = jax.vmap(lambda L, b: jsl.cho_solve((L, True), b))(L, yy)
        out.append(jnp.moveaxis(x, -1, 0).reshape(lead + (G, K)))
    return tuple(out)


@partial(jax.jit, static_argnames=("quantum",))
def _prepare_mmode(system: JointSystem, quantum: int) -> JointMModeState:
    LR, sc = prior_whitening(system.prior)
    nf, n = system.prior.mean.shape
    blocks = mmode_blocks(data_system(system), quantum)  # (Nf, G, S, S): H_nu's m-blocks, identity on padding
    lay = blocks.layout
    scb = bucket_scales(sc, lay)
    chols = []
    for Hd, s in zip(blocks.arrays, scb):
        G, S = s.shape
        Hs = Hd * s[None, :, :, None] * s[None, :, None, :]  # padding rows and columns now 0
        M = jnp.einsum("hf,hk,hgij->gfikj", LR, LR, Hs).reshape(G, nf * S, nf * S)
        chols.append(jnp.linalg.cholesky(M + jnp.eye(nf * S, dtype=M.dtype)))
    chols = tuple(chols)
    terms = joint_evidence_terms(system)
    us = bucket_solve(chols, whiten_buckets(LR, scb, terms["b_res"], lay))
    a_wf = system.prior.mean + color_buckets(LR, scb, us, lay, nf, n)
    return JointMModeState(system, a_wf, chols, LR, sc, terms, blocks.lmax, quantum)


def prepare_joint_mmode(system: JointSystem, options: MModeOptions | None = None, *,
                        check: bool = True) -> JointMModeState:
    """Factorise the joint precision m-block by m-block and solve the Wiener filter.

    Exact only for uniform full-day coverage with time-constant noise (flagged *channels*,
    all-zero ``inv_noise``, are fine; flagged samples within a channel are not):
    :func:`gcrsky.solvers.mmode_check` on the data, checked here on concrete arrays
    (``check``; skipped under a trace).

    Args:
        system: a :class:`JointSystem` with ``op.frame is None``.
        options: :class:`~gcrsky.solvers.MModeOptions` (its ``bucket`` quantum and the
            check's tolerances).

    Returns:
        a :class:`JointMModeState`; blocks of size ``Nf s_m``.

    Raises:
        ValueError: the coverage or noise breaks the m-block structure (``check``).
    """
    options = options or MModeOptions()
    if check and not is_traced(system):
        check_joint_system(system)
        ok = mmode_check(data_system(system), atol=options.atol, rtol=options.rtol)
        if not ok:
            raise ValueError(f"the joint m-mode path does not apply: {ok.reason}")
    lmax_from_nparams(system.prior.mean.shape[-1])
    return _prepare_mmode(system, options.bucket)


@partial(jax.jit, static_argnames=("ndraws",))
def draw_joint_mmode(key: jax.Array, state: JointMModeState, ndraws: int) -> jax.Array:
    """``ndraws`` exact joint posterior draws (ndraws, Nf, n) on the m-mode path (GCR equation)."""
    xw, wa = joint_noise_terms(key, state.system, ndraws)
    lay = mmode_buckets(state.lmax, state.quantum)
    LR, sc = state.chol_r, state.sqrt_c
    scb = bucket_scales(sc, lay)
    nf, n = state.a_wf.shape
    ys = whiten_buckets(LR, scb, state.terms["b_res"] + xw, lay)
    wab = whiten_buckets(jnp.eye(nf, dtype=LR.dtype), bucket_scales(jnp.ones_like(sc), lay), wa, lay)
    us = bucket_solve(state.chol, tuple(y + w for y, w in zip(ys, wab)))
    return state.system.prior.mean + color_buckets(LR, scb, us, lay, nf, n)


def joint_log_evidence_mmode(state: JointSystem | JointMModeState, *, check: bool = True) -> jax.Array:
    """The joint log evidence (scalar) on the m-mode path (module docstring).

    Args:
        state: a :class:`JointSystem` (factorised here, checked as in :func:`prepare_joint_mmode`)
            or a :class:`JointMModeState`.

    Differentiable in the prior's hyperparameters and anything else that keeps the noise
    stationary.
    """
    if isinstance(state, JointSystem):
        state = prepare_joint_mmode(state, check=check)
    logdet = sum(2.0 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1))) for L in state.chol)
    return _evidence(state, logdet)


# ---------------------------------------------------------------- the paths' joint flavours


class JointCholeskyPath(CholeskyPath):
    """The Cholesky path (:class:`~gcrsky.solvers.dense.CholeskyPath`) with its joint flavour: the dense
    a-space joint precision (:func:`prepare_joint_dense`, form ``"dense"``)."""

    joint = True

    def joint_variants(self, joint, full_day, requested):
        if full_day and not requested:  # auto: the per-order a-space form (mmode) instead
            return []
        nf, n = (int(x) for x in np.shape(joint.prior.mean))
        return [JointVariant("dense", joint_dense_bytes(nf, n), float(nf * n))]

    def joint_prepare(self, joint, tol, variant):
        return direct_joint_state(self.name, variant, joint, prepare_joint_dense(joint), tol, whitened_solve)

    def joint_draw(self, key, state, ndraws):
        return direct_joint_draw(draw_joint_dense, key, state, ndraws)


class JointMModePath(MModePath):
    """The m-mode path (:class:`~gcrsky.solvers.mmode.MModePath`) with its joint flavour: the joint
    precision's blocks per order for uniform full-day coverage (:func:`prepare_joint_mmode`, form ``"mmode"``)."""

    joint = True

    def joint_check(self, joint, mmode):
        return "" if bool(mmode) else f"the joint m-mode path does not apply: {mmode.reason}"

    def joint_variants(self, joint, full_day, requested):
        if not full_day:
            return []
        nf, n = (int(x) for x in np.shape(joint.prior.mean))
        lmax = int(round(np.sqrt(n))) - 1
        s = 2 * (lmax + 1 - np.arange(lmax + 1))
        return [JointVariant("mmode", joint_mmode_bytes(nf, n, lmax), float(np.mean(nf * s)))]

    def joint_prepare(self, joint, tol, variant):
        return direct_joint_state(self.name, variant, joint, prepare_joint_mmode(joint), tol, whitened_solve)

    def joint_draw(self, key, state, ndraws):
        return direct_joint_draw(draw_joint_mmode, key, state, ndraws)
