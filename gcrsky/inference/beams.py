"""Per-antenna beams sampled with the sky: the beam block (issue 41, DESIGN section 15).

The model is :mod:`gcrsky.instrument.beammodes`' exactly bilinear one: row ``b = (i, j)`` sees

    ``d_b = D_b sum_{k,l} u_ik u_jl (X^(kl) a)_b + n_b``,  ``u_i = (1, c_i1(nu), .., c_iM(nu))``,

with ``X^(kl)`` the operator of the response set ``R^(kl)`` (symmetric in ``k, l``), ``D`` a
fixed complex row factor (gains and amplitude, or 1) and ``c_ik(nu) = sum_q theta_ikq B_q(nu)``
(``theta`` (Nant, M, Q) real, ``B`` (Nf, Q) smooth frequency modes).  Given the sky and every
other antenna, the data are *exactly* linear in one antenna's ``theta_i``:

    ``d_b = D_b (T_b0 + sum_k c_ik T_bk) + n_b``,  ``T_bk = sum_l u_ol (X^(kl) a)_b``,

``o`` the row's other antenna, so ``theta_i | a, theta_-i, d`` is Gaussian (no linearisation):
with per-component inverse noise ``W``, precision
``sum_f B_q B_q' sum_tb W |D|^2 Re(conj(T_bk) T_bk') + Lambda^-1`` and right-hand side
``sum_f B_q sum_tb W Re(conj(D T_bk) r_b) + Lambda^-1 mu`` (``r = d - D T_0``).  The block
sweeps the antennas one by one (:func:`beam_sweep`, a ``lax.scan``; each antenna's draw is
exact given the others, so the sweep is a valid Gibbs update of the joint ``theta``); the
model visibilities of the ``P`` sets are computed once per sweep (one operator application
of ``P`` times as many rows).  Autocorrelation rows (quadratic in ``theta_i``) are refused.

The sky given the beams (:func:`beam_sky_step`) is the usual exact GCR draw of the system
whose response is :func:`gcrsky.instrument.beammodes.combine_responses` of the current
coefficients (a new response each sweep: the Cholesky path factorises per sweep, ~``Nf n^3 / 3``).

Redundancy: baselines of the same separation no longer share a response once their antennas'
beams differ, so a beam run keeps every baseline (no redundant compression).

Kernels in the blackjax form::

    block = beam_setup(stack, pairs, basis_f, sigma=0.05)
    state = beam_init(sky0, block)
    for k in warm_keys:                                      # a few, discarded
        state, _ = beam_warmup_step(k, state, system, block)
    state, info = beam_step(key, state, system, block)      # jit / lax.scan it

A sweep (:func:`beam_step`) is the exact sky draw, a joint Metropolis-Hastings move of every antenna's
coefficients with the Gauss-Newton Gaussian as proposal (:func:`beam_joint_move`: the antennas trade off
along directions with posterior correlations of +-0.99, which the antenna-by-antenna sweep crosses only
in hundreds of sweeps) and the antenna-by-antenna sweep.
"""

from __future__ import annotations

import logging
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..instrument.beammodes import combine_responses, mode_pairs
from ..model.operator import apply
from ..model.system import LinearSystem
from ..solvers.info import SolveInfo
from ..solvers.options import DEFAULT_TOL, CholeskyOptions
from .gibbs import gcr_init, gcr_step

log = logging.getLogger(__name__)

__all__ = [
    "BeamBlock",
    "BeamEvidence",
    "BeamGram",
    "BeamState",
    "beam_coefficients",
    "beam_gram",
    "beam_gram_bytes",
    "beam_gram_log_evidence",
    "beam_gram_sky_draw",
    "beam_collapsed_step",
    "beam_conditional",
    "beam_conditional_mode",
    "beam_init",
    "beam_joint_move",
    "beam_log_evidence",
    "beam_log_posterior",
    "beam_marginal_log_posterior",
    "beam_log_prior",
    "beam_model",
    "beam_setup",
    "beam_sky_step",
    "beam_step",
    "beam_sweep",
    "beam_system",
    "beam_warmup_step",
    "check_amplitude_identified",
    "fold_row_factor",
    "newton_polish",
    "refold_gram",
    "set_visibilities",
]


class BeamBlock(NamedTuple):
    """The beam block's fixed parts (a PyTree; :func:`beam_setup`).

    Attributes:
        stack: (Nf, P, Nbl, n) the response sets ``R^(kl)`` (:func:`gcrsky.instrument.beammodes.mode_responses`).
        pairs: (Nbl, 2) int, the antenna indices of each row.
        basis_f: (Nf, Q) the frequency modes ``B_q(nu)``.
        prior_inv_var: (M, Q) inverse prior variance of each antenna's ``theta_ikq``.
        prior_mean: (Nant, M, Q) prior mean of ``theta``.
        row_factor: (Nf, Nt, Nbl) complex ``D`` (gains, amplitude), or a scalar 1.
        mean_inv_var: (M, Q) inverse prior variance of the array's mean coefficient
            ``theta_bar = sum_i theta_i / Nant`` (0: no prior beyond each antenna's).
    """

    stack: jax.Array
    pairs: jax.Array
    basis_f: jax.Array
    prior_inv_var: jax.Array
    prior_mean: jax.Array
    row_factor: jax.Array
    mean_inv_var: jax.Array


class BeamState(NamedTuple):
    """The joint chain: ``sky`` a (Nf, n) K; ``theta`` (Nant, M, Q) the beam coefficients; ``log_u`` (Nf,) the
    natural log of the overall amplitude per channel where it is inferred (:func:`beam_system`), else None."""

    sky: jax.Array
    theta: jax.Array
    log_u: jax.Array | None = None


