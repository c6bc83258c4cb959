"""Simulation-based calibration table: both samplers with flags, and two negative controls.

Usage::

    python benchmarks/calibration.py [--replicates 4000] [--draws 31]

The problem and the five runs are those of ``tests/test_calibration.py`` (same
seeds: ``--replicates 1000 --draws 15`` reproduces the test's numbers):
lmax 4, nside 16, one channel, 6 LSTs, heterogeneous noise, isotropic prior,
20% random flags plus one whole time and one whole baseline, NaN in flagged data.

Runs: ``cg`` (dense P, rank-8 Nystrom preconditioner) and ``cholesky``, which must
pass; ``bug 1/sqrt2`` (the reference code's fluctuation term), ``post 2sig2``
(posterior assumes twice the noise variance) and ``data 2sig2`` (data have twice
the variance the posterior assumes), which must fail.  For each functional the
table gives mean z^2 (1 when calibrated; > 1 draws too narrow, < 1 too wide) and
the functional's exact p-value (Bonferroni over its KS, dispersion and bias
tests); the last rows give the family p-value (Bonferroni over functionals:
reject at alpha when p <= alpha, false-alarm rate <= alpha) and the smallest
asymptotic rank-histogram chi-square p-value.  See :mod:`gcrsky.checks.sbc`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

try:
    import gcrsky  # noqa: F401
except ImportError:  # running from a checkout without an install
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gcrsky.parallel import use_safe_cpu_threading  # noqa: E402

use_safe_cpu_threading()  # before JAX's first computation (gcrsky/runtime.py)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)


from gcrsky.checks.sbc import (  # noqa: E402
    GCRSampler,
    default_functionals,
    flagged_example_problem,
    reference_bug_sampler,
    run_sbc,
)
from gcrsky.solvers import CGOptions  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--replicates", type=int, default=4000)
    ap.add_argument("--draws", type=int, default=31)
    args = ap.parse_args(argv)

    prob, flags = flagged_example_problem()
    system = prob.system()
    G, names, _ = default_functionals(system, coefficients=(0, 5, 17))
    doubled = system._replace(inv_noise=system.inv_noise / 2.0)
    chol = GCRSampler("cholesky")
    runs = [
        ("cg", 100, system, GCRSampler("cg", CGOptions(dense=True, preconditioner="nystrom", sketch_size=8)), None, None),
        ("cholesky", 101, system, chol, None, 50),
        ("bug 1/sqrt2", 102, system, reference_bug_sampler, None, 50),
        ("post 2sig2", 103, system, chol, doubled, 50),
        ("data 2sig2", 104, doubled, chol, system, 50),
    ]
    print(
        f"SBC: M = {args.replicates} replicates, L = {args.draws} draws, F = {len(names)} functionals; "
        f"{flags.mean():.0%} of samples flagged (NaN data); jax {jax.__version__} on {jax.devices()[0].platform}"
    )
    results = {}
    for label, seed, sim, sampler, post, bs in runs:
        t0 = time.perf_counter()
        res = run_sbc(
            jax.random.PRNGKey(seed),
            sim,
            sampler,
            n_replicates=args.replicates,
            n_draws=args.draws,
            functionals=G,
            names=names,
            posterior=post,
            batch_size=bs,
        )
        results[label] = (res, time.perf_counter() - t0)

    w = max(len(s) for s in names) + 2
    head = "".join(f"{label:>22s}" for label in results)
    print("\n" + " " * w + head)
    print(" " * w + "".join(f"{'mean z2':>10s}{'p':>12s}" for _ in results))
    for k, name in enumerate(names):
        row = "".join(f"{r.mean_z2[k]:10.3f}{r.p_functional[k]:12.2e}" for r, _ in results.values())
        print(f"{name:<{w}s}{row}")
    print(f"{'family p (exact)':<{w}s}" + "".join(f"{r.p_family:22.2e}" for r, _ in results.values()))
    print(f"{'min chi2 p (asympt.)':<{w}s}" + "".join(f"{r.p_chi2.min():22.2e}" for r, _ in results.values()))
    print(f"{'all converged':<{w}s}" + "".join(f"{bool(r.converged.all())!s:>22s}" for r, _ in results.values()))
    print(f"{'seconds (with compile)':<{w}s}" + "".join(f"{t:22.1f}" for _, t in results.values()))
    alpha = 1e-3
    verdict = {lab: ("PASS" if r.p_family > alpha else "REJECT") for lab, (r, _) in results.items()}
    print(f"{f'verdict at {alpha:g}':<{w}s}" + "".join(f"{v:>22s}" for v in verdict.values()))
    ok = verdict["cg"] == verdict["cholesky"] == "PASS" and all(
        verdict[k] == "REJECT" for k in ("bug 1/sqrt2", "post 2sig2", "data 2sig2")
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
