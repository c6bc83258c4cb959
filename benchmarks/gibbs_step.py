"""A user's Gibbs loop over (sky, noise scale, prior amplitude): ms per step, and the chain against the exact grid.

The model: the standard case (``gcrsky.standard_case(lmax=10, nside=32)``: n = 121, 2
channels, N_d = 900 real data per channel) with the noise variance ``s N`` and the prior
covariance ``A S`` scaled per channel, Jeffreys ``1/s`` and a weak inverse-gamma prior
``IG(1, 0.01)`` on ``A``.  A Gibbs sweep draws ``a | s, A, d`` exactly, then ``s | a, d``
(inverse-gamma, shape ``N_d / 2``) and ``A | a`` (inverse-gamma, shape ``1 + n / 2``).

Rows (ms per sweep, both channels):

* ``gcr_step, CG (today)``: the loop a user writes around :func:`gcrsky.gcr_step` with its
  default matrix-free ``CGOptions``, the system rebuilt with the new scales every step (so
  its Nystrom preconditioner is rebuilt every step); the quadratic forms from the operator.
  A jitted ``lax.scan`` of 20 steps.
* ``gcr_step, Cholesky``: the same loop with ``options=CholeskyOptions()`` (any path's
  options now work): a dense P and its factor per step.
* ``scalar state``: :func:`gcrsky.inference.prepare_scalar` once (timed apart), then
  :func:`~gcrsky.inference.scalar_draw` and :func:`~gcrsky.inference.scalar_quadratics` per
  step, O(n^2): a jitted ``lax.scan`` of 3000 steps.

Compile time is excluded (each program is run once first); best of 2 runs.  Then the check:
the scalar chain's marginal means of ``s`` and ``A`` per channel against ``p(s, A | d)`` on a
(log s, log A) grid from :func:`~gcrsky.inference.scalar_log_evidence` (validated against
the dense evidence in ``tests/test_gibbs_any_path.py``), with batch-means errors.

Run: ``.venv/bin/python benchmarks/gibbs_step.py`` (about a minute).  The table measured in
one run is in ``MEASURED`` below and in the README.
"""

from __future__ import annotations

import time

from gcrsky.parallel import use_safe_cpu_threading

use_safe_cpu_threading()  # before JAX's first computation
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import gcrsky  # noqa: E402
from gcrsky.inference import prepare_scalar, scalar_draw, scalar_log_evidence, scalar_quadratics  # noqa: E402
from gcrsky.model import Prior, apply, scale_noise, with_prior  # noqa: E402

MEASURED = """
standard case lmax 10: n = 121, Nf = 2, build 4.7 s

| loop | ms/step | steps timed | speed-up | note |
|---|---|---|---|---|
| gcr_step, CG (today) | 336 | 20 | 1x | 1.0 CG iterations a step |
| gcr_step, Cholesky | 13 | 20 | 26x |  |
| scalar state | 0.0857 | 3000 | 3924x | set-up once: 229 ms (3.8 s with compiling) |

chain (20000 steps) vs exact grid (largest grid-edge weight 7.0e-26):
| channel | E[s] chain | E[s] grid | (chain-grid)/err | E[A] chain | E[A] grid | (chain-grid)/err |
|---|---|---|---|---|---|---|
| 0 | 1.00267 | 1.00275 | -0.23 | 0.4498 | 0.4520 | -0.98 |
| 1 | 0.99844 | 0.99892 | -1.55 | 1.3120 | 1.3083 | +0.66 |
"""

A_SHAPE, A_SCALE = 1.0, 1e-2


def _draw_scales(key, q_data, q_prior, n_data, n):
    """s | a, d and A | a: inverse-gamma draws (Nf,) from the quadratic forms."""
    ks, kA = jax.random.split(key)
    s = 0.5 * q_data / jax.random.gamma(ks, 0.5 * n_data)
    A = (A_SCALE + 0.5 * q_prior) / jax.random.gamma(kA, A_SHAPE + 0.5 * n, q_prior.shape)
    return s, A


def today_chain(system, options, nsteps):
    """The loop around gcr_step: the system rebuilt with (s, A) every step (jitted scan)."""
    nf, n = system.prior.mean.shape
    n_data = 2.0 * jnp.sum(system.inv_noise > 0, axis=(1, 2))

    def step(carry, k):
        state, s, A = carry
        ka, kh = jax.random.split(k)
        scaled = with_prior(scale_noise(system, s[:, None, None]), Prior(system.prior.mean, system.prior.inv_var / A[:, None]))
        state, info = gcrsky.gcr_step(ka, state, scaled, options=options)
        r = system.data - apply(system.op, state.position)
        q_data = jnp.sum(system.inv_noise * jnp.abs(r) ** 2, axis=(1, 2))
        q_prior = jnp.sum(system.prior.inv_var * (state.position - system.prior.mean) ** 2, axis=-1)
        s, A = _draw_scales(kh, q_data, q_prior, n_data, n)
        return (state, s, A), (s, A, info.iterations)

    ones = jnp.ones(nf)
    init = (gcrsky.gcr_init(system.prior.mean), ones, ones)
    return jax.jit(lambda key: jax.lax.scan(step, init, jax.random.split(key, nsteps))[1])


