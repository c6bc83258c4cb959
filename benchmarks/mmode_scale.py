"""The exact m-mode path at high lmax: bucketed blocks, their factors, the Wiener filter and 200 draws.

Usage::

    python benchmarks/mmode_scale.py                   # lmax 300 and 400, random responses, 165 rows
    python benchmarks/mmode_scale.py --real            # lmax 650, the 331-antenna hexagon's 630 unique rows
    python benchmarks/mmode_scale.py --estimate 650 630 1301   # the memory estimate alone (LMAX NBL NT)

Cases: one channel (100 MHz), ``Nt = 2 lmax + 1`` equally spaced LSTs over 24 h,
time-constant per-baseline noise, isotropic prior.  The small cases use a random complex
response of the shape of the 91-antenna hexagon redundancy-compressed (165 rows): the
block build, the factorisation and the draws cost the same for any values.  ``--real``
builds the 630 unique rows of the 331-antenna HERA-core hexagon (14.6 m spacing, 14 m
Gaussian dishes, nside 512) with :func:`gcrsky.instrument.redundancy.unique_response`,
default route.

Columns: ``response_s`` building R; ``setup_s`` = ``blocks_s`` (:func:`mmode_factor`: every
bucket built from its own columns of R and factorised, compiles included) + ``wiener_s``
(the right-hand side ``X^T W d``, the block solve and the true residual ``b - P a_wf``: three
matrix-free products, ``O(Nt Nbl n)`` each, over chunks of times); ``draws_s`` 200 draws
(compile included); ``peak_GB`` the process's peak resident memory (VmHWM, reset after the
response is built) over the set-up and the draws; ``est_GB`` the estimate made before
building anything: the resident memory then (runtime and system) plus
:func:`gcrsky.solvers.mmode.mmode_memory` (``MModePath.memory_bytes``).

Measured 2026-12-03 on this repository's machine (2 shared cores, CPU JAX float64, one
OpenBLAS thread, XLA's safe threading), with other engineers' jobs loading it heavily
(``cat /proc/loadavg`` at the start / end: ``6.87 11.27 10.96`` / ``11.73 11.53 11.11``)::

    lmax  n       Nbl  Nt    response_s  setup_s (blocks + wiener)  draws200_s  peak_GB  est_GB  buckets  waste  chunk
    300   90601   165  601   4.5            57.6 (19.0 + 38.6)         9.4         2.13     3.10    10       0.160  123
    400   160801  165  801   5.3            97.0 (14.7 + 82.3)         19.2        3.68     4.81    13       0.120  69

    stage peaks (resident before 0.54 / 1.05 GB): blocks 1.04 / 1.92, wiener 1.83 / 2.86, draws 2.13 / 3.68 GB

(random 165-row responses, ``python benchmarks/mmode_scale.py``; ``est_GB`` is the final
formula, the stages summed, on the same run's resident size: the run itself printed 1.95 /
2.89 GB from an earlier formula, factors plus the largest stage, which the peaks exceeded.)
The Wiener step is the three matrix-free products (``O(Nt Nbl n)`` each); the blocks at
lmax 400 (14.7 s) are mostly compiles (13 buckets) and LAPACK.

lmax 650, ``--real`` (MEASURED 2026-12-03 06:37-06:41 UTC, after the m-factorised operator products
and the ducc0 response route were merged; ``OPENBLAS_NUM_THREADS=1 python benchmarks/mmode_scale.py
--real``, load ``5.46 6.42 8.41`` at the start, ``7.62 7.08 8.16`` at the end, other engineers' jobs
running; wall 4 min 26 s, ``/usr/bin/time`` max RSS 12.8 GB)::

    lmax  n       Nbl  Nt    response_s  setup_s (blocks + wiener)  draws200_s  peak_GB  est_GB  buckets  waste  chunk  err_sigma
    650   423801  630  1301  148.9         101.1 (87.1 + 13.9)         7.7         13.09    14.23   21       0.075  1301   7.0e-12

Goals of the issue (response + set-up < 20 min, 200 draws < 1 min, peak < 16 GB): 250 s, 7.7 s,
13.1 GB: met.  The Wiener step (three matrix-free products over all 1301 times) takes 13.9 s on
the m-factorised products (``gcrsky.model.mfactor``); before them, the same products cost ~3e12
flop each and the set-up was OOM-killed twice on this shared machine (a run before the merge:
response by the healpy route 578.7 s, 13.4 GB peak; blocks and draws alone on a random response
of the same shape: 67.5 s and 16.2 s, 12.4 GB).  Where the time goes now: the response (ducc0's
adjoint SHTs over the beam's rings, 60 %), the blocks (Gram products ``~1e12`` flop and 651
Cholesky factors, 35 %), the Wiener step (5 %).
"""

