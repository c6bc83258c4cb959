"""Per-antenna beams (issue 41): the cost of the beam block's steps against a sky step.

A hexagon of 14 m dishes (a short dipole's E-field on a Gaussian dish, HERA latitude), channels
4 MHz apart from 100 MHz, LSTs over 1.5 rad, an isotropic prior ``C_l = 30 / (1 + l)^2`` K^2 and a
truth drawn from it; the five main-lobe modes of ``beam_modes(2)`` on two frequency modes per
antenna (``K = Nant x 10`` coefficients); every baseline kept.  Jitted, compile excluded, best of
5 with ``block_until_ready``:

* the response sets (``mode_responses``: 21 sets, once per run) against one response;
* the sky step given the beams (``beam_sky_step``: the combined response, the dense precision and
  its Cholesky, one draw) and, for reference, one GCR draw of the nominal system on the same path;
* the antenna-by-antenna sweep (``beam_sweep``), the joint Metropolis-Hastings move
  (``beam_joint_move``: two ``K x K`` factorisations) and the collapsed step
  (``beam_collapsed_step``: two dense sky evidences and a sky draw);
* where the data-space Grams fit (``--gram-max-gb``, default 2): the Grams (``beam_gram``, once), the sky step
  given the beams on the data-space path (``DataSpaceOptions``: ``D`` formed from the response, ``O(N_d^2 n)``),
  the same draw from the Grams (``beam_gram_sky_draw``: ``Y`` and ``Y^T`` on vectors) and the collapsed step
  from the Grams (what ``gcrsky run --beams sample`` takes).

Run: ``PYTHONPATH=. .venv/bin/python benchmarks/beam_step.py [--rows 2,3,2] [--lmax 8]`` (about a minute); the
data-space regime of a real file (``n`` above ``N_d``): ``--modes 1 --nt 10 --lmax 60 --nf 1``.
"""

from __future__ import annotations

import argparse
import time

from gcrsky.parallel import use_safe_cpu_threading

use_safe_cpu_threading()
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from gcrsky.checks.uvsim import DipoleGaussianBeam  # noqa: E402
from gcrsky.inference.beams import (  # noqa: E402
    beam_collapsed_step,
    beam_gram,
    beam_gram_bytes,
    beam_gram_sky_draw,
    beam_init,
    beam_joint_move,
    beam_setup,
    beam_sky_step,
    beam_sweep,
    set_visibilities,
)
from gcrsky.inference.gibbs import gcr_init, gcr_step  # noqa: E402
from gcrsky.instrument import HERA_LATITUDE_DEG, hex_array, make_array, response_matrix  # noqa: E402
from gcrsky.instrument.beammodes import beam_modes, mode_responses  # noqa: E402
from gcrsky.model import build_problem, isotropic_prior  # noqa: E402
from gcrsky.model.gains import mode_basis  # noqa: E402
from gcrsky.solvers import CholeskyOptions, DataSpaceOptions  # noqa: E402


