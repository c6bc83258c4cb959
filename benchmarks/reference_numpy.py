"""Yardstick: a NumPy/SciPy re-implementation of the paper's GCR code *as it runs*, vs gcrsky.

What it re-implements (Glasscock et al. 2024, sections 2-4 and App. A; DESIGN.md §2-4, §7)
------------------------------------------------------------------------------------------
* Response: the dense realified visibility operator ``X[f, t, b, k]`` at EVERY LST, by a
  per-pixel simulation for each LST: for each time, the HEALPix pixels above the
  horizon, the beam product ``A_i A_j`` (pyuvdata, evaluated at that time's az/za), the
  fringe ``exp(+2 pi i b_ij . s nu / c)`` with ``b_ij = x_j - x_i`` and the real
  spherical-harmonic basis of every mode, summed over pixels (dense numpy matmuls; no
  harmonic-space rotation trick).  The basis maps are evaluated once on all
  ``12 nside^2`` equatorial pixels (they do not depend on time: the sky is fixed in the
  equatorial frame, only the horizon and the beam/fringe move) with
  ``scipy.special.sph_harm_y`` -- independent of gcrsky's own Legendre recursion.
* Solver: per frequency (the channels are independent posteriors), one
  ``scipy.sparse.linalg.cg`` per solve with a ``LinearOperator`` whose matvec is
  ``X_r^T (W (X_r a)) + X_i^T (W (X_i a)) + S^-1 a`` evaluated left to right (P is never
  formed for the solves), ``W`` = per-component inverse variances (no flags).
  Wiener filter first, from ``x0 = 0`` (DESIGN §4's measurement -- monopole at 397
  instead of 3953 -- is a solve started from zero; from the prior mean, whose monopole is
  the true one, it could not come out 10x low); then each draw: ``P a = b_wf + fluct``
  warm-started from the Wiener filter.  The fluctuation is drawn the reference way,
  ``omega = (randn + 1j randn)/sqrt(2)`` against per-component inverse variances
  (DESIGN §4's under-dispersion bug: the data term of the fluctuation is halved);
  ``--fixed-fluctuation`` draws ``w_r, w_i ~ N(0, 1)`` instead (exact GCR).  The prior
  fluctuation ``S^-1/2 w_a`` uses unit normals in both modes.
* Tolerances: scipy's default (``rtol=1e-5``, ``maxiter=10 n``) and a tight one: the
  loosest ``rtol`` of a sweep (1e-6 ... 1e-12, ``maxiter=200000``) whose Wiener filter
  agrees with the dense solve to <= 1e-6 posterior sigma in every mode (or the best
  reached, stated), unless ``--tight-rtol`` fixes it.
* Exact reference: ``np.linalg.solve`` of the dense ``P``, ``sigma = sqrt(diag(P^-1))``.

Conventions are gcrsky's (so both sides solve the identical posterior): realified vector
``[Re a_lm (healpy order)] ++ [Im a_lm, m >= 1]``, basis ``Y_l0``, ``2 Re Y_lm``,
``-2 Im Y_lm``; idealised LSTs (hour angle = LST - RA, latitude -30.7215 deg, true
coordinates); ENU pixel vectors; UVBeam azimuth (North of East); ``A = sqrt(P_xx)``
of pyuvdata's ``GaussianBeam(diameter=14)``; pixel weight ``4 pi / Npix`` (K sr);
pixels with Up > 0.  The data, per-component noise sigma, prior and truth are taken
from ``gcrsky.standard_case()`` (simulated by gcrsky); only ``X`` is built here, and
checked against ``gcrsky.dense_matrix(prob.operator())``.

Where this is *not* the reference code: the site latitude is the true one (the
reference passes +30.7 deg with sign-flipped declinations: the same operator for the
N-S mirrored array, DESIGN §2); the sky truth is gcrsky's (GSM2016 if present, else the
pyradiosky GSM map); frequencies are solved one at a time.

How it runs
-----------
Three processes, so each side's peak RSS (``ru_maxrss``) is its own: this driver; a
gcrsky worker (JAX x64, ``gcrsky.parallel.use_safe_cpu_threading()``): it times
``response_matrix`` (cross-correlations) and ``standard_case`` (the whole build incl.
``build_problem``) twice each (1st = compile + run, 2nd = run), ``gcrsky.prepare(prob,
method="cg")`` twice and ``gcrsky.draw`` twice, and writes the problem to a temporary
``.npz``; then a numpy-only reference worker (never imports JAX).  Per-draw time of
gcrsky is the batched (vmapped) ``draw`` time / ndraws.  Memory: peak RSS after the stage
minus the RSS after imports and the pyuvdata beam's first call (both sides), plus ``tracemalloc``'s peak of numpy allocations for the
reference response build.

    .venv/bin/python benchmarks/reference_numpy.py --quick          # nside 32, 3 draws, tight rtol 1e-12, ~50 s
    .venv/bin/python benchmarks/reference_numpy.py                  # nside 128, the paper's
    .venv/bin/python benchmarks/reference_numpy.py --nside 64 --nlst 10 --ndraws 5 [--fixed-fluctuation]

Measured
--------
Run 2026-11-22 06:05 UTC, default (paper) size, ``benchmarks/reference_numpy.py`` with no
options, 108 s wall; shared 2-core x86 box (load ~1 from another job), 24 GB, OpenBLAS,
one BLAS thread per worker (``--blas-threads 1``: with 2 OpenBLAS threads on a loaded
box the 45 x Npix @ Npix x 441 products ran ~20x *slower*, which would have flattered
gcrsky).  Sky truth: the offline pyradiosky GSM fallback (GSM2016 not on disk).  gcrsky's
draws are timed as batches of 200 (the paper's count), the fastest of 5; ``auto`` chose
the dense Cholesky path (draws ``a_wf + L^-T z`` with ``L^-T`` formed once).

::

    === reference_numpy vs gcrsky: nside 128, lmax 20, 10 LSTs, 2 freqs, 5 draws, fluctuation reference (randn+1j randn)/sqrt2, BLAS threads 1 ===
    X check: per-LST reference X vs gcrsky.dense_matrix: max|dX|/max|X| = 1.41e-14, ||dX||_F/||X||_F = 1.44e-14
    cond(P) per freq: 2.99e+08 / 2.84e+08;  monopole: true 4075.1 / 3880.7, dense WF 3886.9 / 4084.0, posterior sigma 157 / 150
    
    Reference Wiener-filter rtol sweep (per freq: iterations, max error / monopole error in posterior sigma):
      rtol 1e-06:   4037 it   0.93 s err 1.31e+00/3.61e-01 |   4033 it   0.74 s err 1.06e+00/2.07e-01
      rtol 1e-07:   5637 it   1.20 s err 2.40e-01/1.95e-02 |   5466 it   0.97 s err 2.06e-01/2.92e-02
      rtol 1e-08:   6761 it   1.35 s err 1.17e-02/8.87e-05 |   6566 it   1.18 s err 1.16e-02/2.27e-04
      rtol 1e-09:   7803 it   1.45 s err 6.33e-04/7.51e-06 |   7588 it   1.49 s err 7.00e-04/8.34e-06
      rtol 1e-10:   8357 it   1.76 s err 1.12e-04/4.93e-06 |   8141 it   1.55 s err 1.40e-04/5.33e-06
      rtol 1e-11:   9287 it   1.78 s err 8.57e-06/7.84e-08 |   9130 it   1.77 s err 7.75e-06/8.26e-08
      rtol 1e-12:   9815 it   1.82 s err 1.01e-06/1.31e-08 |   9682 it   1.83 s err 9.24e-07/1.60e-08
    
    quantity (per freq f=100/102 MHz where two)                          reference (numpy/scipy)                            gcrsky    ratio ref/gcrsky
    response build time [s] (gcrsky: 2nd call / 1st call)                                  37.52                       0.25 / 1.27              148.8x
    whole standard_case() build [s] (2nd / 1st call)                                           -                       0.33 / 5.16
    response build peak RSS above imports [MiB]                                             1447                               104               13.9x
      (absolute peak RSS [MiB]; tracemalloc peak ref)                             1685 (tm 1403)                               539
    peak RSS after all solves [MiB]                                                         1685                               827
    WF iterations, rtol 1e-5 (scipy default)                                           746 / 765
    WF iterations, tight rtol 1e-12 | gcrsky tol 1e-6 sigma                          9815 / 9682                             2 / 2
    WF time [s], both freqs, default rtol                                                  0.288
    WF time [s], both freqs, tight | gcrsky prepare (2nd/1st)                              3.650                      0.138 / 4.23               26.4x
    WF error, max over modes [posterior sigma], default                              22.6 / 24.9
    WF error, monopole [posterior sigma], default                                    22.6 / 24.9
      monopole value at default rtol (dense value above)                           322.6 / 343.6
    WF error, max over modes [sigma], tight | gcrsky                             1e-06 / 9.2e-07                 9.5e-09 / 7.5e-09
    WF error, monopole [sigma], tight | gcrsky                                 1.3e-08 / 1.6e-08                 9.2e-09 / 5.3e-09
    draw CG iterations (mean), default rtol                                            140 / 147
    draw CG iterations (mean), tight | gcrsky                                        9206 / 8792                             2 / 2
    per-draw time [s], both freqs, default rtol | gcrsky auto (cholesky)                            0.0596                          4.80e-05               1243x
    per-draw time [s], both freqs, tight | gcrsky auto (cholesky)                            3.4934                          4.80e-05              72846x
    per-draw time [s], both freqs, default rtol | gcrsky CG                               0.0596                          6.12e-04               97.4x
    per-draw time [s], both freqs, tight | gcrsky CG                                      3.4934                          6.12e-04             5710.0x
      gcrsky: batch of 200, 1st call (compile+run) [s], auto | CG                                                         1.77 | 6.54
      gcrsky auto (cholesky) prepare [s] (2nd/1st); WF error max [sigma]                                         0.133 / 1.63; 8e-09 / 9e-09
    draw error max [posterior sigma], default | tight                    23 / 27 | 1e-06 / 1e-06
    
    gcrsky WF vs the reference's own dense solve (its X), 100 MHz: max 3.6e-09 sigma (monopole 2.8e-09); dense reference solve took 0.04 / 0.02 s
    gcrsky preconditioner: NystromPreconditioner.  Wall time: gcrsky worker 30 s, reference worker 78 s, total 108 s.

Reading it: the per-LST X equals gcrsky's rotated-response X to 1.4e-14 at nside 128.
With scipy's default rtol 1e-5 the Wiener filter stops after ~750 iterations with the
monopole at ~330 K instead of ~3890/4080 K: 22.6 / 24.9 posterior sigma off (DESIGN
measured 397 vs 3953, 23 sigma, 1153 iterations, with GSM2016), and draws warm-started
there inherit it (23 / 27 sigma).  Plain CG needs rtol 1e-12 (~9,700 iterations per
solve) to bring every mode within ~1e-6 sigma of the dense solve.  The ratios move with
the load on this shared box (each worker runs alone, but other sessions' jobs do not
stop): over the runs of the final code the response build was 149x and 244x faster
(earlier versions of this stop: 97x, 139x, 142x), its memory 14-16x smaller (pyuvdata's
import and first beam call excluded on both sides), and a draw 1243x and 2679x faster
than the reference at its (wrong) default tolerance (earlier: 756x-1166x, when gcrsky's
batch was timed once, not best of 5), 58,000-149,000x at the tolerance that makes it
right.  A batch of 200 Cholesky draws costs 6-10 ms: JAX's threefry normals (176,400
float64, 2.4 ms quiet) and the L^-T products (2.8 ms).  Matrix-free CG (Nystrom, 2
iterations) is ~100x / ~6,000x.  The dense WF monopoles (3887 / 4084) look swapped
against the truths (4075 / 3881): a coincidence (each is ~1.2 posterior sigma off; the
data fit their own channel's truth, chi2/N = 1.01 / 0.99, vs 163 / 170 with the channels
swapped).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

C_LIGHT = 299792458.0
HERA_LAT_DEG = -30.7215
ROOT = Path(__file__).resolve().parents[1]


def rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def current_rss_mib() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    return float("nan")


# ----------------------------------------------------------------------------------------
# Reference (numpy/scipy only)
# ----------------------------------------------------------------------------------------


def hex_positions(rows=(3, 4, 3), spacing=14.6) -> np.ndarray:
    """The paper's hexagon, numbered row by row (north row first), west to east (ENU m)."""
    dy = spacing * np.sqrt(3.0) / 2.0
    pos = []
    for r, count in enumerate(rows):
        north = ((len(rows) - 1) / 2.0 - r) * dy
        for k in range(count):
            pos.append(((k - (count - 1) / 2.0) * spacing, north, 0.0))
    return np.asarray(pos)


