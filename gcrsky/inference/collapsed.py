"""Collapsed sampling: hyperparameters by NUTS on the exact evidence, then the sky given each.

The joint posterior of the sky coefficients ``a`` and hyperparameters ``theta``
(prior amplitude and slope, noise scale, spectral index, ...) factorises as

    p(a, theta | d) = p(a | theta, d) p(theta | d),
    p(theta | d)   ∝ p(theta) prod_f p(d_f | theta),

and both factors are available exactly: ``p(d | theta)`` is the linear-Gaussian
evidence (:func:`gcrsky.inference.log_evidence_system`, exact and differentiable on
the dense and m-mode paths), and ``a | theta, d`` is the Gaussian ``N(a_wf, P^-1)``
drawn exactly by :func:`gcrsky.inference.sample_system`.  So instead of a Gibbs chain
alternating ``a | theta`` and ``theta | a`` (which mixes slowly where the two are
strongly coupled, e.g. a prior amplitude against the modes the data barely see), the
sky is *collapsed* (integrated out analytically):

1. :func:`sample_hyperparameters` runs NUTS (blackjax) on the low-dimensional density
   ``log p(theta | d) = sum_f log p(d_f | theta) + log_prior(theta) + const``, with
   Stan-style window adaptation of the step size and mass matrix for ``num_warmup``
   steps, then ``num_samples`` NUTS steps in one jitted ``lax.scan``;
2. :func:`draw_given_hyperparameters` draws ``a | theta_i, d`` exactly for every
   sample ``theta_i``.

The pairs ``(a_i, theta_i)`` are then joint posterior samples whose only Monte Carlo
correlation is the NUTS chain's in ``theta`` (the draws of ``a`` are independent
given ``theta``); :func:`effective_sample_size` measures it.

The chain's pieces are pure functions too, for use inside ``jit`` / ``vmap`` (e.g. many
simulated data sets at once, ``tests/test_collapsed_sbc.py``): :func:`flat_log_density`
(the density above on the flattened ``theta``), :func:`nuts_warmup`, :func:`nuts_sample`
and :func:`nuts_chain` (both phases, the chain :func:`sample_hyperparameters` runs).

Conventions follow :mod:`gcrsky.inference.hyper`: ``theta`` is any PyTree of float
arrays, ``make_system: theta -> LinearSystem`` is a pure JAX function (it is traced
and differentiated), ``log_prior: theta -> scalar`` is the log hyperprior (default
flat: then the posterior must be proper by the evidence alone).  NUTS runs on the
flattened ``theta`` (``jax.flatten_util.ravel_pytree`` order); the samples are
returned in ``theta0``'s structure with a leading ``(num_samples,)`` axis.

The log density is :func:`gcrsky.inference.hyper.objective`'s, written out here rather
than imported: importing ``hyper`` would put this module one floor above every other
core module, level with the command line (``tests/test_architecture.py`` keeps the
applications above the core).

blackjax is an optional dependency (the ``nuts`` extra: ``pip install 'gcrsky[nuts]'``),
imported only when a function here is called.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ..base.extras import require
from ..solvers.options import CholeskyOptions
from ..solvers.registry import SolverOptions
from .evidence import log_evidence_system
from .posterior import sample_system

__all__ = [
    "CollapsedInfo",
    "CollapsedSamples",
    "draw_given_hyperparameters",
    "effective_sample_size",
    "flat_log_density",
    "nuts_chain",
    "nuts_sample",
    "nuts_warmup",
    "sample_hyperparameters",
]

log = logging.getLogger(__name__)


def blackjax_module():
    """blackjax, imported, or an ImportError naming the ``nuts`` extra that installs it."""
    return require("blackjax", "nuts", "collapsed hyperparameter sampling (NUTS)")


class CollapsedInfo(NamedTuple):
    """NUTS diagnostics of :func:`sample_hyperparameters`.

    Attributes:
        acceptance_rate: (num_samples,) mean Metropolis acceptance probability over
            each step's trajectory (its average should be near ``target_accept``).
        is_divergent: (num_samples,) bool, the step's trajectory diverged (energy
            error above blackjax's threshold, 1000): any divergence is a warning
            sign that the sampler missed part of the posterior.
        num_integration_steps: (num_samples,) leapfrog steps (gradient evaluations
            of the log evidence) of each step.
        step_size: the adapted step size (scalar).
        inverse_mass_matrix: the adapted inverse mass matrix, (k,) diagonal or
            (k, k) dense, in the flattened ``theta``'s units squared.
        warmup_divergences: number of divergent steps during the warm-up (the
            adaptation's early, badly-tuned steps may diverge harmlessly).
    """

    acceptance_rate: jax.Array
    is_divergent: jax.Array
    num_integration_steps: jax.Array
    step_size: jax.Array
    inverse_mass_matrix: jax.Array
    warmup_divergences: jax.Array


class CollapsedSamples(NamedTuple):
    """What :func:`sample_hyperparameters` returns.

    Attributes:
        theta: ``theta0``'s PyTree, each leaf with a leading ``(num_samples,)`` axis.
        log_density: (num_samples,) the unnormalised log posterior
            ``sum_f log p(d_f | theta) + log_prior(theta)`` at each sample (nats).
        info: :class:`CollapsedInfo`.
    """

    theta: Any
    log_density: jax.Array
    info: CollapsedInfo


def flat_log_density(
    make_system: Callable,
    theta0,
    *,
    log_prior: Callable | None = None,
    options: SolverOptions | None = None,
):
    """The collapsed log posterior of the flattened ``theta``: ``(flat0, unravel, logdensity)``.

    ``logdensity(flat) = sum_f log p(d_f | theta) + log_prior(theta)`` with
    ``theta = unravel(flat)`` (:func:`gcrsky.inference.hyper.objective`'s value, written
    out: module docstring), the density :func:`sample_hyperparameters` runs NUTS on.  It
    is a pure JAX function: ``make_system`` may close over traced values (e.g. one
    replicate's data inside a ``vmap``), so a caller can build one per data set inside a
    traced function and pass it to :func:`nuts_chain`.

    Args:
        make_system, theta0, log_prior, options: as for :func:`sample_hyperparameters`
            (``theta0`` only fixes the structure and the start; default path
            ``CholeskyOptions()``).

    Returns:
        ``flat0`` (k,) float64, the start; ``unravel: (k,) -> theta``; ``logdensity: (k,) -> scalar``.
    """
    options = CholeskyOptions() if options is None else options
    flat0, unravel = ravel_pytree(theta0)
    flat0 = jnp.asarray(flat0, jnp.float64)
    if flat0.ndim != 1 or flat0.size == 0:
        raise ValueError("theta0 must hold at least one float")

    def logdensity(flat):  # = gcrsky.inference.hyper.objective(...)[0], not imported (module docstring)
        theta = unravel(flat)
        lz, _ = log_evidence_system(make_system(theta), options=options)
        return jnp.sum(lz) + (log_prior(theta) if log_prior is not None else 0.0)

    return flat0, unravel, logdensity


def nuts_warmup(
    key: jax.Array,
    logdensity: Callable,
    flat0: jax.Array,
    *,
    num_warmup: int,
    target_accept: float = 0.8,
    dense_mass: bool = True,
    max_num_doublings: int = 10,
):
    """Window adaptation (blackjax) of NUTS on ``logdensity`` from ``flat0``: pure, jittable, vmappable.

    Returns:
        ``(state, step_size, inverse_mass_matrix, n_divergent)``: the last warm-up
        ``HMCState``, the adapted parameters and the number of divergent warm-up steps.
    """
    bj = blackjax_module()
    from blackjax.adaptation.base import get_filter_adapt_info_fn

    adapt = bj.window_adaptation(
        bj.nuts, logdensity, is_mass_matrix_diagonal=not dense_mass, target_acceptance_rate=target_accept,
        adaptation_info_fn=get_filter_adapt_info_fn(info_keys={"is_divergent"}),
        max_num_doublings=max_num_doublings,
    )
    (state, params), info = adapt.run(key, flat0, num_steps=int(num_warmup))
    return state, params["step_size"], params["inverse_mass_matrix"], jnp.sum(info.info.is_divergent)


def nuts_sample(
    key: jax.Array,
    logdensity: Callable,
    state,
    step_size,
    inverse_mass_matrix,
    *,
    num_samples: int,
    max_num_doublings: int = 10,
):
    """``num_samples`` NUTS steps from ``state`` in a ``lax.scan``: pure, jittable, vmappable.

    Step ``i`` uses ``jax.random.split(key, num_samples)[i]``.

    Returns:
        ``(positions (num_samples, k), log_density (num_samples,), NUTSInfo)``.
    """
    kernel = blackjax_module().nuts(logdensity, step_size, inverse_mass_matrix, max_num_doublings=max_num_doublings)

    def step(s, k):
        s, info = kernel.step(k, s)
        return s, (s.position, s.logdensity, info)

    _, out = jax.lax.scan(step, state, jax.random.split(key, int(num_samples)))
    return out


def nuts_chain(
    key: jax.Array,
    logdensity: Callable,
    flat0: jax.Array,
    *,
    num_warmup: int,
    num_samples: int,
    target_accept: float = 0.8,
    dense_mass: bool = True,
    max_num_doublings: int = 10,
):
    """One NUTS chain on ``logdensity``: warm-up then samples; pure, jittable, vmappable.

    The chain of :func:`sample_hyperparameters` without its host-side checks and logging:
    ``key`` is split into the warm-up's and the sampling's keys as there (:func:`nuts_warmup`,
    then :func:`nuts_sample`), so with ``flat0, unravel, logd = flat_log_density(make_system,
    theta0, log_prior=..., options=...)``, ``nuts_chain(key, logd, flat0, ...)`` runs the chain
    of ``sample_hyperparameters(key, make_system, theta0, ...)`` (positions flattened; measured
    equal bit for bit on the small test problem, though the two are compiled differently).
    Being pure, it can be vmapped over keys, starts or data sets (a ``logdensity`` built
    inside the mapped function), e.g. the replicates of a simulation-based calibration
    (``tests/test_collapsed_sbc.py``).  Under ``vmap`` every NUTS step costs the largest
    trajectory of the batch (blackjax's tree building is a ``while_loop``): a smaller
    ``max_num_doublings`` bounds it.

    Args:
        key: PRNG key.
        logdensity: ``(k,) -> scalar`` (e.g. :func:`flat_log_density`'s).
        flat0: (k,) start.
        num_warmup, num_samples, target_accept, dense_mass, max_num_doublings: as for
            :func:`sample_hyperparameters`.

    Returns:
        ``(positions (num_samples, k), log_density (num_samples,), CollapsedInfo)``.
    """
    k_warm, k_sample = jax.random.split(key)
    state, step_size, imm, n_div_warm = nuts_warmup(
        k_warm, logdensity, flat0, num_warmup=num_warmup, target_accept=target_accept, dense_mass=dense_mass,
        max_num_doublings=max_num_doublings,
    )
    positions, logd, info = nuts_sample(
        k_sample, logdensity, state, step_size, imm, num_samples=num_samples, max_num_doublings=max_num_doublings,
    )
    return positions, logd, _collapsed_info(info, step_size, imm, n_div_warm)


def _collapsed_info(info, step_size, imm, n_div_warm) -> CollapsedInfo:
    return CollapsedInfo(
        acceptance_rate=info.acceptance_rate,
        is_divergent=info.is_divergent,
        num_integration_steps=info.num_integration_steps,
        step_size=step_size,
        inverse_mass_matrix=imm,
        warmup_divergences=n_div_warm,
    )


def _programs(
    make_system: Callable,
    theta0,
    *,
    num_samples: int,
    num_warmup: int,
    log_prior: Callable | None,
    options: SolverOptions | None,
    target_accept: float,
    dense_mass: bool,
    max_num_doublings: int,
):
    """The flattened start, its unravel, and the two jitted programs (warm-up, sampling).

    ``warmup(key, flat0) -> (HMCState, step_size, inverse_mass_matrix, n_divergent)`` and
    ``sample(key, state, step_size, inverse_mass_matrix) -> (positions, log_density, NUTSInfo)``
    (:func:`nuts_warmup` and :func:`nuts_sample`, jitted) are separate so that a benchmark
    can compile them ahead of time.
    """
    blackjax_module()  # fail early, naming the extra
    flat0, unravel, logdensity = flat_log_density(make_system, theta0, log_prior=log_prior, options=options)

    @jax.jit
    def warmup(key, flat):
        return nuts_warmup(key, logdensity, flat, num_warmup=num_warmup, target_accept=target_accept,
                           dense_mass=dense_mass, max_num_doublings=max_num_doublings)

    @jax.jit
    def sample(key, state, step_size, inverse_mass_matrix):
        return nuts_sample(key, logdensity, state, step_size, inverse_mass_matrix, num_samples=num_samples,
                           max_num_doublings=max_num_doublings)

    return flat0, unravel, warmup, sample


def sample_hyperparameters(
    key: jax.Array,
    make_system: Callable,
    theta0,
    num_samples: int,
    *,
    log_prior: Callable | None = None,
    num_warmup: int = 500,
    options: SolverOptions | None = None,
    target_accept: float = 0.8,
    dense_mass: bool = True,
    max_num_doublings: int = 10,
) -> CollapsedSamples:
    """NUTS samples of ``p(theta | d) ∝ p(theta) prod_f p(d_f | theta)`` (the sky integrated out).

    Warm-up: ``blackjax.window_adaptation(blackjax.nuts, ...)`` for ``num_warmup``
    steps from ``theta0`` (step size by dual averaging to ``target_accept``, mass
    matrix from the warm-up's windows); then ``num_samples`` NUTS steps in a jitted
    ``lax.scan``.  One chain; run several keys / starts for convergence checks
    (R-hat, :func:`effective_sample_size` over chains).  The two phases are jitted
    programs; this function itself is not meant to be traced (it logs the chain's
    divergences and acceptance from concrete values).

    Cost: each NUTS step evaluates the log evidence and its gradient
    ``num_integration_steps`` times (1 to ``2**max_num_doublings``; a few for a
    well-adapted, near-Gaussian posterior), each one dense factorisation of P per
    channel on the default path.

    Args:
        key: PRNG key (split into the warm-up's and the sampling's).
        make_system: ``theta -> LinearSystem``, a pure JAX function (traced, differentiated).
        theta0: the chain's start, any PyTree of float arrays (a good start, e.g. the
            :func:`gcrsky.inference.fit_hyperparameters` optimum, shortens the warm-up).
        num_samples: NUTS samples kept after the warm-up.
        log_prior: optional ``theta -> scalar`` log hyperprior (nats; default flat,
            then the evidence alone must make the posterior proper).
        num_warmup: adaptation steps (discarded).
        options: the evidence path (default ``CholeskyOptions()``, exact dense);
            ``MModeOptions`` where the system is m-block-diagonal.  A stochastic
            (SLQ, ``CGOptions``) evidence would make the target density noisy: NUTS
            then samples a perturbed posterior, so stay on the exact paths.
        target_accept: the step-size adaptation's target mean acceptance probability.
        dense_mass: adapt a dense (k, k) mass matrix (default: cheap for the few
            hyperparameters this is for, and robust to correlated ones such as a
            power law's amplitude and slope); ``False`` for a diagonal one.
        max_num_doublings: NUTS's maximum tree depth (at most ``2**max`` leapfrog
            steps per sample).

    Returns:
        :class:`CollapsedSamples` (``theta`` shaped like ``theta0`` with a leading
        ``(num_samples,)`` axis).
    """
    num_samples, num_warmup = int(num_samples), int(num_warmup)
    if num_samples < 1 or num_warmup < 0:
        raise ValueError("need num_samples >= 1 and num_warmup >= 0")
    flat0, unravel, warmup, sample = _programs(
        make_system, theta0, num_samples=num_samples, num_warmup=num_warmup, log_prior=log_prior, options=options,
        target_accept=target_accept, dense_mass=dense_mass, max_num_doublings=max_num_doublings,
    )
    k_warm, k_sample = jax.random.split(key)
    state, step_size, imm, n_div_warm = warmup(k_warm, flat0)
    positions, logd, info = sample(k_sample, state, step_size, imm)
    n_div = int(jnp.sum(info.is_divergent))
    if n_div:
        log.warning("NUTS: %d of %d samples diverged (step size %.3g): the posterior may be under-explored",
                    n_div, num_samples, float(step_size))
    log.info("NUTS: %d samples, step size %.3g, mean acceptance %.3f, mean %.1f leapfrog steps per sample",
             num_samples, float(step_size), float(jnp.mean(info.acceptance_rate)),
             float(jnp.mean(info.num_integration_steps)))
    return CollapsedSamples(
        theta=jax.vmap(unravel)(positions),
        log_density=logd,
        info=_collapsed_info(info, step_size, imm, n_div_warm),
    )


def draw_given_hyperparameters(
    key: jax.Array,
    make_system: Callable,
    theta_samples,
    *,
    ndraws: int = 1,
    options: SolverOptions | None = None,
    batch_size: int | None = None,
):
    """Exact draws of ``a | theta_i, d`` for every hyperparameter sample ``theta_i``.

    Sample ``i`` uses ``sample_system(jax.random.split(key, num_samples)[i],
    make_system(theta_i), ndraws, options=options)`` (so, e.g., on the Cholesky path its
    draw ``j`` uses ``jax.random.split(keys[i], ndraws)[j]``).  The samples are
    mapped with ``jax.lax.map`` (one system in memory at a time, or ``batch_size`` of
    them vectorised); the function is jittable.

    Args:
        key: PRNG key.
        make_system: ``theta -> LinearSystem``, as for :func:`sample_hyperparameters`.
        theta_samples: ``theta``'s PyTree with a leading ``(num_samples,)`` axis on every
            leaf (e.g. :attr:`CollapsedSamples.theta`).
        ndraws: draws of ``a`` per hyperparameter sample.
        options: the exact sampling path (default ``CholeskyOptions()``; any path of
            :func:`gcrsky.inference.sample_system`).
        batch_size: optional ``jax.lax.map`` batch size (vectorises that many samples).

    Returns:
        (num_samples, Nf, ndraws, n) draws of the realified coefficients, Kelvin.
    """
    options = CholeskyOptions() if options is None else options
    leaves = jax.tree_util.tree_leaves(theta_samples)
    if not leaves:
        raise ValueError("theta_samples has no leaves")
    num = int(jnp.shape(leaves[0])[0])
    keys = jax.random.split(key, num)

    def one(args):
        k, theta = args
        draws, _ = sample_system(k, make_system(theta), int(ndraws), options=options)
        return draws

    return jax.lax.map(one, (keys, theta_samples), batch_size=batch_size)


def effective_sample_size(chains):
    """Effective sample size of MCMC samples: ``blackjax.diagnostics.effective_sample_size``.

    Stan's estimator (Geyer's initial monotone sequence over the chains' pooled
    autocorrelation), not re-implemented here.

    Args:
        chains: an array, or a PyTree of arrays, each shaped ``(chains, samples, ...)``:
            axis 0 the independent chains, axis 1 the samples of each chain, any
            trailing axes independent variables.  For the single chain of
            :func:`sample_hyperparameters` add the chain axis:
            ``effective_sample_size(jax.tree.map(lambda x: x[None], out.theta))``.

    Returns:
        the same structure with the chain and sample axes removed: the ESS (in
        samples, summed over chains) of every variable.
    """
    ess = blackjax_module().diagnostics.effective_sample_size
    return jax.tree_util.tree_map(lambda x: ess(jnp.asarray(x), chain_axis=0, sample_axis=1), chains)
