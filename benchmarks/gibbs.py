"""Hierarchical sampling: seconds per Gibbs step, and effective samples per second.

Per-step rows, for the paper's standard case (lmax 20, 2 channels, n = 441) and a
partial-coverage case at lmax 50 (10 antennas, 10 LSTs over 8 h, 1 channel, n = 2601),
every one a sweep of ``a | C_l, d`` and the power-law ``(A, alpha) | a`` move:

* ``gcr_step loop`` (the baseline): a hand-written hierarchical Gibbs loop around
  today's :func:`gcrsky.gcr_step`, the prior rebuilt from the current ``C_l`` every
  step, so its Nystrom preconditioner is rebuilt every step too (what a user wrote
  before this kernel existed);
* ``gcr_step, fixed S`` (context only): the same step with a system that does *not*
  change inside the scan: XLA then hoists the preconditioner out of the loop, which is
  why timing ``gcr_step`` alone flatters it (the previous version of this benchmark did);
* ``gibbs dense``: :func:`gcrsky.inference.gibbs_step` with ``CholeskyOptions`` (data term
  built once; one Cholesky of ``H + S^-1(C_l)`` per step);
* ``gibbs cg dense`` / ``gibbs cg matrix-free``: CG warm-started at the last draw with the
  Woodbury-updated preconditioner (rank-128 sketch of ``H`` built once);
* ``+ joint (prior | posterior)``: a Gibbs sweep followed by one
  :func:`gcrsky.inference.joint_step` (Racine et al. 2016 rescaling, or the
  posterior-whitened one), i.e. the cost of a combined step.

Each is a jitted ``lax.scan`` of ``--steps`` steps (compile timed apart; best of 2 runs).

Then effective samples per second of the power law's ``(log A, alpha)`` on channel 0 of
the standard case, at its own noise and with the noise variance scaled up (low
signal-to-noise, where Gibbs mixes slowly): dense Gibbs, Gibbs + joint moves (proposal
covariance from the Gibbs chain, scaled by ``2.38^2 / 2``), and (with the ``[nuts]`` extra)
collapsed NUTS on the exact evidence (``benchmarks/_collapsed_bench.py``).  ESS by
blackjax (Stan's estimator) over the kept steps; seconds are run time, compile excluded.

Run: ``.venv/bin/python benchmarks/gibbs.py`` (about 10 minutes; ``--quick``: the standard
case only; ``--no-nuts``: no collapsed NUTS).  The table measured in one run is in the
module's ``MEASURED`` string below and in the README.
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
from gcrsky.inference import gibbs_init, gibbs_setup, gibbs_step, joint_step, sample_power_law  # noqa: E402
from gcrsky.solvers import CGOptions, CholeskyOptions  # noqa: E402
from gcrsky.solvers.cg import freq_slice  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from gradients import partial_problem  # noqa: E402

MEASURED = """
One run of ``benchmarks/gibbs.py`` (2-core shared CPU, jax 0.10.2; the machine otherwise idle):

=== standard case (lmax 20): n = 441, Nf = 2, Nt = 10, Nbl = 45
step                           compile s   ms/step speed-up  note
gcr_step loop (baseline)            6.00     42.03      1.0  Nystrom rebuilt per step, CG iterations 2.0/step
gcr_step, fixed S (hoisted)         3.60      3.80     11.1  not a hierarchical step: S never changes, XLA hoists the preconditioner
gibbs dense                         2.41      4.19     10.0  setup 0.67 s
  + joint (prior rescaling)         3.05      9.69      4.3  one Gibbs sweep + one joint move
joint (posterior) alone             1.36      9.10      4.6  joint move + exact sky, two factorisations
gibbs cg dense                      3.32      1.06     39.6  setup 2.01 s, CG iterations 2.0/step
  + joint (prior rescaling)         6.01      3.76     11.2  one Gibbs sweep + one joint move
gibbs cg matrix-free                5.04      3.83     11.0  setup 1.19 s, CG iterations 2.0/step

=== lmax 50, 10 antennas, 10 LSTs over 8 h: n = 2601, Nf = 1, Nt = 10, Nbl = 45
step                           compile s   ms/step speed-up  note
gcr_step loop (baseline)            5.97    284.75      1.0  Nystrom rebuilt per step, CG iterations 80.6/step
gcr_step, fixed S (hoisted)         3.93    203.42      1.4  not a hierarchical step: S never changes, XLA hoists the preconditioner
gibbs dense                         3.52    224.18      1.3  setup 1.60 s
  + joint (prior rescaling)         4.19    552.76      0.5  one Gibbs sweep + one joint move
