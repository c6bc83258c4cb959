"""Data-space CG with block-circulant-in-time preconditioners (issue 24 item 2: an investigated route).

Usage::

    .venv/bin/python benchmarks/dataspace_circulant.py                      # the rows below (~10 min)
    .venv/bin/python benchmarks/dataspace_circulant.py --lmax 64 --hours 8 --nfull 144
    .venv/bin/python benchmarks/dataspace_circulant.py --decay            # the lag blocks' norms

Question: for partial coverage the data-space matrix ``D = I + W^1/2 X S X^T W^1/2``
(:mod:`gcrsky.solvers.dataspace`) is block-Toeplitz in time when the noise is stationary and
the prior isotropic: block ``(t, t')`` is ``W^1/2 G((t - t') dtheta) W^1/2`` with ``G`` the lag
blocks (:func:`gcrsky.solvers.dataspace_large.lag_blocks_by_m`).  Products with D then cost one
FFT over time, and a block-circulant approximation is diagonalised by the same FFT into
``Nt`` independent ``2 Nbl x 2 Nbl`` solves.  Does CG in data space, stopped on the rigorous
``||r||_2 <= 1e-6`` (posterior sigma, :mod:`gcrsky.solvers.dataspace_proxy`), reach the
issue's ``<= 200 iterations`` with such a preconditioner?

Problem: the 37-antenna hexagon of ``benchmarks/window_pc.py`` (63 unique baselines, 14 m
Gaussian dishes, 100 MHz), ``C_l = 100 / (1 + l)^2``, SNR ~10 per visibility, the times
``t dtheta`` for ``t < Nt`` with ``dtheta = 2 pi / nfull`` (so that ``nfull`` times tile the
day exactly) and ``Nt = nfull hours / 24``.  Right-hand side ``b ~ N(0, D)`` (a draw's).
Columns, CG iterations to ``||r||_2 <= 1e-6`` (maxiter 3000; ``>3000``: not converged):

* ``none``: no preconditioner;
* ``strang`` / ``chan``: Strang's and T. Chan's block circulants of the ``Nt`` observed times;
* ``fullday``: the exact full-day circulant ``C = I + W^1/2 K_full W^1/2`` (``nfull`` times,
  exactly block-circulant by rotation invariance), its inverse restricted to the observed
  times (``(C^-1)_oo``, the inverse of a Schur complement of C: SPD, eigenvalues of the
  preconditioned D >= 1);
* ``embed2``: a wrap-around circulant embedding on ``2 Nt`` times.

``min eig`` is the smallest eigenvalue of the circulant's ``2 Nbl x 2 Nbl`` blocks (< 0: not a
valid CG preconditioner: Strang and embed2 are indefinite here).

Measured
--------
2026-12-03 20:00-20:25 UTC, this shared 2-core CPU, with a test run alongside (iteration counts do
not depend on the load)::

    lmax  hours  Nt  N_d   n      cond(D)   none  strang      chan  fullday  embed2
      16      8  48  6048    289  5.3e+05    381  >3000 (-2e4)  1194     298  >3000 (-8e3)
      64      8  48  6048   4225  1.5e+05   2159  >3000 (-4e2)  2080     469  >3000 (-2e2)
     100      8  30  3780  10201  7.8e+04   2078  >3000 (-2e2)  1549     412  >3000 (-2e2)

Finding: the full-day circulant restricted to the observed times is the best of these (4-5x fewer
iterations than none at lmax 64-100) but stays above 200.  Why, measured (``--decay``): the spectral
norm of the whitened lag block ``W^1/2 G(k dtheta) W^1/2`` falls from 2.4e4 at lag 0 to ~7e2 within
~10 LSTs (the beam's crossing time) and then only slowly, to ~2e2 at 6 h (lmax 64; lmax 100: 2.0e4 ->
6.5e2 at 6 LSTs -> 1.5e2 at 11 h): the low-l sky seen by the short baselines correlates every pair of
times at ~100x the whitened noise (1).  So the observed window couples strongly to the unobserved part
of the day, not only across its edges, and ``(C^-1)_oo`` misses that coupling in a large number of
directions.  Wrapping the observed window (Strang, embed2) is indefinite; Chan's optimal circulant is
SPD but barely helps.  The exact in-place data space (no iterations) is what meets item 2's time,
memory and accuracy goals (``benchmarks/scale.py`` row D).
"""

from __future__ import annotations

import argparse
import os
import sys

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

import window_pc  # noqa: E402  (benchmarks/: the shared 37-antenna problem)

from gcrsky.model import LinearSystem  # noqa: E402
from gcrsky.solvers.dataspace_large import lag_blocks_by_m  # noqa: E402

TOL = 1e-6
MAXITER = 3000
ROWS = [(16, 8.0, 144), (64, 8.0, 144), (100, 8.0, 90)]


def make_system(lmax: int, hours: float, nfull: int, snr: float = 10.0) -> LinearSystem:
    """The 37-antenna problem of ``benchmarks/window_pc.py`` at the times ``t 2 pi / nfull``, t < nfull hours / 24."""
    nt = int(round(nfull * hours / 24))
    return window_pc.make_system(lmax, hours, snr=snr, lsts=np.arange(nt) * 2 * np.pi / nfull)


def circulant_solver(c: np.ndarray):
    """``x -> (I + C)^-1 x`` for the block circulant C with first block column c (N, B, B), block
    ``(i, j) = c[(i - j) mod N]``, and the smallest eigenvalue of ``I + C``."""
    N, B, _ = c.shape
    blocks = np.fft.fft(c, axis=0) + np.eye(B)[None]
    inv = np.linalg.inv(blocks)
    mineig = min(np.linalg.eigvalsh(0.5 * (q + q.conj().T)).min() for q in blocks)

    def solve(x):
        xh = np.fft.fft(x.reshape(N, B), axis=0)
        return np.fft.ifft(np.einsum("qab,qb->qa", inv, xh), axis=0).real.ravel()

    return solve, float(mineig)


