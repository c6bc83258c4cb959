"""Collapsed NUTS on the standard case: ESS per second of the power-law hyperparameters.

``theta = {"log_amp": log A, "alpha": alpha}`` of the prior ``C_l = A (l + 1)^-alpha``
(K^2; :func:`gcrsky.model.power_law_cl` / :func:`gcrsky.model.prior_from_cl`), shared
by the channels, on every degree ``l >= 1``; the monopole keeps the system's own
prior variance (the paper's 10% prior around the bright, well-known sky mean: a
power law through the monopole would set its amplitude by one mode), and the prior
mean stays the system's ``a0``.  The chain starts at the maximum-evidence point
(:func:`gcrsky.inference.fit_hyperparameters`, from a log-linear fit of the system's
own prior variances), so the warm-up tunes rather than searches.

:func:`benchmark_collapsed` compiles the warm-up and the sampling programs ahead of
time (``jax.jit(...).lower(...).compile()``, timed apart), runs ``num_warmup``
window-adaptation steps and ``num_samples`` NUTS steps, and reports the ESS
(blackjax's, Stan's estimator) per parameter over the sampling run time.  To be
folded into ``benchmarks/gibbs.py``.

Run: ``.venv/bin/python benchmarks/_collapsed_bench.py [--lmax 20] [--warmup 500] [--samples 1000]``.
"""

from __future__ import annotations

import argparse
import logging
import time

from gcrsky.parallel import use_safe_cpu_threading

use_safe_cpu_threading()  # before JAX's first computation (gcrsky/parallel/runtime.py)
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import gcrsky  # noqa: E402
from gcrsky.inference import fit_hyperparameters, log_evidence_system
from gcrsky.inference.api import as_system  # noqa: E402
from gcrsky.inference.collapsed import _programs, effective_sample_size  # noqa: E402
from gcrsky.model import Prior, power_law_cl, prior_from_cl, with_prior  # noqa: E402
from gcrsky.solvers import CholeskyOptions  # noqa: E402
from gcrsky.sphere.modes import lmax_from_nparams, mode_table  # noqa: E402

log = logging.getLogger(__name__)

NAMES = ("log_amp", "alpha")


def power_law_maker(system):
    """``theta -> system`` with ``C_l = exp(log_amp) (l + 1)^-alpha`` on l >= 1 (monopole and mean kept)."""
    n = system.prior.mean.shape[1]
    lmax = lmax_from_nparams(n)
    mono = jnp.asarray(mode_table(lmax).ell == 0)

    def make(theta):
        cl = power_law_cl(jnp.exp(theta["log_amp"]), theta["alpha"], lmax)
        iv = jnp.broadcast_to(prior_from_cl(cl).inv_var, system.prior.inv_var.shape)
        iv = jnp.where(mono[None, :], system.prior.inv_var, iv)
        return with_prior(system, Prior(system.prior.mean, iv))

    return make


def _initial_guess(system):
    """Log-linear least squares of the system's own per-degree prior variance (l >= 1)."""
    n = system.prior.mean.shape[1]
    tab = mode_table(lmax_from_nparams(n))
    var = 1.0 / np.asarray(system.prior.inv_var).mean(axis=0) * np.where(tab.m == 0, 1.0, 2.0)
    ell = np.arange(1, tab.ell.max() + 1)
    cl = np.array([var[tab.ell == ll].mean() for ll in ell])
    slope, icpt = np.polyfit(np.log(ell + 1.0), np.log(cl), 1)
    return {"log_amp": jnp.asarray(icpt), "alpha": jnp.asarray(-slope)}


