"""Per-antenna gains sampled with the beams and the sky: one collapsed chain over both (issue 41).

The model is the beam block's (:mod:`gcrsky.inference.beams`) with the gain factor of :mod:`gcrsky.model.gains`
on each row::

    d_b = D_b(theta_g) u_f (sum_p w_bp(theta_b) X_b^(p)) a + n,    D_b = G_b (1 + x_i + conj(x_j))

``G = gbar_i conj(gbar_j)`` the gains' linearisation point, ``x`` the perturbations of the gain coefficients
``theta_g`` (gauge-fixed: their common amplitude is removed, carried by the amplitude ``u``; the overall phase),
``theta_b`` the beam coefficients, ``u`` the overall amplitude per channel (inferred, or 1) and ``a`` the sky.

**The sky integrated out of both.**  Given ``(theta_b, u, theta_g)`` the data are Gaussian in the sky, and the
gains enter only as the row factor ``D``: ``|d - D V|^2 W = |d / D - V|^2 W |D|^2``.  So the exact marginal
``p(d | theta_b, u, theta_g)`` is the beams' (:func:`gcrsky.inference.beams.beam_marginal_log_posterior`) of the
data ``d / D`` with inverse noise ``W |D|^2`` (:func:`with_gains`), times the Jacobian ``prod |D|^-2`` of ``d / D``
(:func:`gain_log_jacobian`: two real components per sample; a constant at fixed gains, not here).  The
data-space Grams do not depend on ``D`` (:func:`gcrsky.inference.beams.refold_gram`), so each evaluation still
costs ``O(Nf (P N_d)^2)`` and a Cholesky per channel.

**The chain** (:func:`beam_gain_step`) is the collapsed beam chain's with the gains in the move: an independence
Metropolis-Hastings move of ``(theta_b, ln u, theta_g)`` jointly on that exact marginal (proposal: Laplace's
Gaussian, :func:`beam_gain_log_evidence`), then the sky given all three, exactly.  Alternating the gains with
the sky instead (``theta_g | a``, exact and Gaussian) mixes slowly where the gains' phase gradients trade
against the sky's position (the gain runs' ESS ~3 of 100 for them), and a fixed beam proposal under moving gains
missed the beams' conditional (an H1C twin: 2.5 % acceptance); the joint move has neither coupling.  It leaves
``p(a, theta_b, u, theta_g | d)`` invariant for the gain model linearised about ``G``: re-centre between fits
(:func:`gcrsky.inference.gains.recentre`), not within a chain.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..model.gains import gain_factor
from ..solvers.options import CholeskyOptions
from .beams import (
    NEWTON_DECREMENT_TOL,
    BeamBlock,
    BeamGram,
    BeamState,
    beam_log_prior,
    beam_marginal_log_posterior,
    beam_sky_step,
    newton_polish,
    refold_gram,
)
from .gains import GainBlock

__all__ = ["BeamGainEvidence", "BeamGainState", "beam_gain_log_evidence", "beam_gain_log_posterior", "beam_gain_step",
           "gain_log_jacobian", "gain_log_prior", "gain_row_factor", "with_gains"]


class BeamGainState(NamedTuple):
    """The joint chain: ``beam`` the :class:`gcrsky.inference.BeamState` (sky, beam coefficients, ``log_u``) and
    ``gain_theta`` (P,) the gain perturbations about the linearisation point (real-stacked, gauge-fixed)."""

    beam: BeamState
    gain_theta: jax.Array


def gain_row_factor(gains: GainBlock, gain_theta) -> jax.Array:
    """``D = G (1 + x_i + conj(x_j))`` (Nf, Nt, Nbl) complex: the linearised gain factor of each row at
    ``gain_theta`` (P,) about the block's linearisation point ``G`` (``gains.pair_gains``), the scale 1."""
    return gain_factor(gains.model, gain_theta, 1.0) * gains.pair_gains


def with_gains(block: BeamBlock, gains: GainBlock, gain_theta) -> BeamBlock:
    """The beam block whose row factor is its own times the gains' (:func:`gain_row_factor`): what every function of
    :mod:`gcrsky.inference.beams` then folds into the data and noise."""
    return block._replace(row_factor=block.row_factor * gain_row_factor(gains, gain_theta))


