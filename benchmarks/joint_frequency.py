"""Joint sampling of many frequency-coupled channels at lmax 100: the per-m joint data space.

Usage::

    python benchmarks/joint_frequency.py                 # 64 channels, lmax 100 (the issue's size)
    python benchmarks/joint_frequency.py --quick         # 8 channels, lmax 20 (< 1 min), also checked
                                                         # against the a-space joint m-mode path
    python benchmarks/joint_frequency.py --lmax 60 --nchan 32 --ndraws 32

The case: the paper's 10-antenna hexagon (14.6 m spacing, 14 m Gaussian dishes, HERA's latitude),
its 6 shortest non-redundant baselines (3 orientations at 14.6 m, 3 at 25.3 m), ``Nchan`` channels
evenly spaced over 100-120 MHz, ``Nt = 2 lmax + 2`` equally spaced angles over the full day,
time-constant noise sigma 2e-3, the log-frequency kernel prior (A 1.2, beta -2.5, xi 0.05 in
log nu, nugget 1e-2) with ``C_l = 50 / (1 + l)^2`` at 110 MHz; data drawn from that prior.

Rows:

* ``joint``: :func:`gcrsky.solvers.joint_dataspace.prepare_joint_dataspace_mmode` (blocks
  ``Nchan 4 Nbl`` wide, one per order; 1536 at 64 channels, against ``64 x 202 = 12928`` for the
  a-space joint m-blocks, ~45 GB) and its draws;
* ``independent``: the same data, channel by channel, with each channel's own prior variance
  ``R_ff c`` (no coupling), by the existing exact m-mode path
  (:func:`gcrsky.solvers.mmode.prepare_mmode`, :func:`~gcrsky.solvers.mmode.draw_mmode`).

Columns: ``setup_s`` the set-up (compiles included), ``draw_ms`` per draw from a second batch of
``--ndraws`` (compiled), ``peak_GB`` the process's peak resident memory (VmHWM, reset before the
row) during the set-up and draws, ``est_GB`` the resident size before the row plus
:func:`~gcrsky.solvers.joint_dataspace.joint_dataspace_mmode_bytes`, ``wf_resid`` the Wiener filter's accuracy: the relative residual
``|M u - y| / |y|`` of the prior-whitened joint system (``M = I + G^T H G``, ``u = G^-1 (a_wf - a0)``,
``y = G^T X^T W r``; matrix-free, cheap) for the joint row, and for the independent row its own
solve info (``err_sigma``, posterior sigma).  ``--quick`` also compares the joint Wiener filter with
the a-space joint m-mode path's (:func:`gcrsky.solvers.joint.prepare_joint_mmode`).

Measured 2026-12-03 (this repository's machine: 2 shared cores, CPU JAX float64, one OpenBLAS thread,
XLA's safe threading), ``python benchmarks/joint_frequency.py`` at 23:48-23:51 UTC, other engineers' jobs
running (load ``11.96 11.81 8.47`` at the start, ``15.44 12.93 9.34`` at the end; wall 143 s, the
problem built in 16.5 s)::

    lmax 100, 64 channels, 6 baselines, 16 draws per batch
    path                                block  setup_s  draw_ms  peak_GB  est_GB  wf_resid
    joint (per-m data space)             1536     48.5   541.24     3.62    4.08   1.1e-14
    independent (m-mode per channel)      202     28.8   236.26     2.81     nan   6.8e-12
    ratio joint / independent                      1.7      2.3      1.3

The joint row's ``wf_resid`` is the whitened relative residual, the independent row's the m-mode
path's ``err_sigma`` (posterior sigma).  An earlier run that kept the blocks ``D_m`` besides their
factors peaked at 7.05 GB (set-up 76.3 s, 421 ms per draw, load ~13-15); only the factors are kept
now.  ``--quick`` (lmax 20, 8 channels, 23:54 UTC, load ~15): joint set-up 3.9 s, 0.79 ms per draw,
peak 0.65 GB (estimate 0.60: the compiled programs' fixed cost is not in it); independent 7.6 s,
0.23 ms; the joint Wiener filter equal to the a-space joint m-mode path's to 1.2e-14 of its largest
entry.  The timings are of a machine shared with four other jobs
(2 cores, load 12-15): they scatter by tens of per cent between runs.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as benchmarks/mmode_scale.py: threaded LAPACK is slower here

import argparse  # noqa: E402
import time  # noqa: E402

import gcrsky  # noqa: E402, F401  (before scipy's LAPACK loads)
from gcrsky.parallel import use_safe_cpu_threading  # noqa: E402

GB = 1e9
FREQ_RANGE = (100e6, 120e6)
NU0 = 110e6
HYPER = (1.2, -2.5, 0.05)
NUGGET = 1e-2
SIGMA = 2e-3
NBL = 6


def _status(key: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return float(line.split()[1]) * 1024
    return float("nan")


def reset_hwm() -> None:
    """Reset VmHWM to the current resident size (Linux ``clear_refs``)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def short_baselines(positions, nbl: int):
    """The ``nbl`` shortest non-redundant antenna pairs (first pair of each baseline vector, by length)."""
    import numpy as np

    from gcrsky.instrument import antpairs

    pairs = np.asarray(antpairs(positions.shape[0]))
    b = positions[pairs[:, 1]] - positions[pairs[:, 0]]
    keys = np.round(b[:, :2], 3)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = first[np.argsort(np.linalg.norm(b[first], axis=1), kind="stable")]
    return pairs[np.sort(first[:nbl])], np.linalg.norm(b[first[:nbl]], axis=1)


