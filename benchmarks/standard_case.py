"""Stage timings of the paper's standard case (DESIGN §7), compile and run separately.

Usage::

    python benchmarks/standard_case.py [--nside 128] [--lmax 20] [--ndraws 200] [--repeat 3]

Stages: sky truth; response at the reference angle (``response_matrix``);
the whole ``standard_case()`` build; the normal-operator set-up
(``precision_matrix``, ``m_block_preconditioner``); the Wiener filter; ``ndraws``
GCR draws by preconditioned CG and by Cholesky.  Jitted stages are compiled
ahead of time (``jax.jit(f).lower(...).compile()``) so compile and run are timed
separately; run times are the best of ``--repeat`` calls, each ended by
``block_until_ready``.  The response build is partly host code (beam
evaluation), so it is timed as first call (with compilation) and second call.
Peak memory is the process's ``ru_maxrss`` after each stage.  Targets (from the
project brief) are printed next to the numbers.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

try:
    import gcrsky  # noqa: F401
except ImportError:  # running from a checkout without an install
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

import gcrsky
from gcrsky.inference import draw, prepare_system, sample_system, wiener_filter_system
from gcrsky.instrument import antpairs, gaussian_beam, hex_array, make_array, response_matrix
from gcrsky.model.system import precision_matrix
from gcrsky.sim.sky import sky_truth
from gcrsky.solvers import CGOptions
from gcrsky.solvers.preconditioners import m_block_preconditioner, nystrom_preconditioner


def maxrss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def timed(fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args, **kwargs))
    return out, time.perf_counter() - t0


def best_of(repeat: int, fn, *args):
    times = []
    out = None
    for _ in range(repeat):
        out, t = timed(fn, *args)
        times.append(t)
    return out, min(times)


def aot(jitted, *args, **static):
    """Lower and compile a jitted function; returns (compiled, lower+compile seconds)."""
    t0 = time.perf_counter()
    compiled = jitted.lower(*args, **static).compile()
    return compiled, time.perf_counter() - t0


class Table:
    def __init__(self):
        self.rows = []

    def add(self, stage, compile_s=None, run_s=None, target="", note=""):
        self.rows.append((stage, compile_s, run_s, maxrss_mib(), target, note))
        c = "-" if compile_s is None else f"{compile_s:.3f}"
        r = "-" if run_s is None else f"{run_s:.3f}"
        print(f"  ... {stage}: compile {c} s, run {r} s", flush=True)

    def show(self):
        head = ("stage", "compile [s]", "run [s]", "maxrss [MiB]", "target", "notes")
        fmt = "{:<34} {:>11} {:>9} {:>12}  {:<22} {}"
        print()
        print(fmt.format(*head))
        print("-" * 118)
        for stage, c, r, mem, target, note in self.rows:
            print(
                fmt.format(
                    stage,
                    "-" if c is None else f"{c:.3f}",
                    "-" if r is None else f"{r:.3f}",
                    f"{mem:.0f}",
                    target,
                    note,
                )
            )


def verdict(value, limit) -> str:
    return f"< {limit:g} s: {'MET' if value < limit else 'MISSED'}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--nside", type=int, default=128, help="HEALPix nside of the response quadrature")
    p.add_argument("--lmax", type=int, default=20, help="maximum degree")
    p.add_argument("--ndraws", type=int, default=200, help="number of GCR draws")
    p.add_argument("--repeat", type=int, default=3, help="timed runs per stage (best is reported)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--preconditioner",
        nargs="+",
        default=None,
        help="CG preconditioner(s) to time, e.g. nystrom mblock (default: the library default)",
    )
    args = p.parse_args(argv)
    pcs = args.preconditioner or [None]

    dev = jax.devices()[0]
    print(
        f"gcrsky {gcrsky.__version__}, jax {jax.__version__}, device {dev.platform}:{dev.device_kind}, "
        f"{platform.processor() or platform.machine()}, python {platform.python_version()}"
    )
    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r} (the CLI and tests add --xla_cpu_multi_thread_eigen=false)")
    print(f"standard case: lmax={args.lmax} (n={(args.lmax + 1) ** 2}), nside={args.nside}, ndraws={args.ndraws}")
    table = Table()

    # 1. sky truth
    freqs = np.array([100e6, 102e6])
    truth, t = timed(lambda: sky_truth(freqs, args.lmax))
    print(f"sky truth: {truth.note}")
    table.add("sky truth", None, t, note=truth.note.split(":")[0][:60])

    # 2. response at the reference angle (host beam evaluation + jitted quadrature)
    array = make_array(hex_array(), gcrsky.instrument.HERA_LATITUDE_DEG, gaussian_beam(14.0))
    pairs = antpairs(10)
    _, t_first = timed(response_matrix, array, pairs, freqs, args.lmax, args.nside)
    _, t_second = best_of(args.repeat, response_matrix, array, pairs, freqs, args.lmax, args.nside)
    table.add(
        f"response (45 bl, nside {args.nside})",
        t_first - t_second,
        t_second,
        verdict(t_first, 20.0) if args.nside == 128 else "",
        f"first call incl. compile {t_first:.2f} s",
    )

    # 3. the whole problem (truth, response + autos, simulated data, prior)
    problem, t = timed(lambda: gcrsky.standard_case(lmax=args.lmax, nside=args.nside, seed=args.seed))
    table.add("standard_case() build (total)", None, t, note="sky + 2 responses + noise + prior")
    system = problem.system()

    # 4. normal operator set-up
    c_pm, tc = aot(precision_matrix, system)
    _, tr = best_of(args.repeat, c_pm, system)
    table.add("precision_matrix (dense P)", tc, tr)
    c_mb, tc = aot(m_block_preconditioner, system)
    _, tr = best_of(args.repeat, c_mb, system)
    table.add("m_block_preconditioner", tc, tr)
    if bool(np.all(np.asarray(system.prior.inv_var) > 0)):
        P = c_pm(system)
        c_ny, tc = aot(nystrom_preconditioner, system, precision=P)
        _, tr = best_of(args.repeat, lambda: c_ny(system, precision=P))
        table.add("nystrom_preconditioner (dense P)", tc, tr, note="default rank")

    key = jax.random.PRNGKey(args.seed + 1)
    # the system tier, jitted whole so that compile and run are timed apart (its static
    # arguments: the path, its options, the number of draws)
    jit_wf = jax.jit(wiener_filter_system, static_argnames=("method", "options", "tol"))
    jit_sample = jax.jit(sample_system, static_argnames=("ndraws", "method", "options", "tol"))
    jit_draw = jax.jit(draw, static_argnames=("ndraws",))
    cg_infos = {}
    for pc in pcs:
        kw = {} if pc is None else {"options": CGOptions(preconditioner=pc)}
        label = "" if pc is None else f", {pc}"
        # 5. Wiener filter (dense P + PCG)
        c_wf, tc = aot(jit_wf, system, **kw)
        (a_wf, winfo), tr = best_of(args.repeat, c_wf, system)
        table.add(
            f"Wiener filter (PCG{label})",
            tc,
            tr,
            note=f"iters {np.asarray(winfo.iterations).tolist()}, err_sigma max {float(np.max(winfo.err_sigma)):.1e}",
        )
        # 6. draws by CG
        c_cg, tc = aot(jit_sample, key, system, ndraws=args.ndraws, method="cg", **kw)
        (draws_cg, info), tr_cg = best_of(args.repeat, c_cg, key, system)
        it = np.asarray(info.draws.iterations)
        conv = bool(np.all(info.draws.converged)) and bool(np.all(info.wiener.converged))
        table.add(
            f"{args.ndraws} draws, CG{label}",
            tc,
            tr_cg,
            verdict(tr_cg, 10.0),
            f"iters mean {it.mean():.1f} max {it.max()} (wiener {np.asarray(info['wiener'].iterations).tolist()}), "
            f"err_sigma max {float(np.max(info['draws'].err_sigma)):.1e}, all converged: {conv}",
        )
        cg_infos[pc or "default"] = info
    c_ch, tc = aot(jit_sample, key, system, ndraws=args.ndraws, method="cholesky")
    (draws_ch, info_ch), tr_ch = best_of(args.repeat, c_ch, key, system)
    table.add(f"{args.ndraws} draws, Cholesky", tc, tr_ch, verdict(tr_ch, 1.0))
    # 7. set up once, then draws only (what a notebook drawing thousands does)
    for method in ("cg", "cholesky"):
        prepared = jax.block_until_ready(prepare_system(system, method=method))
        c_d, tc = aot(jit_draw, key, prepared, ndraws=args.ndraws)
        _, tr = best_of(args.repeat, c_d, key, prepared)
        table.add(f"{args.ndraws} draws, {method}, after prepare", tc, tr, note="gcrsky.draw(key, prepared, n)")

    table.show()
    print()
    # a sanity check that the samplers describe the same posterior
    sd = np.sqrt(np.diagonal(np.linalg.inv(np.asarray(c_pm(system))), axis1=1, axis2=2))
    for name, info in cg_infos.items():
        diff = np.abs(np.asarray(info.a_wf) - np.asarray(info_ch.a_wf))
        err = np.asarray(info.draws.err_sigma)
        print(
            f"CG ({name}) vs Cholesky Wiener filter: max |diff| / posterior sigma = {np.max(diff / sd):.2e} "
            f"(max |diff| {diff.max():.2e} K); draws err_sigma median {np.median(err):.1e}, max {err.max():.1e} "
            f"(tol {gcrsky.solvers.options.DEFAULT_TOL:g})"
        )
    print(f"peak memory (ru_maxrss): {maxrss_mib():.0f} MiB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