def pcg_iterations(D: np.ndarray, prec, b: np.ndarray) -> int:
    """CG iterations on D x = b from 0 to ``||r||_2 <= TOL`` (-1: not within MAXITER)."""
    x, r = np.zeros_like(b), b.copy()
    z = prec(r)
    p, rz = z.copy(), r @ z
    for it in range(1, MAXITER + 1):
        q = D @ p
        alpha = rz / (p @ q)
        x += alpha * p
        r -= alpha * q
        if np.linalg.norm(r) <= TOL:
            return it if np.linalg.norm(b - D @ x) <= 2 * TOL else -1
        z = prec(r)
        rz_new = r @ z
        if not np.isfinite(rz_new):
            return -1
        p, rz = z + (rz_new / rz) * p, rz_new
    return -1


def whitened_lags(s: LinearSystem, nfull: int) -> np.ndarray:
    """``W^1/2 G(k 2 pi / nfull) W^1/2`` for k < nfull: (nfull, 2 Nbl, 2 Nbl), the first block column of
    the full-day circulant (stationary noise: the first time's weights)."""
    G = np.asarray(lag_blocks_by_m(s, jnp.arange(nfull) * (2 * np.pi / nfull)))[:, 0]
    sw = np.sqrt(np.asarray(s.inv_noise)[0, 0])
    w = np.concatenate([sw, sw])
    return w[None, :, None] * G * w[None, None, :]


def lag_norms(lmax: int, hours: float, nfull: int) -> list[float]:
    """Spectral norms of the whitened lag blocks for lags 0 .. nfull / 2."""
    Gw = whitened_lags(make_system(lmax, hours, nfull), nfull)
    return [float(np.linalg.norm(Gw[k], 2)) for k in range(nfull // 2 + 1)]


def row(lmax: int, hours: float, nfull: int) -> dict:
    s = make_system(lmax, hours, nfull)
    nt, nbl = s.data.shape[1:]
    B = 2 * nbl
    Gw = whitened_lags(s, nfull)  # c_k, block (i, j) of D - I = c_{(i - j) mod nfull}
    idx = (np.arange(nt)[:, None] - np.arange(nt)[None, :]) % nfull
    D = Gw[idx].transpose(0, 2, 1, 3).reshape(nt * B, nt * B) + np.eye(nt * B)
    D = 0.5 * (D + D.T)
    ev = np.linalg.eigvalsh(D)
    b = np.linalg.cholesky(D) @ np.random.default_rng(0).standard_normal(nt * B)
    lag = lambda k: Gw[k % nfull]  # noqa: E731  (k in -(Nt-1) .. Nt-1)

    def restricted(c, N):
        solve, me = circulant_solver(c)

        def prec(r):
            x = np.zeros(N * B)
            x[: nt * B] = r
            return solve(x)[: nt * B]

        return prec, me

    pcs = {
        "strang": circulant_solver(np.stack([lag(k) if k <= nt // 2 else lag(k - nt) for k in range(nt)])),
        "chan": circulant_solver(np.stack([((nt - k) * lag(k) + k * lag(k - nt)) / nt for k in range(nt)])),
        "fullday": restricted(Gw, nfull),
        "embed2": restricted(np.stack([lag(k) if k < nt else (0 * Gw[0] if k == nt else lag(k - 2 * nt))
                                       for k in range(2 * nt)]), 2 * nt),
    }
    out = {"Nt": nt, "N_d": nt * B, "n": (lmax + 1) ** 2, "cond": ev[-1] / ev[0],
           "none": (pcg_iterations(D, lambda r: r, b), None)}
    for name, (prec, me) in pcs.items():
        out[name] = (pcg_iterations(D, prec, b), me)
    return out


def _cell(v) -> str:
    its, me = v
    s = f">{MAXITER}" if its < 0 else str(its)
    return s + (f" ({me:.0e})" if me is not None and me < 0 else "")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lmax", type=int)
    ap.add_argument("--hours", type=float, default=8.0)
    ap.add_argument("--nfull", type=int, default=144, help="times that tile the day (their spacing)")
    ap.add_argument("--decay", action="store_true", help="print the whitened lag blocks' norms instead")
    a = ap.parse_args(argv)
    if a.decay:
        for lmax, hours, nfull in ROWS[1:] if a.lmax is None else [(a.lmax, a.hours, a.nfull)]:
            print(f"lmax {lmax}, {nfull} LSTs a day; lag: ||W^1/2 G W^1/2||_2")
            print("  " + "  ".join(f"{k}: {x:.1e}" for k, x in enumerate(lag_norms(lmax, hours, nfull))))
        return
    rows = ROWS if a.lmax is None else [(a.lmax, a.hours, a.nfull)]
    print(f"{'lmax':>4} {'hours':>6} {'Nt':>3} {'N_d':>5} {'n':>6} {'cond(D)':>9}"
          f" {'none':>6} {'strang':>13} {'chan':>6} {'fullday':>8} {'embed2':>13}")
    for lmax, hours, nfull in rows:
        r = row(lmax, hours, nfull)
        print(f"{lmax:4d} {hours:6g} {r['Nt']:3d} {r['N_d']:5d} {r['n']:6d} {r['cond']:9.1e}"
              f" {_cell(r['none']):>6} {_cell(r['strang']):>13} {_cell(r['chan']):>6}"
              f" {_cell(r['fullday']):>8} {_cell(r['embed2']):>13}", flush=True)


if __name__ == "__main__":
    main()