def beam_setup(stack, pairs, basis_f, *, sigma, mean_sigma=None, n_ant: int | None = None,
               row_factor=1.0) -> BeamBlock:
    """The beam block (pure NumPy set-up).

    Args:
        stack: (Nf, P, Nbl, n) response sets; ``P = (M + 1)(M + 2) / 2``.
        pairs: (Nbl, 2) antenna indices (cross-correlations only).
        basis_f: (Nf, Q) frequency modes (e.g. :func:`gcrsky.model.gains.mode_basis`; ``np.ones((Nf, 1))``
            for coefficients constant in frequency).
        sigma: prior standard deviation of each coefficient (fractional beam change per mode at the disc's
            edge): scalar, (M,) per mode or (M, Q).
        mean_sigma: prior standard deviation of the array's *mean* coefficient (as ``sigma``), or None (no
            such prior).  A perturbation common to every dish is nearly degenerate with the sky (a common
            East-West pointing offset with a rotation of the sky in right ascension: the chain crawls along
            it); the nominal beam is the array's mean beam when this is small.  The prior term
            ``theta_bar^2 / (2 mean_sigma^2)`` couples the antennas, and each one's conditional stays
            Gaussian (:func:`beam_conditional`).
        n_ant: the number of antennas (default: the largest index in ``pairs`` plus one).
        row_factor: ``D``, (Nf, Nt, Nbl) complex or a scalar.

    Raises:
        ValueError: an autocorrelation row, shapes that disagree, or a non-positive sigma.
    """
    stack = jnp.asarray(stack)
    pairs = np.asarray(pairs, np.int64)
    basis_f = np.asarray(basis_f, np.float64)
    nf, npair = stack.shape[:2]
    m = int(round((np.sqrt(8 * npair + 1) - 3) / 2))
    if mode_pairs(m).shape[0] != npair:
        raise ValueError(f"stack has {npair} response sets, not (M + 1)(M + 2) / 2 for any M")
    if pairs.ndim != 2 or pairs.shape != (stack.shape[2], 2):
        raise ValueError(f"pairs has shape {pairs.shape}, expected (Nbl, 2) = ({stack.shape[2]}, 2)")
    if np.any(pairs[:, 0] == pairs[:, 1]):
        raise ValueError("the beam block models cross-correlations only: drop the autocorrelation rows")
    if basis_f.ndim != 2 or basis_f.shape[0] != nf:
        raise ValueError(f"basis_f has shape {basis_f.shape}, expected (Nf, Q) with Nf = {nf}")
    q = basis_f.shape[1]
    sig = np.asarray(sigma, np.float64)
    sig = sig[:, None] if sig.ndim == 1 else sig
    try:
        sig = np.broadcast_to(sig, (m, q))
    except ValueError:
        raise ValueError(f"sigma has shape {np.shape(sigma)}, not broadcastable to (M, Q) = {(m, q)}") from None
    if np.any(~(sig > 0)) or np.any(~np.isfinite(sig)):
        raise ValueError("the beam prior's sigma must be positive and finite")
    mean_iv = np.zeros((m, q))
    if mean_sigma is not None:
        ms = np.asarray(mean_sigma, np.float64)
        ms = np.broadcast_to(ms[:, None] if ms.ndim == 1 else ms, (m, q))
        if np.any(~(ms > 0)) or np.any(~np.isfinite(ms)):
            raise ValueError("the beam prior's mean_sigma must be positive and finite (None: no prior on the mean)")
        mean_iv = 1.0 / ms**2
    nant = int(pairs.max()) + 1 if n_ant is None else int(n_ant)
    return BeamBlock(stack, jnp.asarray(pairs), jnp.asarray(basis_f), jnp.asarray(1.0 / sig**2),
                     jnp.zeros((nant, m, q)), jnp.asarray(row_factor), jnp.asarray(mean_iv))


def beam_init(sky, block: BeamBlock, *, theta=None, log_u=None) -> BeamState:
    """Start the chain at sky ``a`` (Nf, n), ``theta`` (default: the prior mean) and, with the amplitude inferred,
    ``log_u`` (Nf,) (default None: the amplitude is the row factor's)."""
    sky = jnp.asarray(sky)
    th = block.prior_mean if theta is None else jnp.asarray(theta, sky.dtype)
    return BeamState(sky, th, None if log_u is None else jnp.asarray(log_u, sky.dtype))


def beam_coefficients(block: BeamBlock, theta) -> jax.Array:
    """``c_ik(nu) = sum_q theta_ikq B_q(nu)``: (Nant, Nf, M)."""
    return jnp.einsum("amq,fq->afm", theta, block.basis_f)


def beam_system(system: LinearSystem, block: BeamBlock, theta, log_u=None) -> LinearSystem:
    """The sky's system with the response of the beams ``theta`` (and the row factor folded into the data and noise).

    With ``log_u`` (Nf,) the response is also multiplied by the overall amplitude ``u_f = exp(log_u_f)`` (DESIGN
    section 14: the data are ``u X a``, the sky ``a ~ N(a0, S)`` a sky model in K; the amplitude is a parameter of
    the response, not of the data, so the system's evidence stays the density of the data as given)."""
    from .amplitude import scale_response

    resp = combine_responses(block.stack, block.pairs, beam_coefficients(block, theta))
    data, w = fold_row_factor(system, block.row_factor)
    out = system._replace(op=system.op._replace(response=resp), data=data, inv_noise=w)
    return out if log_u is None else scale_response(out, log_u)


def fold_row_factor(system: LinearSystem, row_factor):
    """The data ``d / D`` (0 where ``D = 0``) and inverse noise ``W |D|^2`` (Nf, Nt, Nbl) of the model ``d = D X a + n``
    with the row factor ``D`` (Nf, Nt, Nbl) complex or a scalar folded in: ``|d - D X a|^2 W = |d / D - X a|^2 W |D|^2``."""
    D = jnp.broadcast_to(row_factor, system.data.shape).astype(system.data.dtype)
    w = system.inv_noise * jnp.abs(D) ** 2
    return jnp.where(D == 0, 0.0, system.data / jnp.where(D == 0, 1.0, D)), w


def set_visibilities(system: LinearSystem, block: BeamBlock, sky) -> jax.Array:
    """``X^(kl) a`` of every response set: (Nf, Nt, P, Nbl) complex (one operator application)."""
    nf, npair, nbl, n = block.stack.shape
    op = system.op._replace(response=jnp.reshape(block.stack, (nf, npair * nbl, n)))
    v = apply(op, sky)  # (Nf, Nt, P * Nbl)
    return jnp.reshape(v, v.shape[:2] + (npair, nbl))


def _full_index(m: int) -> np.ndarray:
    """(M+1, M+1) the set index of ``(k, l)`` (symmetric)."""
    idx = np.zeros((m + 1, m + 1), np.int64)
    for p, (k, l) in enumerate(mode_pairs(m)):
        idx[k, l] = idx[l, k] = p
    return idx


def beam_conditional(block: BeamBlock, i, theta, sets, data, inv_noise):
    """Precision (MQ, MQ) and right-hand side (MQ,) of ``theta_i | a, theta_-i, d`` (module docstring).

    Args:
        block: :func:`beam_setup`'s block.
        i: the antenna (an int, or a traced index).
        theta: (Nant, M, Q) the current coefficients (antenna ``i``'s are not used).
        sets: :func:`set_visibilities` of the current sky, (Nf, Nt, P, Nbl).
        data, inv_noise: (Nf, Nt, Nbl) the visibilities and per-component inverse noise variance.
    """
    nant, m, q = theta.shape
    pairs = block.pairs
    involved = (pairs[:, 0] == i) | (pairs[:, 1] == i)  # (Nbl,)
    other = jnp.where(pairs[:, 0] == i, pairs[:, 1], pairs[:, 0])
    u = jnp.concatenate([jnp.ones((nant, block.basis_f.shape[0], 1)), beam_coefficients(block, theta)], axis=-1)
    uo = u[other]  # (Nbl, Nf, M+1)
    full = sets[:, :, jnp.asarray(_full_index(m)), :]  # (Nf, Nt, M+1, M+1, Nbl)
    T = jnp.einsum("ftklb,bfl->ftkb", full, uo)  # (Nf, Nt, M+1, Nbl)
    D = jnp.broadcast_to(block.row_factor, data.shape)
    w = jnp.where(involved[None, None, :], inv_noise, 0.0)
    z = D[:, :, None, :] * T  # (Nf, Nt, M+1, Nbl)
    r = data - z[:, :, 0]
    S = jnp.einsum("ftb,ftkb,ftmb->fkm", w, jnp.conj(z[:, :, 1:]), z[:, :, 1:]).real  # (Nf, M, M)
    g = jnp.einsum("ftb,ftkb,ftb->fk", w, jnp.conj(z[:, :, 1:]), r).real  # (Nf, M)
    B = block.basis_f
    prec = jnp.einsum("fkm,fq,fr->kqmr", S, B, B).reshape(m * q, m * q)
    kappa = block.mean_inv_var / nant**2  # the mean's prior: (kappa / 2) (sum_j theta_j)^2
    others = jnp.sum(theta, axis=0) - theta[i]
    prec = prec + jnp.diag((block.prior_inv_var + kappa).reshape(-1))
    rhs = jnp.einsum("fk,fq->kq", g, B).reshape(-1) + (block.prior_inv_var * block.prior_mean[i]
                                                       - kappa * others).reshape(-1)
    return prec, rhs


