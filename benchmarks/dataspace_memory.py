"""The data-space set-up's peak memory and time against the planner's estimate, per chunk size.

For simulated drift scans of the kind the automatic band limit picks (a 14.6 m hexagon, 2 h, 2
channels at 119.5 and 120.5 MHz, 14 m Gaussian beam, the real frame at 2025-03-21, every
baseline), each (case, times per chunk, Y materialised or not) runs in its own process:
:func:`gcrsky.solvers.dataspace.prepare_dataspace` on the problem's system, and prints

* ``estimate``: :func:`gcrsky.solvers.dataspace.dataspace_memory_bytes` (what the planner and the
  memory check use, 1 draw);
* ``xla``: the compiled set-up's temporaries plus outputs (XLA's ``memory_analysis``);
* ``peak``: the process's peak resident memory while the compiled set-up runs, minus before it
  (``ru_maxrss``; the compilation, which precedes it, is not counted);
* ``time``: the set-up's wall seconds (compilation included, a fresh process each);
* ``chosen``: the chunk :func:`gcrsky.solvers.dataspace.choose_time_chunk` picks on this machine.

The estimate bounds the process's peak at the sizes that matter (lmax 100 and 185 below) and XLA's
analysis everywhere; at the small case the process's fixed cost of running a compiled program
(0.1-0.2 GB: thread pools, code, allocator arenas, not counted for any path) shows above it.
Measured (2026-12-03, this shared 2-core CPU; times under load)::

    case      Nf,Nt,Nbl      n chunk   Y  estimate      xla     peak  time s
    small       2,20,21   3721     1   y      0.24     0.15     0.30     5.5
    small       2,20,21   3721     8   y      0.63     0.33     0.62     3.7
    small       2,20,21   3721     1   n      0.20     0.12     0.42    46.1
    small       2,20,21   3721     8   n      0.99     0.46     0.97    12.6
    mid        2,20,171  10201     1   y      6.58     3.78     4.35    68.9
    mid        2,20,171  10201     2   y      7.79     3.78     5.09    85.5
    mid        2,20,171  10201     4   y     10.20     4.48     8.13    75.4
    mid        2,20,171  10201     8   y     15.03     7.26    12.55    94.3
    mid        2,20,171  10201     1   n                                > 13 min (stopped)
    mid        2,20,171  10201     4   n     12.80     5.70     9.64   403.4
    issue      2,20,171  34596     1   y     15.39     8.42    12.90   401.8

After the Wigner blocks were stored by degree band and the rotations made real (2026-12-03 afternoon, same
machine, the docs build of a fresh clone alongside), the estimate still bounds the peak, which fell::

    small       2,20,21   3721     1   y      0.21     0.11     0.15    16.7
    small       2,20,21   3721     8   y      0.61     0.29     0.37    18.1
    small       2,20,21   3721     1   n      0.17     0.08     0.10    36.4
    small       2,20,21   3721     8   n      0.97     0.35     0.45    22.8
    mid        2,20,171  10201     1   y      6.49     3.57     3.84   102.3
    mid        2,20,171  10201     8   y     14.93     7.04     7.87    80.5

With Y materialised the chunk changes only the memory (69-94 s at lmax 100 whatever the chunk), so
the set-up takes 1 time at once; without it every pair of chunks forms its rows again (46 s at
1 time against 13 s at 8 in the small case, and > 13 min at 1 time in the mid one), so it takes
the largest chunk that fits.  The issue's case under ``method="auto"`` (``gcrsky.prepare`` then
200 draws): data space, 1 time at once, Y materialised, set-up 330 s, 200 draws 10 s, process
peak 15.2 GB (2.2 GB before the set-up).

Run: ``PYTHONPATH=. .venv/bin/python benchmarks/dataspace_memory.py [--cases small,mid,issue]``
(the ``issue`` case, lmax 185 x 171 baselines x 20 times, needs ~12 GB at its largest chunk here).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CASES = {  # name: (lmax, hexagon rows, times, chunks with Y materialised, chunks without)
    "small": (60, (2, 3, 2), 20, (1, 2, 4, 8), (1, 2, 4, 8)),
    "mid": (100, (3, 4, 5, 4, 3), 20, (1, 2, 4, 8), (4,)),  # without Y at 1 time: > 13 min (210 chunk pairs)
    "issue": (185, (3, 4, 5, 4, 3), 20, (1,), ()),
}

CHILD = r"""
import json, resource, sys, time
from gcrsky.parallel import use_safe_cpu_threading
use_safe_cpu_threading()
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
from gcrsky.base.memory import available_memory_bytes
from gcrsky.sim.config import Config
from gcrsky.sim.standard import problem_from_config
from gcrsky.solvers.dataspace import _prepare_dataspace, choose_time_chunk, dataspace_memory_bytes, lag_structure
from gcrsky.solvers.options import DataSpaceOptions
lmax, rows, nt, chunk, mat = json.loads(sys.argv[1])
cfg = Config(lmax=lmax, nside=128 if lmax > 64 else 64, dish_diameter=14.0, freqs_hz=(119.5e6, 120.5e6), n_lst=nt,
             lst_range_hours=(0.0, 2.0), rows=tuple(rows), obs_date="2025-03-21")
system = problem_from_config(cfg).system()
opts = DataSpaceOptions(time_chunk=chunk, materialize=mat)
lags = lag_structure(system)
t0 = time.perf_counter()
compiled = _prepare_dataspace.lower(system, opts, lags, mat).compile()
ma = compiled.memory_analysis()
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0
state = jax.block_until_ready(compiled(system, lags))
seconds = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0 - before
auto = DataSpaceOptions()
print(json.dumps({"shape": list(system.data.shape), "n": int(system.prior.mean.shape[-1]),
                  "estimate": dataspace_memory_bytes(system, 1, mat, chunk),
                  "xla": float(ma.temp_size_in_bytes + ma.output_size_in_bytes), "peak": peak, "seconds": seconds,
                  "chosen": choose_time_chunk(system, auto, available_memory_bytes()),
                  "wiener_rms": float(np.sqrt(np.mean(np.asarray(state.a_wf) ** 2)))}))
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="small,mid", help="comma-separated: " + ", ".join(CASES))
    args = ap.parse_args(argv)
    print(f"{'case':6s} {'Nf,Nt,Nbl':>12s} {'n':>6s} {'chunk':>5s} {'Y':>3s} {'estimate':>9s} {'xla':>8s} "
          f"{'peak':>8s} {'time s':>7s} {'chosen':>6s}  (GB)")
    for name in args.cases.split(","):
        lmax, rows, nt, *chunk_lists = CASES[name]
        for mat, chunks in zip((True, False), chunk_lists):
            for c in chunks:
                p = subprocess.run([sys.executable, "-c", CHILD, json.dumps([lmax, rows, nt, c, mat])],
                                   capture_output=True, text=True)
                if p.returncode != 0:
                    print(f"{name:6s} chunk {c} Y {mat}: failed ({p.returncode}): {p.stderr.strip()[-300:]}")
                    continue
                r = json.loads(p.stdout.strip().splitlines()[-1])
                print(f"{name:6s} {','.join(map(str, r['shape'])):>12s} {r['n']:>6d} {c:>5d} {'y' if mat else 'n':>3s} "
                      f"{r['estimate'] / 1e9:>9.2f} {r['xla'] / 1e9:>8.2f} {r['peak'] / 1e9:>8.2f} {r['seconds']:>7.1f} "
                      f"{r['chosen']:>6d}", flush=True)


if __name__ == "__main__":
    main()