joint (posterior) alone             2.23    443.51      0.6  joint move + exact sky, two factorisations
gibbs cg dense                      5.38     18.53     15.4  setup 5.52 s, CG iterations 2.0/step
  + joint (prior rescaling)         9.99     43.53      6.5  one Gibbs sweep + one joint move
gibbs cg matrix-free                5.23     15.53     18.3  setup 2.16 s, CG iterations 2.0/step

--- standard case, channel 0: effective samples per second of the power law's (log A, alpha)
exact (quadrature of the evidence): alpha 3.153 +- 0.462, log A 12.81 +- 1.25 (grid edge density 8e-15); chains start at the grid's mode
sampler                              run s ESS logA   ESS/s ESS alpha   ESS/s  posterior
gibbs dense, 4000 steps                9.2      221    24.0       234    25.4  alpha 3.155 +- 0.459 (z +0.1), log A 12.84 +- 1.24
gibbs + joint (prior rescaling)       24.5      290    11.8       296    12.1  alpha 3.095 +- 0.446 (z -2.2), log A 12.65 +- 1.18, acceptance 0.00
gibbs + joint (posterior rescaling)    28.2      784    27.8       816    29.0  alpha 3.142 +- 0.475 (z -0.7), log A 12.78 +- 1.28, acceptance 0.36
joint (posterior rescaling) alone     21.0      412    19.6       416    19.8  alpha 3.153 +- 0.455 (z -0.0), log A 12.82 +- 1.23, acceptance 0.36
collapsed NUTS, sampling              56.8      925    16.3       920    16.2  alpha 3.163 +- 0.450 (z +0.7), log A 12.84 +- 1.20
collapsed NUTS, + warm-up            106.6      925     8.7       920     8.6  alpha 3.163 +- 0.450 (z +0.7), log A 12.84 +- 1.20
  NUTS: step size 0.89, 4.2 leapfrog steps/sample, acceptance 0.92, 0 divergences; compile 5.9 s

--- standard case, noise variance x 10000, channel 0: effective samples per second of the power law's (log A, alpha)
exact (quadrature of the evidence): alpha 2.434 +- 0.730, log A 11.10 +- 1.97 (grid edge density 4e-12); chains start at the grid's mode
sampler                              run s ESS logA   ESS/s ESS alpha   ESS/s  posterior
gibbs dense, 4000 steps                9.6      131    13.7       126    13.2  alpha 2.503 +- 0.638 (z +1.2), log A 11.34 +- 1.70
gibbs + joint (prior rescaling)       24.4      159     6.5       162     6.6  alpha 2.281 +- 0.752 (z -2.6), log A 10.64 +- 2.04, acceptance 0.16
gibbs + joint (posterior rescaling)    26.1      733    28.1       725    27.8  alpha 2.412 +- 0.721 (z -0.8), log A 11.05 +- 1.93, acceptance 0.36
joint (posterior rescaling) alone     21.4      542    25.4       525    24.6  alpha 2.443 +- 0.700 (z +0.3), log A 11.12 +- 1.89, acceptance 0.35
collapsed NUTS, sampling              49.4      927    18.8       933    18.9  alpha 2.463 +- 0.674 (z +1.3), log A 11.16 +- 1.80
collapsed NUTS, + warm-up            107.9      927     8.6       933     8.6  alpha 2.463 +- 0.674 (z +1.3), log A 11.16 +- 1.80
  NUTS: step size 0.93, 3.9 leapfrog steps/sample, acceptance 0.91, 0 divergences; compile 5.8 s

total 897 s; jax 0.10.2, cpu, 2 cpus
EXIT 0
"""

ALPHA_RANGE = (-2.0, 8.0)


def ess(x):
    """ESS of one chain (samples,) by blackjax (needs the [nuts] extra)."""
    from blackjax.diagnostics import effective_sample_size

    return float(np.asarray(effective_sample_size(jnp.asarray(x)[None, :])))


def timed_scan(step, init, steps, key):
    """Compile a ``lax.scan`` of ``step`` ahead of time; run it twice: (outputs, compile s, best s per step)."""

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


def start_spectrum(system):
    """The system's own prior variance averaged per degree: (Nf, lmax+1), K^2."""
    nf, n = system.prior.mean.shape
    ell = gcrsky.mode_table(int(round(np.sqrt(n))) - 1).ell
    var = 1.0 / np.asarray(system.prior.inv_var)
    return np.stack([np.bincount(ell, var[f]) / np.bincount(ell) for f in range(nf)])