def _draw(key, prec, rhs):
    L = jnp.linalg.cholesky(prec)
    z = jax.random.normal(key, rhs.shape, rhs.dtype)
    return jax.scipy.linalg.cho_solve((L, True), rhs) + jax.scipy.linalg.solve_triangular(L.T, z, lower=False)


def beam_sweep(key: jax.Array, theta, block: BeamBlock, sets, data, inv_noise) -> jax.Array:
    """One Gibbs sweep over the antennas: each ``theta_i`` drawn exactly given the sky and the others (``lax.scan``).

    Returns:
        the new ``theta`` (Nant, M, Q).
    """
    nant, m, q = theta.shape

    def one(th, xs):
        i, k = xs
        prec, rhs = beam_conditional(block, i, th, sets, data, inv_noise)
        return th.at[i].set(_draw(k, prec, rhs).reshape(m, q)), None

    theta, _ = jax.lax.scan(one, theta, (jnp.arange(nant), jax.random.split(key, nant)))
    return theta


def beam_model(block: BeamBlock, theta, sets) -> jax.Array:
    """The model visibilities ``D sum_{k<=l} w_kl(u_i, u_j) (X^(kl) a)_b`` (Nf, Nt, Nbl) from :func:`set_visibilities`."""
    from ..instrument.beammodes import pair_weights

    nant = theta.shape[0]
    u = jnp.concatenate([jnp.ones((nant, block.basis_f.shape[0], 1)), beam_coefficients(block, theta)], axis=-1)
    w = pair_weights(u[block.pairs[:, 0]], u[block.pairs[:, 1]])  # (Nbl, Nf, P)
    return jnp.broadcast_to(block.row_factor, sets.shape[:2] + sets.shape[3:]) * jnp.einsum("bfp,ftpb->ftb", w, sets)


def beam_log_posterior(block: BeamBlock, theta, sets, data, inv_noise) -> jax.Array:
    """``log p(theta | a, d)`` up to a constant: ``-1/2 sum W |d - model|^2`` plus the beam prior (:func:`beam_log_prior`)."""
    r = data - beam_model(block, theta, sets)
    return -0.5 * jnp.sum(inv_noise * (r.real**2 + r.imag**2)) + beam_log_prior(block, theta)


def _gauss_newton(block: BeamBlock, theta, sets, data, inv_noise):
    """The joint Gauss-Newton system of every antenna's coefficients at ``theta``: ``(P (K, K), g (K,))`` with
    ``P = Re(J^H W J) + prior precision`` and ``g`` the gradient of :func:`beam_log_posterior` (``K = Nant M Q``).

    ``J`` is never formed: row ``b = (i, j)`` depends on antennas ``i`` and ``j`` only, through
    ``T_bk^(i) = sum_l u_jl (X^(kl) a)_b`` and ``T_bk^(j)`` (:func:`beam_conditional`), so the row's 2 x 2 blocks
    of ``M Q x M Q`` are summed over times and scattered into ``P``.
    """
    nant, m, q = theta.shape
    pi, pj = block.pairs[:, 0], block.pairs[:, 1]
    u = jnp.concatenate([jnp.ones((nant, block.basis_f.shape[0], 1)), beam_coefficients(block, theta)], axis=-1)
    full = sets[:, :, jnp.asarray(_full_index(m)), :]  # (Nf, Nt, M+1, M+1, Nbl)
    D = jnp.broadcast_to(block.row_factor, data.shape)
    Zi = D[:, :, None, :] * jnp.einsum("ftklb,bfl->ftkb", full[:, :, 1:], u[pj])  # d model / d c_i: (Nf, Nt, M, Nbl)
    Zj = D[:, :, None, :] * jnp.einsum("ftklb,bfl->ftkb", full[:, :, 1:], u[pi])
    r = data - beam_model(block, theta, sets)
    B = block.basis_f

    def pair_block(Za, Zb):  # (Nbl, M Q, M Q)
        S = jnp.einsum("ftb,ftkb,ftmb->fbkm", inv_noise, jnp.conj(Za), Zb).real
        return jnp.einsum("fbkm,fq,fr->bkqmr", S, B, B).reshape(-1, m * q, m * q)

    P = jnp.zeros((nant, m * q, nant, m * q))
    P = P.at[pi, :, pi, :].add(pair_block(Zi, Zi)).at[pj, :, pj, :].add(pair_block(Zj, Zj))
    cross = pair_block(Zi, Zj)
    P = P.at[pi, :, pj, :].add(cross).at[pj, :, pi, :].add(jnp.swapaxes(cross, 1, 2))
    gi = jnp.einsum("fbk,fq->bkq", jnp.einsum("ftb,ftkb,ftb->fbk", inv_noise, jnp.conj(Zi), r).real, B)
    gj = jnp.einsum("fbk,fq->bkq", jnp.einsum("ftb,ftkb,ftb->fbk", inv_noise, jnp.conj(Zj), r).real, B)
    g = jnp.zeros((nant, m, q)).at[pi].add(gi).at[pj].add(gj)
    kappa = block.mean_inv_var / nant**2
    g = g - block.prior_inv_var * (theta - block.prior_mean) - kappa * jnp.sum(theta, axis=0)
    K = nant * m * q
    P = P.reshape(K, K) + jnp.diag(jnp.broadcast_to(block.prior_inv_var, theta.shape).reshape(-1))
    P = P + jnp.kron(jnp.ones((nant, nant)), jnp.diag(kappa.reshape(-1)))
    return P, g.reshape(-1)


def _proposal(block, theta, sets, data, inv_noise):
    P, g = _gauss_newton(block, theta, sets, data, inv_noise)
    L = jnp.linalg.cholesky(P)
    mean = theta.reshape(-1) + jax.scipy.linalg.cho_solve((L, True), g)
    return mean, L


def _log_q(x, mean, L):
    y = L.T @ (x - mean)  # P = L L^T: the density of N(mean, P^-1) up to the shared 2 pi
    return -0.5 * jnp.sum(y**2) + jnp.sum(jnp.log(jnp.diag(L)))