def gain_log_prior(gains: GainBlock, gain_theta) -> jax.Array:
    """The normalised log density of the gain prior (independent Gaussians: ``gains.prior_mean``,
    ``gains.prior_inv_var``) at ``gain_theta`` (P,)."""
    iv = gains.prior_inv_var
    d = gain_theta - gains.prior_mean
    return -0.5 * (jnp.sum(iv * d**2) - jnp.sum(jnp.log(iv)) + d.size * jnp.log(2 * jnp.pi))


def gain_log_jacobian(system, gains: GainBlock, gain_theta) -> jax.Array:
    """``log prod |D|^-2``: the density of the data ``d`` from that of ``d / D`` (each sample's two real components
    scaled by ``1 / |D|``), over the samples with data (``W > 0``)."""
    D = jnp.broadcast_to(gain_row_factor(gains, gain_theta), system.data.shape)
    keep = system.inv_noise > 0
    return -2.0 * jnp.sum(jnp.where(keep, jnp.log(jnp.abs(jnp.where(keep, D, 1.0))), 0.0))


def beam_gain_log_posterior(system, block: BeamBlock, gains: GainBlock, theta, gain_theta, *, log_u=None,
                            options=None, gram: BeamGram | None = None) -> jax.Array:
    """``log p(d | theta_b [, u], theta_g) + log p(theta_b) [+ log p(u)] + log p(theta_g)``, the sky integrated out
    exactly (module doc).

    Args:
        system: the sky's system with the raw data, noise and prior.
        block: the beam block (its own row factor, without the gains).
        gains: the gain block about the linearisation point.
        theta: (Nant, M, Q) beam coefficients; ``gain_theta`` (P,) gain perturbations; ``log_u`` (Nf,) or None.
        options: the marginal's path without ``gram`` (default Cholesky).
        gram: the data-space Grams of ``system`` and ``block`` (any row factor: re-folded at these gains).
    """
    blk = with_gains(block, gains, gain_theta)
    gr = None if gram is None else refold_gram(gram, system, blk)
    return (beam_marginal_log_posterior(system, blk, theta, log_u=log_u, options=options, gram=gr)
            + gain_log_jacobian(system, gains, gain_theta) + gain_log_prior(gains, gain_theta))


def _pack(theta, log_u, gain_theta):
    parts = [theta.reshape(-1)] + ([] if log_u is None else [log_u]) + [gain_theta]
    return jnp.concatenate(parts)


def _unpacker(theta_shape, nf: int | None, p: int):
    k = int(np.prod(theta_shape))
    nu = 0 if nf is None else nf

    def unpack(x):
        return x[:k].reshape(theta_shape), (None if nf is None else x[k:k + nu]), x[k + nu:k + nu + p]

    return unpack


