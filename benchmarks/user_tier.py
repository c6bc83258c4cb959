"""The user tier under JAX's transformations: first call (compile) against second, one run.

Prints a table for the standard case (lmax 20, nside 128, two channels, 10 LSTs; the planner picks
dense Cholesky) and for matrix-free CG:

* ``gcrsky.sample(key, prob, 200)`` eager, first and second call;
* ``jax.jit(jax.vmap(gcrsky.sample))`` over 8 keys (path fixed with ``gcrsky.choose_path``);
* ``jax.vmap`` over 4 data sets with one factorisation (``gcrsky.draw(..., data=d)``) against a
  fresh ``gcrsky.prepare`` per data set;
* 300 then 301 draws (one bucket of 256: no recompilation) on the CG path.

Measured (2026-12-02, this shared 2-core CPU, load ~6; Cholesky chosen, n = 441)::

    call                                               seconds
    sample(200), eager, first                            5.526
    sample(200), eager, second                           0.081
    jit(vmap(sample)) over 8 keys, first                 5.284
    jit(vmap(sample)) over 8 keys, second                0.437
    vmap over 4 data sets, one factor, first             2.356
    vmap over 4 data sets, one factor, second            0.200
    4 fresh prepares + draws (loop)                      0.679
    CG matrix-free: draw(300), first                    12.175
    CG matrix-free: draw(301), same bucket               2.063

Run: ``.venv/bin/python benchmarks/user_tier.py`` (about a minute on 2 cores).  Each row is the
wall-clock time of one call after ``block_until_ready``; the machines are shared, so compare rows of
one run only.
"""

from __future__ import annotations

import time

from gcrsky.parallel import use_safe_cpu_threading

use_safe_cpu_threading()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

jax.config.update("jax_enable_x64", True)

import gcrsky  # noqa: E402
from gcrsky.solvers import CGOptions  # noqa: E402


def timed(fn):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return time.perf_counter() - t0, out


def main() -> None:
    prob = gcrsky.standard_case(lmax=20, nside=128)
    system = prob.system()
    key = jax.random.PRNGKey(0)
    rows = []
    opts = gcrsky.choose_path(system, ndraws=200)
    rows.append(("sample(200), eager, first", timed(lambda: gcrsky.sample(key, system, 200)[0])[0]))
    rows.append(("sample(200), eager, second", timed(lambda: gcrsky.sample(key, system, 200)[0])[0]))
    keys = jax.random.split(key, 8)
    f = jax.jit(jax.vmap(lambda k: gcrsky.sample(k, system, 200, options=opts)[0]))
    rows.append(("jit(vmap(sample)) over 8 keys, first", timed(lambda: f(keys))[0]))
    rows.append(("jit(vmap(sample)) over 8 keys, second", timed(lambda: f(jax.random.split(keys[0], 8)))[0]))
    datas = jnp.stack([system.data * (1.0 + 0.01 * i) for i in range(4)])
    prepared = gcrsky.prepare(system, options=opts)
    g = jax.jit(jax.vmap(lambda d: gcrsky.draw(key, prepared, 200, data=d)[0]))
    rows.append(("vmap over 4 data sets, one factor, first", timed(lambda: g(datas))[0]))
    rows.append(("vmap over 4 data sets, one factor, second", timed(lambda: g(datas * 1.001))[0]))
    rows.append(("4 fresh prepares + draws (loop)", timed(lambda: [gcrsky.sample(key, system._replace(data=d), 200,
                                                                                 options=opts)[0] for d in datas])[0]))
    cg = gcrsky.prepare(system, options=CGOptions(dense=False))
    rows.append(("CG matrix-free: draw(300), first", timed(lambda: gcrsky.draw(key, cg, 300)[0])[0]))
    rows.append(("CG matrix-free: draw(301), same bucket", timed(lambda: gcrsky.draw(key, cg, 301)[0])[0]))
    print(f"path chosen: {gcrsky.solvers.registry.method_of(opts)}; lmax {prob.lmax}, n = {prob.n}")
    print(f"{'call':48s} {'seconds':>9s}")
    for name, sec in rows:
        print(f"{name:48s} {sec:9.3f}")


if __name__ == "__main__":
    main()
