"""Redundant-baseline compression (gcrsky.instrument.redundancy): what it saves on HERA-like hexagons.

Usage::

    python benchmarks/redundancy.py            # the table below (~1.5-2 min on 2 cores)
    python benchmarks/redundancy.py --quick    # 37 antennas, lmax 20 only

Arrays: hexagons of 37 antennas (rows 4,5,6,7,6,5,4) and 91 antennas (rows
6,7,...,11,...,7,6), 14.6 m spacing, 14 m Gaussian dishes (pyuvdata
``GaussianBeam(diameter=14)``) at HERA's latitude; all cross-correlations ``i < j``.
Two channels (100, 102 MHz), nside 64; the response is the direct quadrature
(``gcrsky.instrument.response_matrix``) at lmax 20 and the SHT route
(``gcrsky.instrument.response_matrix_sht``) at lmax 50, as in ``benchmarks/scale.py``.
Columns:

* ``Nbl``, ``Ngrp``: baselines and redundant groups (``groups_for_array``);
  ``grp_s``: grouping time.
* ``resp_all_s`` / ``resp_uniq_s``: building the response of every baseline vs of the
  representatives only (``unique_response``); quadrature times include one JIT
  compile each (the shapes differ).
* ``row_dev``: largest difference between a member's row (from the full build) and its
  representative's, relative to the channel's max |R| (``check_redundancy``); the
  compression is exact to this level.
* ``Pa_all_ms`` / ``Pa_cmp_ms``: one matrix-free ``precision_apply`` (P a), jitted and
  warm, best of 5, for Nt = 20 rotation angles over 8 h, per-time random inverse
  noise with 10% of the samples flagged; ``speedup`` their ratio.
* ``Pa_reldiff``: ``max |P_cmp a - P a| / max |P a|`` for a random ``a``.

Measured on this repository's machine (2 shared x86 cores, 24 GB, CPU JAX float64,
gcrsky's safe threading ``--xla_cpu_multi_thread_eigen=false``, ``OMP_NUM_THREADS=1``)
while other jobs loaded it heavily (load average 9-11 on 2 cores), 128 s wall; P a times
are the best of 5 (warm)::

    nant  lmax  n     Nbl   Ngrp  grp_s  resp_all_s  resp_uniq_s  row_dev  Pa_all_ms  Pa_cmp_ms  speedup  Pa_reldiff
    37    20    441   666   63    0.05   4.8         2.7          1.3e-15  33.8       2.6        13.0     1.1e-15
    37    50    2601  666   63    0.05   8.7         1.0          6.9e-16  188.1      13.5       13.9     6.9e-16
    91    20    441   4095  165   0.16   21.4        2.5          1.4e-15  183.2      6.7        27.3     1.3e-15
    91    50    2601  4095  165   0.18   52.1        2.1          1.2e-15  1470.1     67.7       21.7     8.5e-16

The timings are noisy under that load; over four runs (load 3-11, 91-128 s wall):
resp_all_s 3.1-5.4 / 6.3-8.7 / 11.2-23.4 / 38.0-52.1, resp_uniq_s 1.6-3.0 / 0.7-1.0 /
1.5-2.5 / 1.3-2.2 and the P a speedup 6.3-18.7 / 7.4-13.9 / 17.0-34.2 / 21.7-36.5 for the
four rows in order.  Ngrp, row_dev and Pa_reldiff are the same in every run.

Reading: a hexagon of N antennas has O(N) distinct baseline vectors (63 for 37
antennas, 165 for 91), so Nbl / Ngrp = 10.6 and 24.8.  The SHT build (lmax 50) scales
with the number of rows built: 9x and 20-29x faster.  At lmax 20 the unique
quadrature build is bounded below by its JIT compile (~1.5 s), hence only 2x (37
antennas) and 7-10x (91).  The matrix-free P a is dominated by the baseline contraction
(the O(Nt lmax^3) rotations are cheap here), so it speeds up by roughly Nbl / Ngrp
(at 91 antennas sometimes more: the uncompressed 340 MB response streams from memory
twice per product).  P a agrees to rounding (<= 1.3e-15 relative) and identical rows
to 1.4e-15 of the channel's max |R|: the compression is exact.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ARRAYS = {37: (4, 5, 6, 7, 6, 5, 4), 91: (6, 7, 8, 9, 10, 11, 10, 9, 8, 7, 6)}
FREQS_HZ = (100e6, 102e6)
NSIDE = 64
NT = 20


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="37 antennas at lmax 20 only")
    args = ap.parse_args()

    import os

    # healpy's OpenMP SHTs spin-wait badly on a shared 2-core host: 0.7 s single-threaded
    # vs 5.5 s with 2 threads for 63 baselines at lmax 50, measured under load
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from gcrsky.parallel import use_safe_cpu_threading

    use_safe_cpu_threading()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from gcrsky.instrument import (
        HERA_LATITUDE_DEG,
        antpairs,
        check_redundancy,
        gaussian_beam,
        groups_for_array,
        hex_array,
        make_array,
        response_matrix,
        response_matrix_sht,
        unique_response,
    )
    from gcrsky.model import LinearSystem, Prior, VisOperator, compress_system
    from gcrsky.model.system import precision_apply

    freqs = np.asarray(FREQS_HZ)
    grid = [(37, 20)] if args.quick else [(37, 20), (37, 50), (91, 20), (91, 50)]
    pa = jax.jit(precision_apply)

    def timed_pa(system, a, reps=5):
        pa(system, a).block_until_ready()  # compile + warm
        ts = []
        for _ in range(reps):
            t0 = time.perf_counter()
            out = pa(system, a).block_until_ready()
            ts.append(time.perf_counter() - t0)
        return out, 1e3 * float(np.min(ts))

    cols = ["nant", "lmax", "n", "Nbl", "Ngrp", "grp_s", "resp_all_s", "resp_uniq_s", "row_dev",
            "Pa_all_ms", "Pa_cmp_ms", "speedup", "Pa_reldiff"]
    widths = [6, 6, 6, 6, 6, 7, 12, 13, 9, 11, 11, 9, 10]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)).rstrip(), flush=True)
    t_start = time.perf_counter()
    for nant, lmax in grid:
        array = make_array(hex_array(ARRAYS[nant], 14.6), HERA_LATITUDE_DEG, gaussian_beam(14.0))
        pairs = antpairs(nant)
        t0 = time.perf_counter()
        groups = groups_for_array(array, pairs)
        t_grp = time.perf_counter() - t0
        method = "quadrature" if lmax <= 20 else "sht"
        build = response_matrix if method == "quadrature" else response_matrix_sht

        t0 = time.perf_counter()
        R = build(array, pairs, freqs, lmax, NSIDE)
        R.block_until_ready()
        t_all = time.perf_counter() - t0
        t0 = time.perf_counter()
        Ru = unique_response(array, groups, freqs, lmax, NSIDE, method=method)
        Ru.block_until_ready()
        t_uniq = time.perf_counter() - t0
        row_dev = check_redundancy(R, groups)
        assert float(jnp.max(jnp.abs(Ru - R[:, groups.representative]))) <= 1e-12 * float(jnp.max(jnp.abs(R)))

        rng = np.random.default_rng(nant + lmax)
        nbl, n = pairs.shape[0], R.shape[2]
        shape = (freqs.size, NT, nbl)
        iv = rng.uniform(0.5, 2.0, shape) * 1e6
        iv[rng.uniform(size=shape) < 0.1] = 0.0
        data = np.where(iv > 0, rng.normal(size=shape) + 1j * rng.normal(size=shape), 0.0)
        prior = Prior(jnp.zeros((freqs.size, n)), jnp.ones((freqs.size, n)))
        angles = jnp.asarray(np.linspace(0.0, 8.0, NT) * 2 * np.pi / 24)
        system = LinearSystem(VisOperator(R, angles), jnp.asarray(data), jnp.asarray(iv), prior)
        small = compress_system(system, groups)
        a = jnp.asarray(rng.normal(size=(freqs.size, n)))
        out_all, ms_all = timed_pa(system, a)
        out_cmp, ms_cmp = timed_pa(small, a)
        reldiff = float(jnp.max(jnp.abs(out_cmp - out_all)) / jnp.max(jnp.abs(out_all)))
        row = [nant, lmax, n, nbl, groups.n_groups, f"{t_grp:.2f}", f"{t_all:.1f}", f"{t_uniq:.1f}",
               f"{row_dev:.1e}", f"{ms_all:.1f}", f"{ms_cmp:.1f}", f"{ms_all / ms_cmp:.1f}", f"{reldiff:.1e}"]
        print("  ".join(str(v).ljust(w) for v, w in zip(row, widths)).rstrip(), flush=True)
        del R, Ru, system, small
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"total {time.perf_counter() - t_start:.0f} s wall; load average {load} on {os.cpu_count()} cores", flush=True)


if __name__ == "__main__":
    main()