def power_law(cl, amp, alpha):
    nl = cl.shape[-1]
    law = amp[:, None] * jnp.arange(1.0, nl + 1)[None, :] ** (-alpha[:, None])
    return jnp.where(jnp.arange(nl) >= 1, law, cl)


def gcr_step_loop(system, cl0):
    """The baseline: a hierarchical Gibbs step written around ``gcr_step`` (prior rebuilt from C_l)."""
    mean = system.prior.mean

    def step(k, s):
        pos, cl, alpha = s
        k1, k2 = jax.random.split(k)
        inv_var = jnp.broadcast_to(gcrsky.prior_from_cl(cl).inv_var, mean.shape)
        st, info = gcrsky.gcr_step(k1, gcrsky.gcr_init(pos), system._replace(prior=system.prior._replace(
            inv_var=inv_var)))
        amp, alpha = sample_power_law(k2, st.position, alpha, alpha_range=ALPHA_RANGE, mean=mean)
        return (st.position, power_law(cl, amp, alpha), alpha), info

    return step, (mean, jnp.asarray(cl0), jnp.full(mean.shape[:1], 2.0))


def bench_steps(name, system, steps, baseline_steps):
    nf, n = system.prior.mean.shape
    cl0 = start_spectrum(system)
    print(f"\n=== {name}: n = {n}, Nf = {nf}, Nt = {system.data.shape[1]}, Nbl = {system.data.shape[2]}")
    print(f"{'step':30s} {'compile s':>9s} {'ms/step':>9s} {'speed-up':>8s}  note")
    key = jax.random.PRNGKey(0)
    step, init = gcr_step_loop(system, cl0)
    (_, infos), tc, t_old = timed_scan(step, init, baseline_steps, key)
    print(f"{'gcr_step loop (baseline)':30s} {tc:9.2f} {1e3 * t_old:9.2f} {1.0:8.1f}  "
          f"Nystrom rebuilt per step, CG iterations {np.asarray(infos.iterations).mean():.1f}/step")
    (_, infos), tc, t = timed_scan(lambda k, s: gcrsky.gcr_step(k, s, system), gcrsky.gcr_init(system.prior.mean),
                                   steps, key)
    print(f"{'gcr_step, fixed S (hoisted)':30s} {tc:9.2f} {1e3 * t:9.2f} {t_old / t:8.1f}  "
          f"not a hierarchical step: S never changes, XLA hoists the preconditioner")
    for label, opts in (("gibbs dense", CholeskyOptions()), ("gibbs cg dense", CGOptions(dense=True)),
                        ("gibbs cg matrix-free", CGOptions(dense=False))):
        t0 = time.perf_counter()
        fixed = jax.block_until_ready(gibbs_setup(system, options=opts))
        t_setup = time.perf_counter() - t0
        init = gibbs_init(fixed, cl0, position=system.prior.mean, alpha=2.0)
        step = lambda k, s, fixed=fixed: gibbs_step(k, s, fixed, family="power_law", alpha_range=ALPHA_RANGE)  # noqa: E731
        (states, infos), tc, t = timed_scan(step, init, steps, key)
        its = np.asarray(infos.solve.iterations)
        note = f"setup {t_setup:.2f} s" + (f", CG iterations {its.mean():.1f}/step" if "cg" in label else "")
        print(f"{label:30s} {tc:9.2f} {1e3 * t:9.2f} {t_old / t:8.1f}  {note}")
        resc = ("prior", "posterior") if isinstance(opts, CholeskyOptions) else ("prior",)
        if not (isinstance(opts, CholeskyOptions) or opts.dense):
            continue
        init = init._replace(amplitude=jnp.full(nf, float(np.median(cl0[:, 1:] * 2.0**2))))
        for r in resc:
            if r == "prior":
                def both(k, s, fixed=fixed):
                    k1, k2 = jax.random.split(k)
                    s, _ = gibbs_step(k1, s, fixed, family="power_law", alpha_range=ALPHA_RANGE)
                    return joint_step(k2, s, fixed, rescale="prior", proposal=jnp.array([0.1, 0.05]),
                                      alpha_range=ALPHA_RANGE)

                label, note = "  + joint (prior rescaling)", "one Gibbs sweep + one joint move"
            else:
                def both(k, s, fixed=fixed):
                    return joint_step(k, s, fixed, rescale="posterior", proposal=jnp.array([0.1, 0.05]),
                                      alpha_range=ALPHA_RANGE, refresh=True)

                label, note = "joint (posterior) alone", "joint move + exact sky, two factorisations"
            _, tc, t = timed_scan(both, init, steps, key)
            print(f"{label:30s} {tc:9.2f} {1e3 * t:9.2f} {t_old / t:8.1f}  {note}")