def beam_joint_move(key: jax.Array, theta, block: BeamBlock, sets, data, inv_noise):
    """One Metropolis-Hastings move of every antenna's coefficients at once (exact: leaves ``theta | a, d`` invariant).

    The proposal is the Gauss-Newton Gaussian at the current point, ``N(theta + P^-1 g, P^-1)``
    (:func:`_gauss_newton`: the model linearised in all the coefficients together), accepted with the
    Metropolis-Hastings ratio that uses the reverse proposal at the new point.  The model is bilinear, so
    the posterior is nearly Gaussian where the perturbations are small and the move is accepted nearly
    always; it crosses in one step the directions along which the antennas trade off (posterior
    correlations of +-0.99 between antennas were measured on a 4-dish problem, where the antenna-by-antenna
    sweep's autocorrelation was still 0.9 after 500 sweeps).  Costs two ``K x K`` Cholesky factorisations.

    Returns:
        ``(theta (Nant, M, Q), accepted (bool))``.
    """
    kp, ku = jax.random.split(key)
    mean, L = _proposal(block, theta, sets, data, inv_noise)
    z = jax.random.normal(kp, mean.shape, mean.dtype)
    new = mean + jax.scipy.linalg.solve_triangular(L.T, z, lower=False)
    new_t = new.reshape(theta.shape)
    mean_b, L_b = _proposal(block, new_t, sets, data, inv_noise)
    log_ratio = (beam_log_posterior(block, new_t, sets, data, inv_noise) + _log_q(theta.reshape(-1), mean_b, L_b)
                 - beam_log_posterior(block, theta, sets, data, inv_noise) - _log_q(new, mean, L))
    accept = jnp.log(jax.random.uniform(ku, (), log_ratio.dtype)) < log_ratio
    accept = accept & jnp.all(jnp.isfinite(new))
    return jnp.where(accept, new_t, theta), accept


def beam_sky_step(key: jax.Array, state: BeamState, system: LinearSystem, block: BeamBlock, *,
                  options=None, gram: BeamGram | None = None) -> tuple[BeamState, SolveInfo]:
    """One exact draw of the sky given the beams: with ``gram`` (:func:`beam_gram`, folded with ``block``'s row
    factor) in the data space from the Grams (:func:`beam_gram_sky_draw`, ``options``' ``tol`` where it has one);
    else :func:`beam_system`, then :func:`gcrsky.inference.gcr_step` on ``options``' path (default Cholesky)."""
    if gram is not None:
        tol = getattr(options, "tol", DEFAULT_TOL)
        sky, info = beam_gram_sky_draw(key, gram, system, block, state.theta, state.log_u, tol=tol)
        return state._replace(sky=sky), info
    sys_b = beam_system(system, block, state.theta, state.log_u)
    new, info = gcr_step(key, gcr_init(state.sky), sys_b, options=CholeskyOptions() if options is None else options)
    return state._replace(sky=new.position), info


def beam_step(key: jax.Array, state: BeamState, system: LinearSystem, block: BeamBlock, *,
              options=None) -> tuple[BeamState, SolveInfo]:
    """One sweep of the joint chain: the sky given the beams, then the beams given that sky: a joint
    Metropolis-Hastings move of every antenna's coefficients (:func:`beam_joint_move`) and the exact
    antenna-by-antenna Gibbs sweep (:func:`beam_sweep`).

    The sky goes first: a chain started at the nominal beams (``theta = 0``) and any sky then moves the beams
    only as far as the data ask (a beam draw given a sky far from the data, e.g. the prior mean, lands
    anywhere in the beam prior, and the chain takes hundreds of sweeps to crawl back).  ``system`` holds the
    raw data, noise, the nominal operator's angles and the sky prior (its response is replaced by the beams'
    each sweep).  Pure; ``jit`` / ``lax.scan`` it.  Returns the new state and the sky step's SolveInfo.
    """
    if state.log_u is not None:
        raise ValueError("beam_step (the alternating chain) holds the amplitude fixed: a state with log_u is the "
                         "collapsed chain's (beam_collapsed_step)")
    ka, km, kb = jax.random.split(key, 3)
    state, info = beam_sky_step(ka, state, system, block, options=options)
    sets = set_visibilities(system, block, state.sky)
    theta, _ = beam_joint_move(km, state.theta, block, sets, system.data, system.inv_noise)
    theta = beam_sweep(kb, theta, block, sets, system.data, system.inv_noise)
    return state._replace(theta=theta), info


class BeamEvidence(NamedTuple):
    """What :func:`beam_log_evidence` returns (scalars summed over the channels, unless stated).

    Attributes:
        log_z: ``log p(d | beam block)``, the beam coefficients marginalised by Laplace's method.
        log_z_nominal: ``log p(d | nominal beams)`` (the coefficients at 0), exact.
        log_bayes_factor: ``log_z - log_z_nominal`` (> 0: the data ask for the block).
        theta: (Nant, M, Q) the maximum of ``log p(d | theta) + log p(theta)``.
        covariance: (k, k) the Laplace covariance of the flattened ``theta`` (then ``log_u``, where inferred).
        converged: the optimiser converged and the Hessian is positive definite.
        log_u: (Nf,) the amplitude at the maximum where it is inferred (``amplitude``), else None.
        log_u_nominal: (Nf,) the maximum of the nominal beams' ``log p(d | u)`` where inferred, else None.
    """

    log_z: jax.Array
    log_z_nominal: jax.Array
    log_bayes_factor: jax.Array
    theta: jax.Array
    covariance: jax.Array
    converged: jax.Array
    log_u: jax.Array | None = None
    log_u_nominal: jax.Array | None = None


def beam_log_prior(block: BeamBlock, theta) -> jax.Array:
    """The normalised log density of the beam prior at ``theta`` (Nant, M, Q): each antenna's Gaussian and the
    array mean's (:func:`beam_setup`), i.e. per mode the Gaussian of precision ``lambda I + kappa 1 1^T``
    (``kappa = mean_inv_var / Nant^2``), whose log determinant is ``(Nant - 1) log lambda + log(lambda + Nant kappa)``."""
    nant = theta.shape[0]
    lam, kappa = block.prior_inv_var, block.mean_inv_var / nant**2
    d = theta - block.prior_mean
    quad = jnp.sum(lam * d**2) + jnp.sum(kappa * jnp.sum(theta, axis=0) ** 2)
    logdet = jnp.sum((nant - 1) * jnp.log(lam) + jnp.log(lam + nant * kappa))
    return -0.5 * (quad - logdet + theta.size * jnp.log(2 * jnp.pi))


#: Newton decrement ``g^T (-H)^-1 g`` below which :func:`beam_log_evidence`'s maximum counts as reached (the
#: objective is then within ~1e-6 of it: far below the evidence's own accuracy).
NEWTON_DECREMENT_TOL = 1e-6


#: Quasi-Newton steps :func:`newton_polish` may take per exact Hessian with ``secant=True``.
SECANT_STEPS_PER_HESSIAN = 25


def _modulus_step(h, g):
    """``|h|^-1 g``: the eigenvalues of the symmetric ``h`` taken in modulus (floored at 1e-12 of the largest)."""
    w, v = jnp.linalg.eigh(0.5 * (h + h.T))
    w = jnp.maximum(jnp.abs(w), 1e-12 * jnp.max(jnp.abs(w)))
    return v @ ((v.T @ g) / w)


