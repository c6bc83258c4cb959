"""Where float32 is safe, and what it costs where it is not (issue 5).

Usage::

    .venv/bin/python benchmarks/float32.py            # ~2 min on 2 cores

Two problems: the paper's standard case (lmax 20, 10 antennas, 10 LSTs over 8 h,
2 channels) and the same array at lmax 50 (nside 64, isotropic prior, 10% noise, as
``benchmarks/scale.py``'s ``l50-a10-t10-8h-f1``).  Reference: the dense Cholesky
Wiener filter; errors are max over modes of |a - a_ref| / posterior sigma.

Rows:

* **safe**: the CG preconditioner (Nystrom rank 128, m-blocks) stored and applied in
  float32 (``pc_dtype="float32"``), CG itself float64: the answer meets the same
  tolerance; the table shows the iterations and time per matrix-free draw.
* **not safe, measured**: (a) the response rounded to complex64 (then solved in
  float64): the posterior of a slightly different instrument; (b) the dense P
  rounded to float32 and factorised in float32; (c) the visibilities ``X a`` in
  float32 (forward simulation only), relative error.

Measured
--------
2026-11-22, this 2-core CPU box while other jobs ran (load 5-7: the ms/draw column is
noisy, iterations are not), 1030 s wall, matrix-free CG to 1e-8 sigma, 20 draws::

    === standard case (lmax 20): n = 441, Nf = 2, cond(P) = 3.0e+08
    path                                 WF it  draw it  ms/draw  WF err [sigma]
    matrix-free CG, nystrom pc float64       2      2.0    10.78         5.7e-09
    matrix-free CG, nystrom pc float32      18      9.3    43.32         5.7e-09
    matrix-free CG, mblock pc float64      854    873.7  1251.22         2.6e-07
    matrix-free CG, mblock pc float32     1677   1733.0  1817.04         2.3e-07
    (a) response rounded to complex64, exact float64 solve: WF error 3.4e-05 sigma
    (b) float32 dense P + Cholesky: WF error 7.1e-02 sigma
    (c) visibilities X a in float32: max |dV| / rms |V| = 1.5e-06

    === lmax 50, 10 antennas, 10 LSTs over 8 h: n = 2601, Nf = 1, cond(P) = 3.4e+06
    matrix-free CG, nystrom pc float64      41     39.5   230.03         9.1e-10
    matrix-free CG, nystrom pc float32      50     46.7   274.34         9.2e-10
    matrix-free CG, mblock pc float64      522    563.2  7118.87         5.2e-09
    matrix-free CG, mblock pc float32     564    611.4   999.44         5.4e-09
    (a) response rounded to complex64, exact float64 solve: WF error 1.1e-07 sigma
    (b) float32 dense P + Cholesky: WF error 7.5e-05 sigma
    (c) visibilities X a in float32: max |dV| / rms |V| = 3.8e-06

Reading: a float32 preconditioner never changes the answer (same error as float64),
but costs iterations where P is badly conditioned (standard case, cond 3e8: 2 -> 18
Wiener iterations with Nystrom, 2x with m-blocks; at lmax 50, cond 3e6: +10-20%), and
on this CPU it saves no time, so gcrsky keeps float64 as the default and offers
``pc_dtype="float32"`` for memory-bound accelerators.  Forward simulation in float32
is safe (visibilities to ~1e-6 relative).  The solve itself is not: a float32 dense P
and factor miss the standard case's Wiener filter by 0.07 sigma, which is why the
linear algebra refuses float32 (``gcrsky.base.check_float64``); storing the
response in complex64 and solving in float64 costs 3e-5 sigma (standard case) to
1e-7 sigma (lmax 50): usable for maps, not offered as "exact".
"""

from __future__ import annotations

import sys
import time

from gcrsky.parallel import use_safe_cpu_threading

use_safe_cpu_threading()
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import gcrsky  # noqa: E402
from gcrsky.inference import draw, prepare_system  # noqa: E402
from gcrsky.instrument import (  # noqa: E402
    HERA_LATITUDE_DEG,
    antpairs,
    gaussian_beam,
    hex_array,
    make_array,
    response_matrix,  # noqa: E402
)
from gcrsky.model import apply, build_problem, isotropic_prior
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.solvers import CGOptions  # noqa: E402