def exact_posterior(one):
    """The exact posterior of the power law's (log A, alpha) by quadrature of the exact evidence on a grid
    (flat in log A: the 1/A prior; alpha uniform on ALPHA_RANGE; the monopole's variance kept):
    (mean, sd) of each and the grid's mode."""
    from _collapsed_bench import power_law_maker

    from gcrsky.inference import log_evidence_system

    make = power_law_maker(one)
    row = jax.jit(jax.vmap(lambda la, al: log_evidence_system(make({"log_amp": la, "alpha": al}),
                                                              options=CholeskyOptions())[0][0], (None, 0)))
    la = np.linspace(-5.0, 25.0, 121)
    al = np.linspace(*ALPHA_RANGE, 81)
    lz = np.stack([np.asarray(row(x, jnp.asarray(al))) for x in la])
    lz = np.where(np.isfinite(lz), lz, -np.inf)
    p = np.exp(lz - lz.max())
    edge = max(p[0].max(), p[-1].max())
    p /= p.sum()
    out = {}
    for name, g, w in (("log A", la, p.sum(1)), ("alpha", al, p.sum(0))):
        m = float(np.sum(g * w))
        out[name] = (m, float(np.sqrt(np.sum((g - m) ** 2 * w))))
    dl, da = np.meshgrid(la - out["log A"][0], al - out["alpha"][0], indexing="ij")
    out["cov"] = np.array([[np.sum(dl * dl * p), np.sum(dl * da * p)], [np.sum(dl * da * p), np.sum(da * da * p)]])
    i, j = np.unravel_index(np.argmax(p), p.shape)
    return out, (la[i], al[j]), edge


def chain_ess(label, step, init, steps, key, exact):
    (states, infos), tc, t = timed_scan(step, init, steps, key)
    burn = steps // 5
    logA, alpha = np.log(np.asarray(states.amplitude)[burn:, 0]), np.asarray(states.alpha)[burn:, 0]
    secs = t * (steps - burn)
    acc = getattr(infos, "accepted", None)
    e_a, e_l = ess(alpha), ess(logA)
    z = "" if exact is None else f" (z {(alpha.mean() - exact['alpha'][0]) / (alpha.std() / np.sqrt(e_a)):+.1f})"
    note = "" if acc is None else f", acceptance {float(np.mean(np.asarray(acc)[burn:])):.2f}"
    print(f"{label:34s} {secs:7.1f} {e_l:8.0f} {e_l / secs:7.1f} {e_a:9.0f} {e_a / secs:7.1f}  "
          f"alpha {alpha.mean():.3f} +- {alpha.std():.3f}{z}, log A {logA.mean():.2f} +- "
          f"{logA.std():.2f}{note}")
    return logA, alpha