def scalar_chain(state, nsteps):
    """The same loop on the scalar state: O(n^2) a step (jitted scan)."""
    nf, n = state.prior_mean.shape

    def step(carry, k):
        s, A = carry
        ka, kh = jax.random.split(k)
        a = scalar_draw(ka, state, s, A)[:, 0]
        q = scalar_quadratics(state, a)
        s, A = _draw_scales(kh, q.data, q.prior, state.n_data, n)
        return (s, A), (s, A)

    ones = jnp.ones(nf)
    return jax.jit(lambda key: jax.lax.scan(step, (ones, ones), jax.random.split(key, nsteps))[1])


def _time(fn, key, reps=2):
    jax.block_until_ready(fn(key))  # compile
    best = np.inf
    for r in range(reps):
        t = time.perf_counter()
        out = jax.block_until_ready(fn(jax.random.fold_in(key, r)))
        best = min(best, time.perf_counter() - t)
    return best, out


def grid_means(state, ls=np.linspace(-0.6, 0.6, 481), lA=np.linspace(-5.0, 4.0, 721)):
    """E[s], E[A] per channel from p(s, A | d) on a (log s, log A) grid (flat in log s, IG on A)."""
    S, AA = np.meshgrid(ls, lA, indexing="ij")
    logev = np.asarray(jax.jit(jax.vmap(lambda x, y: scalar_log_evidence(state, jnp.exp(x), jnp.exp(y))))(
        jnp.asarray(S.ravel()), jnp.asarray(AA.ravel())))
    logw = logev + (-A_SHAPE * AA.ravel() - A_SCALE * np.exp(-AA.ravel()))[:, None]
    w = np.exp(logw - logw.max(axis=0))
    w /= w.sum(axis=0)
    edge = max(w.reshape(S.shape + (-1,))[[0, -1]].max(), w.reshape(S.shape + (-1,))[:, [0, -1]].max())
    return np.exp(S.ravel()) @ w, np.exp(AA.ravel()) @ w, edge


def batch_error(x, nbatch=40):
    b = x[: x.shape[0] // nbatch * nbatch].reshape(nbatch, -1, x.shape[1]).mean(axis=1)
    return b.std(axis=0, ddof=1) / np.sqrt(nbatch)


def main():
    t = time.perf_counter()
    prob = gcrsky.standard_case(lmax=10, nside=32)
    system = prob.system()
    print(f"standard case lmax 10: n = {prob.n}, Nf = {system.data.shape[0]}, build {time.perf_counter() - t:.1f} s")
    key = jax.random.PRNGKey(0)
    rows = []
    for label, opts in (("gcr_step, CG (today)", None), ("gcr_step, Cholesky", gcrsky.CholeskyOptions())):
        nsteps = 20
        sec, out = _time(today_chain(system, opts, nsteps), key)
        extra = f"{float(np.mean(np.asarray(out[2]))):.1f} CG iterations a step" if opts is None else ""
        rows.append((label, 1e3 * sec / nsteps, nsteps, extra))
    t = time.perf_counter()
    state = jax.block_until_ready(prepare_scalar(system))
    first = time.perf_counter() - t
    t = time.perf_counter()
    state = jax.block_until_ready(prepare_scalar(system))
    setup = time.perf_counter() - t
    nsteps = 3000
    sec, (s, A) = _time(scalar_chain(state, nsteps), key)
    rows.append(("scalar state", 1e3 * sec / nsteps, nsteps, f"set-up once: {1e3 * setup:.0f} ms ({first:.1f} s with compiling)"))
    base = rows[0][1]
    print("\n| loop | ms/step | steps timed | speed-up | note |\n|---|---|---|---|---|")
    for label, ms, steps, note in rows:
        print(f"| {label} | {ms:.3g} | {steps} | {base / ms:.0f}x | {note} |")

    # the chain against the exact grid (a longer chain, burn-in 500)
    _, (s, A) = _time(scalar_chain(state, 20500), jax.random.PRNGKey(1), reps=1)
    s, A = np.asarray(s)[500:], np.asarray(A)[500:]
    es, eA, edge = grid_means(state)
    print(f"\nchain (20000 steps) vs exact grid (largest grid-edge weight {edge:.1e}):")
    print("| channel | E[s] chain | E[s] grid | (chain-grid)/err | E[A] chain | E[A] grid | (chain-grid)/err |")
    print("|---|---|---|---|---|---|---|")
    zs, zA = (s.mean(0) - es) / batch_error(s), (A.mean(0) - eA) / batch_error(A)
    for f in range(s.shape[1]):
        print(f"| {f} | {s[:, f].mean():.5f} | {es[f]:.5f} | {zs[f]:+.2f} | {A[:, f].mean():.4f} | {eA[f]:.4f} | "
              f"{zA[f]:+.2f} |")


if __name__ == "__main__":
    main()
