"""Hyperparameters by maximum evidence: a BFGS fit (optimistix) with Laplace error bars.

``fit_hyperparameters(make_system, theta0)`` maximises
``sum_f log_evidence(make_system(theta)) + log_prior(theta)`` over any PyTree
``theta`` (e.g. ``{"log_noise": 0.0, "log_amp": 1.0, "alpha": 2.0}``), where
``make_system`` is a pure JAX function building the :class:`~gcrsky.model.LinearSystem`
(so the evidence differentiates through it: priors from
:func:`gcrsky.model.prior_from_cl` / :func:`gcrsky.model.power_law_cl`, noise scales,
a spectral index with :func:`gcrsky.model.spectral_template_system`, a beam width
with :func:`gcrsky.instrument.gaussian_response`).  The covariance is the Laplace
approximation: the inverse Hessian of the negative objective at the optimum,
flattened to ``(k, k)`` in the order of ``jax.flatten_util.ravel_pytree(theta)``.

Why optimistix: it is the maintained JAX optimiser of the equinox family (jaxopt,
which the design notes also name, is no longer developed); its BFGS runs inside
``jit`` and reports its result code and step count.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ..solvers.options import CholeskyOptions, SLQOptions
from ..solvers.registry import SolverOptions
from .evidence import log_evidence_system

__all__ = ["FitResult", "fit_hyperparameters", "objective"]


class FitResult(NamedTuple):
    """What :func:`fit_hyperparameters` found (a PyTree: every field is an array, so the fit jits).

    Attributes:
        theta: the maximiser, shaped like ``theta0``.
        log_evidence: ``sum_f log p(d | theta)`` there (without the log prior).
        objective: ``log_evidence + log_prior(theta)``.
        covariance: (k, k) Laplace covariance of the flattened theta (the order of
            ``jax.flatten_util.ravel_pytree(theta0)``).
        std: the Laplace error bars (square-root diagonal of ``covariance``), shaped like ``theta``.
        converged: (bool array) the optimiser reported success and the Hessian is positive definite.
        num_steps: (int array) optimiser steps taken.
        result: optimistix's result (``optimistix.RESULTS`` item); :attr:`message` says it in words.
    """

    theta: Any
    log_evidence: jax.Array
    objective: jax.Array
    covariance: jax.Array
    std: Any
    converged: jax.Array
    num_steps: jax.Array
    result: Any

    @property
    def message(self) -> str:
        """The outcome in words (host-side): ``"successful"``, optimistix's message, or
        that the Hessian at the optimum is not positive definite."""
        import optimistix as optx

        if bool(self.converged):
            return "successful"
        text = optx.RESULTS[self.result]
        return text or "the optimiser stopped, but the Hessian at the optimum is not positive definite"


def objective(make_system: Callable, theta, *, options: SolverOptions, log_prior: Callable | None = None,
              slq: SLQOptions | None = None, key=None):
    """``(sum_f log p(d | theta) + log_prior(theta), sum_f log p(d | theta))`` (pure, differentiable)."""
    system = make_system(theta)
    lz, _ = log_evidence_system(system, options=options, slq=slq, key=key)
    total = jnp.sum(lz)
    return total + (log_prior(theta) if log_prior is not None else 0.0), total


def fit_hyperparameters(
    make_system: Callable,
    theta0,
    *,
    log_prior: Callable | None = None,
    options: SolverOptions | None = None,
    slq: SLQOptions | None = None,
    key: jax.Array | None = None,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 200,
    covariance: bool = True,
) -> FitResult:
    """Maximise the log evidence (plus an optional log prior) over hyperparameters ``theta``.

    Args:
        make_system: ``theta -> LinearSystem``, a pure JAX function (it is traced).
        theta0: starting point, any PyTree of float scalars / arrays.
        log_prior: optional ``theta -> scalar`` log hyperprior.
        options: the evidence path (:func:`gcrsky.inference.log_evidence_system`);
            default dense Cholesky; ``CGOptions`` means stochastic Lanczos quadrature
            (then fix ``key`` so the objective is deterministic).
        slq, key: SLQ settings and probe key for the matrix-free evidence.
        rtol, atol: BFGS's step-size tolerances (optimistix).
        max_steps: cap on BFGS steps.
        covariance: compute the Laplace covariance (the objective's Hessian: ``k`` Hessian-vector
            products); False: ``covariance`` and ``std`` are NaN and ``converged`` is BFGS's alone
            (for a caller that refines the maximum and its curvature itself).

    Returns:
        :class:`FitResult`.  Pure: the optimiser runs inside JAX, so
        ``jax.jit(lambda t0: fit_hyperparameters(make_system, t0))`` works (``make_system`` and
        ``log_prior`` are closed over; the evidence path must then be fixed, as ``options`` is).
    """
    import optimistix as optx

    options = CholeskyOptions() if options is None else options
    flat0, unravel = ravel_pytree(theta0)
    flat0 = jnp.asarray(flat0, jnp.float64)

    def negative(flat, _):
        obj, _ = objective(make_system, unravel(flat), options=options, log_prior=log_prior, slq=slq, key=key)
        return -obj

    sol = optx.minimise(negative, optx.BFGS(rtol=rtol, atol=atol), flat0, max_steps=max_steps, throw=False)
    flat = sol.value
    obj, lz = objective(make_system, unravel(flat), options=options, log_prior=log_prior, slq=slq, key=key)
    ok = sol.result == optx.RESULTS.successful
    if covariance:
        hess = jax.hessian(lambda x: negative(x, None))(flat)
        hess = 0.5 * (hess + hess.T)
        cov = jnp.linalg.inv(hess)
        ok = ok & jnp.all(jnp.linalg.eigvalsh(hess) > 0)
    else:
        cov = jnp.full((flat.size, flat.size), jnp.nan, flat.dtype)
    return FitResult(
        theta=unravel(flat),
        log_evidence=lz,
        objective=obj,
        covariance=cov,
        std=unravel(jnp.sqrt(jnp.abs(jnp.diagonal(cov)))),
        converged=ok,
        num_steps=sol.stats["num_steps"],
        result=sol.result,
    )