def beam_gain_step(key: jax.Array, state: BeamGainState, system, block: BeamBlock, gains: GainBlock, proposal, *,
                   options=None, gram: BeamGram | None = None, with_info: bool = False):
    """One step of the collapsed chain over (sky, beams, amplitude, gains) (module doc): an independence
    Metropolis-Hastings move of ``(theta_b, ln u, theta_g)`` on their exact marginal, then the sky given them.
    Pure; ``jit`` / ``lax.scan`` it.

    Args:
        key: PRNG key.
        state: :class:`BeamGainState`.
        system: the sky's system with the raw data, noise and prior (its response is replaced per step).
        block: :func:`gcrsky.inference.beam_setup`'s block (its own row factor, without the gains).
        gains: :func:`gcrsky.inference.gain_setup`'s block about the linearisation point.
        proposal: ``(mean (K,), chol (K, K))``, ``K = theta_b.size [+ Nf] + P`` in that order (theta flattened;
            ``log_u`` where inferred): e.g. :func:`beam_gain_log_evidence`'s maximum and covariance, widened.
        options: without ``gram``, the marginal's and the sky draw's path (default Cholesky); with it, the sky
            draw's ``tol``.
        gram: the data-space Grams of ``system`` and ``block`` (:func:`gcrsky.inference.beams.beam_gram`), or None:
            with them the marginal and the sky draw (:func:`gcrsky.inference.beams.beam_gram_sky_draw`, at the
            step's gains: :func:`gcrsky.inference.beams.refold_gram`) cost no factorisation of size ``n``.
        with_info: also return the sky draw's SolveInfo.

    Returns:
        ``(state, accepted)``; with ``with_info``, ``(state, (accepted, info))``.
    """
    mean, chol = proposal
    beam = state.beam
    nf = None if beam.log_u is None else beam.log_u.shape[0]
    unpack = _unpacker(beam.theta.shape, nf, state.gain_theta.shape[0])
    old = _pack(beam.theta, beam.log_u, state.gain_theta)
    if mean.shape != old.shape:
        raise ValueError(f"the proposal has {mean.shape[0]} parameters, the state {old.shape[0]} (theta"
                         + ("" if nf is None else ", log_u") + " and the gains)")
    kp, ku, ka = jax.random.split(key, 3)
    new = mean + chol @ jax.random.normal(kp, mean.shape, mean.dtype)

    def log_q(x):
        y = jax.scipy.linalg.solve_triangular(chol, x - mean, lower=True)
        return -0.5 * jnp.sum(y**2)

    def log_p(x):
        th, lu, tg = unpack(x)
        return beam_gain_log_posterior(system, block, gains, th, tg, log_u=lu, options=options, gram=gram)

    log_ratio = log_p(new) + log_q(old) - log_p(old) - log_q(new)
    accept = (jnp.log(jax.random.uniform(ku, (), log_ratio.dtype)) < log_ratio) & jnp.all(jnp.isfinite(new))
    th, lu, tg = unpack(jnp.where(accept, new, old))
    blk = with_gains(block, gains, tg)
    beam, info = beam_sky_step(ka, beam._replace(theta=th, log_u=lu), system, blk, options=options,
                               gram=None if gram is None else refold_gram(gram, system, blk))
    out = BeamGainState(beam, tg)
    return (out, (accept, info)) if with_info else (out, accept)


class BeamGainEvidence(NamedTuple):
    """What :func:`beam_gain_log_evidence` returns (scalars summed over the channels).

    Attributes:
        log_z: ``log p(d | beam block, gains)``: beams, amplitude (where inferred) and gains by Laplace, the sky
            exactly.
        log_z_nominal: ``log p(d | nominal beams, gains)``: the same with the beams held at 0.
        log_bayes_factor: ``log_z - log_z_nominal``.
        theta: (Nant, M, Q), ``log_u`` (Nf,) or None, ``gain_theta`` (P,): the joint maximum.
        covariance: (K, K) the Laplace covariance of the flattened ``(theta, log_u, gain_theta)``.
        converged: both Hessians positive definite and both Newton decrements below
            :data:`gcrsky.inference.beams.NEWTON_DECREMENT_TOL`.
        log_u_nominal, gain_theta_nominal: the nominal model's maximum (``log_u_nominal`` None where not inferred).
    """

    log_z: jax.Array
    log_z_nominal: jax.Array
    log_bayes_factor: jax.Array
    theta: jax.Array
    log_u: jax.Array | None
    gain_theta: jax.Array
    covariance: jax.Array
    converged: jax.Array
    log_u_nominal: jax.Array | None
    gain_theta_nominal: jax.Array


def _flat_log_posterior(x, system, block, gains, gram, *, theta_shape, nf, options, nominal: bool):
    """:func:`beam_gain_log_posterior` of the flat vector ``x`` (:func:`_pack`'s order); ``nominal``: ``x`` holds
    ``(log_u, gain_theta)`` only, the beams at 0 (not integrated: their prior's density there taken off)."""
    p = gains.prior_mean.shape[0]
    if nominal:
        _, lu, tg = _unpacker((0,), nf, p)(x)
        zero = jnp.zeros(theta_shape, x.dtype)
        return (beam_gain_log_posterior(system, block, gains, zero, tg, log_u=lu, options=options, gram=gram)
                - beam_log_prior(block, zero))
    th, lu, tg = _unpacker(theta_shape, nf, p)(x)
    return beam_gain_log_posterior(system, block, gains, th, tg, log_u=lu, options=options, gram=gram)