def newton_polish(fun, x, steps: int, *, jit: bool = False, value_grad=None, hess=None, secant: bool = False):
    """Damped Newton steps maximising ``fun`` (flat -> scalar) from ``x``: the step ``|-H|^-1 g`` (eigenvalues of
    ``-H`` taken in modulus: a saddle is left, not approached), halved up to 29 times until ``fun`` increases (else
    the step is not taken, and the polish ends), until the Newton decrement ``g^T |-H|^-1 g`` falls below
    :data:`NEWTON_DECREMENT_TOL` or after ``steps`` exact Hessians.

    ``secant``: between exact Hessians, BFGS updates of the last one (a step then costs a gradient, not a Hessian's
    ``K`` Hessian-vector products; the Grams' marginal's gradient costs ~1.1 of its value, its Hessian ~2 K):
    an exact Hessian at the start, again wherever the secant step's line search stalls (halved below 1/16), after
    :data:`SECANT_STEPS_PER_HESSIAN` secant steps, and where the secant decrement falls below the tolerance; the
    polish ends only at an exact Hessian's decrement.  The maximum is the same (to the tolerance) and the returned
    Hessian is always exact, at the returned point.

    The loop is eager; ``jit``: its pieces (value and gradient, Hessian, value) each compiled once (the primal
    path's pieces jitted stalled XLA's CPU runtime once, jax 0.10.2, and it stays eager; the Grams' are small and
    compile).  ``value_grad`` and ``hess``: those of ``fun``, given (e.g. module-level compiled functions that a
    closure would recompile per fit).  Returns ``(x, fun(x), Hessian of -fun at x, Newton decrement at x)``."""
    value_grad = jax.value_and_grad(fun) if value_grad is None else value_grad
    hess = jax.hessian(fun) if hess is None else hess
    if jit:
        value_grad, hess, fun = jax.jit(value_grad), jax.jit(hess), jax.jit(fun)

    def exact(x):
        h = -hess(x)
        return 0.5 * (h + h.T)

    t0 = time.perf_counter()
    f, g = value_grad(x)
    h = b = exact(x)
    n_hess, since, n_steps = 1, 0, 0  # exact Hessians so far; secant steps since the last one; steps taken
    while True:
        step = _modulus_step(b, g)
        fresh = b is h  # the step is from the exact Hessian at x
        dec = float(g @ step)
        if fresh and (dec < NEWTON_DECREMENT_TOL or (not secant and n_steps >= steps)):
            break
        stale = not fresh and (dec < NEWTON_DECREMENT_TOL or since >= SECANT_STEPS_PER_HESSIAN)
        t = 0.0
        if not stale:
            t = 1.0
            while t > 2.0**-30:
                fx = float(fun(x + t * step))
                if np.isfinite(fx) and fx > float(f):
                    break
                t *= 0.5
            else:
                t = 0.0
            stale = not fresh and t < 1.0 / 16  # the secant model is poor here
        if stale:  # an exact Hessian at x, within the budget
            if n_hess >= steps:
                break
            h = b = exact(x)
            n_hess, since = n_hess + 1, 0
            continue
        if t == 0.0:
            break
        x_new = x + t * step
        n_steps += 1
        f_new, g_new = value_grad(x_new)
        if secant:
            s, y = x_new - x, g - g_new  # the gradient of -fun changes by y along s
            sy = float(s @ y)
            if sy > 1e-12 * float(jnp.linalg.norm(s) * jnp.linalg.norm(y)):
                bs = b @ s
                b = b + jnp.outer(y, y) / sy - jnp.outer(bs, bs) / float(s @ bs)
            elif b is h:
                b = h + 0.0  # a new object: the next step counts as a secant one
            since += 1
        x, f, g = x_new, f_new, g_new
        if not secant:
            h = b = exact(x)
            n_hess += 1
    if b is not h:  # ended on a secant model: the exact Hessian at x
        h = exact(x)
        n_hess += 1
    decrement = g @ _modulus_step(h, g)
    log.info("newton_polish: %d steps, %d exact Hessians (K = %d), decrement %.3g, %.1f s", n_steps, n_hess, x.size,
             float(decrement), time.perf_counter() - t0)
    return x, f, h, decrement


def beam_log_evidence(system: LinearSystem, block: BeamBlock, *, theta0=None, amplitude: bool = False, log_u0=None,
                      options=None, max_steps: int = 200, newton_steps: int = 0,
                      gram: BeamGram | None = None) -> BeamEvidence:
    """Whether the data ask for the beam block: its evidence against the nominal beams'.

    ``log p(d | block) = log int p(d | theta) p(theta) dtheta``, with ``p(d | theta)`` the exact evidence of
    the sky model whose response is the beams ``theta``'s (:func:`gcrsky.inference.log_evidence_system`,
    dense Cholesky by default) and the integral over the ``k = Nant M Q`` coefficients by Laplace's method
    about the maximum of ``f = log p(d | theta) + log p(theta)``: BFGS (:func:`gcrsky.inference.
    fit_hyperparameters`; pure, ``jit``/``vmap`` it) and, with ``newton_steps > 0``, up to that many damped
    Newton steps with the exact Hessian (eager, not under ``jit``: BFGS alone stalls along the antennas'
    strongly correlated directions: on a 7-dish matvis twin it stopped 46 nats short of the maximum after 500
    steps, or at an indefinite Hessian from the nominal beams; what ``gcrsky run --beams sample`` uses), ``log Z ~ f(theta*) + k/2 log 2 pi + 1/2 log det Sigma``, ``Sigma`` the
    inverse Hessian of ``-f``.  Laplace is exact for a Gaussian integrand; ``tests/test_beam_block.py`` checks
    it against importance sampling of the exact integrand.  The row factor is folded in as in :func:`beam_system`.

    **The amplitude inferred** (``amplitude=True``): the response is ``u_f`` times the beams' (DESIGN section 14),
    ``u`` per channel with the prior uniform in ``ln u`` (:func:`gcrsky.inference.amplitude.amplitude_log_prior`),
    and both models integrate it out: the nominal one exactly per channel (:func:`gcrsky.inference.amplitude.
    log_evidence_over_u`: the data-space marginal on a grid across the prior's range), the block's by Laplace
    jointly with ``theta`` (``k = Nant M Q + Nf``; BFGS starts at the nominal's most probable ``u``).  Needs
    ``newton_steps > 0`` (eager), and data that determine ``u`` (else ``ValueError``: Laplace in ``ln u`` would
    be meaningless where the posterior runs to the prior's end).

    Args:
        system: the sky's system (raw data, noise, prior; its response is replaced).
        block: :func:`beam_setup`'s block.
        theta0: the optimiser's start (default the prior mean; a start near the maximum, e.g. a few
            :func:`beam_warmup_step`'s, saves most of the steps).
        amplitude: infer the overall amplitude per channel (above); False: it is the row factor's (fixed).
        log_u0: (Nf,) where the search in ``ln u`` starts (default: the nominal beams' most probable ``u``; a
            mis-specified nominal model may have its maximum far from the block's: start from each of its modes,
            :func:`gcrsky.inference.amplitude.local_modes`, and keep the best).
        options: the evidence path's options (default ``CholeskyOptions()``).
        max_steps: BFGS's step cap.
        newton_steps: the most exact Hessians (``k`` Hessian-vector products each) after BFGS, with quasi-Newton
            steps between them (:func:`newton_polish`'s ``secant``); 0: none.
        gram: the data-space Grams (:func:`beam_gram`): with ``newton_steps``, every evaluation of the marginal
            from them and no BFGS (Newton's steps from ``theta0`` alone, each Hessian cheap).

    Returns:
        :class:`BeamEvidence`; ``converged``: the Hessian of ``-f`` is positive definite and BFGS converged
        or (with Newton steps) the Newton decrement is below :data:`NEWTON_DECREMENT_TOL`.

    Raises:
        ValueError: ``amplitude`` without ``newton_steps``; the amplitude not identified by the data (naming
            the channels and its posterior spread).
    """
    from jax.flatten_util import ravel_pytree

    from .amplitude import amplitude_log_prior, log_evidence_over_u
    from .evidence import log_evidence_system
    from .hyper import fit_hyperparameters

    options = CholeskyOptions() if options is None else options
    start = block.prior_mean if theta0 is None else jnp.asarray(theta0)
    if amplitude:
        if not newton_steps:
            raise ValueError("beam_log_evidence with the amplitude integrates it out eagerly: give newton_steps > 0")
        nom = log_evidence_over_u(beam_system(system, block, jnp.zeros_like(start)))
        check_amplitude_identified(nom)
        lu0 = nom.log_u if log_u0 is None else jnp.broadcast_to(jnp.asarray(log_u0, jnp.float64), nom.log_u.shape)
        if gram is None:
            fit = fit_hyperparameters(lambda p: beam_system(system, block, p[0], p[1]), (start, lu0),
                                      options=options, log_prior=lambda p: beam_log_prior(block, p[0])
                                      + amplitude_log_prior(p[1]), max_steps=max_steps, covariance=False)
            flat, unravel = ravel_pytree(fit.theta)
        else:  # the Grams make Newton's steps cheap: no BFGS first
            flat, unravel = ravel_pytree((start, lu0))
        nominal = jnp.sum(nom.log_z)

        def fun(x):
            th, lu = unravel(x)
            return beam_marginal_log_posterior(system, block, th, log_u=lu, options=options, gram=gram)
    elif gram is not None and newton_steps:  # the Grams make Newton's steps cheap: no BFGS first
        nominal = jnp.sum(beam_gram_log_evidence(gram, block, jnp.zeros_like(start)))
        flat, unravel = ravel_pytree(start)
        nom = None

        def fun(x):
            return beam_marginal_log_posterior(system, block, unravel(x), gram=gram)
    else:
        fit = fit_hyperparameters(lambda th: beam_system(system, block, th), start, options=options,
                                  log_prior=lambda th: beam_log_prior(block, th), max_steps=max_steps,
                                  covariance=not newton_steps)  # the Newton steps compute their own
        nominal = jnp.sum(log_evidence_system(beam_system(system, block, jnp.zeros_like(start)), options=options,
                                              check=False)[0])
        if not newton_steps:  # pure: BFGS's maximum and its Hessian
            k = fit.covariance.shape[0]
            sign, logdet = jnp.linalg.slogdet(fit.covariance)
            log_z = fit.objective + 0.5 * k * jnp.log(2 * jnp.pi) + 0.5 * logdet
            return BeamEvidence(log_z, nominal, log_z - nominal, fit.theta, fit.covariance,
                                fit.converged & (sign > 0))
        flat, unravel = ravel_pytree(fit.theta)
        nom = None

        def fun(x):
            return beam_marginal_log_posterior(system, block, unravel(x), options=options, gram=gram)

    flat, obj, hess, decrement = newton_polish(fun, flat, newton_steps, jit=gram is not None, secant=True)
    k = flat.size
    evals, vecs = jnp.linalg.eigh(hess)
    cov = (vecs / evals) @ vecs.T
    log_z = obj + 0.5 * k * jnp.log(2 * jnp.pi) - 0.5 * jnp.sum(jnp.log(jnp.abs(evals)))
    converged = jnp.all(evals > 0) & (decrement < NEWTON_DECREMENT_TOL)
    best = unravel(flat)
    if nom is None:
        return BeamEvidence(log_z, nominal, log_z - nominal, best, cov, converged)
    return BeamEvidence(log_z, nominal, log_z - nominal, best[0], cov, converged, best[1], nom.log_u)


