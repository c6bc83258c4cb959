"""Scaling benchmark (issue 5 item 4): response build, set-up and draw cost of each sampler path.

Usage::

    python benchmarks/scale.py              # default grid (~15 min on 2 cores)
    python benchmarks/scale.py --quick      # tiny grid (< 2 min)
    python benchmarks/scale.py --only l100-a37-t240-24h-f2
    python benchmarks/scale.py --one CONFIG --json   # one configuration (used internally)

Every configuration runs in its own subprocess so ``ru_maxrss`` is that configuration's
peak resident memory.  A configuration is named ``l{lmax}-a{nants}-t{nlst}-{hours}h-f{nfreq}``:
hexagonal array of 10 / 37 / 91 antennas (rows 3-4-3, 4..7..4, 6..11..6; 14.6 m), a
Gaussian 14 m dish beam, ``nlst`` equally spaced LSTs over ``hours`` (24 h: full day,
endpoint excluded, so the m-mode path applies when Nt > 2 lmax), ``nfreq`` channels
from 100 MHz in 2 MHz steps.  The truth is a draw from an isotropic prior
``C_l = 100 K^2 / (1 + l)^2`` (also the prior used for inference), the noise a fixed
per-component sigma, 10% of the rms model visibility (constant in time and baseline,
so the noise is time-stationary): nothing depends on a sky model.

Response: ``gcrsky.instrument.response_matrix`` (ring-factored quadrature, beam floor
1e-16); nside 64 for lmax <= 50, 128 for lmax 100, 256 for lmax 200.  The response
column includes the autos' response.  ``auto`` is the path ``method="auto"`` picks
(:func:`gcrsky.solvers.plan_sampler`).

Sampler paths (``gcrsky.prepare`` + ``gcrsky.draw`` unless noted):

* ``chol``:  dense P + Cholesky;
* ``cgD-ny`` / ``cgD-mb``: CG on the dense P, Nystrom / m-block preconditioner;
* ``cgMF-ny``: matrix-free CG, Nystrom preconditioner;
* ``mmode``: ``gcrsky.solvers.prepare_mmode`` / ``draw_mmode`` (exact; needs uniform
  full-day coverage with Nt > 2 lmax and time-stationary noise, else 'n/a' with the
  reason ``mmode_check`` gives).

For each: compile time (``jit(...).lower(...).compile()``, AOT, so it never runs the
computation twice), set-up run time, time per draw (``ndraws`` draws in one call /
``ndraws``), and for CG the iterations of the Wiener solve (mean over channels) and the
mean iterations per draw.  ``it_noPC`` is plain CG (identity preconditioner,
``gcrsky.solvers.pcg`` on the dense P of channel 0, started at 0 like the Wiener solve)
run until its residual ``||b - P x||`` reaches the relative residual the m-block CG
Wiener solve achieved (the same tolerance in residual terms), capped at 20000
('capped').  ``P_MB`` is the size of one dense P (all channels) where formed.
A path is skipped ('skip') when its estimated cost exceeds the per-configuration
budget (dense P: 8 Nf Nt Nbl n^2 flops > 4e11, or P > 3 GB; matrix-free CG: the
matvecs for set-up + draws > ~6e11 flops); the reason is printed.

Measured (2026-11-22, this repository's machine: 2 shared x86 cores, 24 GB, CPU JAX float64,
gcrsky safe threading; load 2-4 from other jobs, so times are ~2x the quiet machine's),
default grid, 1226 s wall (the first two rows re-run after the Cholesky sampler started
drawing with a precomputed ``L^-T``).  Path cell: setup compile s + setup run s / time
per draw [CG iterations: Wiener, mean per draw]; resp_s includes the autos; prob_s =
simulate data + assemble the problem; ``auto`` is what ``method="auto"`` picks; skips are
explained in the run output (dense P or matrix-free CG over budget; mmode n/a when
coverage is not a uniform full day with Nt > 2 lmax).  it_noPC on the 24 h rows targets
the m-block solve's ~1e-16 relative residual (m-blocks are exact there), i.e. machine
precision: not meaningful ('nc': not reached).

::

    config               n      Nbl  resp_s  prob_s  P_MB    peak_MB  auto     it_noPC   chol                          cgD-ny                        cgD-mb                        cgMF-ny                       mmode
    l20-a10-t10-8h-f1    441    45      2.0     1.2  1.6     739      cholesky 909       1.9+0.3/0.153ms               3.0+0.9/2.03ms [1,1]          3.3+0.1/8.14ms [179,195]      3.3+2.5/2.86ms [1,1]          skip
    l20-a10-t240-24h-f1  441    45      1.9     1.1  1.6     1089     mmode    2192(nc)  1.8+1.4/0.146ms               2.9+1.3/11ms [8,8]            2.2+1.7/8.55ms [2,1]          3.5+3.0/77.5ms [8,8]          1.4+0.0/0.126ms
    l20-a37-t10-8h-f1    441    666     3.3     1.5  1.6     808      cholesky 1716      4.5+1.4/0.327ms               8.4+1.8/4.34ms [2,2]          3.1+1.1/18.8ms [370,389]      6.0+3.2/29.3ms [2,2]          skip
    l20-a37-t240-24h-f1  441    666     6.7     4.8  1.6     851      mmode    4883(nc)  6.7+33.1/0.169ms              8.2+20.6/41.4ms [26,23]       3.2+27.3/45ms [2,2]           skip                          4.0+0.3/0.36ms
    l20-a91-t10-8h-f1    441    4095    9.7     2.7  1.6     1039     cholesky 3013      3.8+6.3/0.284ms               6.3+5.8/17.2ms [2,2]          8.3+16.0/141ms [683,707]      13.7+5.7/140ms [2,2]          skip
    l20-a91-t240-24h-f1  441    4095    7.8     3.5  1.6     930      mmode    n/a (no dense P) skip                          skip                          skip                          skip                          6.1+2.9/0.15ms
    l50-a10-t10-8h-f1    2601   45      4.3     2.1  54.1    962      cholesky 3039      5.0+5.5/6.4ms                 5.7+6.3/22.3ms [34,33]        2.0+2.8/394ms [400,441]       3.3+0.6/51.7ms [34,33]        skip
    l50-a10-t60-8h-f1    2601   45      3.6     1.8  54.1    1338     cholesky 6659      3.6+14.8/9.28ms               6.3+19.4/65.6ms [90,83]       2.6+11.7/729ms [658,738]      5.6+7.2/834ms [90,83]         skip
    l50-a10-t240-24h-f1  2601   45      2.7     1.7  54.1    614      mmode    n/a (no dense P) skip                          skip                          skip                          skip                          1.8+0.1/0.802ms
    l50-a37-t10-8h-f1    2601   666     4.6     1.8  54.1    1115     cholesky 8031      2.3+25.0/7.95ms               6.3+25.5/71.1ms [114,105]     2.7+21.0/2.97e+03ms [1247,1336]  2.1+2.3/1.05e+03ms [110,103]  skip
    l50-a37-t240-24h-f1  2601   666     5.5     1.7  54.1    978      mmode    n/a (no dense P) skip                          skip                          skip                          skip                          2.2+1.2/0.644ms
    l100-a37-t240-24h-f2 10201  666    30.4     4.9  1665.0  3307     mmode    n/a (no dense P) skip                          skip                          skip                          skip                          2.8+13.2/2.5ms
    l200-a37-t480-24h-f1 40401  666    80.7    13.1  13057.9 5351     mmode    n/a (no dense P) skip                          skip                          skip                          skip                          2.6+60.0/14.7ms

Headline (l100-a37-t240-24h-f2, ring response, m-mode path): response 30.4 s, set-up
13.2 s (+2.8 s compile), 200 draws 0.50 s, peak 3.3 GB (targets: < 5 min, < 5 min,
< 12 GB).  lmax 200 (37 antennas, 480 LSTs): response 81 s, set-up 60 s, 200 draws 2.95 s,
peak 5.4 GB.  Partial coverage at lmax 50 (8 h): no-preconditioner / m-block Wiener
iterations = 3039/400 (7.6x, 10 LSTs, 10 ants), 6659/658 (10.1x, 60 LSTs, 10 ants),
8031/1247 (6.4x, 10 LSTs, 37 ants); the prior-whitened Nystrom preconditioner needs
34 / 90 / 114 (89x, 74x, 70x).  Why m-blocks stop near 10x there: m-modes are global in
RA, 8 h of coverage is local, so the block diagonal credits the unobserved RA range
with the data's information; the m-block-preconditioned operator of the first case has
201 of 2601 eigenvalues below 0.1 (smallest 1.2e-3, i.e. ~1/SNR) -- grouping 2-8
consecutive m per block does not help (300-500 iterations).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

ROWS = {10: (3, 4, 3), 37: (4, 5, 6, 7, 6, 5, 4), 91: (6, 7, 8, 9, 10, 11, 10, 9, 8, 7, 6)}

# (lmax, nants, nlst, hours, nfreq, ndraws)
DEFAULT_GRID = [
    (20, 10, 10, 8, 1, 20),
    (20, 10, 240, 24, 1, 20),
    (20, 37, 10, 8, 1, 20),
    (20, 37, 240, 24, 1, 20),
    (20, 91, 10, 8, 1, 20),
    (20, 91, 240, 24, 1, 20),
    (50, 10, 10, 8, 1, 20),
    (50, 10, 60, 8, 1, 20),  # target (b): partial coverage at lmax 50
    (50, 10, 240, 24, 1, 20),
    (50, 37, 10, 8, 1, 20),
    (50, 37, 240, 24, 1, 20),
    (100, 37, 240, 24, 2, 200),  # the headline
    (200, 37, 480, 24, 1, 200),  # lmax 200 "if it fits"
]
QUICK_GRID = [(20, 10, 10, 8, 1, 5), (20, 10, 48, 24, 1, 5)]

DENSE_FLOP_MAX = 4e11
DENSE_BYTES_MAX = 3e9
MF_FLOP_MAX = 6e11
NOPC_CAP = 20000


def name_of(c) -> str:
    lmax, na, nt, h, nf, nd = c
    return f"l{lmax}-a{na}-t{nt}-{h}h-f{nf}"


def parse_name(s: str, grid):
    for c in grid + DEFAULT_GRID + QUICK_GRID:
        if name_of(c) == s:
            return c
    lm, a, t, h, f = s.split("-")
    lmax = int(lm[1:])
    return (lmax, int(a[1:]), int(t[1:]), int(h[:-1]), int(f[1:]), 200 if lmax >= 100 else 20)


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KB


# ---------------------------------------------------------------- one configuration


def run_one(c) -> dict:
    from gcrsky.parallel import use_safe_cpu_threading

    use_safe_cpu_threading()
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import gcrsky
    from gcrsky.inference import draw, prepare_sampler
    from gcrsky.instrument import HERA_LATITUDE_DEG, antpairs, gaussian_beam, hex_array, make_array, response_matrix
    from gcrsky.model import build_problem, isotropic_prior
    from gcrsky.solvers import CGOptions, draw_mmode, mmode_check, pcg, plan_sampler
    from gcrsky.solvers.mmode import _prepare as _prep_mm
    from gcrsky.sphere import n_params

    lmax, nants, nt, hours, nf, ndraws = c
    out = {"name": name_of(c), "lmax": lmax, "nants": nants, "nlst": nt, "hours": hours, "nfreq": nf,
           "ndraws": ndraws, "paths": {}, "notes": []}
    nside = 64 if lmax <= 50 else (128 if lmax <= 100 else 256)
    n = n_params(lmax)
    nbl = nants * (nants - 1) // 2
    out.update(n=n, nbl=nbl, nside=nside)
    freqs = 100e6 + 2e6 * np.arange(nf)
    arr = make_array(hex_array(ROWS[nants], 14.6), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    pairs = antpairs(nants)
    autop = np.stack([np.arange(nants)] * 2, 1)

    t0 = time.perf_counter()
    out["response"] = "rings"
    resp = response_matrix(arr, pairs, freqs, lmax, nside).block_until_ready()
    auto = response_matrix(arr, autop, freqs, lmax, nside).block_until_ready()
    out["t_response"] = time.perf_counter() - t0

    # synthetic truth, prior, fixed sigma
    t0 = time.perf_counter()
    ell = np.arange(lmax + 1)
    cl = np.tile(100.0 / (1.0 + ell) ** 2, (nf, 1))
    prior = isotropic_prior(cl, n)
    std = 1.0 / np.sqrt(np.asarray(prior.inv_var))
    a_true = std * np.random.default_rng(1).standard_normal((nf, n))
    R = np.asarray(resp)
    vrms = np.sqrt(np.mean(np.einsum("fbk,fk->fb", np.abs(R) ** 2, std**2)))  # rms |V| under the prior
    sigma = 0.1 * vrms / np.sqrt(2.0)
    del R
    if hours >= 24:
        lsts = np.arange(nt) * (2 * np.pi / nt)
    else:
        lsts = np.linspace(0.0, hours * 2 * np.pi / 24.0, nt)
    prob = build_problem(arr, freqs, lsts, lmax, nside, a_true=a_true, sigma=sigma, prior=prior,
                         responses=(resp, auto), key=jax.random.PRNGKey(3))
    system = prob.system()
    jax.block_until_ready(system.data)
    out["t_problem"] = time.perf_counter() - t0
    out["auto"] = plan_sampler(system, ndraws=ndraws).method
    key = jax.random.PRNGKey(7)

    jit_prepare = jax.jit(prepare_sampler, static_argnames=("method", "options", "tol"))
    jit_draw = jax.jit(draw, static_argnames=("ndraws",))

    def timed(jitted, args, static, dyn_kw=None):
        """AOT compile (timed), then one timed run."""
        dyn_kw = dyn_kw or {}
        t0 = time.perf_counter()
        comp = jitted.lower(*args, **static, **dyn_kw).compile()
        tc = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = jax.block_until_ready(comp(*args, **dyn_kw))
        return res, tc, time.perf_counter() - t0

    dense_flops = 8.0 * nf * nt * nbl * n * n
    dense_bytes = 8.0 * nf * n * n
    mv_flops = 16.0 * nf * nt * nbl * n
    dense_ok = dense_flops <= DENSE_FLOP_MAX and dense_bytes <= DENSE_BYTES_MAX
    dense_why = (f"dense P ~{dense_flops:.1e} flop, {dense_bytes / 1e9:.2f} GB "
                 f"(limits {DENSE_FLOP_MAX:.0e} flop, {DENSE_BYTES_MAX / 1e9:.0f} GB)")
    out["P_MB"] = dense_bytes / 1e6

    paths = [("chol", dict(method="cholesky")),
             ("cgD-ny", dict(options=CGOptions(dense=True, preconditioner="nystrom"))),
             ("cgD-mb", dict(options=CGOptions(dense=True, preconditioner="mblock"))),
             ("cgMF-ny", dict(options=CGOptions(dense=False, preconditioner="nystrom")))]
    rel_mb = None
    for pname, static in paths:
        rec = {}
        if static.get("method") == "cholesky" or static["options"].dense:
            if not dense_ok:
                out["paths"][pname] = {"skip": dense_why}
                continue
        else:
            est = mv_flops * (128 + 2 * 40 + ndraws * 2 * 40)
            if est > MF_FLOP_MAX:
                out["paths"][pname] = {"skip": f"matrix-free CG ~{est:.1e} flop (~{mv_flops:.1e}/matvec) > {MF_FLOP_MAX:.0e}"}
                continue
        prep, tc, tr = timed(jit_prepare, (system,), static)
        rec.update(setup_compile=tc, setup=tr)
        (dr, info), tc2, tr2 = timed(jit_draw, (key, prep), dict(ndraws=ndraws))
        rec.update(draw_compile=tc2, draw_total=tr2, per_draw=tr2 / ndraws)
        rec["ok"] = bool(np.all(np.asarray(info["draws"].converged)) and np.all(np.asarray(prep.wiener.converged)))
        if prep.method == "cg":
            rec["it_wiener"] = float(np.mean(np.asarray(prep.wiener.iterations)))
            rec["it_draw"] = float(np.mean(np.asarray(info["draws"].iterations)))
            if pname == "cgD-mb":
                rel_mb = float(np.asarray(prep.wiener.rel_residual)[0])
                P0 = prep.precision[0]
                b0 = gcrsky.model.wiener_rhs(system)[0]
                tol = rel_mb * float(jnp.linalg.norm(b0))
                f = jax.jit(lambda P, b, tol: pcg(lambda x: P @ x, lambda r: r, b, jnp.zeros_like(b), tol=tol,
                                                  maxiter=NOPC_CAP)[1])
                t0 = time.perf_counter()
                inf0 = jax.block_until_ready(f(P0, b0, tol))
                k = int(inf0.iterations)
                conv = bool(inf0.converged)
                out["it_noPC"] = "capped" if (k >= NOPC_CAP and not conv) else (k if conv else f"{k}(nc)")
                out["it_noPC_s"] = time.perf_counter() - t0
                out["rel_target"] = rel_mb
        out["paths"][pname] = rec
        del prep, dr, info
    if "it_noPC" not in out:
        out["it_noPC"] = "n/a (no dense P)"

    chk = mmode_check(system)
    if not chk.ok:
        out["paths"]["mmode"] = {"skip": "n/a: " + chk.reason}
    else:
        prep, tc, tr = timed(_prep_mm, (system,), {})
        rec = dict(setup_compile=tc, setup=tr)
        (dr, info), tc2, tr2 = timed(draw_mmode, (key, prep), dict(ndraws=ndraws))
        rec.update(draw_compile=tc2, draw_total=tr2, per_draw=tr2 / ndraws)
        rec["ok"] = bool(np.all(np.asarray(info["draws"].converged)))
        rec["wiener_rel_resid"] = float(np.max(np.asarray(prep.wiener.rel_residual)))
        out["paths"]["mmode"] = rec
        del prep, dr, info
    out["peak_MB"] = peak_mb()
    return out


# ---------------------------------------------------------------- driver and table


def fmt_path(r) -> str:
    if r is None:
        return "-"
    if "skip" in r:
        return "skip"
    s = f"{r['setup_compile']:.1f}+{r['setup']:.1f}/{r['per_draw'] * 1e3:.3g}ms"
    if "it_wiener" in r:
        s += f" [{r['it_wiener']:.0f},{r['it_draw']:.0f}]"
    if not r.get("ok", True):
        s += "!"
    return s


PATHS = ["chol", "cgD-ny", "cgD-mb", "cgMF-ny", "mmode"]


def print_table(results) -> None:
    print()
    print("config               n      Nbl  resp_s  prob_s  P_MB    peak_MB  auto     it_noPC   "
          + "  ".join(f"{p:<28}" for p in PATHS))
    for r in results:
        if "error" in r:
            print(f"{r['name']:<20} FAILED: {r['error']}")
            continue
        cols = "  ".join(f"{fmt_path(r['paths'].get(p)):<28}" for p in PATHS)
        print(f"{r['name']:<20} {r['n']:<6} {r['nbl']:<4} {r['t_response']:>6.1f}  {r['t_problem']:>6.1f}  "
              f"{r['P_MB']:<7.1f} {r['peak_MB']:<8.0f} {r.get('auto', '?'):<8} {str(r['it_noPC']):<9} {cols}")
    print("\npath cell: setup compile s + setup run s / time per draw (ms) [CG iters: Wiener, per draw]; "
          "'!' = a solve did not converge")
    notes = []
    for r in results:
        for p, v in r.get("paths", {}).items():
            if v and "skip" in v:
                notes.append(f"  {r['name']} {p}: skipped ({v['skip']})")
        if "rel_target" in r:
            notes.append(f"  {r['name']}: no-PC CG target rel. residual {r['rel_target']:.2e} "
                         f"(m-block Wiener solve), {r['it_noPC_s']:.1f} s")
        if "mmode" in r.get("paths", {}) and "skip" not in r["paths"]["mmode"]:
            m = r["paths"]["mmode"]
            notes.append(f"  {r['name']} mmode: {r['ndraws']} draws in {m['draw_total']:.2f} s "
                         f"(+{m['draw_compile']:.1f} s compile), Wiener rel. residual {m['wiener_rel_resid']:.1e}")
    print("\n".join(notes))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny grid (< 2 min)")
    ap.add_argument("--only", nargs="+", help="configuration names (see --list)")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--one", help="run one configuration in this process")
    ap.add_argument("--json", action="store_true", help="with --one: print the result as JSON")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per configuration")
    a = ap.parse_args(argv)
    grid = QUICK_GRID if a.quick else DEFAULT_GRID
    if a.list:
        print("\n".join(name_of(c) for c in grid))
        return 0
    if a.one:
        res = run_one(parse_name(a.one, grid))
        print("JSON:" + json.dumps(res) if a.json else res)
        return 0
    if a.only:
        grid = [parse_name(s, grid) for s in a.only]
    results = []
    t_all = time.perf_counter()
    for c in grid:
        nm = name_of(c)
        t0 = time.perf_counter()
        try:
            p = subprocess.run([sys.executable, os.path.abspath(__file__), "--one", nm, "--json"],
                               capture_output=True, text=True, timeout=a.timeout)
            line = [s for s in p.stdout.splitlines() if s.startswith("JSON:")]
            if p.returncode != 0 or not line:
                res = {"name": nm, "error": (p.stderr.strip().splitlines() or ["?"])[-1]}
            else:
                res = json.loads(line[-1][5:])
        except subprocess.TimeoutExpired:
            res = {"name": nm, "error": f"skipped (exceeded {a.timeout:.0f} s)"}
        res["wall"] = time.perf_counter() - t0
        print(f"{nm}: {res['wall']:.1f} s wall" + (f"  ({res['error']})" if "error" in res else ""), flush=True)
        results.append(res)
    print_table(results)
    print(f"\ntotal {time.perf_counter() - t_all:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