_STATIC = ("theta_shape", "nf", "options", "nominal")
#: The Newton fits' pieces compiled once per shape (closures would recompile at every fit: minutes on H1C).
_VALUE = jax.jit(_flat_log_posterior, static_argnames=_STATIC)
_VALUE_GRAD = jax.jit(jax.value_and_grad(_flat_log_posterior), static_argnames=_STATIC)
_HESSIAN = jax.jit(jax.hessian(_flat_log_posterior), static_argnames=_STATIC)


def _laplace(args, kw, x0, steps: int):
    """Newton's maximum of :func:`_flat_log_posterior` (``args``, ``kw``) from ``x0`` and Laplace's
    ``log int exp(f)``: (x, log Z, covariance, converged)."""
    x, obj, hess, decrement = newton_polish(lambda y: _VALUE(y, *args, **kw), x0, steps,
                                             value_grad=lambda y: _VALUE_GRAD(y, *args, **kw),
                                             hess=lambda y: _HESSIAN(y, *args, **kw), secant=True)
    evals, vecs = jnp.linalg.eigh(hess)
    cov = (vecs / evals) @ vecs.T
    log_z = obj + 0.5 * x.size * jnp.log(2 * jnp.pi) - 0.5 * jnp.sum(jnp.log(jnp.abs(evals)))
    return x, log_z, cov, jnp.all(evals > 0) & (decrement < NEWTON_DECREMENT_TOL)


def beam_gain_log_evidence(system, block: BeamBlock, gains: GainBlock, *, theta0=None, gain_theta0=None,
                           log_u0=None, options=None, gram: BeamGram | None = None, newton_steps: int = 30,
                           nominal: bool = True) -> BeamGainEvidence:
    """Laplace's approximation of the joint marginal of the beams, the amplitude (where ``log_u0`` is given: it is
    inferred) and the gains (:func:`beam_gain_log_posterior`, the sky integrated out exactly), and of the nominal
    beams' model with the same gains and amplitude: each by damped Newton steps with the exact Hessian (an eager
    loop, as :func:`gcrsky.inference.beam_log_evidence`'s, its pieces compiled once per shape), the nominal one
    started from the joint maximum's gains and amplitude.  ``log Z = f* + K/2 log 2 pi - 1/2 log det(-H)``.

    Args:
        system, block, gains, options, gram: as :func:`beam_gain_log_posterior`.
        theta0: the beams' start (default the prior mean); ``gain_theta0`` the gains' (default 0);
            ``log_u0`` (Nf,) the amplitude's start, or None (not inferred).
        newton_steps: the most exact Hessians (``K`` columns each) of each fit; quasi-Newton steps between them
            (:func:`gcrsky.inference.beams.newton_polish`'s ``secant``).
        nominal: also fit the nominal model (False: its fields are NaN, its maximum the joint one's; e.g. for a fit
            whose only use is to move the gains' linearisation point).

    Returns:
        :class:`BeamGainEvidence`.
    """
    options = CholeskyOptions() if options is None else options
    theta0 = block.prior_mean if theta0 is None else jnp.asarray(theta0)
    g0 = jnp.zeros_like(gains.prior_mean) if gain_theta0 is None else jnp.asarray(gain_theta0)
    lu0 = None if log_u0 is None else jnp.asarray(log_u0, jnp.float64)
    nf = None if lu0 is None else lu0.shape[0]
    args = (system, block, gains, gram)
    kw = dict(theta_shape=tuple(theta0.shape), nf=nf, options=options)
    x, log_z, cov, ok = _laplace(args, {**kw, "nominal": False}, _pack(theta0, lu0, g0), newton_steps)
    th, lu, tg = _unpacker(theta0.shape, nf, g0.shape[0])(x)
    if not nominal:
        nan = jnp.asarray(jnp.nan)
        return BeamGainEvidence(log_z, nan, nan, th, lu, tg, cov, ok, lu, tg)
    y, log_z_nom, _, ok_nom = _laplace(args, {**kw, "nominal": True}, _pack(jnp.zeros(0), lu, tg), newton_steps)
    _, lu_n, tg_n = _unpacker((0,), nf, g0.shape[0])(y)
    return BeamGainEvidence(log_z, log_z_nom, log_z - log_z_nom, th, lu, tg, cov, ok & ok_nom, lu_n, tg_n)