def check_amplitude_identified(nom) -> None:
    """Refuse an amplitude the data do not determine (:class:`gcrsky.inference.amplitude.AmplitudeEvidence`'s
    ``identified``), naming the channels and the posterior spread of ``ln u``."""
    bad = np.flatnonzero(~np.asarray(nom.identified))
    if bad.size:
        sd = ", ".join(f"{float(nom.sd[i]):.3g}" for i in bad[:5])
        raise ValueError(f"the data do not determine the overall amplitude in channel(s) {bad.tolist()[:10]} (posterior "
                         f"sd of ln u {sd}, or it runs to the prior's end): the modelled sky is below the noise "
                         "there (e.g. a low lmax whose marginalised sky dominates the data); raise lmax, choose other "
                         "channels, or give calibrated data with the amplitude fixed")


def beam_conditional_mode(theta, block: BeamBlock, sets, data, inv_noise, *, iterations: int = 5) -> jax.Array:
    """The mode of ``theta | a, d`` by ``iterations`` Gauss-Newton steps from ``theta`` (:func:`_gauss_newton`).

    Not a Markov-chain move: the warm-up's way to the posterior's bulk (:func:`beam_warmup_step`).  The joint
    Metropolis-Hastings move is accepted ~80 % of the time near the mode (measured) but almost never from far
    away (from the nominal beams on a 4-dish problem: log ratio -95), where the reverse proposal has no mass.
    """
    def one(t, _):
        mean, _ = _proposal(block, t, sets, data, inv_noise)
        return mean.reshape(t.shape), None

    theta, _ = jax.lax.scan(one, theta, None, length=iterations)
    return theta


def beam_warmup_step(key: jax.Array, state: BeamState, system: LinearSystem, block: BeamBlock, *, iterations: int = 3,
                     options=None, gram: BeamGram | None = None) -> tuple[BeamState, SolveInfo]:
    """One warm-up sweep: the sky given the beams (exact; from the Grams where ``gram`` is given,
    :func:`beam_sky_step`), then the beams moved to their conditional mode given that sky
    (:func:`beam_conditional_mode`).  Run a few before :func:`beam_step` and discard them (not a valid
    Markov-chain step: it optimises the beams).  With the amplitude (``state.log_u``) it is held where it is."""
    state, info = beam_sky_step(key, state, system, block, options=options, gram=gram)
    sets = set_visibilities(system, block, state.sky)
    if state.log_u is not None:  # the response sets are linear in the response: the amplitude scales them
        sets = sets * jnp.exp(state.log_u)[:, None, None, None].astype(sets.dtype)
    theta = beam_conditional_mode(state.theta, block, sets, system.data, system.inv_noise, iterations=iterations)
    return state._replace(theta=theta), info


class BeamGram(NamedTuple):
    """The beams' exact marginal in the data space, precomputed (:func:`beam_gram`; a PyTree).

    The response of row ``b = (i, j)`` is ``sum_p w_bp(theta) R_b^(p)`` with real weights ``w`` (:func:`gcrsky.
    instrument.beammodes.pair_weights`), so the realified data's covariance given the beams and the amplitude is
    ``u^2 sum_{p,p'} w_p w_p' G^(p,p') + N``, ``G^(p,p') = X^(p) S X^(p')T``, and its mean ``u sum_p w_p X^(p) a0``:
    once the Grams are formed, the marginal costs ``O(Nf (P N_d)^2)`` for the weights and ``N_d^3 / 3`` for one
    Cholesky, whatever ``n`` (H1C's 10 integrations at lmax 200: ``N_d = 560`` against ``n = 40401``).

    Attributes:
        grams: (Nf, Nt, 2, P, Nbl, Nt, 2, P, Nbl) the Grams of the response sets, rows in
            :func:`gcrsky.solvers.dataspace.to_rows`' layout (time, real/imaginary, set, baseline).
        means: (Nf, Nt, 2, P, Nbl) the sets' visibilities of the prior mean ``X^(p) a0``.
        rows: (Nf, Nt, 2, Nbl) the data (the row factor divided out), realified.
        sqrt_w: (Nf, Nt, 2, Nbl) the square-root inverse noise of each real component (0: flagged).
    """

    grams: jax.Array
    means: jax.Array
    rows: jax.Array
    sqrt_w: jax.Array