def build(lmax: int, nchan: int, seed: int = 0):
    """The :class:`~gcrsky.solvers.joint.JointSystem` of the module docstring and the baselines' lengths."""
    import jax.numpy as jnp
    import numpy as np

    from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array, response_matrix
    from gcrsky.model.operator import VisOperator, apply
    from gcrsky.model.spectral import frequency_prior, log_frequency_kernel
    from gcrsky.solvers.joint import JointSystem

    array = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    pairs, lengths = short_baselines(np.asarray(array.positions_enu_m), NBL)
    freqs = np.linspace(*FREQ_RANGE, nchan)
    nside = max(16, 1 << int(np.ceil(np.log2((lmax + 1) / 1.5))))  # 3 nside >= 2 (lmax + 1)
    resp = response_matrix(array, pairs, freqs, lmax, nside)
    nt = 2 * lmax + 2
    op = VisOperator(resp, jnp.asarray(2 * np.pi * np.arange(nt) / nt + 0.1))
    cl = 50.0 / (1.0 + np.arange(lmax + 1)) ** 2
    prior = frequency_prior(cl, log_frequency_kernel(freqs, NU0, *HYPER, nugget=NUGGET))
    rng = np.random.default_rng(seed)
    LR = np.linalg.cholesky(np.asarray(prior.freq_cov))
    truth = (LR @ rng.standard_normal(prior.mean.shape)) * np.sqrt(np.asarray(prior.mode_var))
    v = np.asarray(apply(op, jnp.asarray(truth)))
    d = v + SIGMA * (rng.standard_normal(v.shape) + 1j * rng.standard_normal(v.shape))
    w = np.full(v.shape, SIGMA**-2)
    return JointSystem(op, jnp.asarray(d), jnp.asarray(w), prior), lengths, nside


def whitened_residual(system, a_wf) -> float:
    """``|M u - y| / |y|`` of the prior-whitened joint system (module docstring), matrix-free."""
    import jax.numpy as jnp
    import jax.scipy.linalg as jsl

    from gcrsky.model.operator import adjoint, apply

    prior = system.prior
    LR, sc = jnp.linalg.cholesky(prior.freq_cov), jnp.sqrt(prior.mode_var)
    g = lambda u: (LR @ u) * sc  # noqa: E731
    gt = lambda v: LR.T @ (v * sc)  # noqa: E731
    w = system.inv_noise
    y = gt(adjoint(system.op, w * (system.data - apply(system.op, prior.mean))))
    u = jsl.solve_triangular(LR, (a_wf - prior.mean) / sc, lower=True)
    Mu = u + gt(adjoint(system.op, w * apply(system.op, g(u))))
    return float(jnp.linalg.norm(Mu - y) / jnp.linalg.norm(y))