def best(f, *args, repeat=5):
    jax.block_until_ready(f(*args))  # compile
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t)
    return min(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", default="2,3,2", help="hexagon rows (default 2,3,2: 7 dishes)")
    ap.add_argument("--lmax", type=int, default=8)
    ap.add_argument("--nside", type=int, default=32)
    ap.add_argument("--nf", type=int, default=3)
    ap.add_argument("--nt", type=int, default=24)
    ap.add_argument("--modes", type=int, default=2, help="Zernike degree of the beam modes (1: the two tilts)")
    ap.add_argument("--dense-max-n", type=int, default=8000, help="largest n for the dense (Cholesky) rows")
    ap.add_argument("--gram-max-gb", type=float, default=2.0, help="largest data-space Grams to time (GB)")
    args = ap.parse_args()
    pos = hex_array(tuple(int(r) for r in args.rows.split(",")))
    array = make_array(pos, HERA_LATITUDE_DEG, DipoleGaussianBeam(diameter=14.0))
    freqs = 100e6 + 4e6 * np.arange(args.nf)
    n = (args.lmax + 1) ** 2
    prior = isotropic_prior(np.stack([30.0 / (1.0 + np.arange(args.lmax + 1)) ** 2] * args.nf), n)
    truth = np.asarray(prior.inv_var) ** -0.5 * np.random.default_rng(0).standard_normal((args.nf, n))
    prob = build_problem(array, freqs, np.linspace(0.0, 1.5, args.nt), args.lmax, args.nside, a_true=truth,
                         sigma=1e-4, prior=prior, key=jax.random.PRNGKey(0))
    system = prob.system()
    pairs = np.asarray(prob.antpairs)
    modes = beam_modes(args.modes)
    t = time.perf_counter()
    stack = jax.block_until_ready(mode_responses(array, pairs, freqs, args.lmax, args.nside, modes))
    t_stack = time.perf_counter() - t
    t = time.perf_counter()
    jax.block_until_ready(response_matrix(array, pairs, freqs, args.lmax, args.nside, method="rings"))
    t_resp = time.perf_counter() - t
    block = beam_setup(stack, pairs, mode_basis(args.nf, min(2, args.nf), "legendre"), sigma=0.1, mean_sigma=0.01)
    k = block.prior_mean.size
    state = beam_init(jnp.asarray(truth), block)
    key = jax.random.PRNGKey(1)
    sets = set_visibilities(system, block, state.sky)
    proposal = (jnp.zeros(k), 0.01 * jnp.eye(k))
    rows = [
        ("response sets (once)", t_stack, f"{stack.shape[1]} sets; one response {t_resp:.3f} s"),
        ("set visibilities (per sweep)", best(jax.jit(lambda s: set_visibilities(system, block, s)), state.sky), ""),
        ("antenna-by-antenna sweep", best(jax.jit(lambda kk: beam_sweep(kk, state.theta, block, sets, system.data,
                                                                        system.inv_noise)), key), ""),
        ("joint MH move", best(jax.jit(lambda kk: beam_joint_move(kk, state.theta, block, sets, system.data,
                                                                  system.inv_noise)[0]), key), f"K = {k}"),
    ]
    if n <= args.dense_max_n:  # the dense precision (n x n) and its Cholesky
        rows += [
            ("sky step, nominal (reference)", best(jax.jit(lambda kk: gcr_step(
                kk, gcr_init(state.sky), system, options=CholeskyOptions())[0].position), key), ""),
            ("sky step given the beams", best(jax.jit(lambda kk: beam_sky_step(kk, state, system, block)[0].sky),
                                              key), ""),
            ("collapsed step", best(jax.jit(lambda kk: beam_collapsed_step(kk, state, system, block,
                                                                           proposal)[0]), key),
             "two sky evidences + a sky draw"),
        ]
    gb = beam_gram_bytes(system, block) / 1e9
    if gb <= args.gram_max_gb:
        t = time.perf_counter()
        gram = jax.block_until_ready(jax.jit(beam_gram)(system, block))
        ds = DataSpaceOptions()
        rows += [
            ("data-space Grams (once)", time.perf_counter() - t, f"{gb:.2f} GB, incl. compile"),
            ("sky step, data space", best(jax.jit(lambda kk: beam_sky_step(kk, state, system, block,
                                                                           options=ds)[0].sky), key),
             "D formed from the response"),
            ("sky draw from the Grams", best(jax.jit(lambda kk: beam_gram_sky_draw(kk, gram, system, block,
                                                                                   state.theta)[0]), key), ""),
            ("collapsed step from the Grams", best(jax.jit(lambda kk: beam_collapsed_step(
                kk, state, system, block, proposal, gram=gram)[0]), key), "two marginals + a sky draw"),
        ]
    else:
        print(f"(the data-space Grams, {gb:.1f} GB, exceed --gram-max-gb: not timed)")
    print(f"{len(pos)} dishes, {pairs.shape[0]} baselines, {args.nf} channels, {args.nt} LSTs, lmax {args.lmax} "
          f"(n = {n}), nside {args.nside}; {jax.devices()[0].platform}")
    print(f"| {'step':32s} | {'seconds':>9s} | note |")
    print(f"|{'-' * 34}|{'-' * 11}|------|")
    for name, sec, note in rows:
        print(f"| {name:32s} | {sec:9.4f} | {note} |")


if __name__ == "__main__":
    main()