def ess_comparison(name, system, steps, nuts, nuts_steps=(500, 1000), start=None):
    """ESS/s of the power law's (log A, alpha), one channel: Gibbs, joint moves, collapsed NUTS, against
    the exact posterior by quadrature (z: the chain mean's offset from it in its own Monte-Carlo errors)."""
    one = freq_slice(system, 0)
    cl0 = start_spectrum(one)
    fixed = gibbs_setup(one)
    print(f"\n--- {name}, channel 0: effective samples per second of the power law's (log A, alpha)")
    if start is None:  # small n: the exact posterior by quadrature, the chains start at its mode
        exact, (la0, al0), edge = exact_posterior(one)
        print(f"exact (quadrature of the evidence): alpha {exact['alpha'][0]:.3f} +- {exact['alpha'][1]:.3f}, "
              f"log A {exact['log A'][0]:.2f} +- {exact['log A'][1]:.2f} (grid edge density {edge:.0e}); "
              f"chains start at the grid's mode")
    else:  # too big for a grid (a dense evidence takes ~1 s): start at the simulated truth, z against NUTS
        exact, (la0, al0) = None, start
        print(f"chains start at the simulated spectrum (log A, alpha) = ({la0:.2f}, {al0:.2f}); z: offset from "
              f"the exact value is not available at this size")
    print(f"{'sampler':34s} {'run s':>7s} {'ESS logA':>8s} {'ESS/s':>7s} {'ESS alpha':>9s} {'ESS/s':>7s}  posterior")
    init = gibbs_init(fixed, cl0, position=one.prior.mean, alpha=al0, amplitude=float(np.exp(la0)))
    init = init._replace(cl=power_law(init.cl, init.amplitude, init.alpha))
    gibbs = lambda k, s: gibbs_step(k, s, fixed, family="power_law", alpha_range=ALPHA_RANGE)  # noqa: E731
    logA, alpha = chain_ess(f"gibbs dense, {steps - steps // 5} steps", gibbs, init, steps, jax.random.PRNGKey(1),
                            exact)
    # random-walk proposal: the posterior covariance (exact, or the Gibbs chain's), scaled by 2.38^2 / 2
    cov = jnp.asarray(np.cov(np.stack([logA, alpha])) if exact is None else exact["cov"]) * 2.38**2 / 2

    def gibbs_joint(k, s):
        k1, k2 = jax.random.split(k)
        s, _ = gibbs(k1, s)
        return joint_step(k2, s, fixed, rescale="prior", proposal=cov, alpha_range=ALPHA_RANGE)

    chain_ess("gibbs + joint (prior rescaling)", gibbs_joint, init, steps, jax.random.PRNGKey(2), exact)

    def gibbs_joint_post(k, s):
        k1, k2 = jax.random.split(k)
        s, _ = gibbs(k1, s)
        return joint_step(k2, s, fixed, rescale="posterior", proposal=cov, alpha_range=ALPHA_RANGE)

    chain_ess("gibbs + joint (posterior rescaling)", gibbs_joint_post, init, steps, jax.random.PRNGKey(4), exact)
    marginal = lambda k, s: joint_step(k, s, fixed, rescale="posterior", proposal=cov,  # noqa: E731
                                       alpha_range=ALPHA_RANGE, refresh=True)
    chain_ess("joint (posterior rescaling) alone", marginal, init, steps, jax.random.PRNGKey(3), exact)
    if not nuts:
        return
    try:
        from _collapsed_bench import benchmark_collapsed
    except ImportError as err:
        print(f"collapsed NUTS skipped: {err}")
        return
    r = benchmark_collapsed(one, num_warmup=nuts_steps[0], num_samples=nuts_steps[1])
    z = "" if exact is None else f" (z {(r['mean_alpha'] - exact['alpha'][0]) / r['std_alpha'] * r['ess_alpha']**0.5:+.1f})"
    for label, secs in (("collapsed NUTS, sampling", r["sample_s"]),
                        ("collapsed NUTS, + warm-up", r["warmup_s"] + r["sample_s"])):
        print(f"{label:34s} {secs:7.1f} {r['ess_log_amp']:8.0f} {r['ess_log_amp'] / secs:7.1f} "
              f"{r['ess_alpha']:9.0f} {r['ess_alpha'] / secs:7.1f}  alpha {r['mean_alpha']:.3f} +- "
              f"{r['std_alpha']:.3f}{z}, log A {r['mean_log_amp']:.2f} +- {r['std_log_amp']:.2f}")
    print(f"  NUTS: step size {r['step_size']:.2f}, {r['mean_leapfrog']:.1f} leapfrog steps/sample, "
          f"acceptance {r['mean_accept']:.2f}, {r['divergences']} divergences; compile "
          f"{r['compile_warmup_s'] + r['compile_sample_s']:.1f} s")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--baseline-steps", type=int, default=20, help="steps of the (slow) gcr_step loop")
    ap.add_argument("--ess-steps", type=int, default=5000)
    ap.add_argument("--low-snr", type=float, default=1e4, help="noise-variance scale of the low-S/N ESS case")
    ap.add_argument("--quick", action="store_true", help="the standard case only")
    ap.add_argument("--ess-lmax50", action="store_true",
                    help="also the ESS comparison at lmax 50 (about an hour: 1000 steps, NUTS 60 + 120)")
    ap.add_argument("--no-nuts", action="store_true", help="skip collapsed NUTS (about 4 minutes per case)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    std = gcrsky.standard_case().system()
    bench_steps("standard case (lmax 20)", std, args.steps, args.baseline_steps)
    if not args.quick:
        bench_steps("lmax 50, 10 antennas, 10 LSTs over 8 h", partial_problem().system(), max(args.steps // 10, 5),
                    max(args.baseline_steps // 4, 3))
    ess_comparison("standard case", std, args.ess_steps, not args.no_nuts)
    low = gcrsky.standard_case(noise_scale=args.low_snr).system()  # data simulated with that noise
    ess_comparison(f"standard case, noise variance x {args.low_snr:g}", low, args.ess_steps, not args.no_nuts)
    if args.ess_lmax50:
        ess_comparison("lmax 50, 10 antennas, 10 LSTs over 8 h", partial_problem().system(), 1000, not args.no_nuts,
                       nuts_steps=(60, 120), start=(float(np.log(100.0)), 2.0))
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; jax {jax.__version__}, {jax.devices()[0].platform}, "
          f"{os.cpu_count()} cpus")


if __name__ == "__main__":
    main()
