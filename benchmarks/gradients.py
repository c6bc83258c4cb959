"""What gradients cost: a Wiener solve and the log evidence, forward and ``jax.grad``, per path.

For the paper's standard case (lmax 20, 2 channels, n = 441) and a partial-coverage
case at lmax 50 (10 antennas, 10 LSTs over 8 h, 1 channel, n = 2601), with
hyperparameters ``theta = (log noise-variance scale, log prior-variance scale)``:

* ``wiener``: ``theta -> sum(c * a_wf(theta))`` (a fixed random ``c``);
* ``evidence``: ``theta -> sum_f log p(d | theta)``.

Each function and its gradient are jitted and compiled ahead of time (compile timed
apart), then run ``--repeat`` times (best reported).  Goal (issue 11): a gradient at
most 3x its forward evaluation.  The SLQ rows also print the estimate's standard
error and its difference from the exact (Cholesky) value.

Run: ``.venv/bin/python benchmarks/gradients.py`` (about 3 minutes on 2 cores;
``--quick`` skips lmax 50, ``--lmax100`` adds the evidence at n = 10201, +2 minutes).

Measured in one run (``--lmax100``, 2-core shared CPU, jax 0.10.2, seconds, best of 3;
lmax 100 once):

    case       quantity  path                     fwd run  grad run  grad/fwd  note
    lmax 20    wiener    cholesky                  0.084     0.141     1.67
    lmax 20    wiener    cg dense, nystrom         0.101     0.160     1.59
    lmax 20    wiener    cg matrix-free            0.107     0.105     0.98
    lmax 20    evidence  cholesky (exact)          0.086     0.171     2.00
    lmax 20    evidence  slq, matrix-free          0.486     1.187     2.44  stderr 6.1e-7, minus exact +1.2e-6
    lmax 50    wiener    cholesky                  1.265     2.122     1.68
    lmax 50    wiener    cg dense, nystrom         1.425     2.804     1.97
    lmax 50    wiener    cg matrix-free            0.515     0.658     1.28
    lmax 50    evidence  cholesky (exact)          1.199     2.991     2.50
    lmax 50    evidence  slq, matrix-free          1.391     3.495     2.51  stderr 2.74, minus exact +1.35
    lmax 100   evidence  cholesky (exact)         22.48     74.36      3.31
    lmax 100   evidence  slq, matrix-free          5.80     12.98      2.24  stderr 10.5, minus exact +11.3

Compile times: 0.6-1.2 s (dense), 2.4-3.7 s (CG), 3.7-8.7 s (SLQ, with its gradient).
Every gradient is within the 3x goal at lmax 20 and 50.  The dense gradient needs
``P^-1`` explicitly (``tr(P^-1 dP)``, 2 n^3 after the n^3/3 factor), so its ratio grows
with n (3.3x at n = 10201); SLQ's does not.  SLQ is worth it from n ~ 3000 up (lmax
50: a tie; lmax 100: 3.9x faster forward, 5.7x faster gradient, off by 1.1 stderr)
and wherever the dense P does not fit; below that the exact path is
as fast and has no error.
"""

from __future__ import annotations

import argparse
import os
import time

from gcrsky.parallel import use_safe_cpu_threading

use_safe_cpu_threading()  # before JAX's first computation (gcrsky/parallel/runtime.py)
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import gcrsky  # noqa: E402
from gcrsky.inference import log_evidence_system  # noqa: E402
from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array  # noqa: E402
from gcrsky.model import build_problem, isotropic_prior  # noqa: E402
from gcrsky.solvers import CGOptions, CholeskyOptions, SLQOptions  # noqa: E402


def scaled(system, t):
    return system._replace(
        inv_noise=system.inv_noise * jnp.exp(-t[0]),
        prior=system.prior._replace(inv_var=system.prior.inv_var * jnp.exp(-t[1])),
    )


