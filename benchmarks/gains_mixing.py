"""Gains sampled with the sky (issue 23): mixing along the gauge, the cost of each block, the linearisation bias.

Simulations with known gains: a hexagon of antennas (14 m Gaussian dishes, HERA latitude),
channels 1 MHz apart from 100 MHz, LSTs over 1.5 rad, an isotropic prior
``C_l = 50 / (1 + l)^2`` K^2 and a truth drawn from it; per antenna 5 % amplitude and 5 deg
phase errors in the constant mode and 1 % in the slow modes (2 x 2 DPSS modes in frequency x
time), the exact model ``g_i conj(g_j) V``, noise 1 % of the rms visibility.

1. **Mixing** of the gain amplitude ``q = A^2`` (its constant coefficient ``s_0``): the joint
   chain (:func:`gcrsky.inference.joint_gain_step`) with 0 gauge moves (plain Gibbs) and with 4
   per sweep; ESS by blackjax (Stan's estimator) over the kept sweeps after a re-centred burn-in,
   seconds of run time (compile excluded).
2. **Cost of a step** (jitted, best of 5, ``block_until_ready``): the gain block (one ``X a``,
   the mode sums, a P x P Cholesky), the sky given gains (Cholesky path: the data term
   ``X^T W |D|^2 X`` rebuilt and factorised), the scale, one gauge move, and for reference the
   plain sky step with the data term built once (:func:`gcrsky.inference.sky_step`).
3. **Linearisation bias** at gain errors of 1, 3, 5 % amplitude (and as many degrees of phase):
   the rms of the neglected term relative to the visibilities, the scale's bias (noise-free least
   squares of the exact model on the linear one), and the gain posterior's bias given the true
   sky in posterior sigma (rms over the P coefficients of the whitened bias), about ``gbar = 1``
   and after one re-centring at the first mean (:func:`gcrsky.inference.recentre`).

Run: ``PYTHONPATH=. .venv/bin/python benchmarks/gains_mixing.py`` (about 2 minutes; ``--steps``).
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

from gcrsky.inference import (
    effective_sample_size,
    gain_init,
    gain_setup,
    gain_sky_step,
    gains_step,
    gauge_step,
    gibbs_setup,
    joint_gain_step,
    recentre,
    scale_step,
    sky_step,
)
from gcrsky.inference.gains import gain_posterior, gauge_step_size, scale_sky_step
from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array  # noqa: E402
from gcrsky.model import (  # noqa: E402
    build_problem,
    gain_factor,
    gain_model,
    isotropic_prior,
    n_gain_params,
    phase_gradient_directions,
)
from gcrsky.model.gains import perturbation_coefficients  # noqa: E402
from gcrsky.model.operator import apply  # noqa: E402


def simulate(rows, nf, nt, lmax, amp=0.05, seed=3):
    """(system, block, theta_true, truth) of a simulation with known gains (module docstring)."""
    arr = make_array(hex_array(rows), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    freqs = 100e6 + 1e6 * np.arange(nf)
    n = (lmax + 1) ** 2
    prior = isotropic_prior(np.tile(50.0 / (1.0 + np.arange(lmax + 1)) ** 2, (nf, 1)), n)
    truth = np.asarray(prior.inv_var) ** -0.5 * np.random.default_rng(1).standard_normal((nf, n))
    prob = build_problem(arr, freqs, np.linspace(0.0, 1.5, nt), lmax, 32, a_true=truth, sigma=1.0, prior=prior,
                         key=jax.random.PRNGKey(0))
    model = gain_model(prob.antpairs, nf, nt, (2, 2))
    theta = true_theta(model, amp, np.random.default_rng(seed))
    V = prob.visibilities(truth)
    rng = np.random.default_rng(seed + 1)
    sigma = 0.01 * float(jnp.sqrt(jnp.mean(jnp.abs(V) ** 2)))
    data = gain_factor(model, theta, 1.0, exact=True) * V + sigma * (rng.standard_normal(V.shape)
                                                                      + 1j * rng.standard_normal(V.shape))
    system = prob.system()._replace(data=data, inv_noise=jnp.full(V.shape, sigma**-2))
    return system, gain_setup(model, sigma=np.array([[0.1, 0.02], [0.02, 0.02]])), theta, truth


def true_theta(model, amp, rng):
    """theta of rms amplitude error ``amp`` and ``100 amp`` degrees of phase per unit in the constant mode,
    1/5 of that in the slow modes, in the gauge (no common phase, no common per-channel amplitude)."""
    nu = model.units.shape[0]
    c = np.zeros((nu, 2, 2), complex)
    c[:, 0, 0] = amp * rng.standard_normal(nu) + 1j * np.deg2rad(100 * amp) * rng.standard_normal(nu)
    c[:, 1:, :] += 0.2 * amp * (rng.standard_normal((nu, 1, 2)) + 1j * rng.standard_normal((nu, 1, 2)))
    c[:, 0, 1] += 0.2 * amp * (rng.standard_normal(nu) + 1j * rng.standard_normal(nu))
    c.imag -= c.imag.mean(axis=0)
    c.real[:, :, 0] -= c.real[:, :, 0].mean(axis=0)
    J = np.asarray(jax.jacfwd(lambda t: perturbation_coefficients(model, t).ravel())(jnp.zeros(n_gain_params(model))))
    A = np.concatenate([J.real, J.imag])
    return np.linalg.lstsq(A, np.concatenate([c.ravel().real, c.ravel().imag]), rcond=None)[0]


def _scan(fixed, block, state, key, nsteps, moves, collapsed):
    def body(s, k):
        s, info = joint_gain_step(k, s, fixed, block, gauge_moves=moves, collapsed=collapsed)
        return s, (s.scale[0], info.gauge_accept)

    return jax.lax.scan(body, state, jax.random.split(key, nsteps))


_scan_jit = jax.jit(_scan, static_argnums=(4, 5, 6))

#: The mixing rows: (label, gauge moves, collapsed).
SWEEPS = (("plain Gibbs", 0, False), ("+ 4 gauge moves", 4, False), ("+ 16 gauge moves", 16, False),
          ("collapsed scale, 8 moves", 8, True))


def mixing(system, block, steps, burn=300):
    """Rows (label, steps, seconds, ESS of s_0, ESS/s, posterior sd of s_0, acceptance of the moves)."""
    fixed = gibbs_setup(system)
    rows = []
    for label, moves, collapsed in SWEEPS:
        st = gain_init(system.prior.mean, block)
        st, _ = jax.block_until_ready(_scan_jit(fixed, block, st, jax.random.PRNGKey(1), burn, moves, collapsed))
        blk, st = recentre(block, st)
        jax.block_until_ready(_scan_jit(fixed, blk, st, jax.random.PRNGKey(2), steps, moves, collapsed))  # compile
        t0 = time.perf_counter()
        _, (s0, acc) = jax.block_until_ready(_scan_jit(fixed, blk, st, jax.random.PRNGKey(3), steps, moves, collapsed))
        sec = time.perf_counter() - t0
        ess = float(effective_sample_size(np.asarray(s0)[None]))
        rows.append((label, steps, sec, ess, ess / sec, float(np.std(s0)), float(np.mean(acc)) if moves else np.nan))
    return rows


def directions(system, block, steps, positions, burn=300):
    """Rows (direction, posterior sd, prior sd, ratio, ESS) from a chain with 4 gauge moves a sweep."""
    fixed = gibbs_setup(system)

    def scan(blk, st, key, n):
        def body(s, k):
            s, _ = joint_gain_step(k, s, fixed, blk)
            return s, (s.theta, s.scale)

        return jax.lax.scan(body, st, jax.random.split(key, n))

    run = jax.jit(scan, static_argnums=3)
    st, _ = run(block, gain_init(system.prior.mean, block), jax.random.PRNGKey(1), burn)
    blk, st = recentre(block, st)
    _, (th, sc) = run(blk, st, jax.random.PRNGKey(4), steps)
    th, sc = np.asarray(th), np.asarray(sc)
    T = phase_gradient_directions(block.model, positions)
    sd_prior = 1.0 / np.sqrt(np.asarray(block.prior_inv_var))
    rows = []
    for name, x, prior_sd in (("phase gradient east", th @ T[0], sd_prior[np.argmax(np.abs(T[0]))]),
                              ("phase gradient north", th @ T[1], sd_prior[np.argmax(np.abs(T[1]))]),
                              ("scale s_0 (flat prior)", sc[:, 0], np.inf),
                              ("scale s_1 (flat prior)", sc[:, 1], np.inf)):
        ess = float(effective_sample_size(x[None]))
        rows.append((name, float(np.std(x)), prior_sd, float(np.std(x)) / prior_sd, ess))
    ratio = th.std(0) * np.sqrt(np.asarray(block.prior_inv_var))
    ess = np.asarray(effective_sample_size(th[None]))
    rows.append(("theta, median of P", float(np.median(th.std(0))), float(np.median(sd_prior)), float(np.median(ratio)),
                 float(np.median(ess))))
    rows.append(("theta, least ESS", float(th.std(0)[np.argmin(ess)]), float(sd_prior[np.argmin(ess)]),
                 float(ratio[np.argmin(ess)]), float(ess.min())))
    return rows


def _best(f, *args, reps=5):
    jax.block_until_ready(f(*args))
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def step_costs(system, block, theta):
    """Seconds per call of each block, jitted."""
    fixed = gibbs_setup(system)
    st = gain_init(system.prior.mean, block, theta=theta)
    key = jax.random.PRNGKey(0)
    tau = gauge_step_size(fixed, block)
    return {
        "gains_step (theta | a, s)": _best(jax.jit(lambda k, s: gains_step(k, s, fixed, block).theta), key, st),
        "gain_sky_step (a | theta, s)": _best(jax.jit(lambda k, s: gain_sky_step(k, s, fixed, block)[0].sky), key, st),
        "scale_step (s | a, theta)": _best(jax.jit(lambda k, s: scale_step(k, s, fixed, block).scale), key, st),
        "gauge_step (one move)": _best(jax.jit(lambda k, s: gauge_step(k, s, fixed, block, tau)[0].scale), key, st),
        "sky_step, no gains (reference)": _best(jax.jit(lambda k, a: sky_step(k, fixed, a)[0]), key, st.sky),
        "scale_sky_step (s, a | theta; 8 moves)": _best(jax.jit(lambda k, s: scale_sky_step(k, s, fixed, block)[0].sky),
                                                        key, st),
        "joint_gain_step (one sweep)": _best(jax.jit(lambda k, s: joint_gain_step(k, s, fixed, block)[0].sky), key, st),
        "joint_gain_step (collapsed sweep)": _best(jax.jit(lambda k, s: joint_gain_step(k, s, fixed, block, gauge_moves=8,
                                                                                     collapsed=True)[0].sky), key, st),
    }


def bias_rows(rows, nf, nt, lmax):
    """Rows (gain error, rel. rms neglected term, scale bias, theta bias in sigma: about 1, re-centred)."""
    out = []
    for amp in (0.01, 0.03, 0.05):
        system, block, theta, truth = simulate(rows, nf, nt, lmax, amp=amp)
        model = block.model
        V = apply(system.op, jnp.asarray(truth))
        ex, lin = gain_factor(model, theta, 1.0, exact=True) * V, gain_factor(model, theta, 1.0) * V
        rel = float(jnp.sqrt(jnp.mean(jnp.abs(ex - lin) ** 2) / jnp.mean(jnp.abs(V) ** 2)))
        U = lin
        q = float(jnp.sum(system.inv_noise * jnp.real(jnp.conj(U) * ex)) / jnp.sum(system.inv_noise * jnp.abs(U) ** 2))
        sigmas = []
        blk, st = block, gain_init(jnp.asarray(truth), block)
        for _ in range(2):
            mean, cov = gain_posterior(blk, ex, system.inv_noise, V, jnp.array([1.0, 0.0]))
            target = _about(model, theta, blk, block)
            L = np.linalg.cholesky(np.asarray(cov))
            sigmas.append(float(np.sqrt(np.mean(np.linalg.solve(L, np.asarray(mean) - target) ** 2))))
            blk, st = recentre(blk, st._replace(theta=mean))
        out.append((amp, rel, q - 1.0, *sigmas))
    return out


def _about(model, theta, blk, block):
    """The true theta about ``blk``'s linearisation point (least squares in the span)."""
    from gcrsky.model import perturbations

    if blk is block:
        return theta
    P = n_gain_params(model)
    J = np.asarray(jax.jacfwd(lambda t: perturbations(model, t).ravel())(jnp.zeros(P)))
    x0 = _x0(blk, block)
    x = np.asarray(perturbations(model, theta))
    target = ((1 + x) / (1 + x0) - 1).ravel()
    return np.linalg.lstsq(np.concatenate([J.real, J.imag]), np.concatenate([target.real, target.imag]), rcond=None)[0]


