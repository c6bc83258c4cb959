"""CG iterations with the window preconditioner against coverage and lmax (issue 24 item 2).

Usage::

    .venv/bin/python benchmarks/window_pc.py                      # lmax 16 32 64, 2..20 h
    .venv/bin/python benchmarks/window_pc.py --lmax 16 --hours 8 16

Problem: the 37-antenna hexagon (14.6 m spacing, 14 m Gaussian dishes; 63 unique
baselines), 100 MHz, isotropic prior ``C_l = 100 / (1 + l)^2``, noise for an SNR of
~10 per visibility, 6 LSTs per hour (10 min) over the first ``hours`` of the day,
nside 64 (128 above lmax 64).  The right-hand side is a GCR fluctuation
(``fluctuation_rhs``: b ~ N(0, P), so the solution has unit posterior-sigma scale),
solved from 0 with CG on the dense P.

Every column stops on the same *rigorous* criterion, ``sqrt(r^T S r) <= 1e-6``
(``P >= S^-1`` so it bounds the error's P-norm, in posterior sigma; the window
preconditioner's stop in gcrsky), counted over both passes of the residual restart;
``nys(M)`` is Nystrom with its own (also rigorous, tighter) stop
``sqrt(r^T M^-1 r)``.  Columns: ``none`` (M = I), ``prior`` (M = S^-1), ``mblock``,
``nys`` (Nystrom, sketch 128, from the dense P), ``win B`` (window, bandwidth B).
``>N``: not converged within maxiter; ``-``: not run (``--skip none``).  ``build`` / ``MiB``: the window
preconditioner at B = 8, seconds (after compilation) and its stored factor
(``window_memory_bytes(...)["peak"]`` the estimated build peak in brackets).

Measured
--------
(filled in below from the run)
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from gcrsky.instrument import (  # noqa: E402
    HERA_LATITUDE_DEG,
    gaussian_beam,
    groups_for_array,
    hex_array,
    make_array,
    unique_response,
)
from gcrsky.model import LinearSystem, VisOperator, fluctuation_rhs, isotropic_prior, precision_matrix  # noqa: E402
from gcrsky.solvers import auto_bandwidth, make_preconditioner, pcg  # noqa: E402
from gcrsky.solvers.preconditioners import precondition_one, stop_norm  # noqa: E402
from gcrsky.solvers.window import window_memory_bytes  # noqa: E402
from gcrsky.sphere import n_params  # noqa: E402

TOL = 1e-6
BANDS = (2, 4, 8)


def make_system(lmax: int, hours: float, per_hour: int = 6, snr: float = 10.0) -> LinearSystem:
    """The 37-antenna problem above; (LinearSystem, 1 channel)."""
    arr = make_array(hex_array((4, 5, 6, 7, 6, 5, 4), 14.6), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    g = groups_for_array(arr)
    R = unique_response(arr, g, np.array([100e6]), lmax, 64 if lmax <= 64 else 128)
    nt = max(4, round(per_hour * hours))
    lsts = np.linspace(0, hours * 2 * np.pi / 24, nt)
    cl = 100.0 / (1.0 + np.arange(lmax + 1)) ** 2
    prior = isotropic_prior(cl[None], n_params(lmax))
    std = 1 / np.sqrt(np.asarray(prior.inv_var))
    counts = np.asarray(g.counts, float)
    p = np.einsum("fbk,fk->fb", np.abs(np.asarray(R)) ** 2, std**2)
    sigma = np.sqrt(np.average(p, axis=1, weights=counts).mean()) / snr / np.sqrt(2)
    iv = jnp.broadcast_to(jnp.asarray(counts / sigma**2), (1, nt, len(counts)))
    return LinearSystem(VisOperator(R, jnp.asarray(lsts)), jnp.zeros((1, nt, len(counts)), complex), iv, prior)


def count(P, prec, b, stop, maxiter):
    """Iterations of gcrsky's pcg to TOL (both passes); -1 if it did not converge."""
    run = jax.jit(lambda b: pcg(lambda x: P @ x, prec, b, jnp.zeros_like(b), tol=TOL, maxiter=maxiter, stop=stop))
    _, info = run(b)
    return int(info.iterations) if bool(info.converged) else -1


def row(lmax: int, hours: float, maxiter: int, skip=()):
    s = make_system(lmax, hours)
    P = precision_matrix(s)
    b = fluctuation_rhs(jax.random.PRNGKey(0), s)[0]
    svar = 1.0 / s.prior.inv_var[0]
    sstop = lambda r: jnp.vdot(r, svar * r)  # noqa: E731
    out = {"none": None if "none" in skip else count(P[0], lambda r: r, b, sstop, maxiter),
           "prior": count(P[0], lambda r: svar * r, b, sstop, maxiter)}
    mb = make_preconditioner(s, "mblock")
    out["mblock"] = count(P[0], lambda r: precondition_one(mb, 0, r), b, sstop, maxiter)
    ny = make_preconditioner(s, "nystrom", P, 128)
    out["nys"] = count(P[0], lambda r: precondition_one(ny, 0, r), b, sstop, maxiter)
    out["nys(M)"] = count(P[0], lambda r: precondition_one(ny, 0, r), b, None, maxiter)
    for B in BANDS:
        t0 = time.perf_counter()
        pc = jax.block_until_ready(make_preconditioner(s, "window", bandwidth=B))
        if B == BANDS[-1]:
            t0 = time.perf_counter()  # the second build: without compilation
            pc = jax.block_until_ready(make_preconditioner(s, "window", bandwidth=B))
            out["build"] = time.perf_counter() - t0
            out["MiB"] = (pc.chol.nbytes + pc.low.nbytes) / 2**20
            out["peakMiB"] = window_memory_bytes(lmax, B, s.op.response.shape[1])["peak"] / 2**20
        out[f"win{B}"] = count(P[0], lambda r, pc=pc: precondition_one(pc, 0, r), b, stop_norm(pc, 0), maxiter)
    out["auto"] = auto_bandwidth(s.op.angles, s.inv_noise, lmax)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lmax", type=int, nargs="+", default=[16, 32, 64])
    ap.add_argument("--hours", type=float, nargs="+", default=[2, 4, 8, 12, 16, 20])
    ap.add_argument("--maxiter", type=int, default=3000)
    ap.add_argument("--skip", nargs="*", default=[], help="columns not run (only 'none' is skippable)")
    a = ap.parse_args(argv)
    cols = ["none", "prior", "mblock", "nys", "nys(M)"] + [f"win{B}" for B in BANDS]
    with open("/proc/loadavg") as fh:
        print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "loadavg", fh.read().strip())
    print(f"{'lmax':>4} {'hours':>5} " + " ".join(f"{c:>7}" for c in cols) + "  auto  build[s]  MiB (peak est.)")
    for lmax in a.lmax:
        for h in a.hours:
            t0 = time.perf_counter()
            o = row(lmax, h, a.maxiter, a.skip)
            fmt = lambda v: "-" if v is None else str(v) if v >= 0 else f">{a.maxiter}"  # noqa: E731
            it = " ".join(f"{fmt(o[c]):>7}" for c in cols)
            print(f"{lmax:>4} {h:>5g} {it}  {o['auto']:>4}  {o['build']:8.2f}  {o['MiB']:.1f} ({o['peakMiB']:.1f})"
                  f"   [{time.perf_counter() - t0:.0f} s]", flush=True)
    with open("/proc/loadavg") as fh:
        print("end", time.strftime("%H:%M UTC", time.gmtime()), "loadavg", fh.read().strip())


if __name__ == "__main__":
    main()