def run(lmax: int, nchan: int, ndraws: int, quick: bool) -> list[dict]:
    import gc

    import jax
    import jax.numpy as jnp
    import numpy as np

    from gcrsky.model.prior import Prior
    from gcrsky.model.system import LinearSystem
    from gcrsky.solvers.joint_dataspace import (
        draw_joint_dataspace_mmode,
        joint_dataspace_mmode_bytes,
        prepare_joint_dataspace_mmode,
    )
    from gcrsky.solvers.mmode import draw_mmode, prepare_mmode

    t0 = time.perf_counter()
    system, lengths, nside = build(lmax, nchan)
    jax.block_until_ready(system.data)
    print(f"problem: lmax {lmax} (n {(lmax + 1) ** 2}), {nchan} channels, {NBL} baselines "
          f"(lengths {np.round(lengths, 1).tolist()} m), Nt {system.data.shape[1]}, nside {nside}; "
          f"built in {time.perf_counter() - t0:.1f} s; estimate of the joint set-up "
          f"{joint_dataspace_mmode_bytes(nchan, NBL, lmax) / GB:.2f} GB", flush=True)
    key = jax.random.PRNGKey(1)
    rows = []

    # the joint per-m data space
    gc.collect()
    rss0 = _status("VmRSS")
    reset_hwm()
    t = time.perf_counter()
    st = prepare_joint_dataspace_mmode(system)
    jax.block_until_ready(st.a_wf)
    setup = time.perf_counter() - t
    jax.block_until_ready(draw_joint_dataspace_mmode(key, st, ndraws))  # compile
    t = time.perf_counter()
    jax.block_until_ready(draw_joint_dataspace_mmode(jax.random.PRNGKey(2), st, ndraws))
    per_draw = (time.perf_counter() - t) / ndraws
    row = dict(path="joint (per-m data space)", block=int(st.chol.shape[-1]), setup_s=setup,
               draw_ms=1e3 * per_draw, peak_GB=_status("VmHWM") / GB, rss0_GB=rss0 / GB,
               est_GB=(rss0 + joint_dataspace_mmode_bytes(nchan, NBL, lmax)) / GB,
               wf_resid=whitened_residual(system, st.a_wf))
    if quick:
        from gcrsky.solvers.joint import prepare_joint_mmode

        ref = prepare_joint_mmode(system)
        row["vs_a_space"] = float(jnp.max(jnp.abs(ref.a_wf - st.a_wf)) / jnp.max(jnp.abs(ref.a_wf)))
        del ref
    rows.append(row)
    print(row, flush=True)
    del st
    gc.collect()

    # 64 independent channels: each channel's own prior variance R_ff c, the exact m-mode path
    R = np.asarray(system.prior.freq_cov)
    iv = 1.0 / (np.diag(R)[:, None] * np.asarray(system.prior.mode_var)[None, :])
    ind = LinearSystem(system.op, system.data, system.inv_noise, Prior(system.prior.mean, jnp.asarray(iv)))
    rss0 = _status("VmRSS")
    reset_hwm()
    t = time.perf_counter()
    sm = prepare_mmode(ind)
    jax.block_until_ready(sm.a_wf)
    setup = time.perf_counter() - t
    jax.block_until_ready(draw_mmode(key, sm, ndraws)[0])
    t = time.perf_counter()
    jax.block_until_ready(draw_mmode(jax.random.PRNGKey(2), sm, ndraws)[0])
    per_draw = (time.perf_counter() - t) / ndraws
    row = dict(path="independent (m-mode per channel)", block=2 * (lmax + 1), setup_s=setup,
               draw_ms=1e3 * per_draw, peak_GB=_status("VmHWM") / GB, rss0_GB=rss0 / GB, est_GB=float("nan"),
               wf_resid=float(jnp.max(sm.wiener.err_sigma)))
    rows.append(row)
    print(row, flush=True)
    return rows


def table(rows: list[dict]) -> str:
    head = (f"    {'path':34s} {'block':>6s} {'setup_s':>8s} {'draw_ms':>8s} {'peak_GB':>8s} {'est_GB':>7s} "
            f"{'wf_resid':>9s}")
    lines = [head]
    for r in rows:
        lines.append(f"    {r['path']:34s} {r['block']:6d} {r['setup_s']:8.1f} {r['draw_ms']:8.2f} "
                     f"{r['peak_GB']:8.2f} {r['est_GB']:7.2f} {r['wf_resid']:9.1e}")
    j, i = rows
    lines.append(f"    {'ratio joint / independent':34s} {'':6s} {j['setup_s'] / i['setup_s']:8.1f} "
                 f"{j['draw_ms'] / i['draw_ms']:8.1f} {j['peak_GB'] / i['peak_GB']:8.1f}")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--lmax", type=int, default=100)
    p.add_argument("--nchan", type=int, default=64)
    p.add_argument("--ndraws", type=int, default=16)
    p.add_argument("--quick", action="store_true", help="8 channels at lmax 20 (< 1 min), with the a-space check")
    args = p.parse_args(argv)
    use_safe_cpu_threading()
    import jax

    jax.config.update("jax_enable_x64", True)
    lmax, nchan = (20, 8) if args.quick else (args.lmax, args.nchan)
    with open("/proc/loadavg") as f:
        load0 = " ".join(f.read().split()[:3])
    t = time.perf_counter()
    rows = run(lmax, nchan, args.ndraws, args.quick)
    with open("/proc/loadavg") as f:
        load1 = " ".join(f.read().split()[:3])
    print(f"\nlmax {lmax}, {nchan} channels, {NBL} baselines, {args.ndraws} draws per batch; "
          f"load {load0} at the start, {load1} at the end; wall {time.perf_counter() - t:.0f} s")
    print(table(rows))
    if args.quick:
        print(f"    joint Wiener filter vs the a-space joint m-mode path: max |diff| / max |a_wf| = "
              f"{rows[0]['vs_a_space']:.1e}")


if __name__ == "__main__":
    main()
