"""Gains sampled with the sky: the gain block, the sky given gains, the gauge move (issue 23).

The model is :mod:`gcrsky.model.gains`' linearised one, ``d = q G (1 + x_i + conj(x_j)) X a + n``
with ``G = gbar_i conj(gbar_j)`` the applied calibration, ``x`` the perturbation coefficients
``theta`` (P,) (real-stacked, gauge-fixed), ``q = A^2`` the overall amplitude squared and ``a``
the sky.  It is linear in each of ``a``, ``theta`` and ``q`` given the others, so every block
has an exact Gaussian conditional (per-component inverse noise variance ``W``, as in
:mod:`gcrsky.model.system`):

* ``theta | a, q, d`` (:func:`gains_step`): with ``z = q G X a`` and ``r = d - z``,
  ``P_theta = Re(J^H W J) + Lambda^-1`` and ``b = Re(J^H W r)``, where
  ``J theta = z (x_i + conj(x_j))``.  ``J`` is never built: per row the weighted mode
  products ``Q_b = sum_ft W |z|^2 B B^T`` (Nbl, K, K) and ``R_b = sum_ft W conj(r) z B``
  reduce the data in ``O(Nf Nt Nbl K^2)``, and ``P_theta`` is the Hessian of the quadratic
  form ``1/2 sum_b e_b^H Q_b e_b`` (``e_b = c_i + conj(c_j)``) by autodiff, ``O(P Nbl K^2)``;
  then one ``P x P`` Cholesky;
* ``a | theta, q, d`` (:func:`gain_sky_step`): the sky's system with data ``d / D`` and
  inverse noise ``W |D|^2`` (``D = q G (1 + x_i + conj(x_j))``); the response, its rotation and
  (CG path) the preconditioner's sketch are reused, the data term rebuilt on the Cholesky path
  (``~8 Nf Nbl n^2`` flop and one Cholesky per channel);
* ``s | a, theta, d`` (:func:`scale_step`): ``q(nu) = A^2 = basis_f s`` on the frequency
  modes; Gaussian, truncated to ``q > 0``, under a Gaussian prior on ``s`` (flat by default);
* the gauge move (:func:`gauge_step`): the likelihood depends on ``q(nu) a(nu)`` only, so plain
  Gibbs crawls along ``(s, a) -> (s', a q / q')``, pinned only by the priors.  The move
  proposes ``s' = s + delta`` (symmetric) and accepts with
  ``pi(s', a') prod_f (q_f / q'_f)^n / pi(s, a)`` (the Jacobian): the likelihood cancels
  exactly, so a move costs ``O(Nf n)``.

:func:`joint_gain_step` is one sweep of all of them, in the blackjax form::

    fixed = gibbs_setup(system)                       # the sky system with the raw data d and W
    block = gain_setup(model, sigma=0.05)             # the gain prior and the applied gains
    state = gain_init(system.prior.mean, block)
    state, info = joint_gain_step(key, state, fixed, block)   # jit / lax.scan it
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.gains import (
    GainModel,
    gain_factor,
    n_gain_params,
    pair_gains,
    perturbation_coefficients,
    perturbations,
    scale_profile,
)
from ..model.operator import adjoint, apply
from ..model.system import precision_data_matrix
from ..solvers.info import SolveInfo, direct_info
from .gibbs import GibbsFixed, sky_step

__all__ = [
    "GainBlock",
    "GainInfo",
    "GainState",
    "gain_conditional",
    "gain_init",
    "gain_posterior",
    "gain_setup",
    "gain_sky_step",
    "gained_fixed",
    "gains_step",
    "gauge_step",
    "gauge_step_size",
    "joint_gain_step",
    "recentre",
    "scale_conditional",
    "scale_sky_step",
    "scale_step",
    "theta_draw",
]


class GainBlock(NamedTuple):
    """The gain block's fixed parts (a PyTree; :func:`gain_setup`).

    Attributes:
        model: the perturbations' layout (:func:`gcrsky.model.gain_model`).
        pair_gains: ``G = gbar_i conj(gbar_j)`` (Nf, Nt, Nbl) complex, the applied calibration.
        prior_inv_var: (P,) inverse prior variance of ``theta`` (fractional gain per mode)^-2.
        prior_mean: (P,) prior mean of ``theta`` (0; ``-theta0`` after :func:`recentre` at ``theta0``).
        scale_mean, scale_inv_var: (Kf,) the Gaussian prior of the scale's coefficients ``s``
            (``q(nu) = basis_f s``; inverse variance 0: flat on ``q > 0``).
    """

    model: GainModel
    pair_gains: jax.Array
    prior_inv_var: jax.Array
    prior_mean: jax.Array
    scale_mean: jax.Array
    scale_inv_var: jax.Array


class GainState(NamedTuple):
    """The joint chain: ``sky`` a (Nf, n) K; ``theta`` (P,); ``scale`` s (Kf,), ``q(nu) = A^2 = basis_f s``."""

    sky: jax.Array
    theta: jax.Array
    scale: jax.Array


class GainInfo(NamedTuple):
    """Per sweep: the sky step's SolveInfo, and the gauge moves' acceptance rate and last log ratio."""

    solve: SolveInfo
    gauge_accept: jax.Array
    gauge_log_ratio: jax.Array


def gain_setup(model: GainModel, *, sigma, gbar=None, scale_mean=1.0, scale_sd=np.inf) -> GainBlock:
    """The gain block's prior and applied gains (pure NumPy set-up).

    Args:
        model: :func:`gcrsky.model.gain_model`'s layout.
        sigma: prior standard deviation of each mode's coefficient (rms fractional gain):
            scalar, or (Kf, Kt) per mode (e.g. falling with delay and fringe rate).
        gbar: (Nf, Nt, U) applied gains, or None (1).
        scale_mean, scale_sd: prior of the scale's coefficients ``s`` (Kf,): a scalar mean is
            the constant ``q = scale_mean`` (``s = (scale_mean, 0, ...)``); ``scale_sd`` scalar or
            (Kf,) (``inf``: flat on ``q > 0``).

    Raises:
        ValueError: a non-positive sigma or scale_sd, or sigma of the wrong shape.
    """
    kf, kt = model.basis_f.shape[1], model.basis_t.shape[1]
    sig = np.asarray(sigma, float)
    try:
        sig = np.broadcast_to(sig, (kf, kt)).ravel()
    except ValueError:
        raise ValueError(f"sigma has shape {sig.shape}, not broadcastable to the modes (Kf, Kt) = {(kf, kt)}") from None
    sd = np.broadcast_to(np.asarray(scale_sd, float), (kf,))
    if np.any(~(sig > 0)) or np.any(~(sd > 0)):
        raise ValueError("the gain prior's sigma and scale_sd must be positive (inf for a flat scale prior)")
    mean = np.asarray(scale_mean, float)
    if mean.ndim == 0:
        mean = np.concatenate([[float(mean)], np.zeros(kf - 1)])
    if mean.shape != (kf,):
        raise ValueError(f"scale_mean must be a scalar or (Kf,) = ({kf},), got shape {mean.shape}")
    iv = 1.0 / sig[model.param_mode] ** 2
    return GainBlock(model, pair_gains(model, gbar), jnp.asarray(iv), jnp.zeros(iv.size), jnp.asarray(mean),
                     jnp.asarray(1.0 / sd**2))


def gain_init(sky, block: GainBlock, *, theta=None, scale=None) -> GainState:
    """Start the joint chain at sky ``a`` (Nf, n), ``theta`` (default 0) and ``s`` (Kf,) (default the prior mean)."""
    sky = jnp.asarray(sky)
    th = jnp.zeros(n_gain_params(block.model), sky.dtype) if theta is None else jnp.asarray(theta, sky.dtype)
    q = block.scale_mean if scale is None else jnp.asarray(scale, sky.dtype)
    return GainState(sky, th, q)


def _mode_sums(model: GainModel, weight, vec):
    """``sum_ft weight B_kl`` style reductions: (Nbl, K, K) of ``weight`` and (Nbl, K) of ``vec``."""
    bf, bt = model.basis_f, model.basis_t
    Q = jnp.einsum("ftb,fk,tl,fm,tn->bklmn", weight, bf, bt, bf, bt)
    R = jnp.einsum("ftb,fk,tl->bkl", vec, bf, bt)
    nb, kf, kt = R.shape
    return Q.reshape(nb, kf * kt, kf * kt), R.reshape(nb, kf * kt)


def gain_conditional(block: GainBlock, data, inv_noise, sky_vis, scale):
    """Precision (P, P) and right-hand side (P,) of ``theta | a, q, d`` (no dense J; see the module doc).

    Args:
        block: :func:`gain_setup`'s block.
        data: (Nf, Nt, Nbl) complex visibilities ``d`` (finite where flagged).
        inv_noise: (Nf, Nt, Nbl) per-component inverse noise variance ``W`` (0 = flagged).
        sky_vis: ``X a`` (Nf, Nt, Nbl) complex, the sky's model visibilities.
        scale: ``s`` (Kf,) (or a scalar q).
    """
    model = block.model
    z = scale_profile(model, scale)[:, None, None] * block.pair_gains * sky_vis
    Q, R = _mode_sums(model, inv_noise * jnp.abs(z) ** 2, inv_noise * jnp.conj(data - z) * z)
    i, j = model.unit_pairs[:, 0], model.unit_pairs[:, 1]

    def pair_sums(theta):
        c = perturbation_coefficients(model, theta).reshape(model.amp_proj.shape[0], -1)
        return c[i] + jnp.conj(c[j])  # (Nbl, K)

    def quad(theta):
        e = pair_sums(theta)
        return 0.5 * jnp.real(jnp.einsum("bk,bkm,bm->", jnp.conj(e), Q, e))

    zero = jnp.zeros(model.param_mode.size, Q.dtype)
    prec = jax.hessian(quad)(zero) + jnp.diag(block.prior_inv_var)
    rhs = jax.grad(lambda t: jnp.real(jnp.sum(pair_sums(t) * R)))(zero) + block.prior_inv_var * block.prior_mean
    return prec, rhs


def gain_posterior(block: GainBlock, data, inv_noise, sky_vis, scale):
    """Mean (P,) and covariance (P, P) of ``theta | a, s, d``."""
    prec, rhs = gain_conditional(block, data, inv_noise, sky_vis, scale)
    L = jnp.linalg.cholesky(prec)
    mean = jax.scipy.linalg.cho_solve((L, True), rhs)
    return mean, jax.scipy.linalg.cho_solve((L, True), jnp.eye(rhs.size, dtype=rhs.dtype))


def gains_step(key: jax.Array, state: GainState, fixed: GibbsFixed, block: GainBlock) -> GainState:
    """One exact draw of ``theta | a, q, d``: ``mean + L^-T z`` with ``P_theta = L L^T``, ``z ~ N(0, I)``.

    ``fixed.system`` holds the raw data ``d``, ``W`` and the operator; one operator
    application ``X a``, the mode sums and a ``P x P`` Cholesky.
    """
    system = fixed.system
    theta = theta_draw(key, block, system.data, system.inv_noise, apply(system.op, state.sky), state.scale)
    return state._replace(theta=theta)


def theta_draw(key: jax.Array, block: GainBlock, data, inv_noise, sky_vis, scale) -> jax.Array:
    """One exact draw (P,) of ``theta | a, q, d`` from the model visibilities ``X a`` (Nf, Nt, Nbl) and the scale
    ``s`` (Kf,) or ``q`` (a scalar, or (Nf,) per channel folded into ``sky_vis`` with ``scale=1``):
    :func:`gain_conditional`, then ``mean + L^-T z``."""
    prec, rhs = gain_conditional(block, data, inv_noise, sky_vis, scale)
    L = jnp.linalg.cholesky(prec)
    z = jax.random.normal(key, rhs.shape, rhs.dtype)
    return jax.scipy.linalg.cho_solve((L, True), rhs) + jax.scipy.linalg.solve_triangular(L.T, z, lower=False)


def recentre(block: GainBlock, state: GainState) -> tuple[GainBlock, GainState]:
    """Move the linearisation point to the current gains: ``G' = G (1 + x_i) conj(1 + x_j)`` (exact), ``theta = 0``.

    The linearised model is exact to first order in ``x`` about ``G``; its neglected term
    ``x_i conj(x_j)`` is ~1 % of the visibility at 5 % / 5 deg gain errors, many noise sigma at
    high signal to noise.  Re-centred at a burn-in's mean, what is left is second order in the
    posterior's spread.  The prior of the new perturbation is centred at ``prior_mean - theta0``
    (the old prior to first order).  The target changes with the linearisation point: re-centre
    between chain segments (burn-in), and keep the draws of a segment run at one point.

    Returns:
        (the block about the new point, the state with ``theta = 0``).
    """
    x = perturbations(block.model, state.theta)
    i, j = block.model.unit_pairs[:, 0], block.model.unit_pairs[:, 1]
    G = block.pair_gains * (1.0 + x[..., i]) * jnp.conj(1.0 + x[..., j])
    new = block._replace(pair_gains=G, prior_mean=block.prior_mean - state.theta)
    return new, state._replace(theta=jnp.zeros_like(state.theta))


def gained_fixed(fixed: GibbsFixed, factor) -> GibbsFixed:
    """:func:`gibbs_setup`'s data term for the data with gain factor ``D`` (Nf, Nt, Nbl) applied.

    ``|d - D X a|^2 W = |d / D - X a|^2 W |D|^2``: the system's data become ``d / D`` (0 where
    ``D = 0``) and its inverse noise ``W |D|^2``.  The operator is kept.  Cholesky path: the
    data term ``X^T W |D|^2 X`` and the factor are rebuilt (:func:`gcrsky.model.system.precision_data_matrix`);
    matrix-free CG path: nothing else (the sketch of the ungained data term preconditions:
    a stale preconditioner costs iterations only, the draw stays exact to the tolerance).

    Raises:
        ValueError: the dense-CG path (its data term's square root would need an eigendecomposition a step).
    """
    system = fixed.system
    if fixed.data_sqrt is not None:
        raise ValueError("the gain block runs on gibbs_setup's Cholesky path or CGOptions(dense=False)")
    D = jnp.asarray(factor, system.data.dtype)
    w = system.inv_noise * jnp.abs(D) ** 2
    data = jnp.where(D == 0, 0.0, system.data / jnp.where(D == 0, 1.0, D))
    sys_g = system._replace(data=data, inv_noise=w)
    rhs = adjoint(system.op, system.inv_noise * jnp.conj(D) * system.data)
    if fixed.data_term is None:
        return eqx.tree_at(lambda f: (f.system, f.data_rhs), fixed, (sys_g, rhs))
    H = precision_data_matrix(system.op, w)
    chol = jnp.linalg.cholesky(H + jax.vmap(jnp.diag)(system.prior.inv_var))
    return eqx.tree_at(lambda f: (f.system, f.data_rhs, f.data_term, f.factor), fixed, (sys_g, rhs, H, chol))


def gain_sky_step(key: jax.Array, state: GainState, fixed: GibbsFixed, block: GainBlock) -> tuple[GainState, SolveInfo]:
    """One exact draw of the sky ``a | theta, q, d`` (the system's own prior): :func:`gained_fixed` then
    :func:`gcrsky.inference.sky_step` warm-started at the current sky."""
    D = gain_factor(block.model, state.theta, state.scale) * block.pair_gains  # gbar=None: G = 1
    sky, info = sky_step(key, gained_fixed(fixed, D), state.sky)
    return state._replace(sky=sky), info


def scale_conditional(block: GainBlock, data, inv_noise, sky_vis, theta):
    """Precision (Kf, Kf) and right-hand side (Kf,) of ``s | a, theta, d`` (untruncated).

    The model is ``sum_k s_k B_k(nu) U`` with ``U = G (1 + x_i + conj(x_j)) X a``: precision
    ``Re sum W conj(U_k) U_m + diag(1/sd^2)``, rhs ``Re sum W conj(U_k) d + s0 / sd^2``.

    Args:
        block: :func:`gain_setup`'s block; data, inv_noise: (Nf, Nt, Nbl); sky_vis: ``X a``; theta: (P,).
    """
    U = gain_factor(block.model, theta, 1.0) * block.pair_gains * sky_vis
    Uk = jnp.einsum("fk,ftb->kftb", block.model.basis_f, U)
    prec = jnp.einsum("kftb,ftb,mftb->km", jnp.conj(Uk), inv_noise, Uk).real + jnp.diag(block.scale_inv_var)
    rhs = jnp.einsum("kftb,ftb->k", jnp.conj(Uk), inv_noise * data).real + block.scale_inv_var * block.scale_mean
    return prec, rhs


def scale_step(key: jax.Array, state: GainState, fixed: GibbsFixed, block: GainBlock) -> GainState:
    """One exact draw of ``s | a, theta, d`` (Kf,) (:func:`scale_conditional`), truncated to
    ``q(nu) = basis_f s > 0`` by rejection (a ``while_loop`` that redraws while some ``q <= 0``;
    the posterior is far from 0 in practice, so it draws once)."""
    system = fixed.system
    prec, rhs = scale_conditional(block, system.data, system.inv_noise, apply(system.op, state.sky), state.theta)
    L = jnp.linalg.cholesky(prec)
    mean = jax.scipy.linalg.cho_solve((L, True), rhs)

    def draw(carry):
        k, _ = carry
        k, sub = jax.random.split(k)
        return k, mean + jax.scipy.linalg.solve_triangular(L.T, jax.random.normal(sub, mean.shape, mean.dtype),
                                                           lower=False)

    bad = lambda carry: jnp.any(scale_profile(block.model, carry[1]) <= 0)  # noqa: E731
    _, s = jax.lax.while_loop(bad, draw, draw((key, mean)))
    return state._replace(scale=s)


def _gauge_log_target(fixed: GibbsFixed, block: GainBlock, sky, scale):
    """Log prior of ``(a, s)`` (the likelihood is constant along the gauge orbit)."""
    prior = fixed.system.prior
    return (-0.5 * jnp.sum(prior.inv_var * (sky - prior.mean) ** 2)
            - 0.5 * jnp.sum(block.scale_inv_var * (scale - block.scale_mean) ** 2))


def gauge_step(key: jax.Array, state: GainState, fixed: GibbsFixed, block: GainBlock, step_size):
    """One Metropolis-Hastings move along the exact gauge orbit ``(s, a) -> (s + delta, a q / q')``.

    ``delta ~ N(0, step_size^2 I)`` (Kf,), symmetric; ``q = basis_f s``, ``q' = basis_f (s + delta)``
    per channel, the sky of channel f multiplied by ``q_f / q'_f``.  The map is a bijection whose
    inverse is the move with ``-delta``; its Jacobian is ``prod_f (q_f / q'_f)^n``.  Accepted with
    ``log r = log pi(a', s') - log pi(a, s) + n sum_f log(q_f / q'_f)`` (``-inf`` where some
    ``q' <= 0``).  The likelihood is invariant (``q(nu) D_theta X a(nu)`` depends on ``q a``),
    so no solve and no operator application: ``O(Nf n)``.

    Returns:
        (GainState, accepted (bool), log r).
    """
    k_s, k_u = jax.random.split(key)
    dtype = state.sky.dtype
    s_new = state.scale + step_size * jax.random.normal(k_s, state.scale.shape, dtype)
    q, q_new = scale_profile(block.model, state.scale), scale_profile(block.model, s_new)
    ok = jnp.all(q_new > 0)
    ratio = jnp.where(ok, q / jnp.where(ok, q_new, 1.0), 1.0)
    sky_new = state.sky * ratio[:, None]
    log_r = (_gauge_log_target(fixed, block, sky_new, s_new) - _gauge_log_target(fixed, block, state.sky, state.scale)
             + state.sky.shape[1] * jnp.sum(jnp.log(ratio)))
    log_r = jnp.where(ok, log_r, -jnp.inf)
    accept = jnp.log(jax.random.uniform(k_u, (), dtype)) < log_r
    new = state._replace(sky=jnp.where(accept, sky_new, state.sky), scale=jnp.where(accept, s_new, state.scale))
    return new, accept, log_r


def gauge_step_size(fixed: GibbsFixed, block: GainBlock) -> float:
    """A default random-walk scale of ``delta``: ``2.4 / sqrt(Kf) / sqrt(2 N)`` (N = Nf n): the orbit's
    density in each (unit-rms) frequency mode is about ``1 / sqrt(2 N)`` wide for a prior-dominated
    sky at q ~ 1 (narrower where the prior mean is away from 0)."""
    kf = block.model.basis_f.shape[1]
    return float(2.4 / np.sqrt(kf) / np.sqrt(2.0 * fixed.system.prior.mean.size))


class _Whitened(NamedTuple):
    """Per channel, the sky's data term given the gains but not the scale, in the prior-whitened frame."""

    lam: jax.Array  # (Nf, n) eigenvalues of S^1/2 H1 S^1/2 (clamped at 0)
    vec: jax.Array  # (Nf, n, n) its eigenvectors
    g1: jax.Array  # (Nf, n) V^T S^1/2 b1
    g2: jax.Array  # (Nf, n) V^T S^1/2 H1 a0
    e1: jax.Array  # (Nf,) a0 . b1
    e2: jax.Array  # (Nf,) a0 . H1 a0


def _whitened(fixed: GibbsFixed, block: GainBlock, theta) -> _Whitened:
    """``H1 = X^T W |D1|^2 X`` and ``b1 = X^T W conj(D1) d`` with ``D1 = G (1 + x_i + conj(x_j))``, whitened by the prior."""
    system = fixed.system
    D1 = gain_factor(block.model, theta, 1.0) * block.pair_gains
    H1 = precision_data_matrix(system.op, system.inv_noise * jnp.abs(D1) ** 2)
    b1 = adjoint(system.op, system.inv_noise * jnp.conj(D1) * system.data)
    a0, sd = system.prior.mean, 1.0 / jnp.sqrt(system.prior.inv_var)
    lam, V = jnp.linalg.eigh(sd[:, :, None] * H1 * sd[:, None, :])
    H1a0 = jnp.einsum("fij,fj->fi", H1, a0)
    proj = lambda v: jnp.einsum("fij,fi->fj", V, sd * v)  # noqa: E731
    return _Whitened(jnp.maximum(lam, 0.0), V, proj(b1), proj(H1a0), jnp.sum(a0 * b1, -1), jnp.sum(a0 * H1a0, -1))


def _log_marginal_q(w: _Whitened, q):
    """``log p(d | q, theta)`` per channel (Nf,) up to a constant, the sky integrated out: O(Nf n)."""
    q = q[:, None]
    beta = q * (w.g1 - q * w.g2)
    quad = jnp.sum(beta**2 / (1.0 + q**2 * w.lam), -1)
    return q[:, 0] * w.e1 - 0.5 * q[:, 0] ** 2 * w.e2 + 0.5 * quad - 0.5 * jnp.sum(jnp.log1p(q**2 * w.lam), -1)


def scale_sky_step(key: jax.Array, state: GainState, fixed: GibbsFixed, block: GainBlock, *, moves: int = 8,
                   step_size=None) -> tuple[GainState, jax.Array]:
    """The scale and the sky jointly, ``(s, a) | theta, d``: the amplitude collapsed analytically.

    Given the gains the model is ``q(nu) D1 X a`` with the sky Gaussian, so the scale's marginal
    ``p(s | theta, d) = p(s) prod_f N(d_f; q_f D1 X a0, q_f^2 D1 X S X^H D1^H + N)`` is exact.  In the
    eigenbasis of the prior-whitened data term ``S^1/2 X^T W |D1|^2 X S^1/2 = V diag(lam) V^T``
    (one ``eigh`` per channel and sweep) it costs O(Nf n) per value of ``s``: ``moves`` random-walk
    Metropolis steps ``s' = s + N(0, step_size^2)`` on it, then the sky drawn exactly at the
    accepted scale, ``a = a0 + S^1/2 V (V^T beta + q sqrt(lam) z1 + z2) / (1 + q^2 lam)``
    with ``beta = q S^1/2 X^T W conj(D1) (d - q D1 X a0)``.  Cholesky path only (dense data term).

    Args:
        step_size: the walk's scale of ``s`` (default 0.1: the scale's marginal is as wide as the
            sky prior's leverage on it, typically 0.05-0.3 for a prior-dominated overall flux).

    Returns:
        (GainState, the moves' acceptance rate).
    """
    if fixed.data_term is None:
        raise ValueError("scale_sky_step needs gibbs_setup's Cholesky path (a dense data term)")
    w = _whitened(fixed, block, state.theta)
    tau = 0.1 if step_size is None else step_size
    model = block.model

    def log_target(s):
        q = scale_profile(model, s)
        lp = jnp.sum(_log_marginal_q(w, q)) - 0.5 * jnp.sum(block.scale_inv_var * (s - block.scale_mean) ** 2)
        return jnp.where(jnp.all(q > 0), lp, -jnp.inf)

    def move(carry, k):
        s, lp = carry
        k1, k2 = jax.random.split(k)
        s_new = s + tau * jax.random.normal(k1, s.shape, s.dtype)
        lp_new = log_target(s_new)
        ok = jnp.log(jax.random.uniform(k2, (), s.dtype)) < lp_new - lp
        return (jnp.where(ok, s_new, s), jnp.where(ok, lp_new, lp)), ok

    k_m, k_a = jax.random.split(key)
    (s, _), acc = jax.lax.scan(move, (state.scale, log_target(state.scale)), jax.random.split(k_m, moves))
    q = scale_profile(model, s)[:, None]
    beta = q * (w.g1 - q * w.g2)
    z1, z2 = jax.random.normal(k_a, (2,) + beta.shape, beta.dtype)
    u = (beta + q * jnp.sqrt(w.lam) * z1 + z2) / (1.0 + q**2 * w.lam)
    prior = fixed.system.prior
    sky = prior.mean + jnp.einsum("fij,fj->fi", w.vec, u) / jnp.sqrt(prior.inv_var)
    return state._replace(sky=sky, scale=s), jnp.mean(acc)


def joint_gain_step(key: jax.Array, state: GainState, fixed: GibbsFixed, block: GainBlock, *,
                    gauge_moves: int = 4, step_size=None, collapsed: bool = False) -> tuple[GainState, GainInfo]:
    """One sweep of the joint (sky, gains, scale) chain.  Pure; jit / ``lax.scan`` it yourself.

    * ``collapsed=False``: sky ``a | theta, s`` (:func:`gain_sky_step`), gains ``theta | a, s``
      (:func:`gains_step`), scale ``s | a, theta`` (:func:`scale_step`), then ``gauge_moves``
      moves along the gauge orbit (:func:`gauge_step`; 0: plain Gibbs, which crawls along it);
    * ``collapsed=True``: ``(s, a) | theta`` with the amplitude collapsed analytically
      (:func:`scale_sky_step`, ``gauge_moves`` Metropolis steps on the scale's exact marginal,
      Cholesky path only), then ``theta | a, s``.

    Args:
        key: PRNG key.
        state: :class:`GainState`.
        fixed: :func:`gcrsky.inference.gibbs_setup` of the system with the raw data ``d``
            (Cholesky path, or ``CGOptions(dense=False)``).
        block: :func:`gain_setup`'s block (same rows, times and channels as the system).
        gauge_moves: Metropolis moves per sweep, along the orbit (each ``O(N)``) or on the
            collapsed marginal (each ``O(Nf n)``).
        step_size: their scale (defaults: :func:`gauge_step_size`; 0.1 collapsed).
        collapsed: which of the two sweeps.

    Returns:
        (GainState, GainInfo); the collapsed sweep's SolveInfo is a direct solve's.
    """
    if collapsed:
        k_a, k_g = jax.random.split(key)
        state, acc = scale_sky_step(k_a, state, fixed, block, moves=max(gauge_moves, 1), step_size=step_size)
        state = gains_step(k_g, state, fixed, block)
        zeros = jnp.zeros(state.sky.shape[0], state.sky.dtype)
        info = direct_info(zeros, zeros, jnp.all(jnp.isfinite(state.sky), axis=1), fixed.options.tol)
        return state, GainInfo(info, acc, jnp.zeros((), state.sky.dtype))
    k_a, k_g, k_q, k_m = jax.random.split(key, 4)
    state, info = gain_sky_step(k_a, state, fixed, block)
    state = gains_step(k_g, state, fixed, block)
    state = scale_step(k_q, state, fixed, block)
    tau = gauge_step_size(fixed, block) if step_size is None else step_size
    acc = jnp.zeros((), state.sky.dtype)
    log_r = jnp.zeros((), state.sky.dtype)
    for k in jax.random.split(k_m, gauge_moves):
        state, ok, log_r = gauge_step(k, state, fixed, block, tau)
        acc = acc + ok
    return state, GainInfo(info, acc / max(gauge_moves, 1), log_r)