def _timed(fn, *args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def benchmark_collapsed(problem=None, *, num_warmup: int = 500, num_samples: int = 1000, seed: int = 0,
                        log_prior=None, dense_mass: bool = True, options=None) -> dict:
    """ESS per second of collapsed NUTS over ``(log A, alpha)`` of a power-law prior.

    Args:
        problem: a :class:`~gcrsky.model.Problem` or system (default ``gcrsky.standard_case()``:
            lmax 20, 2 channels, n = 441).
        num_warmup, num_samples: window-adaptation steps and kept NUTS samples.
        seed: PRNG seed of the chain.
        log_prior: ``theta -> scalar`` log hyperprior (default flat: the evidence is
            sharply peaked, the posterior proper).
        dense_mass: dense (2, 2) mass matrix (amplitude and slope are correlated).
        options: the evidence path (default ``CholeskyOptions()``).

    Returns:
        a dict of numbers: times in seconds (``build_s``, ``fit_s`` (the start, not
        part of the chain), ``compile_warmup_s``, ``compile_sample_s``, ``warmup_s``,
        ``sample_s``), ``grad_eval_s`` (one evidence value-and-gradient, jitted),
        chain diagnostics (``step_size``, ``mean_accept``, ``mean_leapfrog``,
        ``divergences``, ``warmup_divergences``) and per parameter ``p`` in
        ``("log_amp", "alpha")``: ``start_p``, ``mean_p``, ``std_p``, ``ess_p``,
        ``ess_per_s_p`` (ESS over ``sample_s``) and ``ess_per_s_total_p`` (over
        ``warmup_s + sample_s``), plus ``corr`` (their posterior correlation).
    """
    t0 = time.perf_counter()
    problem = gcrsky.standard_case() if problem is None else problem
    system = as_system(problem)
    build_s = time.perf_counter() - t0
    options = CholeskyOptions() if options is None else options
    make = power_law_maker(system)

    t0 = time.perf_counter()
    fit = fit_hyperparameters(make, _initial_guess(system), log_prior=log_prior, options=options)
    fit_s = time.perf_counter() - t0
    if not fit.converged:
        log.warning("the maximum-evidence fit did not converge (%s): starting from it anyway", fit.result)
    theta0 = {k: jnp.asarray(fit.theta[k]) for k in NAMES}

    flat0, unravel, warmup, sample = _programs(
        make, theta0, num_samples=num_samples, num_warmup=num_warmup, log_prior=log_prior, options=options,
        target_accept=0.8, dense_mass=dense_mass, max_num_doublings=10,
    )
    k_warm, k_sample = jax.random.split(jax.random.PRNGKey(seed))

    t0 = time.perf_counter()
    warm_c = warmup.lower(k_warm, flat0).compile()
    compile_warmup_s = time.perf_counter() - t0
    (state, step_size, imm, n_div_warm), warmup_s = _timed(warm_c, k_warm, flat0)

    t0 = time.perf_counter()
    sample_c = sample.lower(k_sample, state, step_size, imm).compile()
    compile_sample_s = time.perf_counter() - t0
    (positions, _, info), sample_s = _timed(sample_c, k_sample, state, step_size, imm)

    vg = jax.jit(jax.value_and_grad(lambda x: jnp.sum(log_evidence_system(make(unravel(x)), options=options)[0])))
    jax.block_until_ready(vg(flat0))
    grad_eval_s = min(_timed(vg, flat0)[1] for _ in range(3))

    theta = jax.vmap(unravel)(positions)
    ess = effective_sample_size({k: theta[k][None] for k in NAMES})
    out = {
        "n": int(system.prior.mean.shape[1]), "nf": int(system.prior.mean.shape[0]),
        "num_warmup": int(num_warmup), "num_samples": int(num_samples),
        "build_s": build_s, "fit_s": fit_s,
        "compile_warmup_s": compile_warmup_s, "compile_sample_s": compile_sample_s,
        "warmup_s": warmup_s, "sample_s": sample_s, "grad_eval_s": grad_eval_s,
        "step_size": float(step_size), "mean_accept": float(jnp.mean(info.acceptance_rate)),
        "mean_leapfrog": float(jnp.mean(info.num_integration_steps)),
        "divergences": int(jnp.sum(info.is_divergent)), "warmup_divergences": int(n_div_warm),
        "corr": float(np.corrcoef(np.asarray(theta["log_amp"]), np.asarray(theta["alpha"]))[0, 1]),
    }
    for k in NAMES:
        x = np.asarray(theta[k])
        e = float(ess[k])
        out.update({f"start_{k}": float(theta0[k]), f"mean_{k}": float(x.mean()), f"std_{k}": float(x.std()),
                    f"ess_{k}": e, f"ess_per_s_{k}": e / sample_s, f"ess_per_s_total_{k}": e / (warmup_s + sample_s)})
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lmax", type=int, default=None, help="override the standard case's lmax (default 20)")
    ap.add_argument("--warmup", type=int, default=500)
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    problem = None if args.lmax is None else gcrsky.standard_case(lmax=args.lmax)
    res = benchmark_collapsed(problem, num_warmup=args.warmup, num_samples=args.samples, seed=args.seed)
    for k, v in res.items():
        print(f"{k:24s} {v:.6g}" if isinstance(v, float) else f"{k:24s} {v}")


if __name__ == "__main__":
    main()
