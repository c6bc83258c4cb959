"""Response routes side by side (rings, healpy SHT, ducc0 SHT) on the unique rows of a hexagon.

Usage::

    python benchmarks/response_routes.py LMAX NSIDE NANTS     # e.g. 300 256 331
    python benchmarks/response_routes.py --hera650            # the issue-24 case and lmax 300

``LMAX NSIDE NANTS`` builds the response of the redundant groups' representatives (one
channel, 100 MHz, a 14 m Gaussian dish) three times in one process --
``response_matrix(method="sht")`` first, then ``method="rings"``, then ``method="ducc"`` --
and prints the times, the ratios, the largest difference relative to the largest entry, and
the worst row-relative difference over the rows with norm above 1e-6 of the largest (rows
whose fringes lie far beyond lmax are ~1e-14 of the largest, and there the routes differ at
the level of the rings' beam-floor cut).

``--hera650`` (issue 24, item 1): the 331-antenna HERA core (630 unique rows), one channel,
first all 630 rows at lmax 650 / nside 512 by ducc (the fastest route) with the process's
peak memory (``ru_maxrss``; the result alone is 630 x 423801 complex128 = 4.27 GB), then, at
lmax 650 / nside 512 and at lmax 300 / nside 256, the time per row of each route on 32 of the
630 rows (evenly spaced in the group order: short and long baselines) and the routes'
agreement there, then all 630 rows at lmax 300 by ducc.

Measured 2026-12-02 (2 shared cores, load 0.4-2; ``benchmarks/scale.py`` section (B'))::

    lmax 300, nside 256, 331 antennas (630 rows): rings 115.6 s, sht 41.5 s (2.79x); max rel 3.3e-14;
        rows above 1e-6 of the largest: 9.2e-09 (423 rows); peak 4.2 GB
    lmax 150, nside 256, 331 antennas (630 rows): rings 27.0 s, sht 24.6 s (1.10x); max rel 2.3e-14

``--hera650``, 2026-12-03 05:31 UTC, load 12.75 8.61 4.77 at the start and 16-22 throughout
(other jobs on the 2 cores; every time inflated)::

    lmax 650, nside 512, all 630 rows, ducc: 135.0 s (0.214 s/row); peak 5.10 GB (result 4.27 GB)
    lmax 650, nside 512, 32 rows: ducc 0.248 s/row, sht 0.834 s/row, rings 4.917 s/row (3.4x, 19.8x);
        max |diff| / max |R|: ducc-sht 1.6e-14, ducc-rings 4.5e-14, sht-rings 4.3e-14
    lmax 300, nside 256, 32 rows: ducc 0.020 s/row, sht 0.051 s/row, rings 0.141 s/row (2.6x, 7.1x)
    lmax 300, nside 256, all 630 rows, ducc: 13.0 s

again at 06:01 UTC (load 8.9-12): 630 rows at lmax 650 by ducc 178.7 s, peak 5.10 GB; per row at
lmax 650 ducc 0.258 / sht 0.856 / rings 6.155 s (3.3x, 23.9x); lmax 300: 0.051 / 0.156 / 0.500 s;
630 rows at lmax 300 by ducc 31.7 s.

So ``response_matrix(method="auto")`` built by the SHT from lmax 200 on
(``gcrsky.instrument.response.RESPONSE_SHT_MIN_LMAX``); with ducc0 it builds by ducc at every
lmax (``RESPONSE_DUCC_MIN_LMAX`` = 0; table of ``--hera650`` in
``gcrsky/instrument/response_ducc.py``).
"""

from __future__ import annotations

import os
import resource
import sys
import time

import gcrsky  # noqa: F401  (before scipy's LAPACK loads: the thread settings below must precede it)
from gcrsky.parallel import use_safe_cpu_threading