def lmax50_problem():
    lmax, nside, nf = 50, 64, 1
    n = (lmax + 1) ** 2
    freqs = np.array([100e6])
    arr = make_array(hex_array((3, 4, 3), 14.6), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    resp = response_matrix(arr, antpairs(10), freqs, lmax, nside)
    auto = response_matrix(arr, np.stack([np.arange(10)] * 2, 1), freqs, lmax, nside)
    cl = np.tile(100.0 / (1.0 + np.arange(lmax + 1)) ** 2, (nf, 1))
    prior = isotropic_prior(cl, n)
    std = 1 / np.sqrt(np.asarray(prior.inv_var))
    truth = std * np.random.default_rng(1).standard_normal((nf, n))
    R = np.asarray(resp)
    sigma = 0.1 * np.sqrt(np.mean(np.einsum("fbk,fk->fb", np.abs(R) ** 2, std**2))) / np.sqrt(2)
    lsts = np.linspace(0.0, 2 * np.pi / 3, 10)
    return build_problem(arr, freqs, lsts, lmax, nside, a_true=truth, sigma=sigma, prior=prior,
                         responses=(resp, auto), key=jax.random.PRNGKey(3))


def err_sigma(a, a_ref, sig) -> float:
    return float(np.max(np.abs(np.asarray(a) - a_ref) / sig))


def run(name, prob, ndraws=20):
    system = prob.system()
    P = np.asarray(precision_matrix(system))
    b = np.asarray(wiener_rhs(system))
    a_ref = np.stack([np.linalg.solve(P[f], b[f]) for f in range(P.shape[0])])
    sig = np.stack([np.sqrt(np.diag(np.linalg.inv(P[f]))) for f in range(P.shape[0])])
    key = jax.random.PRNGKey(0)
    print(f"\n=== {name}: n = {prob.n}, Nf = {P.shape[0]}, cond(P) = {np.linalg.cond(P[0]):.1e}")
    print(f"{'path':34s} {'WF it':>7s} {'draw it':>8s} {'ms/draw':>8s} {'WF err [sigma]':>15s}")
    for pc in ("nystrom", "mblock"):
        for dt in ("float64", "float32"):
            kw = dict(options=CGOptions(dense=False, preconditioner=pc, pc_dtype=dt, tol=1e-8, maxiter=20000))
            prep = jax.block_until_ready(prepare_system(system, **kw))
            jax.block_until_ready(draw(key, prep, ndraws))  # compile
            t0 = time.perf_counter()
            _, info = jax.block_until_ready(draw(key, prep, ndraws))
            dt_ms = (time.perf_counter() - t0) / ndraws * 1e3
            ok = bool(np.all(np.asarray(info.draws.converged)) and np.all(np.asarray(prep.wiener.converged)))
            print(f"{'matrix-free CG, ' + pc + ' pc ' + dt:34s} {float(np.mean(prep.wiener.iterations)):7.0f} "
                  f"{float(np.mean(info['draws'].iterations)):8.1f} {dt_ms:8.2f} "
                  f"{err_sigma(prep.a_wf, a_ref, sig):15.1e}{'' if ok else '  (not converged)'}")
    # (a) response rounded to complex64, solved exactly in float64
    r32 = system.op.response.astype(jnp.complex64).astype(jnp.complex128)
    s32 = system._replace(op=system.op._replace(response=r32))
    P32 = np.asarray(precision_matrix(s32))
    b32 = np.asarray(wiener_rhs(s32))
    a32 = np.stack([np.linalg.solve(P32[f], b32[f]) for f in range(P.shape[0])])
    print(f"(a) response rounded to complex64, exact float64 solve: WF error {err_sigma(a32, a_ref, sig):.1e} sigma")
    # (b) dense P and factor in float32
    Pf = P.astype(np.float32)
    try:
        L = np.linalg.cholesky(Pf)
        a_b = np.stack([np.linalg.solve(L[f].T, np.linalg.solve(L[f], b[f].astype(np.float32))) for f in range(P.shape[0])])
        print(f"(b) float32 dense P + Cholesky: WF error {err_sigma(a_b, a_ref, sig):.1e} sigma")
    except np.linalg.LinAlgError as e:
        print(f"(b) float32 dense P + Cholesky: fails ({e})")
    # (c) forward visibilities in float32
    a = jnp.asarray(a_ref)
    v64 = np.asarray(apply(system.op, a))
    op32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.complex64) if jnp.iscomplexobj(x) else x.astype(jnp.float32),
                                  system.op)
    with jax.numpy_dtype_promotion("standard"):
        v32 = np.asarray(apply(op32, a.astype(jnp.float32)))
    print(f"(c) visibilities X a in float32: max |dV| / rms |V| = {np.abs(v32 - v64).max() / np.sqrt(np.mean(np.abs(v64) ** 2)):.1e}")


def main() -> int:
    t0 = time.time()
    run("standard case (lmax 20)", gcrsky.standard_case())
    if "--quick" not in sys.argv:
        run("lmax 50, 10 antennas, 10 LSTs over 8 h", lmax50_problem())
    print(f"\ntotal {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
