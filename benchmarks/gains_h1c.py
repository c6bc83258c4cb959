"""The posterior flux scale of the real HERA H1C file with its omnical solutions, against the autocorrelation check.

Redundant calibration fixes neither the overall amplitude nor the phase gradients: the H1C file
after its omnical solutions is ~300x below Jy by its autocorrelations (the flux-scale check of
:mod:`gcrsky.model.fluxscale`: data autos / GSM autos through the beam).  Here the gains are
sampled with the sky from the cross-correlations alone: the file read by
:func:`gcrsky.ingest.from_uvdata` (``--cal`` applied, pI, channels 30 and 40 = 146.9 and 162.5 MHz,
lmax 10 (``--lmax``) with the sky above it marginalised as noise, 14 m Gaussian beam, the GSM prior with the
GSM's coefficients as its mean), gains of 1 x 1 modes per antenna (constant over the 1.6 min
and the two channels) with a 10 % prior, applied gains ``gbar = sqrt(autos ratio)`` so that
the scale ``q`` measures the cross-correlations' flux scale relative to the autos'.  The joint
chain (:func:`gcrsky.inference.joint_gain_step`, 4 gauge moves a sweep) runs a burn-in,
is re-centred, and keeps ``--steps`` sweeps.

Prints the autos ratio, the posterior flux-scale factor ``q x ratio`` (mean, sd, 95 % interval),
its ESS, and the phase gradients' posterior sd against the prior's.

Run: ``PYTHONPATH=. .venv/bin/python benchmarks/gains_h1c.py [DATA_DIR]`` (about 2 minutes at the default
lmax 10; ``--lmax 24 --steps 1500 --burn 300``: 16 minutes).  Measured (2026-12-02)::

    lmax 10: autos 0.00346; crosses q x ratio 0.30 +- 0.30 (95 %: 0.009-1.06), ESS 1481 of 3000
    lmax 24: autos 0.00346; crosses q x ratio 0.067 +- 0.057 (95 %: 0.0021-0.21), ESS 1120 of 1500
    phase gradients: posterior sd 0.096-0.101 against the 0.1 prior (prior-dominated)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from gcrsky.parallel import use_safe_cpu_threading

use_safe_cpu_threading()
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from gcrsky.inference import effective_sample_size, gain_init, gain_setup, gibbs_setup, joint_gain_step, recentre  # noqa: E402
from gcrsky.ingest.uvdata import from_uvdata  # noqa: E402
from gcrsky.model import gain_model, phase_gradient_directions  # noqa: E402

DATA = "zen.2458098.45361.HH_downselected.uvh5"
CAL = "zen.2458098.45361.HH.omni_downselected.calfits"


def _chain(fixed, block, state, key, n):
    def body(s, k):
        s, _ = joint_gain_step(k, s, fixed, block)
        return s, (s.theta, s.scale)

    return jax.lax.scan(body, state, jax.random.split(key, n))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data_dir", nargs="?", default=str(Path(__file__).resolve().parents[2] / "shared/data/real"))
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--burn", type=int, default=500)
    ap.add_argument("--lmax", type=int, default=10)
    args = ap.parse_args(argv)
    d = Path(args.data_dir)
    t0 = time.perf_counter()
    prob = from_uvdata(d / DATA, lmax=args.lmax, nside=32, dish_diameter_m=14.0, freq_chans=[30, 40], cal=d / CAL,
                       prior="gsm", prior_mean="gsm", band_limit="marginalise")
    ratio = float(prob.config.checks["flux_scale"]["ratio"])
    system = prob.system()
    nf, nt, nbl = system.data.shape
    model = gain_model(prob.antpairs, nf, nt, (1, 1))
    block = gain_setup(model, sigma=0.1, gbar=np.sqrt(ratio))
    fixed = gibbs_setup(system)
    run = jax.jit(_chain, static_argnums=4)
    state, _ = run(fixed, block, gain_init(system.prior.mean, block), jax.random.PRNGKey(1), args.burn)
    block, state = recentre(block, state)
    _, (th, sc) = jax.block_until_ready(run(fixed, block, state, jax.random.PRNGKey(2), args.steps))
    th, q = np.asarray(th), np.asarray(sc)[:, 0]
    flux = q * ratio
    print(f"H1C with omnical, pI, {nf} channels ({', '.join(f'{f / 1e6:.1f}' for f in np.asarray(prob.freqs_hz))} MHz), "
          f"{nt} times, {nbl} rows, lmax {prob.lmax}; {args.steps} sweeps after {args.burn} "
          f"({time.perf_counter() - t0:.0f} s in all)")
    print(f"autocorrelation check (data autos / GSM autos):   {ratio:.5f}")
    lo, hi = np.percentile(flux, [2.5, 97.5])
    print(f"posterior flux-scale factor q x ratio (crosses):  {flux.mean():.5f} +- {flux.std():.5f} "
          f"(95 %: {lo:.5f}-{hi:.5f}); q = {q.mean():.3f} +- {q.std():.3f}; ESS {float(effective_sample_size(q[None])):.0f}")
    pos = np.asarray(prob.antpos_enu_m)[model.units[:, 0]]
    T = phase_gradient_directions(model, pos)
    for name, t in zip(("east", "north"), T):
        x = th @ t
        print(f"phase gradient {name}: posterior sd {x.std():.4f} (prior 0.1), ESS {float(effective_sample_size(x[None])):.0f}")


if __name__ == "__main__":
    main()