def beam_gram_bytes(system: LinearSystem, block: BeamBlock) -> float:
    """Bytes of :func:`beam_gram`'s Grams (the largest part): ``8 Nf (2 Nt P Nbl)^2``."""
    nf, npair, nbl = block.stack.shape[:3]
    return 8.0 * nf * (2 * system.data.shape[1] * npair * nbl) ** 2


def beam_gram(system: LinearSystem, block: BeamBlock) -> BeamGram:
    """The data-space Grams of every pair of response sets (:class:`BeamGram`): one data-space matrix
    (:func:`gcrsky.solvers.dataspace.dataspace_matrix`) of the system whose rows are the ``P`` sets' (``P Nbl``
    rows, unit weights), ``O(Nf (2 Nt P Nbl)^2 n)`` once.  The row factor is folded into the data and noise as in
    :func:`beam_system`; the system's prior must be proper."""
    from ..solvers.dataspace import dataspace_matrix, to_rows

    nf, npair, nbl, n = block.stack.shape
    nt = system.data.shape[1]
    op = system.op._replace(response=jnp.reshape(block.stack, (nf, npair * nbl, n)))
    # D = I + k^2 G: a weight k^2 that makes G's largest entries ~1e10 keeps G's digits when the I is taken off
    # (a bound on its diagonal: the response's row norms (in its own basis, before the frame map) times S's largest)
    diag = jnp.max(jnp.sum(jnp.abs(block.stack) ** 2, axis=-1)) * jnp.max(1.0 / system.prior.inv_var)
    k2 = 1e10 / jnp.maximum(diag, jnp.finfo(diag.dtype).tiny)
    stacked = system._replace(op=op, data=jnp.zeros((nf, nt, npair * nbl), system.data.dtype),
                              inv_noise=jnp.full((nf, nt, npair * nbl), k2, system.inv_noise.dtype))
    big = 2 * nt * npair * nbl
    grams = (dataspace_matrix(stacked) - jnp.eye(big)) / k2
    means = to_rows(apply(op, system.prior.mean)).reshape(nf, nt, 2, npair, nbl)
    return refold_gram(BeamGram(grams.reshape((nf, nt, 2, npair, nbl, nt, 2, npair, nbl)), means, None, None),
                       system, block)


def refold_gram(gram: BeamGram, system: LinearSystem, block: BeamBlock) -> BeamGram:
    """``gram`` with the data and noise of ``system`` under ``block``'s row factor (:func:`fold_row_factor`): the Grams
    ``X^(p) S X^(p')T`` do not depend on the row factor, so a new one (e.g. the gains of a chain's step,
    :mod:`gcrsky.inference.beam_gains`) costs ``O(Nf Nt Nbl)``, not a new :func:`beam_gram`."""
    from ..solvers.dataspace import to_rows

    nf, nt, nbl = system.data.shape
    data, w = fold_row_factor(system, block.row_factor)
    pos = w > 0
    sw = jnp.where(pos, jnp.sqrt(jnp.where(pos, w, 1.0)), 0.0)
    return gram._replace(rows=to_rows(data).reshape(nf, nt, 2, nbl),
                         sqrt_w=jnp.broadcast_to(sw[:, :, None, :], (nf, nt, 2, nbl)))


def _gram_whitened(gram: BeamGram, block: BeamBlock, theta, log_u=None):
    """The whitened data-space matrix ``D = I + W^1/2 X S X^T W^1/2`` (Nf, N_d, N_d) of the beams ``theta`` (and the
    amplitude ``exp(log_u)``) from the Grams, the whitened residual ``W^1/2 (d - X a0)`` (Nf, N_d) and ``W^1/2``
    (Nf, N_d), in :func:`gcrsky.solvers.dataspace.to_rows`' layout."""
    from ..instrument.beammodes import pair_weights

    nant = theta.shape[0]
    u = jnp.concatenate([jnp.ones((nant, block.basis_f.shape[0], 1)), beam_coefficients(block, theta)], axis=-1)
    w = jnp.transpose(pair_weights(u[block.pairs[:, 0]], u[block.pairs[:, 1]]), (1, 2, 0))  # (Nf, P, Nbl)
    if log_u is not None:
        w = w * jnp.exp(jnp.asarray(log_u))[:, None, None]
    nf, nt, _, nbl = gram.rows.shape
    nd = 2 * nt * nbl
    cov = jnp.einsum("fpb,ftcpbsdqe,fqe->ftcbsde", w, gram.grams, w).reshape(nf, nd, nd)
    mean = jnp.einsum("fpb,ftcpb->ftcb", w, gram.means)
    sw = gram.sqrt_w.reshape(nf, nd)
    D = jnp.eye(nd) + sw[:, :, None] * cov * sw[:, None, :]
    r = jnp.where(sw > 0, sw * (gram.rows - mean).reshape(nf, nd), 0.0)  # flagged samples may hold anything
    return 0.5 * (D + jnp.swapaxes(D, -1, -2)), r, sw


def beam_gram_log_evidence(gram: BeamGram, block: BeamBlock, theta, log_u=None) -> jax.Array:
    """``log p(d_f | theta [, u])`` (Nf,), the sky integrated out, from the Grams (:class:`BeamGram`): equal to
    :func:`gcrsky.inference.log_evidence_system` of :func:`beam_system` (``tests/test_beam_amplitude.py``)."""
    D, r, sw = _gram_whitened(gram, block, theta, log_u)
    L = jnp.linalg.cholesky(D)
    z = jax.scipy.linalg.solve_triangular(L, r[..., None], lower=True)[..., 0]
    keep = sw > 0
    logdet_w = 2.0 * jnp.sum(jnp.where(keep, jnp.log(jnp.where(keep, sw, 1.0)), 0.0), axis=-1)
    n_keep = jnp.sum(keep, axis=-1)
    return -0.5 * (jnp.sum(z**2, axis=-1) + 2.0 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
                   + n_keep * jnp.log(2 * jnp.pi) - logdet_w)


