"""Hierarchical sampling: seconds per Gibbs step, and effective samples per second.

Rows, for the paper's standard case (lmax 20, 2 channels, n = 441) and a partial-coverage
case at lmax 50 (10 antennas, 10 LSTs over 8 h, 1 channel, n = 2601):

* ``gcr_step``: today's GCR step (matrix-free CG, Nystrom preconditioner rebuilt from the
  system at every call), the C_l step not included;
* ``gibbs dense``: :func:`gcrsky.inference.gibbs_step` with ``CholeskyOptions`` (the data
  term ``H`` built once; one Cholesky of ``H + S^-1(C_l)`` per step), power-law C_l move
  included;
* ``gibbs cg``: the same with matrix-free CG warm-started at the last draw and the
  Woodbury-updated preconditioner (rank 128 sketch of ``H`` built once).

Each is a jitted ``lax.scan`` of ``--steps`` steps (compile timed apart; best of 2 runs).
Then the effective sample size (blackjax's ``effective_sample_size``) per second of the
power-law hyperparameters ``(A, alpha)`` from the dense Gibbs chain, and (if
``benchmarks/_collapsed_bench.py`` is present) from collapsed NUTS on the exact evidence.

Run: ``.venv/bin/python benchmarks/gibbs.py`` (about 5 minutes; ``--quick``: the standard
case only, ``--no-nuts``: no collapsed NUTS).

Measured in one run (2-core shared CPU, jax 0.10.2; ms per step, compile apart):

    case                  step                   ms/step  vs gcr_step  note
    standard (n = 441)    gcr_step (today)         4.68      1.0
                          gibbs dense              3.03      1.5       one Cholesky of 2 x 441^2
                          gibbs cg dense           1.49      3.2       2.0 CG iterations
                          gibbs cg matrix-free     3.68      1.3       2.0 CG iterations
    lmax 50 (n = 2601)    gcr_step (today)       195.6       1.0
                          gibbs dense            228.8       0.9       the n^3/3 Cholesky
                          gibbs cg dense         137.2       1.4       86 CG iterations
                          gibbs cg matrix-free   139.7       1.4       84 CG iterations

    standard case, channel 0, power law (log A, alpha)   run s  ESS/s logA  ESS/s alpha  alpha
    gibbs dense, 3200 kept steps                          11.2     19.9        21.1      3.165 +- 0.461
    collapsed NUTS, 1000 samples (sampling only)          68.3     13.6        13.5      3.163 +- 0.450
    collapsed NUTS, with its 500 warm-up steps           124.5      7.4         7.4

The issue's 20x goal for the kernel is not met: on this CPU today's ``gcr_step`` costs
4.7 ms on the standard case (not 30 ms), and an exact step that touches the 441 x 441
data term is bound by memory traffic (one pass over H: ~0.1 ms per channel; a Cholesky
1.1-1.4 ms).  NUTS's gradient of the exact evidence costs ~16 ms per leapfrog step.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from gcrsky.parallel import use_safe_cpu_threading

use_safe_cpu_threading()  # before JAX's first computation (gcrsky/parallel/runtime.py)
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import gcrsky  # noqa: E402
from gcrsky.inference import gibbs_init, gibbs_setup, gibbs_step  # noqa: E402
from gcrsky.solvers import CGOptions, CholeskyOptions  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from gradients import partial_problem  # noqa: E402


def ess(x):
    """ESS of one chain (samples,) by blackjax (needs the [nuts] extra)."""
    from blackjax.diagnostics import effective_sample_size

    return float(np.asarray(effective_sample_size(jnp.asarray(x)[None, :])))


def timed_scan(step, init, steps, key):
    def run(k):
        def body(s, kk):
            s, info = step(kk, s)
            return s, (s, info)

        return jax.lax.scan(body, init, jax.random.split(k, steps))[1]

    t0 = time.perf_counter()
    comp = jax.jit(run).lower(key).compile()
    tc = time.perf_counter() - t0
    best, out = np.inf, None
    for _ in range(2):
        t0 = time.perf_counter()
        out = jax.block_until_ready(comp(key))
        best = min(best, time.perf_counter() - t0)
    return out, tc, best / steps


def bench(name, system, steps, ess_steps):
    nf, n = system.prior.mean.shape
    lmax = int(round(np.sqrt(n))) - 1
    # the starting spectrum: the prior's own variance averaged per l (power law for l >= 1 from here on)
    ell = gcrsky.mode_table(lmax).ell
    var = 1.0 / np.asarray(system.prior.inv_var)
    cl0 = np.stack([np.bincount(ell, var[f]) / np.bincount(ell) for f in range(nf)])
    print(f"\n=== {name}: n = {n}, Nf = {nf}, Nt = {system.data.shape[1]}, Nbl = {system.data.shape[2]}")
    print(f"{'step':22s} {'compile s':>9s} {'ms/step':>9s} {'vs gcr_step':>11s}  note")
    key = jax.random.PRNGKey(0)
    _, tc, t_old = timed_scan(lambda k, s: gcrsky.gcr_step(k, s, system), gcrsky.gcr_init(system.prior.mean),
                              steps, key)
    print(f"{'gcr_step (today)':22s} {tc:9.2f} {1e3 * t_old:9.2f} {1.0:11.1f}")
    rows = {}
    for label, opts in (("gibbs dense", CholeskyOptions()), ("gibbs cg dense", CGOptions(dense=True)), ("gibbs cg matrix-free", CGOptions(dense=False))):
        t0 = time.perf_counter()
        fixed = jax.block_until_ready(gibbs_setup(system, options=opts))
        t_setup = time.perf_counter() - t0
        init = gibbs_init(fixed, cl0, position=system.prior.mean, alpha=2.0)
        step = lambda k, s, fixed=fixed: gibbs_step(k, s, fixed, family="power_law", alpha_range=(0.0, 6.0))  # noqa: E731
        (states, infos), tc, t = timed_scan(step, init, steps, key)
        its = np.asarray(infos.solve.iterations)
        note = f"setup {t_setup:.2f} s" + (f", CG iterations {its.mean():.1f}/step" if "cg" in label else "")
        print(f"{label:22s} {tc:9.2f} {1e3 * t:9.2f} {t_old / t:11.1f}  {note}")
        rows[label] = (step, init, t)
    return cl0


def ess_comparison(name, system, ess_steps, nuts):
    """ESS/s of the power-law (log A, alpha), one channel: dense Gibbs vs collapsed NUTS."""
    from gcrsky.solvers.cg import freq_slice

    one = freq_slice(system, 0)
    n = one.prior.mean.shape[1]
    lmax = int(round(np.sqrt(n))) - 1
    ell = gcrsky.mode_table(lmax).ell
    var = 1.0 / np.asarray(one.prior.inv_var)[0]
    cl0 = (np.bincount(ell, var) / np.bincount(ell))[None]
    fixed = gibbs_setup(one)
    init = gibbs_init(fixed, cl0, position=one.prior.mean, alpha=2.0)
    step = lambda k, s: gibbs_step(k, s, fixed, family="power_law", alpha_range=(-2.0, 8.0))  # noqa: E731
    (states, _), tc, t = timed_scan(step, init, ess_steps, jax.random.PRNGKey(1))
    burn = ess_steps // 5
    logA, alpha = np.log(np.asarray(states.amplitude)[burn:, 0]), np.asarray(states.alpha)[burn:, 0]
    secs = t * (ess_steps - burn)
    print(f"\n--- {name}, channel 0: effective samples per second of the power law's (log A, alpha)")
    print(f"{'sampler':34s} {'run s':>7s} {'ESS logA':>8s} {'ESS/s':>7s} {'ESS alpha':>9s} {'ESS/s':>7s}  posterior")
    print(f"{'gibbs dense, %d steps' % (ess_steps - burn):34s} {secs:7.1f} {ess(logA):8.0f} {ess(logA) / secs:7.1f} "
          f"{ess(alpha):9.0f} {ess(alpha) / secs:7.1f}  alpha {alpha.mean():.3f} +- {alpha.std():.3f}, "
          f"log A {logA.mean():.2f} +- {logA.std():.2f}")
    if not nuts:
        return
    try:
        from _collapsed_bench import benchmark_collapsed
    except ImportError as err:
        print(f"collapsed NUTS skipped: {err}")
        return
    r = benchmark_collapsed(one)
    for label, secs in (("collapsed NUTS, sampling", r["sample_s"]), ("collapsed NUTS, + warm-up", r["warmup_s"] +
                                                                                   r["sample_s"])):
        print(f"{label:34s} {secs:7.1f} {r['ess_log_amp']:8.0f} {r['ess_log_amp'] / secs:7.1f} "
              f"{r['ess_alpha']:9.0f} {r['ess_alpha'] / secs:7.1f}  alpha {r['mean_alpha']:.3f} +- "
              f"{r['std_alpha']:.3f}, log A {r['mean_log_amp']:.2f} +- {r['std_log_amp']:.2f}")
    print(f"  NUTS: step size {r['step_size']:.2f}, {r['mean_leapfrog']:.1f} leapfrog steps/sample, "
          f"acceptance {r['mean_accept']:.2f}, {r['divergences']} divergences; compile "
          f"{r['compile_warmup_s'] + r['compile_sample_s']:.1f} s")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--ess-steps", type=int, default=5000)
    ap.add_argument("--quick", action="store_true", help="the standard case only")
    ap.add_argument("--no-nuts", action="store_true", help="skip collapsed NUTS (about 4 minutes)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    std = gcrsky.standard_case().system()
    bench("standard case (lmax 20)", std, args.steps, args.ess_steps)
    if not args.quick:
        bench("lmax 50, 10 antennas, 10 LSTs over 8 h", partial_problem().system(), args.steps, args.ess_steps)
    ess_comparison("standard case", std, args.ess_steps, not args.no_nuts)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; jax {jax.__version__}, {jax.devices()[0].platform}, "
          f"{os.cpu_count()} cpus")


if __name__ == "__main__":
    main()