def partial_problem(lmax=50, nside=64):
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    n = (lmax + 1) ** 2
    cl = 100.0 / (1.0 + np.arange(lmax + 1)) ** 2
    prior = isotropic_prior(cl[None], n)
    truth = np.asarray(prior.inv_var) ** -0.5 * np.random.default_rng(1).standard_normal((1, n))
    truth[0, 0] += 500.0  # a positive sky: radiometer noise from the autos
    lsts = np.linspace(0, 8, 10) * 2 * np.pi / 24
    return build_problem(arr, [100e6], lsts, lmax, nside, a_true=truth, prior=prior, key=jax.random.PRNGKey(2))


def timed(fn, theta, repeat):
    t0 = time.perf_counter()
    comp = jax.jit(fn).lower(theta).compile()
    tc = time.perf_counter() - t0
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = jax.block_until_ready(comp(theta))
        best = min(best, time.perf_counter() - t0)
    return out, tc, best


def bench(name, system, paths, repeat):  
    theta = jnp.array([0.1, -0.1])
    c = jnp.asarray(np.random.default_rng(0).standard_normal(system.prior.mean.shape))
    n = system.prior.mean.shape[1]
    print(f"\n=== {name}: n = {n}, Nf = {system.prior.mean.shape[0]}, Nt = {system.data.shape[1]}, "
          f"Nbl = {system.data.shape[2]}")
    print(f"{'quantity':10s} {'path':26s} {'fwd compile':>11s} {'fwd run':>9s} {'grad compile':>12s} "
          f"{'grad run':>9s} {'grad/fwd':>8s}  note")
    exact = None
    for qty, label, opts in paths:
        if qty == "wiener":
            def f(t, opts=opts):
                return jnp.sum(c * gcrsky.wiener_filter_system(scaled(system, t), options=opts)[0])
        else:
            def f(t, opts=opts):
                return jnp.sum(log_evidence_system(scaled(system, t), options=opts, slq=SLQOptions())[0])
        val, tcf, trf = timed(f, theta, repeat)
        _, tcg, trg = timed(jax.grad(f), theta, repeat)
        note = ""
        if qty == "evidence":
            if isinstance(opts, CholeskyOptions):
                exact = float(val)
            else:
                _, info = jax.jit(lambda t: log_evidence_system(scaled(system, t), options=opts,
                                                                slq=SLQOptions()))(theta)
                se = float(jnp.sqrt(jnp.sum(info.stderr**2)))
                note = f"stderr {se:.3g}" + (f", minus exact {float(val) - exact:+.3g}" if exact is not None else "")
        print(f"{qty:10s} {label:26s} {tcf:11.2f} {trf:9.4f} {tcg:12.2f} {trg:9.4f} {trg / trf:8.2f}  {note}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="the standard case only")
    ap.add_argument("--lmax100", action="store_true", help="also the evidence at lmax 100 (n = 10201; ~4 GB)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    std = gcrsky.standard_case().system()
    paths = [
        ("wiener", "cholesky", CholeskyOptions()),
        ("wiener", "cg dense, nystrom", CGOptions(preconditioner="nystrom")),
        ("wiener", "cg matrix-free, nystrom", CGOptions(preconditioner="nystrom", dense=False)),
        ("evidence", "cholesky (exact)", CholeskyOptions()),
        ("evidence", "slq, matrix-free", CGOptions(preconditioner="nystrom", dense=False)),
    ]
    bench("standard case (lmax 20)", std, paths, args.repeat)
    if not args.quick:
        bench("lmax 50, 10 antennas, 10 LSTs over 8 h", partial_problem().system(), paths, args.repeat)
    if args.lmax100:  # where SLQ pays: the evidence only, once each
        bench("lmax 100, 10 antennas, 10 LSTs over 8 h", partial_problem(100, 128).system(),
              [p for p in paths if p[0] == "evidence"], 1)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; jax {jax.__version__}, {jax.devices()[0].platform}, "
          f"{os.cpu_count()} cpus")


if __name__ == "__main__":
    main()