def _hexagon(nants: int):
    """The ``nants`` hexagon (14.6 m) with 14 m Gaussian dishes and its groups' representatives."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from scale import ROWS

    from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, groups_for_array, hex_array, make_array

    arr = make_array(hex_array(ROWS[nants], 14.6), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    return arr, groups_for_array(arr).representative_antpairs


def _load() -> str:
    with open("/proc/loadavg") as fh:
        return fh.read().strip()


def _peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6  # KiB on Linux -> GB


def _timed(arr, pairs, lmax: int, nside: int, how: str):
    """``(R (Nbl, n) complex, seconds)`` of ``response_matrix(..., method=how)`` at 100 MHz."""
    import numpy as np

    from gcrsky.instrument import response_matrix

    t0 = time.perf_counter()
    r = response_matrix(arr, pairs, [100e6], lmax, nside, method=how)
    r.block_until_ready()
    dt = time.perf_counter() - t0
    return np.asarray(r)[0], dt


def hera650(nsub: int = 32) -> int:
    """The issue-24 case: all 630 rows at lmax 650 by ducc, then the routes on ``nsub`` rows."""
    import numpy as np

    arr, reps = _hexagon(331)
    print(f"date {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; load {_load()}", flush=True)
    r, dt = _timed(arr, reps, 650, 512, "ducc")
    shape = r.shape
    del r
    print(
        f"lmax 650 nside 512, all {len(reps)} rows, ducc: {dt:.1f} s ({dt / len(reps):.3f} s/row), "
        f"result {shape} complex128 = {16 * np.prod(shape) / 1e9:.2f} GB; peak {_peak_gb():.2f} GB; "
        f"load {_load()}",
        flush=True,
    )
    sub = reps[np.linspace(0, len(reps) - 1, nsub).astype(int)]
    for lmax, nside in ((650, 512), (300, 256)):
        out, times = {}, {}
        for how in ("ducc", "sht", "rings"):
            out[how], times[how] = _timed(arr, sub, lmax, nside, how)
            print(
                f"lmax {lmax} nside {nside}, {nsub} rows, {how}: {times[how]:.1f} s "
                f"({times[how] / nsub:.3f} s/row); load {_load()}",
                flush=True,
            )
        big = float(np.abs(out["sht"]).max())
        agree = ", ".join(
            f"{a}-{b} {np.abs(out[a] - out[b]).max() / big:.1e}"
            for a, b in (("ducc", "sht"), ("ducc", "rings"), ("sht", "rings"))
        )
        print(
            "  per row: "
            + ", ".join(f"{h} {times[h] / nsub:.3f} s" for h in times)
            + f"; sht/ducc {times['sht'] / times['ducc']:.1f}x, rings/ducc {times['rings'] / times['ducc']:.1f}x; "
            f"max |diff| / max |R|: {agree}",
            flush=True,
        )
        del out
    r, dt = _timed(arr, reps, 300, 256, "ducc")
    del r
    print(
        f"lmax 300 nside 256, all {len(reps)} rows, ducc: {dt:.1f} s ({dt / len(reps):.3f} s/row); "
        f"peak {_peak_gb():.2f} GB; load {_load()}",
        flush=True,
    )
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv == ["--hera650"]:
        use_safe_cpu_threading()
        import jax

        jax.config.update("jax_enable_x64", True)
        return hera650()
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
    for how in ("sht", "rings", "ducc"):
        t0 = time.perf_counter()
        out[how] = np.asarray(response_matrix(arr, reps, [100e6], lmax, nside, method=how))[0]
        times[how] = time.perf_counter() - t0
        print(f"{how} {times[how]:.1f} s, load {os.getloadavg()[0]:.1f}", flush=True)
    rr, rs, rd = out["rings"], out["sht"], out["ducc"]
    rel = float(np.max(np.abs(rr - rs)) / np.max(np.abs(rr)))
    norms = np.linalg.norm(rr, axis=-1)
    rowrel = np.linalg.norm(rr - rs, axis=-1) / norms
    big = norms > 1e-6 * norms.max()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(
        f"lmax {lmax}, nside {nside}, {nants} antennas ({len(reps)} rows): rings {times['rings']:.1f} s, "
        f"sht {times['sht']:.1f} s ({times['rings'] / times['sht']:.2f}x); max rel {rel:.1e}; rows above 1e-6 "
        f"of the largest: {rowrel[big].max():.1e} ({int(big.sum())} rows); peak {peak:.1f} GB"
    )
    reld = float(np.max(np.abs(rd - rs)) / np.max(np.abs(rr)))
    print(
        f"ducc {times['ducc']:.1f} s ({times['sht'] / times['ducc']:.2f}x faster than sht, "
        f"{times['rings'] / times['ducc']:.2f}x than rings); ducc-sht max rel {reld:.1e}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
