"""Rings vs healpy-SHT response, side by side, on every unique row of a hexagon.

Usage::

    python benchmarks/response_routes.py LMAX NSIDE NANTS     # e.g. 300 256 331

Builds the response of the redundant groups' representatives (one channel, 100 MHz, a
14 m Gaussian dish) twice in one process -- ``response_matrix(method="sht")`` first, then
``method="rings"`` -- and prints both times, their ratio, the largest difference relative
to the largest entry, and the worst row-relative difference over the rows with norm
above 1e-6 of the largest (rows whose fringes lie far beyond lmax are ~1e-14 of the
largest, and there the two routes differ at the level of the rings' beam-floor cut).

Measured 2026-12-02 (2 shared cores, load 0.4-2; ``benchmarks/scale.py`` section (B'))::

    lmax 300, nside 256, 331 antennas (630 rows): rings 115.6 s, sht 41.5 s (2.79x); max rel 3.3e-14;
        rows above 1e-6 of the largest: 9.2e-09 (423 rows); peak 4.2 GB
    lmax 150, nside 256, 331 antennas (630 rows): rings 27.0 s, sht 24.6 s (1.10x); max rel 2.3e-14

So ``response_matrix(method="auto")`` builds by the SHT from lmax 200 on
(``gcrsky.instrument.response.RESPONSE_SHT_MIN_LMAX``).
"""

from __future__ import annotations

import os
import resource
import sys
import time

import gcrsky  # noqa: F401  (before scipy's LAPACK loads: the thread settings below must precede it)
from gcrsky.parallel import use_safe_cpu_threading


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 3:
        print(__doc__)
        return 2
    lmax, nside, nants = (int(x) for x in argv)
    use_safe_cpu_threading()
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from scale import ROWS

    from gcrsky.instrument import (
        HERA_LATITUDE_DEG,
        gaussian_beam,
        groups_for_array,
        hex_array,
        make_array,
        response_matrix,
    )

    arr = make_array(hex_array(ROWS[nants], 14.6), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    reps = groups_for_array(arr).representative_antpairs
    print(f"lmax {lmax} nside {nside} rows {len(reps)} load {os.getloadavg()[0]:.1f}", flush=True)
    times = {}
    out = {}
    for how in ("sht", "rings"):
        t0 = time.perf_counter()
        out[how] = np.asarray(response_matrix(arr, reps, [100e6], lmax, nside, method=how))[0]
        times[how] = time.perf_counter() - t0
        print(f"{how} {times[how]:.1f} s, load {os.getloadavg()[0]:.1f}", flush=True)
    rr, rs = out["rings"], out["sht"]
    rel = float(np.max(np.abs(rr - rs)) / np.max(np.abs(rr)))
    norms = np.linalg.norm(rr, axis=-1)
    rowrel = np.linalg.norm(rr - rs, axis=-1) / norms
    big = norms > 1e-6 * norms.max()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(f"lmax {lmax}, nside {nside}, {nants} antennas ({len(reps)} rows): rings {times['rings']:.1f} s, "
          f"sht {times['sht']:.1f} s ({times['rings'] / times['sht']:.2f}x); max rel {rel:.1e}; rows above 1e-6 "
          f"of the largest: {rowrel[big].max():.1e} ({int(big.sum())} rows); peak {peak:.1f} GB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