from __future__ import annotations

import os

# One OpenBLAS thread, set before NumPy loads it: the blocks' Cholesky and triangular solves
# run in LAPACK, and threaded OpenBLAS on this loaded 2-core machine was 10-25x slower
# (32 Cholesky factors of 576 x 576: 0.46 s with one thread, 6-12 s without, at load 11).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import time

import gcrsky  # noqa: F401  (before scipy's LAPACK loads: the thread settings below must precede it)
from gcrsky.parallel import use_safe_cpu_threading

GB = 1e9


def hwm_bytes() -> float:
    """The process's peak resident memory (VmHWM) in bytes."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) * 1024
    return float("nan")


def rss_bytes() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) * 1024
    return float("nan")


def reset_hwm() -> None:
    """Reset VmHWM (and so ``ru_maxrss``) to the current resident size (Linux ``clear_refs``)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def real_response(lmax: int, nside: int):
    """(1, 630, n) complex: the unique rows of the 331-antenna hexagon at 100 MHz, and the time."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from scale import ROWS

    from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, groups_for_array, hex_array, make_array
    from gcrsky.instrument.redundancy import unique_response

    arr = make_array(hex_array(ROWS[331], 14.6), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    groups = groups_for_array(arr)
    t0 = time.perf_counter()
    R = unique_response(arr, groups, [100e6], lmax, nside).block_until_ready()
    return R, time.perf_counter() - t0


def random_response(lmax: int, nbl: int):
    import jax
    import jax.numpy as jnp

    t0 = time.perf_counter()
    R = jax.random.normal(jax.random.PRNGKey(lmax), (1, nbl, (lmax + 1) ** 2), jnp.complex128).block_until_ready()
    return R, time.perf_counter() - t0


def make_system(R):
    """Full-day uniform LSTs (Nt = 2 lmax + 1), stationary noise, an isotropic prior."""
    import jax.numpy as jnp
    import numpy as np

    from gcrsky.model import LinearSystem, VisOperator, isotropic_prior
    from gcrsky.sphere import lmax_from_nparams

    nf, nbl, n = R.shape
    lmax = lmax_from_nparams(n)
    nt = 2 * lmax + 1
    rng = np.random.default_rng(1)
    scale = float(jnp.max(jnp.abs(R)))
    sigma = 0.1 * scale * rng.uniform(0.5, 2.0, (nf, nbl))
    w = np.broadcast_to(1.0 / sigma[:, None, :] ** 2, (nf, nt, nbl)).copy()
    prior = isotropic_prior(np.tile(1.0 / (1.0 + np.arange(lmax + 1)) ** 2, (nf, 1)), n)
    data = (rng.normal(size=(nf, nt, nbl)) + 1j * rng.normal(size=(nf, nt, nbl))) * scale
    angles = 2 * np.pi * np.arange(nt) / nt
    return LinearSystem(VisOperator(R, jnp.asarray(angles)), jnp.asarray(data), jnp.asarray(w), prior)


def run_case(R, response_s: float, ndraws: int = 200) -> dict:
    """Set-up and draws on one response; timings and memory (see the module docstring)."""
    import jax

    from gcrsky.solvers.mmode import MModeOptions, MModeState, _chunk_of, _mmode_wiener_jit, draw_mmode, mmode_factor
    from gcrsky.solvers.registry import path_of

    system = make_system(R)
    _, nt, nbl = system.data.shape
    n = R.shape[2]
    opts = MModeOptions()
    base = rss_bytes()
    est = base + path_of("mmode").memory_bytes(system, opts, ndraws)
    peaks = []
    reset_hwm()
    t0 = time.perf_counter()
    L = jax.block_until_ready(mmode_factor(system, opts.bucket))
    t1 = time.perf_counter()
    peaks.append(hwm_bytes())
    reset_hwm()
    a_wf, info = jax.block_until_ready(_mmode_wiener_jit(system, L, opts, _chunk_of(system)))
    t2 = time.perf_counter()
    peaks.append(hwm_bytes())
    reset_hwm()
    state = MModeState(system, a_wf, info, L, opts)
    _, dinfo = jax.block_until_ready(draw_mmode(jax.random.PRNGKey(0), state, ndraws))
    t3 = time.perf_counter()
    peaks.append(hwm_bytes())
    print(f"  resident before {base / GB:.2f} GB; stage peaks: blocks {peaks[0] / GB:.2f}, wiener "
          f"{peaks[1] / GB:.2f}, draws {peaks[2] / GB:.2f} GB", flush=True)
    assert bool(info.converged.all()) and bool(dinfo.draws.converged.all()), (info, dinfo.draws)
    return {"lmax": L.lmax, "n": n, "nbl": nbl, "nt": nt, "response_s": response_s, "blocks_s": t1 - t0,
            "wiener_s": t2 - t1, "setup_s": t2 - t0, "draws_s": t3 - t2, "peak": max(peaks), "est": est,
            "err": float(info.err_sigma.max()), "buckets": len(L.arrays), "waste": L.layout.waste,
            "chunk": _chunk_of(system)}


def print_row(r: dict, header: bool) -> None:
    if header:
        print("lmax  n       Nbl  Nt    response_s  setup_s (blocks + wiener)  draws200_s  peak_GB  est_GB"
              "  buckets  waste  chunk  err_sigma")
    print(f"{r['lmax']:<5} {r['n']:<7} {r['nbl']:<4} {r['nt']:<5} {r['response_s']:<11.1f} "
          f"{r['setup_s']:7.1f} ({r['blocks_s']:.1f} + {r['wiener_s']:.1f}){'':<8} {r['draws_s']:<11.1f} "
          f"{r['peak'] / GB:<8.2f} {r['est'] / GB:<7.2f} {r['buckets']:<8} {r['waste']:<6.3f} {r['chunk']:<6} "
          f"{r['err']:.1e}", flush=True)


def loadavg() -> str:
    with open("/proc/loadavg") as f:
        return f.read().strip()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", action="store_true", help="lmax 650, the 331-antenna hexagon's 630 unique rows")
    ap.add_argument("--lmax", type=int, nargs="*", default=None)
    ap.add_argument("--nbl", type=int, default=165, help="rows of the random response (small cases)")
    ap.add_argument("--nside", type=int, default=512)
    ap.add_argument("--random", action="store_true", help="with --real: a random response of the same shape")
    ap.add_argument("--estimate", type=int, nargs=3, metavar=("LMAX", "NBL", "NT"))
    args = ap.parse_args(argv)
    use_safe_cpu_threading()
    import jax

    jax.config.update("jax_enable_x64", True)
    from gcrsky.solvers.mmode import mmode_buckets, mmode_memory

    if args.estimate:
        lmax, nbl, nt = args.estimate
        mem, lay = mmode_memory(1, nbl, nt, lmax, 200), mmode_buckets(lmax)
        print(f"lmax {lmax}, Nbl {nbl}, Nt {nt}, 200 draws: response {16 * nbl * (lmax + 1) ** 2 / GB:.2f} GB; "
              f"factors {mem.factors / GB:.2f} GB ({len(lay.orders)} buckets, padding {100 * lay.waste:.1f} %), "
              f"then the largest of build {mem.build / GB:.2f}, products {mem.products / GB:.2f}, "
              f"draws {mem.draws / GB:.2f} GB: peak {mem.peak / GB:.2f} GB beyond the system and the runtime")
        return 0
    print(f"load {loadavg()}", flush=True)
    lmaxes = args.lmax or ([650] if args.real else [300, 400])
    for i, lmax in enumerate(lmaxes):
        if args.real and not args.random:
            R, rs = real_response(lmax, args.nside)
        else:
            R, rs = random_response(lmax, 630 if args.real else args.nbl)
        print(f"lmax {lmax}: response {rs:.1f} s, peak so far {hwm_bytes() / GB:.2f} GB", flush=True)
        print_row(run_case(R, rs), header=i == 0)
        del R
    print(f"load {loadavg()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
