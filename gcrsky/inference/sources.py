"""Point-source fluxes as a linear Gaussian block, and the two-block (sky, fluxes) Gibbs step.

A few sources at known positions with unknown fluxes ``s`` (Nf, Ns) add ``K s`` to
the model visibilities, ``V = X a + K s``, with ``K`` (Nf, Nt, Nbl, Ns) their unit-flux
response (:func:`gcrsky.instrument.problem_source_response`; K sr per Jy by default,
so ``s`` is in Jy).  Channels are independent, as for the sky.  Given the residual
``r = d - X a`` (data minus the sky's model visibilities) and a Gaussian prior
``s ~ N(mu, C)``, the conditional is Gaussian with, per channel (realified: each
complex sample is two real numbers with per-component inverse variance ``W``, as in
:mod:`gcrsky.model.system`),

* precision ``P_s = K_r^T W K_r + K_i^T W K_i + C^-1 = Re(K^H W K) + C^-1`` (Ns, Ns),
* mean ``P_s^-1 (Re(K^H W r) + C^-1 mu)``,

and :func:`flux_step` draws from it exactly: ``s = mean + L^-T z`` with ``P_s = L L^T``
and ``z ~ N(0, I)`` (``Cov = P_s^-1``).  Flagged samples (``W = 0``) contribute nothing.
``P_s`` does not depend on the residual, so :func:`flux_setup` factorises it once.

The sky block is :func:`gcrsky.inference.sky_step` (the sky given the data minus the
sources' model visibilities); :func:`sky_source_step` alternates the two, each
conditioned on the other's current model visibilities::

    fixed = gibbs_setup(system)                               # sky: data term and factor, once
    block = flux_setup(K, system.inv_noise, mu, prior_var=sigma**2)   # fluxes: P_s factor, once
    state = sky_source_init(system.prior.mean, mu)
    state, info = sky_source_step(key, state, fixed, block)   # jit / lax.scan it

All functions are pure and jittable.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..base.dtypes import check_float64
from ..model.operator import apply
from ..solvers.info import SolveInfo
from .gibbs import GibbsFixed, sky_step

__all__ = [
    "FluxBlock",
    "SkySourceState",
    "flux_posterior",
    "flux_setup",
    "flux_step",
    "sample_fluxes",
    "sky_source_init",
    "sky_source_step",
    "source_visibilities",
]


class FluxBlock(NamedTuple):
    """The flux block's fixed parts (a PyTree; built by :func:`flux_setup`).

    Attributes:
        response: ``K`` (Nf, Nt, Nbl, Ns) complex, K sr per unit flux.
        inv_noise: ``W`` (Nf, Nt, Nbl) per-component inverse noise variance (0 = flagged),
            (K sr)^-2: the sky system's ``inv_noise``.
        prior_mean: ``mu`` (Nf, Ns), flux units.
        prior_precision: ``C^-1`` (Nf, Ns, Ns), flux units^-2.
        factor: lower Cholesky factor ``L`` of ``P_s = Re(K^H W K) + C^-1`` (Nf, Ns, Ns).
    """

    response: jax.Array
    inv_noise: jax.Array
    prior_mean: jax.Array
    prior_precision: jax.Array
    factor: jax.Array


class SkySourceState(NamedTuple):
    """State of the two-block chain: ``sky`` a (Nf, n), K; ``fluxes`` s (Nf, Ns), flux units."""

    sky: jax.Array
    fluxes: jax.Array


def source_visibilities(response, fluxes) -> jax.Array:
    """Model visibilities ``K s`` of the sources: (Nf, Nt, Nbl) complex, K sr.

    Args:
        response: ``K`` (Nf, Nt, Nbl, Ns), K sr per unit flux.
        fluxes: ``s`` (Nf, Ns) (or (Ns,), the same in every channel).
    """
    K = jnp.asarray(response)
    s = jnp.broadcast_to(jnp.asarray(fluxes, K.real.dtype), (K.shape[0], K.shape[-1]))
    return jnp.einsum("ftbs,fs->ftb", K, s.astype(K.dtype))


def _prior_precision(nf: int, ns: int, dtype, prior_var, prior_cov):
    """``C^-1`` (Nf, Ns, Ns) from a diagonal variance or a full covariance."""
    if (prior_var is None) == (prior_cov is None):
        raise ValueError("give exactly one of prior_var (diagonal, broadcastable to (Nf, Ns)) and prior_cov "
                         "(full, broadcastable to (Nf, Ns, Ns))")
    if prior_var is not None:
        var = jnp.asarray(prior_var, dtype)
        try:
            var = jnp.broadcast_to(var, (nf, ns))
        except ValueError:
            raise ValueError(f"prior_var has shape {var.shape}, not broadcastable to (Nf, Ns) = {(nf, ns)}") from None
        return jax.vmap(jnp.diag)(1.0 / var)  # an infinite variance is a flat direction
    cov = jnp.asarray(prior_cov, dtype)
    try:
        cov = jnp.broadcast_to(cov, (nf, ns, ns))
    except ValueError:
        raise ValueError(f"prior_cov has shape {cov.shape}, not broadcastable to (Nf, Ns, Ns) = {(nf, ns, ns)}") from None
    eye = jnp.eye(ns, dtype=dtype)
    return jax.vmap(lambda c: jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(c), True), eye))(cov)


def flux_setup(response, inv_noise, prior_mean, *, prior_var=None, prior_cov=None) -> FluxBlock:
    """Set up the flux block once: the prior precision and the Cholesky factor of ``P_s`` (pure).

    Args:
        response: ``K`` (Nf, Nt, Nbl, Ns) complex, K sr per unit flux
            (:func:`gcrsky.instrument.problem_source_response`).
        inv_noise: (Nf, Nt, Nbl) per-component inverse noise variance, (K sr)^-2 (the sky
            system's ``inv_noise``; 0 = flagged).
        prior_mean: ``mu``, broadcastable to (Nf, Ns), flux units.
        prior_var: diagonal prior variance, broadcastable to (Nf, Ns) (``inf``: flat), or
        prior_cov: full prior covariance, broadcastable to (Nf, Ns, Ns) (positive definite).

    Returns:
        :class:`FluxBlock`.  A source never seen (below the horizon, or flagged) under a flat
        prior makes ``P_s`` singular and the factor NaN.

    Raises:
        ValueError: shapes that do not match, or neither / both of ``prior_var`` and ``prior_cov``.
    """
    K = jnp.asarray(response)
    if K.ndim != 4:
        raise ValueError(f"response must be (Nf, Nt, Nbl, Ns), got shape {K.shape}")
    nf, nt, nbl, ns = K.shape
    W = jnp.asarray(inv_noise)
    if W.shape != (nf, nt, nbl):
        raise ValueError(f"inv_noise has shape {W.shape}, the response needs (Nf, Nt, Nbl) = {(nf, nt, nbl)}")
    check_float64(K, W)
    dtype = K.real.dtype
    try:
        mu = jnp.broadcast_to(jnp.asarray(prior_mean, dtype), (nf, ns))
    except ValueError:
        raise ValueError(f"prior_mean has shape {jnp.shape(prior_mean)}, not broadcastable to (Nf, Ns) = "
                         f"{(nf, ns)}") from None
    cinv = _prior_precision(nf, ns, dtype, prior_var, prior_cov)
    P = jnp.einsum("ftbs,ftb,ftbr->fsr", jnp.conj(K), W, K).real + cinv
    return FluxBlock(K, W, mu, cinv, jnp.linalg.cholesky(P))


def _rhs(block: FluxBlock, residual_vis) -> jax.Array:
    r = jnp.asarray(residual_vis, block.response.dtype)
    if r.shape != block.inv_noise.shape:
        raise ValueError(f"residual_vis has shape {r.shape}, expected (Nf, Nt, Nbl) = {block.inv_noise.shape}")
    data = jnp.einsum("ftbs,ftb->fs", jnp.conj(block.response), block.inv_noise * r).real
    return data + jnp.einsum("fsr,fr->fs", block.prior_precision, block.prior_mean)


def flux_posterior(block: FluxBlock, residual_vis) -> tuple[jax.Array, jax.Array]:
    """Mean (Nf, Ns) and covariance (Nf, Ns, Ns) of ``s | residual`` (flux units).

    Args:
        block: :func:`flux_setup`'s block.
        residual_vis: (Nf, Nt, Nbl) complex, K sr: the data minus every other block's model
            visibilities (e.g. ``d - X a``).
    """
    L = block.factor
    mean = jax.vmap(lambda Lf, bf: jax.scipy.linalg.cho_solve((Lf, True), bf))(L, _rhs(block, residual_vis))
    eye = jnp.eye(L.shape[-1], dtype=L.dtype)
    cov = jax.vmap(lambda Lf: jax.scipy.linalg.cho_solve((Lf, True), eye))(L)
    return mean, cov


def flux_step(key: jax.Array, block: FluxBlock, residual_vis) -> jax.Array:
    """One exact draw of the fluxes ``s | residual`` (Nf, Ns): ``mean + L^-T z``, ``z ~ N(0, I)``.

    Two triangular solves per channel (``P_s``'s factor is :func:`flux_setup`'s).  The
    standard normals are ``jax.random.normal(key, (Nf, Ns))``.

    Args:
        key: PRNG key.
        block: :func:`flux_setup`'s block.
        residual_vis: (Nf, Nt, Nbl) complex, K sr: data minus the other blocks' model visibilities.
    """
    L = block.factor
    b = _rhs(block, residual_vis)
    z = jax.random.normal(key, b.shape, b.dtype)

    def one(Lf, bf, zf):
        return jax.scipy.linalg.cho_solve((Lf, True), bf) + jax.scipy.linalg.solve_triangular(Lf.T, zf, lower=False)

    return jax.vmap(one)(L, b, z)


def sample_fluxes(key: jax.Array, response, inv_noise, residual_vis, prior_mean, *, prior_var=None,
                  prior_cov=None) -> jax.Array:
    """One exact draw of point-source fluxes given the residual visibilities: (Nf, Ns) (pure, jittable).

    :func:`flux_setup` followed by :func:`flux_step` (inside a loop, set up once and call
    :func:`flux_step`: the factorisation does not depend on the residual).

    Args:
        key: PRNG key.
        response: ``K`` (Nf, Nt, Nbl, Ns) complex, K sr per unit flux.
        inv_noise: (Nf, Nt, Nbl) per-component inverse noise variance, (K sr)^-2 (0 = flagged).
        residual_vis: (Nf, Nt, Nbl) complex, K sr: data minus the sky's model visibilities.
        prior_mean: broadcastable to (Nf, Ns), flux units.
        prior_var: diagonal prior variance, broadcastable to (Nf, Ns); or
        prior_cov: full prior covariance, broadcastable to (Nf, Ns, Ns).

    Returns:
        (Nf, Ns) fluxes, distributed exactly as ``N(P_s^-1 (Re(K^H W r) + C^-1 mu), P_s^-1)``.
    """
    block = flux_setup(response, inv_noise, prior_mean, prior_var=prior_var, prior_cov=prior_cov)
    return flux_step(key, block, residual_vis)


def sky_source_init(sky, fluxes) -> SkySourceState:
    """Start the two-block chain at sky ``a`` (Nf, n) and fluxes ``s`` (Nf, Ns) (e.g. the priors' means)."""
    return SkySourceState(jnp.asarray(sky), jnp.asarray(fluxes))


def sky_source_step(
    key: jax.Array, state: SkySourceState, fixed: GibbsFixed, block: FluxBlock
) -> tuple[SkySourceState, SolveInfo]:
    """One sweep of the two-block Gibbs sampler (pure; jit / ``lax.scan`` it yourself).

    1. sky ``a | s, d``: :func:`gcrsky.inference.sky_step` on the data minus the sources'
       model visibilities ``d - K s``, under the system's own prior (factor reused);
    2. fluxes ``s | a, d``: :func:`flux_step` on the residual ``d - X a``.

    Both blocks must describe the same data and noise: ``fixed = gibbs_setup(system)``,
    ``block = flux_setup(K, system.inv_noise, ...)`` (not checked: traced values).

    Returns:
        (the new :class:`SkySourceState`, the sky step's :class:`~gcrsky.solvers.SolveInfo`).
    """
    k_sky, k_flux = jax.random.split(key)
    system = fixed.system
    sky, info = sky_step(k_sky, fixed, state.sky, data=system.data - source_visibilities(block.response, state.fluxes))
    fluxes = flux_step(k_flux, block, system.data - apply(system.op, sky))
    return SkySourceState(sky, fluxes), info