def real_basis_scipy(lmax: int, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(Npix, (lmax+1)^2) realified basis maps, from scipy.special.sph_harm_y."""
    from scipy.special import sph_harm_y

    ell, em = [], []
    for m in range(lmax + 1):  # healpy order: m-major
        for l in range(m, lmax + 1):
            ell.append(l)
            em.append(m)
    nalm = len(ell)
    n = (lmax + 1) ** 2
    F = np.empty((theta.size, n))
    j_im = nalm
    for i, (l, m) in enumerate(zip(ell, em)):
        y = sph_harm_y(l, m, theta, phi)
        if m == 0:
            F[:, i] = y.real
        else:
            F[:, i] = 2.0 * y.real
            F[:, j_im] = -2.0 * y.imag
            j_im += 1
    return F


def gaussian_beam_amplitude(diameter, az, za, freqs) -> np.ndarray:
    """``sqrt(P_xx)`` of pyuvdata's GaussianBeam(diameter), (Nf, Npix) (as gcrsky.instrument)."""
    from pyuvdata import BeamInterface
    from pyuvdata.analytic_beam import GaussianBeam

    bi = BeamInterface(GaussianBeam(diameter=float(diameter)))
    if bi.beam_type == "efield":
        bi = bi.as_power_beam(include_cross_pols=False)
    if bi.Npols > 1:
        bi = bi.with_feeds(["x"])
    power = np.real(np.asarray(bi.compute_response(az_array=az, za_array=za, freq_array=freqs))[0, 0])
    return np.sqrt(np.clip(power, 0.0, None))


def build_X_per_lst(nside, lmax, freqs, lsts_rad, pos, lat_rad, diameter):
    """Dense complex X (Nf, Nt, Nbl, n): per-LST pixel sums (the reference's simulation)."""
    import healpy as hp

    npix = hp.nside2npix(nside)
    theta, phi = hp.pix2ang(nside, np.arange(npix))
    F = real_basis_scipy(lmax, theta, phi)  # (Npix, n), fixed equatorial frame
    dec = np.pi / 2 - theta
    i, j = np.triu_indices(pos.shape[0], k=1)
    bvec = pos[j] - pos[i]  # x_j - x_i
    nf, nt, nbl, n = freqs.size, lsts_rad.size, bvec.shape[0], F.shape[1]
    X = np.empty((nf, nt, nbl, n), complex)
    w = 4 * np.pi / npix
    sl, cl = np.sin(lat_rad), np.cos(lat_rad)
    for t, lst in enumerate(lsts_rad):
        ha = lst - phi
        e = -np.cos(dec) * np.sin(ha)
        nn = cl * np.sin(dec) - sl * np.cos(dec) * np.cos(ha)
        u = sl * np.sin(dec) + cl * np.cos(dec) * np.cos(ha)
        up = u > 0
        s = np.stack([e[up], nn[up], u[up]], axis=1)  # (Np, 3)
        az = np.mod(np.arctan2(s[:, 1], s[:, 0]), 2 * np.pi)
        za = np.arccos(np.clip(s[:, 2], -1.0, 1.0))
        A = gaussian_beam_amplitude(diameter, az, za, freqs)  # (Nf, Np); identical dishes
        Fu = F[up]  # (Np, n)
        for f in range(nf):
            phase = (2 * np.pi * freqs[f] / C_LIGHT) * (bvec @ s.T)  # (Nbl, Np)
            beam = (A[f] * A[f] * w)[None, :]
            X[f, t] = (beam * np.cos(phase)) @ Fu + 1j * ((beam * np.sin(phase)) @ Fu)
    return X


def reference_worker(npz_path: str, out_json: str, ndraws: int, tight_rtol: float | None, fixed: bool, seed: int):
    from scipy.sparse.linalg import LinearOperator, cg

    z = np.load(npz_path)
    nside, lmax = int(z["nside"]), int(z["lmax"])
    freqs, lsts = z["freqs_hz"], z["lsts_rad"]
    pos = hex_positions()
    assert np.allclose(pos, z["positions"]), "hex layout differs from gcrsky's"
    # ---- response build (pyuvdata's import and first-call set-up, ~1.5 s and ~170 MiB, are
    # not counted, on either side: the baseline RSS is taken after them)
    gaussian_beam_amplitude(float(z["dish"]), np.zeros(2), np.full(2, 0.1), freqs)
    base_rss = current_rss_mib()
    res: dict = {"base_rss_mib": base_rss}
    tracemalloc.start()
    t0 = time.perf_counter()
    X = build_X_per_lst(nside, lmax, freqs, lsts, pos, np.deg2rad(HERA_LAT_DEG), float(z["dish"]))
    res["build_s"] = time.perf_counter() - t0
    res["build_tracemalloc_peak_mib"] = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    res["build_peak_rss_mib"] = rss_mib()
    Xg = z["X_gcrsky"]
    res["X_rel_diff_max"] = float(np.max(np.abs(X - Xg)) / np.max(np.abs(Xg)))
    res["X_rel_diff_fro"] = float(np.linalg.norm(X - Xg) / np.linalg.norm(Xg))

    data, sigma = z["data"], z["sigma"]  # (Nf, Nt, Nbl)
    a0, sinv = z["prior_mean"], z["prior_inv_var"]  # (Nf, n)
    nf, nt, nbl, n = X.shape
    rng = np.random.default_rng(seed)

    per_f = []
    for f in range(nf):
        Xr = np.ascontiguousarray(X[f].real.reshape(nt * nbl, n))  # contiguous: BLAS-friendly
        Xi = np.ascontiguousarray(X[f].imag.reshape(nt * nbl, n))
        W = (1.0 / sigma[f] ** 2).reshape(-1)  # per-component inverse variance
        dr, di = data[f].real.reshape(-1), data[f].imag.reshape(-1)
        Sinv = sinv[f]

        def matvec(a, Xr=Xr, Xi=Xi, W=W, Sinv=Sinv):
            a = np.ravel(a)
            return Xr.T @ (W * (Xr @ a)) + Xi.T @ (W * (Xi @ a)) + Sinv * a

        Pop = LinearOperator((n, n), matvec=matvec, dtype=np.float64)
        b_wf = Xr.T @ (W * dr) + Xi.T @ (W * di) + Sinv * a0[f]

        # dense exact reference
        t0 = time.perf_counter()
        P = Xr.T @ (W[:, None] * Xr) + Xi.T @ (W[:, None] * Xi) + np.diag(Sinv)
        a_dense = np.linalg.solve(P, b_wf)
        Pinv = np.linalg.inv(P)
        psig = np.sqrt(np.diag(Pinv))
        t_dense = time.perf_counter() - t0
        ev = np.linalg.eigvalsh(P)

        def solve(b, x0, rtol, maxiter):
            it = [0]

            def cb(xk):
                it[0] += 1

            t0 = time.perf_counter()
            x, info = cg(Pop, b, x0=x0, rtol=rtol, maxiter=maxiter, callback=cb)
            return x, it[0], time.perf_counter() - t0, info

        def err_sigma(x, exact):
            e = np.abs(x - exact) / psig
            return float(e.max()), float(e[0])

        fr: dict = {"dense_s": t_dense, "cond_P": float(ev[-1] / ev[0]), "monopole_dense": float(a_dense[0]),
                    "a_true_monopole": float(z["a_true"][f, 0]), "psig_monopole": float(psig[0])}
        # Wiener filter at the default tolerance, from x0 = 0
        x, it, dt, info = solve(b_wf, np.zeros(n), 1e-5, None)
        fr["wf_default"] = dict(iters=it, time_s=dt, info=int(info), err_max=err_sigma(x, a_dense)[0],
                                err_monopole=err_sigma(x, a_dense)[1], monopole=float(x[0]))
        a_wf_def = x
        # tolerance sweep
        sweep = []
        rtols = [tight_rtol] if tight_rtol else [1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12]
        chosen = None
        for rt in rtols:
            x, it, dt, info = solve(b_wf, np.zeros(n), rt, 200000)
            em, e0 = err_sigma(x, a_dense)
            sweep.append(dict(rtol=rt, iters=it, time_s=dt, info=int(info), err_max=em, err_monopole=e0))
            if chosen is None or (sweep[chosen]["err_max"] > 1e-6 and em < sweep[chosen]["err_max"]):
                chosen = len(sweep) - 1
                a_wf_tight = x
            if em <= 1e-6:
                break
        fr["wf_sweep"] = sweep
        fr["wf_tight"] = sweep[chosen]
        rt_tight = sweep[chosen]["rtol"]

        # draws: P a = b_wf + fluct, warm start at the Wiener filter
        def fluct():
            if fixed:
                wr, wi = rng.standard_normal(nt * nbl), rng.standard_normal(nt * nbl)
            else:
                om = (rng.standard_normal(nt * nbl) + 1j * rng.standard_normal(nt * nbl)) / np.sqrt(2)
                wr, wi = om.real, om.imag
            sW = np.sqrt(W)
            return Xr.T @ (sW * wr) + Xi.T @ (sW * wi) + np.sqrt(Sinv) * rng.standard_normal(n)

        for label, rt, mi, x0 in (("default", 1e-5, None, a_wf_def), ("tight", rt_tight, 200000, a_wf_tight)):
            its, ts, errs = [], [], []
            for _ in range(ndraws):
                b = b_wf + fluct()
                x, it, dt, info = solve(b, x0.copy(), rt, mi)
                its.append(it)
                ts.append(dt)
                errs.append(err_sigma(x, np.linalg.solve(P, b))[0])
            fr[f"draw_{label}"] = dict(rtol=rt, iters_mean=float(np.mean(its)), time_mean_s=float(np.mean(ts)),
                                       err_max=float(np.max(errs)))
        per_f.append(fr)
        if f == 0:
            res["a_dense_f0"] = a_dense.tolist()
            res["psig_f0"] = psig.tolist()
    res["per_freq"] = per_f
    res["solve_peak_rss_mib"] = rss_mib()
    Path(out_json).write_text(json.dumps(res))


# ----------------------------------------------------------------------------------------
# gcrsky fast path
# ----------------------------------------------------------------------------------------


#: gcrsky's draws are timed as batches of this many (the paper drew 200), fastest of 5
GCR_NDRAWS = 200


def gcrsky_worker(npz_path: str, out_json: str, nside: int, nlst: int, ndraws: int):
    sys.path.insert(0, str(ROOT))
    from gcrsky.parallel import use_safe_cpu_threading

    use_safe_cpu_threading()
    import jax

    jax.config.update("jax_enable_x64", True)
    import gcrsky
    from gcrsky.instrument import HERA_LATITUDE_DEG, antpairs, gaussian_beam, hex_array, make_array, response_matrix

    def timed(fn, *a, **k):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*a, **k))
        return out, time.perf_counter() - t0

    jax.block_until_ready(jax.numpy.zeros(3) + 1)
    lmax, freqs = 20, np.array([100e6, 102e6])
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    from gcrsky.instrument import beam_amplitude

    beam_amplitude(arr.beams[0], np.zeros(2), np.full(2, 0.1), freqs)  # pyuvdata import + set-up, as the reference
    base_rss = current_rss_mib()
    res: dict = {"base_rss_mib": base_rss}
    pairs = antpairs(10)
    _, res["resp_first_s"] = timed(response_matrix, arr, pairs, freqs, lmax, nside)
    _, res["resp_second_s"] = timed(response_matrix, arr, pairs, freqs, lmax, nside)
    res["resp_peak_rss_mib"] = rss_mib()

    prob, res["case_first_s"] = timed(gcrsky.standard_case, nside=nside, n_lst=nlst)
    prob, res["case_second_s"] = timed(gcrsky.standard_case, nside=nside, n_lst=nlst)
    res["case_peak_rss_mib"] = rss_mib()
    res["sky_note"] = prob.sky_note

    Xg = np.asarray(gcrsky.dense_matrix(prob.operator()))
    np.savez(
        npz_path, nside=nside, lmax=prob.lmax, freqs_hz=np.asarray(prob.freqs_hz), lsts_rad=np.asarray(prob.lsts_rad),
        positions=np.asarray(arr.positions_enu_m), dish=14.0, data=np.asarray(prob.data), sigma=np.asarray(prob.sigma),
        prior_mean=np.asarray(prob.prior.mean), prior_inv_var=np.asarray(prob.prior.inv_var),
        a_true=np.asarray(prob.a_true), X_gcrsky=Xg,
    )
    assert np.all(np.asarray(prob.weights) == 1.0)

    # the default path (method="auto": dense Cholesky here) and CG, each timed on a batch of
    # GCR_NDRAWS draws (the paper's 200), 2nd call (the 1st compiles)
    pa, res["auto_prepare_first_s"] = timed(gcrsky.prepare, prob)
    pa, res["auto_prepare_second_s"] = timed(gcrsky.prepare, prob)
    res["auto_method"] = pa.method
    _, res["auto_draw_first_s"] = timed(gcrsky.draw, jax.random.PRNGKey(5), pa, GCR_NDRAWS)
    # steady state (what a user drawing thousands sees): the fastest of 5 batches
    res["auto_draw_second_s"] = min(timed(gcrsky.draw, jax.random.PRNGKey(6 + i), pa, GCR_NDRAWS)[1] for i in range(5))
    a_auto = np.asarray(pa.a_wf)
    prep, res["prepare_first_s"] = timed(gcrsky.prepare, prob, method="cg")
    prep, res["prepare_second_s"] = timed(gcrsky.prepare, prob, method="cg")
    key = jax.random.PRNGKey(7)
    (dr, info), res["draw_first_s"] = timed(gcrsky.draw, key, prep, GCR_NDRAWS)
    (dr, info), res["draw_second_s"] = timed(gcrsky.draw, jax.random.PRNGKey(8), prep, GCR_NDRAWS)
    res["draw_second_s"] = min([res["draw_second_s"]] + [timed(gcrsky.draw, jax.random.PRNGKey(9 + i), prep,
                                                               GCR_NDRAWS)[1] for i in range(4)])
    res["solve_peak_rss_mib"] = rss_mib()
    res["wf_iters"] = np.asarray(prep.wiener.iterations).tolist()
    res["draw_iters_mean"] = np.asarray(info.draws.iterations).mean(axis=1).tolist()
    res["preconditioner"] = type(prep.pc).__name__

    # errors vs a dense numpy solve of gcrsky's own (dense-X) posterior
    a_wf = np.asarray(prep.a_wf)
    errs, mono, auto_errs = [], [], []
    nf, nt, nbl, n = Xg.shape
    for f in range(nf):
        Xr, Xi = Xg[f].real.reshape(-1, n), Xg[f].imag.reshape(-1, n)
        W = (1.0 / np.asarray(prob.sigma)[f] ** 2).reshape(-1)
        d = np.asarray(prob.data)[f].reshape(-1)
        sinv = np.asarray(prob.prior.inv_var)[f]
        P = Xr.T @ (W[:, None] * Xr) + Xi.T @ (W[:, None] * Xi) + np.diag(sinv)
        b = Xr.T @ (W * d.real) + Xi.T @ (W * d.imag) + sinv * np.asarray(prob.prior.mean)[f]
        ad = np.linalg.solve(P, b)
        ps = np.sqrt(np.diag(np.linalg.inv(P)))
        e = np.abs(a_wf[f] - ad) / ps
        errs.append(float(e.max()))
        mono.append(float(e[0]))
        auto_errs.append(float((np.abs(a_auto[f] - ad) / ps).max()))
    res["wf_err_max"] = errs
    res["wf_err_monopole"] = mono
    res["auto_wf_err_max"] = auto_errs
    res["a_wf_f0"] = a_wf[0].tolist()
    Path(out_json).write_text(json.dumps(res))


