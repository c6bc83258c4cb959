"""The visibility operator's products: per time against m-factorised, one vector and a batch of 16.

For each case (lmax, baselines, times; one channel, a random complex response and random
angles) it times, in one run, ``X a`` and ``X^T v`` by

* ``old``: the per-time formulas (``gcrsky.model.operator._apply_by_time`` /
  ``_adjoint_by_time``; a batch is ``jax.vmap`` of them, as CG's draws are);
* ``mfac``: :func:`gcrsky.model.mfactor.apply` / ``adjoint`` (a batch is one call on
  (16, Nf, n): one pass over the response for all draws);

each jitted, one warm-up call, then the median of 5 timed calls (``block_until_ready``),
in milliseconds; ``ratio`` is old / mfac.  ``--variants`` adds, for ``X a``, the other
layouts of the per-order sums over l that were tried (see :mod:`gcrsky.model.mfactor`):
``grid`` (a padded (lmax+1, 2 (lmax+1)) grid of R gathered per call, 2x R transient) and
``tri`` (the triangle packing, order m with order lmax - m in one row, a 1x R copy per
call).

Run: ``GCRSKY_COMPILE_CACHE=off PYTHONPATH=. .venv/bin/python benchmarks/operator_products.py
[--cases tiny,l100,l300,nt1000] [--variants]`` (12 minutes here under load, most of it the
per-time batches at lmax 300; lmax 300 holds a 0.9 GB response, and with ``--variants`` the
grid layout's 2x R copy took the process to a 6.7 GB peak: leave ``l300`` out of
``--variants`` runs on a shared machine).

Measured in one run (2026-12-03 ~05:42-05:54 UTC, this shared 2-core CPU, jax 0.10.2; ms,
median of 5; the load average (``/proc/loadavg``) before / after is in the header: other
engineers' jobs were running, so the absolute times are inflated and noisy, the ratios less
so).  ``old 1`` / ``mfac 1``: one vector; ``old 16`` / ``mfac 16``: 16 draws (old: vmapped;
mfac: one call); the variants' rows give their one-vector and 16-draw times of ``X a``::

    load average before 16.61 15.91 10.56, after 8.18 11.16 10.93; jax 0.10.2
    case    lmax  Nbl    Nt prod        old 1     mfac 1  ratio      old 16     mfac 16  ratio
    tiny       8    3     5 X a          0.04       0.08   0.53        0.15        0.08   1.78
    tiny       8    3     5 X^T v        0.04       0.05   0.77        0.15        0.08   1.97
    tiny       8    3     5 X a          grid       0.04                           2.81        (rel. err 4e-16)
    tiny       8    3     5 X a           tri       0.05                           0.07        (rel. err 4e-16)
            m-factorised X a vs per time: max rel. difference 4.5e-16
    l100     100  630    30 X a         67.14      37.47   1.79      928.69       99.98   9.29
    l100     100  630    30 X^T v      185.21      46.82   3.96     1127.98      160.02   7.05
    l100     100  630    30 X a          grid     266.71                         343.38        (rel. err 1e-15)
    l100     100  630    30 X a           tri     179.98                         197.20        (rel. err 1e-15)
            m-factorised X a vs per time: max rel. difference 1.3e-15
    l300     300  630    30 X a        920.82     350.50   2.63    13247.82     1046.88  12.65
    l300     300  630    30 X^T v     1909.15     484.78   3.94    20770.11     1731.97  11.99
    l300     300  630    30 X a          grid    4420.22                        5404.06        (rel. err 2e-15)
    l300     300  630    30 X a           tri    2663.37                        3939.97        (rel. err 2e-15)
            m-factorised X a vs per time: max rel. difference 1.5e-15
    nt1000   100   45  1000 X a        724.96      15.83  45.80    10774.41       48.18 223.61
    nt1000   100   45  1000 X^T v      595.20      12.79  46.54    12467.87       50.69 245.94
    nt1000   100   45  1000 X a          grid      14.36                          54.93        (rel. err 2e-15)
    nt1000   100   45  1000 X a           tri      24.22                         105.45        (rel. err 2e-15)
            m-factorised X a vs per time: max rel. difference 1.5e-15

So the m-factorised products are faster in every case that matters, 1.8-4x for one vector
at Nt = 30, 7-13x for 16 draws and ~46x (one vector) / ~230x (16 draws) at Nt = 1000;
the gathered grid and the triangle packing lose to them everywhere except the grid at
Nt = 1000 (a tie with one vector), because each call writes an R-sized copy.  In the tiny
case (lmax 8, 3 baselines, 5 times) the m-factorised single product costs ~0.08 ms
against ~0.04 ms (the loops' fixed overhead), so ``gcrsky.model.apply`` / ``adjoint`` keep
the per-time formulas unless ``Nt >= 4`` and ``Nt Nbl n >= 2^15``
(:func:`gcrsky.model.operator.uses_mfactor`).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from gcrsky.model import mfactor  # noqa: E402
from gcrsky.model.operator import VisOperator, _adjoint_by_time, _apply_by_time  # noqa: E402

CASES = {"tiny": (8, 3, 5), "l100": (100, 630, 30), "l300": (300, 630, 30), "nt1000": (100, 45, 1000)}
BATCH = 16


def timed(f, *args, reps: int = 5) -> float:
    """Median wall time (ms) of ``f(*args)`` over ``reps`` calls after one warm-up call."""
    jax.block_until_ready(f(*args))
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts))


def _columns(op, a):
    """``[a, J a]`` per draw, (Nf, n, 2K), and the batch size K (as mfactor.apply builds them)."""
    lay = mfactor.layout(int(round(np.sqrt(a.shape[-1]))) - 1)
    ak = a.reshape((-1,) + a.shape[-2:])
    X = jnp.stack([ak, jnp.asarray(lay.sign) * ak[..., lay.partner]], axis=-1)
    return jnp.moveaxis(X, 0, -2).reshape(a.shape[-2], a.shape[-1], -1), ak.shape[0]


def _fourier(op, Y, K):
    """V (K, Nf, Nt, Nbl) from the per-order sums Y (M, Nf, Nbl, 2K)."""
    M, nf, nbl = Y.shape[:3]
    ph = op.angles[:, None] * jnp.arange(M)
    cs = jnp.stack([jnp.cos(ph), jnp.sin(ph)], -1).astype(Y.dtype)
    return jnp.einsum("tmq,mfbkq->kftb", cs, Y.reshape(M, nf, nbl, K, 2))


def _grid_index(L):
    """(M, 2 (L+1)) realified index of a padded per-order grid (Re run then Im run) and its mask."""
    lay = mfactor.layout(L)
    idx, ok = np.zeros((L + 1, 2 * (L + 1)), int), np.zeros((L + 1, 2 * (L + 1)))
    for m in range(L + 1):
        ln = L + 1 - m
        idx[m, :ln], ok[m, :ln] = np.arange(lay.start[m], lay.start[m + 1]), 1
        if m:
            idx[m, L + 1 : L + 1 + ln], ok[m, L + 1 : L + 1 + ln] = idx[m, :ln] + lay.off, 1
    return idx, ok


@jax.jit
def apply_grid(op, a):
    """Variant: R gathered into a padded (Nf, Nbl, M, 2 (L+1)) grid per call."""
    L = int(round(np.sqrt(a.shape[-1]))) - 1
    idx, ok = _grid_index(L)
    X, K = _columns(op, a)
    Xg = X[:, idx] * jnp.asarray(ok)[..., None]  # (Nf, M, J, 2K)
    G = op.response[..., idx]  # (Nf, Nbl, M, J)
    Y = jnp.einsum("fbmj,fmjc->mfbc", G.real, Xg) + 1j * jnp.einsum("fbmj,fmjc->mfbc", G.imag, Xg)
    return _fourier(op, Y, K)


def _tri_rows(L):
    """Triangle packing: per row p, the realified runs of orders p and L - p (Re, Re, Im, Im)."""
    lay = mfactor.layout(L)
    rows = []
    for p in range(L // 2 + 1):
        ms = [p] if L - p == p else [p, L - p]
        runs = [(lay.start[m], lay.start[m + 1], s) for s, m in enumerate(ms)]
        runs += [(lay.start[m] + lay.off, lay.start[m + 1] + lay.off, s) for s, m in enumerate(ms) if m]
        rows.append([(int(k0), int(k1), s) for k0, k1, s in runs])
    return rows


@jax.jit
def apply_tri(op, a):
    """Variant: R copied into the triangle packing (Nf, P, Nbl, 2 (L+2)) per call."""
    L = int(round(np.sqrt(a.shape[-1]))) - 1
    width = 2 * (L + 2)
    X, K = _columns(op, a)
    R = op.response
    packs, xs = [], []
    for runs in _tri_rows(L):
        used = sum(k1 - k0 for k0, k1, _ in runs)
        pad = [jnp.zeros(R.shape[:-1] + (width - used,), R.dtype)] if used < width else []
        packs.append(jnp.concatenate([R[..., k0:k1] for k0, k1, _ in runs] + pad, -1))
        cols = [jnp.zeros((X.shape[0], width, 2, X.shape[-1]))]
        j = 0
        for k0, k1, s in runs:
            cols[0] = cols[0].at[:, j : j + k1 - k0, s].set(X[:, k0:k1])
            j += k1 - k0
        xs.append(cols[0].reshape(X.shape[0], width, -1))
    Rp, Xp = jnp.stack(packs, 1), jnp.stack(xs, 1)  # (Nf, P, Nbl, width), (Nf, P, width, 4K)
    Y = jnp.einsum("fpbj,fpjc->pfbc", Rp.real, Xp) + 1j * jnp.einsum("fpbj,fpjc->pfbc", Rp.imag, Xp)
    Y = Y.reshape(Y.shape[:3] + (2, -1))  # (P, Nf, Nbl, slot, 2K)
    lo, hi = Y[:, :, :, 0], Y[:, :, :, 1][: L + 1 - Y.shape[0]][::-1]
    return _fourier(op, jnp.concatenate([lo, hi], 0), K)


def run_case(name: str, variants: bool, rng) -> list[str]:
    """Time one case; returns its table rows."""
    L, nbl, nt = CASES[name]
    n = (L + 1) ** 2
    R = jnp.asarray(rng.standard_normal((1, nbl, n)) + 1j * rng.standard_normal((1, nbl, n)))
    op = VisOperator(R, jnp.asarray(np.sort(rng.uniform(0, 2 * np.pi, nt))))
    a = jnp.asarray(rng.standard_normal((1, n)))
    ab = jnp.asarray(rng.standard_normal((BATCH, 1, n)))
    v = jnp.asarray(rng.standard_normal((1, nt, nbl)) + 1j * rng.standard_normal((1, nt, nbl)))
    vb = jnp.asarray(rng.standard_normal((BATCH, 1, nt, nbl)) + 1j * rng.standard_normal((BATCH, 1, nt, nbl)))
    new_ap, new_ad = jax.jit(mfactor.apply), jax.jit(mfactor.adjoint)
    old_apb, old_adb = jax.jit(jax.vmap(_apply_by_time, (None, 0))), jax.jit(jax.vmap(_adjoint_by_time, (None, 0)))
    err = float(jnp.max(jnp.abs(new_ap(op, a) - _apply_by_time(op, a))) / jnp.max(jnp.abs(_apply_by_time(op, a))))
    rows = []
    for what, old1, new1, oldb, newb, x1, xb in (("X a", _apply_by_time, new_ap, old_apb, new_ap, a, ab),
                                                 ("X^T v", _adjoint_by_time, new_ad, old_adb, new_ad, v, vb)):
        o1, n1, ob, nb = timed(old1, op, x1), timed(new1, op, x1), timed(oldb, op, xb), timed(newb, op, xb)
        rows.append(f"{name:7s} {L:4d} {nbl:4d} {nt:5d} {what:6s} {o1:10.2f} {n1:10.2f} {o1 / n1:6.2f} "
                    f"{ob:11.2f} {nb:11.2f} {ob / nb:6.2f}")
    if variants:
        for vname, f in (("grid", apply_grid), ("tri", apply_tri)):
            e = float(jnp.max(jnp.abs(f(op, a)[0] - _apply_by_time(op, a))) / jnp.max(jnp.abs(_apply_by_time(op, a))))
            t1, tb = timed(f, op, a), timed(f, op, ab)
            rows.append(f"{name:7s} {L:4d} {nbl:4d} {nt:5d} X a    {vname:>10s} {t1:10.2f} {'':6s} {'':11s} {tb:11.2f}"
                        f"        (rel. err {e:.0e})")
    rows.append(f"{'':7s} m-factorised X a vs per time: max rel. difference {err:.1e}")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--variants", action="store_true", help="also time the grid and triangle layouts (X a)")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    load0 = open("/proc/loadavg").read().split()[:3]
    rows = []
    for name in args.cases.split(","):
        rows += run_case(name, args.variants, rng)
    load1 = open("/proc/loadavg").read().split()[:3]
    print(f"load average before {' '.join(load0)}, after {' '.join(load1)}; jax {jax.__version__}")
    print(f"{'case':7s} {'lmax':>4s} {'Nbl':>4s} {'Nt':>5s} {'prod':6s} {'old 1':>10s} {'mfac 1':>10s} {'ratio':>6s} "
          f"{'old 16':>11s} {'mfac 16':>11s} {'ratio':>6s}")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
