"""The small joint problem the frequency-coupled solver tests share (test_joint_frequency, _dataspace, _cg).

The shared 10-antenna hexagon's first 12 baselines, lmax 6 (n = 49), 4 channels 100-112 MHz around
``NU0`` = 106 MHz, ``NT`` = 16 angles, noise sigma ``SIGMA`` = 2e-3 (the data constrain the low modes
well and leave the high ones to the prior, so the channels' coupling matters), ``C_l = 50 / (1 + l)^2``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from gcrsky.model.operator import apply
from gcrsky.solvers.joint import JointSystem

LMAX = 6
N = (LMAX + 1) ** 2
FREQS = np.array([100e6, 104e6, 108e6, 112e6])
NU0 = 106e6
NT = 16
SIGMA = 2e-3
CL = 50.0 / (1.0 + np.arange(LMAX + 1)) ** 2


def simulate_joint(op, prior, seed: int, flagged=(), flag_fraction: float = 0.0) -> JointSystem:
    """Data from a truth drawn from the joint ``prior`` (dense Cholesky of ``S = R (x) diag(c)``) plus noise
    ``SIGMA``; channels ``flagged`` and a random ``flag_fraction`` of the other samples weight 0 (data 0)."""
    rng = np.random.default_rng(seed)
    S = np.kron(np.asarray(prior.freq_cov), np.diag(np.asarray(prior.mode_var)))
    truth = np.asarray(prior.mean) + (np.linalg.cholesky(S) @ rng.standard_normal(S.shape[0])).reshape(FREQS.size, N)
    v = np.asarray(apply(op, jnp.asarray(truth)))
    d = v + SIGMA * (rng.standard_normal(v.shape) + 1j * rng.standard_normal(v.shape))
    w = np.full(v.shape, SIGMA**-2)
    w[rng.random(v.shape) < flag_fraction] = 0.0
    w[list(flagged)] = 0.0
    d[w == 0] = 0.0
    return JointSystem(op, jnp.asarray(d), jnp.asarray(w), prior)
