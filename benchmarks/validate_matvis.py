"""gcrsky's real-time visibility operator against ``matvis.simulate_vis``: the full grid.

Usage::

    python benchmarks/validate_matvis.py [--ntimes 8] [--span-hours 9] [--start 2025-03-01T00:00:00]
        [--nside-gaussian 128] [--nside-airy 512] [--nside-uvbeam 256] [--lmax 20]
        [--only airy,hex] [--no-jacobian] [--quick]

Grid: 3 beams (pyuvdata ``GaussianBeam`` and ``AiryBeam``, 14 m; matvis' HERA dipole
UVBeam) x 2 layouts (the 10-antenna hexagon, redundant, 14.6-43.8 m; 10 antennas at
random in a 48 m square, non-redundant, 14.0-58.6 m) x 2 sites (HERA, -30.72 deg; Green
Bank, +38.43 deg), each over ``--ntimes`` real UTC times spanning ``--span-hours``
(>= 8 h of LST) at two frequencies (100 and 150 MHz; 100 and 101 MHz for the UVBeam,
the two frequencies its file holds).  One row per configuration: the error figure
``max |V_gcrsky - 2 V_matvis| / rms(V_gcrsky)`` over all cross-correlations, times and
frequencies, the worst visibility, and wall times (gcrsky's includes the frame map,
the response build and JIT compilation; matvis' its per-time astropy transforms).
See :mod:`gcrsky.checks.matvis` for the method and the error floors.

Default nsides are what each beam needs for the 1e-3 target (Gaussian 128; Airy
512 because of its horizon sidelobes, see :mod:`gcrsky.checks.matvis`); the UVBeam runs at
256, where it reads up to 1.8e-3 (``--nside-uvbeam 512``: <= 6.5e-4, +~4 min).  The
whole grid takes about 6 minutes on 2 cores, most of it the four Airy rows;
``--quick`` (Airy 256, UVBeam 128, 6 times) about 1.5 minutes, with those rows above
the target.

IERS: astropy is kept offline (bundled tables; they cover 2025).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import warnings
from pathlib import Path

try:
    import gcrsky  # noqa: F401
except ImportError:  # running from a checkout without an install
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gcrsky.parallel import use_safe_cpu_threading  # noqa: E402

use_safe_cpu_threading()  # before JAX's first computation (gcrsky/runtime.py)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np
from astropy.utils import iers

from gcrsky.checks import matvis as V
from gcrsky.instrument import gaussian_beam, hex_array

DISH_M = 14.0
TARGET = 1e-3


def build_grid(args) -> list[V.MatvisCase]:
    from pyuvdata.analytic_beam import AiryBeam

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no information about the orientation of the feeds"
        uvbeam = V.hera_dipole_power_beam()
    beams = {
        "gaussian": (gaussian_beam(DISH_M), args.nside_gaussian, (100e6, 150e6)),
        "airy": (AiryBeam(diameter=DISH_M), args.nside_airy, (100e6, 150e6)),
        "uvbeam": (uvbeam, args.nside_uvbeam, (100e6, 101e6)),
    }
    layouts = {"hex": hex_array(), "random": V.random_layout(10, 48.0, 14.0, seed=1)}
    sites = {"HERA": V.HERA_SITE, "GBT": V.GREEN_BANK_SITE}
    times = V.observing_times(args.start, args.span_hours, args.ntimes)
    only = set(args.only.split(",")) if args.only else set()
    cases = []
    for bname, (beam, nside, freqs) in beams.items():
        for lname, pos in layouts.items():
            for sname, s in sites.items():
                if only and not only <= {bname, lname, sname}:
                    continue
                cases.append(
                    V.MatvisCase(
                        name=f"{bname}/{lname}/{sname}",
                        beam=beam,
                        positions_enu_m=pos,
                        location=V.site(*s),
                        times=times,
                        freqs_hz=np.asarray(freqs),
                        lmax=args.lmax,
                        nside=nside,
                        flux_jacobian=not args.no_jacobian,
                    )
                )
    return cases


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ntimes", type=int, default=8)
    p.add_argument("--span-hours", type=float, default=9.0)
    p.add_argument("--start", default="2025-03-01T00:00:00", help="first UTC time (ISO)")
    p.add_argument("--lmax", type=int, default=20)
    p.add_argument("--nside-gaussian", type=int, default=128)
    p.add_argument("--nside-airy", type=int, default=512)
    p.add_argument("--nside-uvbeam", type=int, default=256)
    p.add_argument("--only", default="", help="comma-separated filter, e.g. 'airy,hex' or 'GBT'")
    p.add_argument(
        "--no-jacobian",
        action="store_true",
        help="do not apply the aberration solid-angle factor to matvis' fluxes (shows its ~2e-4 effect)",
    )
    p.add_argument("--quick", action="store_true", help="Airy nside 256, UVBeam 128, 6 times (not all rows meet 1e-3)")
    args = p.parse_args(argv)
    if args.quick:
        args.nside_airy, args.nside_uvbeam, args.ntimes = 256, 128, 6

    print(
        f"gcrsky vs matvis, real times: {args.ntimes} times over {args.span_hours} h "
        f"from {args.start} UTC, lmax {args.lmax}"
    )
    print(
        f"python {platform.python_version()}, jax {jax.__version__}, {os.cpu_count()} cpus, "
        f"aberration jacobian {not args.no_jacobian}"
    )
    hdr = (
        f"{'configuration':<22} {'lat':>7} {'nside':>5} {'MHz':>8} {'LST span':>8} {'max|dV| Jy':>10} "
        f"{'rms Jy':>8} {'max/rms':>9} {'worst (f,t,pair,|b|)':>24} {'t_gcrsky':>8} {'t_matvis':>8}"
    )
    t_all = time.perf_counter()
    with iers.conf.set_temp("auto_download", False), iers.conf.set_temp("auto_max_age", None):
        cases = build_grid(args)
        print(hdr)
        print("-" * len(hdr))
        worst_analytic = 0.0
        for case in cases:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = V.compare_with_matvis(case)
            span_h = np.ptp(np.unwrap(r.lsts_rad)) * 12 / np.pi
            f, t, (i, j) = r.worst
            worst = f"{f},{t},({i},{j}),{r.worst_baseline_m:.1f}m"
            mhz = "/".join(f"{x / 1e6:g}" for x in case.freqs_hz)
            flag = "" if r.rel_err < TARGET else " *"
            print(
                f"{case.name:<22} {case.location.lat.deg:>7.2f} {case.nside:>5} {mhz:>8} {span_h:>7.2f}h "
                f"{r.max_abs_err:>10.3e} {r.rms:>8.3f} {r.rel_err:>9.2e} {worst:>24} "
                f"{r.t_gcrsky_s:>7.1f}s {r.t_matvis_s:>7.1f}s{flag}",
                flush=True,
            )
            if not case.name.startswith("uvbeam"):
                worst_analytic = max(worst_analytic, r.rel_err)
    print(f"worst analytic-beam figure {worst_analytic:.2e} (target {TARGET:g}); '*' marks rows above the target")
    print(f"total wall time {time.perf_counter() - t_all:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