def beam_gram_sky_draw(key: jax.Array, gram: BeamGram, system: LinearSystem, block: BeamBlock, theta, log_u=None, *,
                       tol: float = DEFAULT_TOL) -> tuple[jax.Array, SolveInfo]:
    """One exact draw of the sky given the beams ``theta`` (and ``exp(log_u)``), in the data space, from the Grams.

    Matheron's rule (Hoffman & Ribak), as :func:`gcrsky.solvers.dataspace.draw_dataspace`:
    ``a = a0 + delta + S Y^T D^-1 (r - Y delta - z)``, ``Y = W^1/2 X`` the whitened response of :func:`beam_system`,
    ``delta ~ N(0, S)``, ``z ~ N(0, I)`` on the rows with data, ``r = W^1/2 (d - X a0)``.  ``D = I + Y S Y^T`` is the
    Grams' weighted sum (:func:`_gram_whitened`, what the marginal already forms), so the draw needs only ``Y`` and
    ``Y^T`` on vectors: ``O(Nf Nt Nbl n)`` and one ``N_d``-sized Cholesky, not the ``O(Nf N_d^2 n)`` of forming ``D``
    anew from the response (:func:`beam_sky_step` with ``options``).

    The draw's accuracy is measured, not assumed: it solves ``P (a - a0) = S^-1 delta + Y^T (r - z)`` exactly, so
    the true residual ``rho`` of that equation gives ``err = sqrt(rho^T P^-1 rho)`` (posterior sigma; ``P^-1``
    through the same factor).

    Args:
        key: PRNG key (``k_a, k_n = split(key)``: ``delta`` from ``k_a``, ``z`` from ``k_n``).
        gram: :func:`beam_gram` of ``system`` under ``block`` (its row factor folded: :func:`refold_gram`).
        system: the sky's system with the raw data, noise and a proper prior.
        block, theta, log_u: the beams (and the amplitude, or None).
        tol: the accuracy (posterior sigma) the draw must reach to count as converged.

    Returns:
        the sky (Nf, n) K and its :class:`~gcrsky.solvers.SolveInfo` ((Nf,) fields; no iterations).
    """
    from ..solvers.dataspace import sqrt_weights, whitened_adjoint, whitened_apply
    from ..solvers.info import direct_info

    sys_b = beam_system(system, block, theta, log_u)
    D, r, sw = _gram_whitened(gram, block, theta, log_u)
    L = jnp.linalg.cholesky(D)
    sw3 = sqrt_weights(sys_b)
    s = 1.0 / sys_b.prior.inv_var
    a0 = sys_b.prior.mean
    ka, kn = jax.random.split(key)
    delta = jnp.sqrt(s) * jax.random.normal(ka, a0.shape, a0.dtype)
    z = jnp.where(sw > 0, jax.random.normal(kn, sw.shape, a0.dtype), 0.0)

    def solve(b):
        return jax.vmap(lambda l, v: jax.scipy.linalg.cho_solve((l, True), v))(L, b)

    def y(v):
        return whitened_apply(sys_b, sw3, v)

    def yt(u):
        return whitened_adjoint(sys_b, sw3, u)

    x = a0 + delta + s * yt(solve(r - y(delta) - z))
    b = delta / s + yt(r - z)
    rho = b - ((x - a0) / s + yt(y(x - a0)))
    p_inv_rho = s * rho - s * yt(solve(y(s * rho)))
    err = jnp.sqrt(jnp.abs(jnp.sum(rho * p_inv_rho, axis=-1)))
    finite = jnp.all(jnp.isfinite(L), axis=(1, 2)) & jnp.all(jnp.isfinite(x), axis=-1)
    return x, direct_info(err, jnp.linalg.norm(rho, axis=-1) / jnp.linalg.norm(b, axis=-1), finite, tol)


def beam_marginal_log_posterior(system: LinearSystem, block: BeamBlock, theta, *, log_u=None,
                                options=None, gram: BeamGram | None = None) -> jax.Array:
    """``log p(d | theta [, u]) + log p(theta) [+ log p(u)]``: the sky marginalised exactly (the sky evidence of the
    beams ``theta``'s response, times the amplitude ``exp(log_u)`` where given, :func:`gcrsky.inference.
    log_evidence_system`, summed over channels; with ``gram`` the same from the data-space Grams,
    :func:`beam_gram_log_evidence`) plus the beam prior (and :func:`amplitude_log_prior`)."""
    from .amplitude import amplitude_log_prior
    from .evidence import log_evidence_system

    options = CholeskyOptions() if options is None else options
    if gram is not None:
        lz = beam_gram_log_evidence(gram, block, theta, log_u)
    else:
        lz = log_evidence_system(beam_system(system, block, theta, log_u), options=options, check=False)[0]
    prior = beam_log_prior(block, theta) + (0.0 if log_u is None else amplitude_log_prior(log_u))
    return jnp.sum(lz) + prior


def _flat(theta, log_u):
    """The collapsed chain's parameter vector: ``theta`` flattened, then ``log_u`` where inferred."""
    return theta.reshape(-1) if log_u is None else jnp.concatenate([theta.reshape(-1), log_u])


def beam_collapsed_step(key: jax.Array, state: BeamState, system: LinearSystem, block: BeamBlock, proposal, *,
                        options=None, with_info: bool = False, gram: BeamGram | None = None):
    """One exact step of the collapsed chain: the beams from their marginal ``p(theta | d)`` (the sky integrated
    out exactly) by an independence Metropolis-Hastings move, then the sky given them (exact GCR).

    The alternating chain (:func:`beam_step`) mixes slowly where the sky and the beams trade off (on a 4-dish SBC
    problem its ranks were over-dispersed, mean z^2 ~2, after 100 sweeps); integrating the sky out removes
    that coupling.  ``proposal = (mean (K,), chol (K, K))``: a Gaussian close to the marginal, e.g. Laplace's at
    its maximum (:func:`beam_log_evidence`'s ``theta`` and ``covariance``, widened a little).  Costs two sky
    evidences (a Cholesky of the dense precision each) and one sky draw.  With the amplitude inferred
    (``state.log_u`` not None) the move is joint in ``(theta, log_u)``: the proposal's ``K`` is then
    ``theta.size + Nf``, ``theta`` flattened first (:func:`beam_log_evidence`'s covariance, in that order).
    With ``gram`` (:func:`beam_gram`) the marginal and the sky draw come from the data-space Grams
    (:func:`beam_gram_sky_draw`); without, both take ``options``' path.

    Returns:
        ``(state, accepted)``; with ``with_info``, ``(state, (accepted, info))``, ``info`` the sky draw's
        :class:`~gcrsky.solvers.SolveInfo`.
    """
    mean, chol = proposal
    kp, ku, ka = jax.random.split(key, 3)
    k = state.theta.size
    old = _flat(state.theta, state.log_u)
    if mean.shape != old.shape:
        raise ValueError(f"the proposal has {mean.shape[0]} parameters, the state {old.shape[0]} (theta"
                         + ("" if state.log_u is None else " and log_u") + ")")
    z = jax.random.normal(kp, mean.shape, mean.dtype)
    new = mean + chol @ z

    def split(x):
        return x[:k].reshape(state.theta.shape), (None if state.log_u is None else x[k:])

    def log_q(x):  # the independence proposal's log density, up to a constant
        y = jax.scipy.linalg.solve_triangular(chol, x - mean, lower=True)
        return -0.5 * jnp.sum(y**2)

    def log_p(x):
        th, lu = split(x)
        return beam_marginal_log_posterior(system, block, th, log_u=lu, options=options, gram=gram)

    log_ratio = log_p(new) + log_q(old) - log_p(old) - log_q(new)
    accept = (jnp.log(jax.random.uniform(ku, (), log_ratio.dtype)) < log_ratio) & jnp.all(jnp.isfinite(new))
    theta, log_u = split(jnp.where(accept, new, old))
    state, info = beam_sky_step(ka, state._replace(theta=theta, log_u=log_u), system, block, options=options,
                                gram=gram)
    return (state, (accept, info)) if with_info else (state, accept)