def _x0(blk, block):
    """The re-centring perturbation of ``blk`` from its prior mean (-theta0 about gbar = 1)."""
    from gcrsky.model import perturbations

    return np.asarray(perturbations(block.model, -np.asarray(blk.prior_mean)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=4000, help="kept sweeps of each mixing chain")
    args = ap.parse_args(argv)
    case = ((2, 3), 3, 8, 4)
    system, block, theta, _ = simulate(*case)
    P, n = n_gain_params(block.model), system.prior.mean.shape[1]
    print(f"case: 5 antennas (10 rows), 3 channels, 8 LSTs, lmax 4 (n = {n} per channel), P = {P} gain "
          "coefficients, 2 x 2 DPSS modes")
    print("\n1. mixing of the gain amplitude s_0 (q = A^2 per channel on the frequency modes)")
    print(f"{'sweep':<26} {'sweeps':>7} {'run s':>7} {'ESS s_0':>8} {'ESS/s':>8} {'sd s_0':>9} {'accept':>7}")
    for r in mixing(system, block, args.steps):
        print(f"{r[0]:<26} {r[1]:>7d} {r[2]:>7.2f} {r[3]:>8.1f} {r[4]:>8.1f} {r[5]:>9.4f} {r[6]:>7.2f}")
    print("\n1b. which directions stay prior-dominated (chain with 4 gauge moves a sweep; ratio = posterior / prior sd)")
    print(f"{'direction':<26} {'post sd':>9} {'prior sd':>9} {'ratio':>7} {'ESS':>7}")
    for name, sd, psd, ratio, ess in directions(system, block, args.steps, hex_array((2, 3))):
        print(f"{name:<26} {sd:>9.4f} {psd:>9.3f} {ratio:>7.3f} {ess:>7.1f}")
    for label, c in (("small (above)", case), ("10 antennas, 4 channels, 12 LSTs, lmax 8", ((3, 4, 3), 4, 12, 8))):
        sys_c, blk_c, th_c, _ = simulate(*c)
        print(f"\n2. cost of a step, {label}: n = {sys_c.prior.mean.shape[1]}, Nf = {sys_c.data.shape[0]}, "
              f"Nt = {sys_c.data.shape[1]}, Nbl = {sys_c.data.shape[2]}, P = {n_gain_params(blk_c.model)}")
        for name, sec in step_costs(sys_c, blk_c, th_c).items():
            print(f"   {name:<40} {1e3 * sec:9.3f} ms")
    print("\n3. linearisation bias (exact-model data, noise-free; sigma: the gain posterior's given the true sky)")
    print(f"{'gain error':>10} {'|x_i x_j*| / |V|':>17} {'q bias':>9} {'bias/sigma':>11} {'re-centred':>11}")
    for amp, rel, dq, b0, b1 in bias_rows(*case):
        print(f"{100 * amp:>5.0f} %/{100 * amp:.0f} deg {100 * rel:>13.3f} % {100 * dq:>7.3f} % {b0:>11.2f} {b1:>11.3f}")


if __name__ == "__main__":
    main()