# ----------------------------------------------------------------------------------------
# driver
# ----------------------------------------------------------------------------------------


def _run(args: list[str], blas_threads: int) -> float:
    env = dict(os.environ)
    if blas_threads > 0:
        for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env[k] = str(blas_threads)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, __file__, *args], check=True, env=env)
    return time.perf_counter() - t0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--nside", type=int, default=128)
    ap.add_argument("--nlst", type=int, default=10)
    ap.add_argument("--ndraws", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="nside 32, 3 draws (smoke test, < 1 min)")
    ap.add_argument("--fixed-fluctuation", action="store_true", help="unit-variance data fluctuation (exact GCR)")
    ap.add_argument("--tight-rtol", type=float, default=None, help="skip the sweep, use this rtol")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="OPENBLAS/OMP/MKL threads for both workers (0: leave the environment alone)")
    ap.add_argument("--_worker", choices=["ref", "gcr"], help=argparse.SUPPRESS)
    ap.add_argument("--_npz", help=argparse.SUPPRESS)
    ap.add_argument("--_json", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.quick:
        a.nside, a.ndraws = 32, 3
        if a.tight_rtol is None:
            a.tight_rtol = 1e-12  # skip the sweep (measured at full size: 1e-12 is what 1e-6 sigma needs)
    if a._worker == "ref":
        return reference_worker(a._npz, a._json, a.ndraws, a.tight_rtol, a.fixed_fluctuation, a.seed)
    if a._worker == "gcr":
        return gcrsky_worker(a._npz, a._json, a.nside, a.nlst, a.ndraws)

    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        npz, gj, rj = (os.path.join(tmp, x) for x in ("problem.npz", "gcr.json", "ref.json"))
        common = ["--nside", str(a.nside), "--nlst", str(a.nlst), "--ndraws", str(a.ndraws), "--_npz", npz]
        t_g = _run(common + ["--_worker", "gcr", "--_json", gj], a.blas_threads)
        extra = (["--fixed-fluctuation"] if a.fixed_fluctuation else []) + (
            ["--tight-rtol", str(a.tight_rtol)] if a.tight_rtol else []
        )
        t_r = _run(common + ["--_worker", "ref", "--_json", rj, "--seed", str(a.seed)] + extra, a.blas_threads)
        g = json.loads(Path(gj).read_text())
        r = json.loads(Path(rj).read_text())
    report(a, g, r, t_g, t_r, time.perf_counter() - t_start)


def report(a, g, r, t_g, t_r, t_all) -> None:
    pf = r["per_freq"]

    def fj(vals, fmt):
        return " / ".join(fmt.format(v) for v in vals)

    print()
    print(f"=== reference_numpy vs gcrsky: nside {a.nside}, lmax 20, {a.nlst} LSTs, 2 freqs, {a.ndraws} draws, "
          f"fluctuation {'fixed (unit)' if a.fixed_fluctuation else 'reference (randn+1j randn)/sqrt2'}, "
          f"BLAS threads {a.blas_threads or 'default'} ===")
    print(f"sky: {g['sky_note']}")
    print(f"X check: per-LST reference X vs gcrsky.dense_matrix: max|dX|/max|X| = {r['X_rel_diff_max']:.2e}, "
          f"||dX||_F/||X||_F = {r['X_rel_diff_fro']:.2e}")
    print(f"cond(P) per freq: {fj([p['cond_P'] for p in pf], '{:.2e}')};  monopole: true {fj([p['a_true_monopole'] for p in pf], '{:.1f}')}, "
          f"dense WF {fj([p['monopole_dense'] for p in pf], '{:.1f}')}, posterior sigma {fj([p['psig_monopole'] for p in pf], '{:.3g}')}")
    print("\nReference Wiener-filter rtol sweep (per freq: iterations, max error / monopole error in posterior sigma):")
    for k in range(len(pf[0]["wf_sweep"])):
        rows = [p["wf_sweep"][k] if k < len(p["wf_sweep"]) else None for p in pf]
        rt = next(x for x in rows if x)["rtol"]
        cells = ["-" if x is None else f"{x['iters']:6d} it {x['time_s']:6.2f} s err {x['err_max']:.2e}/{x['err_monopole']:.2e}" for x in rows]
        print(f"  rtol {rt:.0e}: " + " | ".join(cells))

    w = 34
    print(f"\n{'quantity (per freq f=100/102 MHz where two)':<58}{'reference (numpy/scipy)':>{w}}{'gcrsky':>{w}}{'ratio ref/gcrsky':>20}")
    line = lambda name, rv, gv, ratio="": print(f"{name:<58}{rv:>{w}}{gv:>{w}}{ratio:>20}")
    rb, gb = r["build_s"], g["resp_second_s"]
    line("response build time [s] (gcrsky: 2nd call / 1st call)", f"{rb:.2f}", f"{gb:.2f} / {g['resp_first_s']:.2f}", f"{rb / gb:.1f}x")
    line("whole standard_case() build [s] (2nd / 1st call)", "-", f"{g['case_second_s']:.2f} / {g['case_first_s']:.2f}")
    rm = r["build_peak_rss_mib"] - r["base_rss_mib"]
    gm = g["resp_peak_rss_mib"] - g["base_rss_mib"]
    line("response build peak RSS above imports [MiB]", f"{rm:.0f}", f"{gm:.0f}", f"{rm / max(gm, 1):.1f}x")
    line("  (absolute peak RSS [MiB]; tracemalloc peak ref)", f"{r['build_peak_rss_mib']:.0f} (tm {r['build_tracemalloc_peak_mib']:.0f})", f"{g['resp_peak_rss_mib']:.0f}")
    line("peak RSS after all solves [MiB]", f"{r['solve_peak_rss_mib']:.0f}", f"{g['solve_peak_rss_mib']:.0f}")
    rtt = pf[0]["wf_tight"]["rtol"]
    line("WF iterations, rtol 1e-5 (scipy default)", fj([p["wf_default"]["iters"] for p in pf], "{}"), "")
    line(f"WF iterations, tight rtol {rtt:.0e} | gcrsky tol 1e-6 sigma", fj([p["wf_tight"]["iters"] for p in pf], "{}"), fj(g["wf_iters"], "{}"))
    wd = sum(p["wf_default"]["time_s"] for p in pf)
    wt = sum(p["wf_tight"]["time_s"] for p in pf)
    gp = g["prepare_second_s"]
    line("WF time [s], both freqs, default rtol", f"{wd:.3f}", "")
    line("WF time [s], both freqs, tight | gcrsky prepare (2nd/1st)", f"{wt:.3f}", f"{gp:.3f} / {g['prepare_first_s']:.2f}", f"{wt / gp:.1f}x")
    line("WF error, max over modes [posterior sigma], default", fj([p["wf_default"]["err_max"] for p in pf], "{:.3g}"), "")
    line("WF error, monopole [posterior sigma], default", fj([p["wf_default"]["err_monopole"] for p in pf], "{:.3g}"), "")
    line("  monopole value at default rtol (dense value above)", fj([p["wf_default"]["monopole"] for p in pf], "{:.1f}"), "")
    line("WF error, max over modes [sigma], tight | gcrsky", fj([p["wf_tight"]["err_max"] for p in pf], "{:.2g}"), fj(g["wf_err_max"], "{:.2g}"))
    line("WF error, monopole [sigma], tight | gcrsky", fj([p["wf_tight"]["err_monopole"] for p in pf], "{:.2g}"), fj(g["wf_err_monopole"], "{:.2g}"))
    line("draw CG iterations (mean), default rtol", fj([p["draw_default"]["iters_mean"] for p in pf], "{:.0f}"), "")
    line("draw CG iterations (mean), tight | gcrsky", fj([p["draw_tight"]["iters_mean"] for p in pf], "{:.0f}"), fj(g["draw_iters_mean"], "{:.0f}"))
    dd = sum(p["draw_default"]["time_mean_s"] for p in pf)
    dt = sum(p["draw_tight"]["time_mean_s"] for p in pf)
    gd = g["draw_second_s"] / GCR_NDRAWS
    ga = g["auto_draw_second_s"] / GCR_NDRAWS
    am = g["auto_method"]
    line(f"per-draw time [s], both freqs, default rtol | gcrsky auto ({am})", f"{dd:.4f}", f"{ga:.2e}", f"{dd / ga:.0f}x")
    line(f"per-draw time [s], both freqs, tight | gcrsky auto ({am})", f"{dt:.4f}", f"{ga:.2e}", f"{dt / ga:.0f}x")
    line("per-draw time [s], both freqs, default rtol | gcrsky CG", f"{dd:.4f}", f"{gd:.2e}", f"{dd / gd:.1f}x")
    line("per-draw time [s], both freqs, tight | gcrsky CG", f"{dt:.4f}", f"{gd:.2e}", f"{dt / gd:.1f}x")
    line(f"  gcrsky: batch of {GCR_NDRAWS}, 1st call (compile+run) [s], auto | CG", "",
         f"{g['auto_draw_first_s']:.2f} | {g['draw_first_s']:.2f}")
    line(f"  gcrsky auto ({am}) prepare [s] (2nd/1st); WF error max [sigma]", "",
         f"{g['auto_prepare_second_s']:.3f} / {g['auto_prepare_first_s']:.2f}; " + fj(g["auto_wf_err_max"], "{:.1g}"))
    line("draw error max [posterior sigma], default | tight", fj([p["draw_default"]["err_max"] for p in pf], "{:.2g}") + " | " + fj([p["draw_tight"]["err_max"] for p in pf], "{:.1g}"), "")
    # cross-check: gcrsky WF vs the reference's dense solve (f = 100 MHz)
    x = (np.array(g["a_wf_f0"]) - np.array(r["a_dense_f0"])) / np.array(r["psig_f0"])
    print(f"\ngcrsky WF vs the reference's own dense solve (its X), 100 MHz: max {np.abs(x).max():.2g} sigma "
          f"(monopole {abs(x[0]):.2g}); dense reference solve took {fj([p['dense_s'] for p in pf], '{:.2f}')} s")
    print(f"gcrsky preconditioner: {g['preconditioner']}.  Wall time: gcrsky worker {t_g:.0f} s, reference worker {t_r:.0f} s, "
          f"total {t_all:.0f} s.")


if __name__ == "__main__":
    main()
