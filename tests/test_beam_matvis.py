"""The beam block on matvis files whose dishes each have their own beam (issue 41).

matvis (independent of gcrsky's response) simulates 7 dishes whose E-field beams differ as
real ones do, parametrised physically (:class:`gcrsky.checks.beamsim.PerturbedDishBeam`:
widths scattered by 3 % per axis, pointings by 5 mrad), 3 channels, 24 times over 4 h, noise
1 % of the visibilities' rms (above the simulators' disagreement).  The file is read as a user
would (``from_uvdata``, every baseline kept: redundancy no longer holds), with the nominal
beam.  The nominal model is rejected; the joint (beam, sky) chain fits; the pointings are
recovered.  The control: a file whose dishes all share the nominal beam.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("matvis")

from gcrsky import ingest  # noqa: E402
from gcrsky.checks.beamsim import scattered_beams  # noqa: E402
from gcrsky.checks.matvis import HERA_SITE, observing_times, random_sky, site  # noqa: E402
from gcrsky.checks.uvsim import DipoleGaussianBeam, simulate_uvdata  # noqa: E402
from gcrsky.inference.beams import (  # noqa: E402
    beam_init,
    beam_setup,
    beam_sky_step,
    beam_step,
    beam_system,
    beam_warmup_step,
)
from gcrsky.instrument import hex_array, make_array  # noqa: E402
from gcrsky.instrument.beammodes import beam_modes, mode_responses  # noqa: E402
from gcrsky.model.gains import mode_basis  # noqa: E402
from gcrsky.model.operator import apply  # noqa: E402

LMAX, NSIDE = 8, 64
FREQS = np.array([100e6, 105e6, 110e6])
NOMINAL = DipoleGaussianBeam(diameter=14.0)
MODES = beam_modes(2)


def _problem(width_rms, offset_rms_rad):
    pos = hex_array((2, 3, 2))
    scatter = scattered_beams(len(pos), width_rms=width_rms, offset_rms_rad=offset_rms_rad, seed=2)
    sim = simulate_uvdata(pos, site(*HERA_SITE), observing_times("2025-03-21T18:00:00", 4.0, 24), FREQS,
                          scatter.beams, random_sky(LMAX, 3), LMAX, beam_idx=np.arange(len(pos)), nside_matvis=64,
                          pols=("xx",), noise_seed=None)
    uvd = sim.uvdata
    cross = uvd.ant_1_array != uvd.ant_2_array
    sigma = 1e-2 * np.sqrt(np.mean(np.abs(sim.model[cross]) ** 2))
    rng = np.random.default_rng(0)
    uvd.data_array = sim.model + sigma * (rng.standard_normal(sim.model.shape) + 1j * rng.standard_normal(sim.model.shape))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = ingest.from_uvdata(uvd, lmax=LMAX, nside=NSIDE, beam=NOMINAL, pol="xx", compress=False,
                                  band_limit="truncate", flux_scale="accept", noise=float(sigma))
    array = make_array(prob.antpos_enu_m, HERA_SITE[0], NOMINAL)
    lmax_resp = int(round(np.sqrt(prob.response.shape[-1]))) - 1
    stack = mode_responses(array, np.asarray(prob.antpairs), FREQS, lmax_resp, NSIDE, MODES,
                           lst_ref_rad=prob.lst_ref_rad, pols=list(prob.pols))
    block = beam_setup(stack, np.asarray(prob.antpairs), mode_basis(FREQS.size, 2, "legendre"), sigma=0.2,
                       mean_sigma=0.02)
    return prob, block, scatter


def _chi2(system, block, theta, sky):
    v = apply(beam_system(system, block, jnp.asarray(theta)).op, jnp.asarray(sky))
    return float(jnp.sum(system.inv_noise * jnp.abs(system.data - v) ** 2)) / (2 * np.sum(system.inv_noise > 0))


def _run(system, block, sweeps):
    state = beam_init(system.prior.mean, block)
    warm = jax.jit(lambda k, s: beam_warmup_step(k, s, system, block)[0])
    for k in jax.random.split(jax.random.PRNGKey(4), 5):
        state = warm(k, state)
    step = jax.jit(lambda k, s: beam_step(k, s, system, block)[0])
    chain = []
    for k in jax.random.split(jax.random.PRNGKey(1), sweeps):
        state = step(k, state)
        chain.append(np.asarray(state.theta))
    return state, np.stack(chain)


def _nominal_chi2(system, block):
    state, _ = jax.jit(lambda k, s: beam_sky_step(k, s, system, block))(jax.random.PRNGKey(0),
                                                                         beam_init(system.prior.mean, block))
    return _chi2(system, block, np.zeros(block.prior_mean.shape), state.sky)


@pytest.mark.slow
def test_dishes_with_their_own_beams_rejected_nominal_fitted_with_the_block():
    """Measured: the nominal model's chi2/dof 74 (3024 dof); with the block (5 warm-up steps, 150 sweeps of
    :func:`beam_step`) 1.02; the posterior-mean tilts (after 50) correlate with the true pointing offsets at
    0.99 (East and North; 0.91 East without the joint move and the warm-up).  The stack's unperturbed set
    equals the file's response (1e-14)."""
    prob, block, scatter = _problem(0.03, 0.005)
    assert float(jnp.max(jnp.abs(block.stack[:, 0] - prob.response)) / jnp.max(jnp.abs(prob.response))) < 1e-12
    system = prob.system()
    assert _nominal_chi2(system, block) > 10.0
    state, chain = _run(system, block, 150)
    assert _chi2(system, block, state.theta, state.sky) < 1.1
    mean = chain[50:].mean(0)
    assert np.corrcoef(mean[:, 0, 0], scatter.offset_east_rad)[0, 1] > 0.95
    assert np.corrcoef(mean[:, 1, 0], scatter.offset_north_rad)[0, 1] > 0.95


@pytest.mark.slow
def test_dishes_that_share_the_nominal_beam_the_block_finds_nothing():
    """The control: every dish the nominal beam.  Both models fit alike (chi2/dof within 0.1 of 1 and of each
    other; measured 0.99 and 1.01) and the block finds no perturbation worth the name: every posterior-mean
    coefficient below 0.04 (measured max 0.024; the scattered dishes' tilts reach 0.28).  Not 0 within its
    posterior sd, though (measured |mean| / sd up to 7 on 70 coefficients, sd ~0.005): at this noise (1 % of
    the rms) the block absorbs ~1e-3 of disagreement between matvis and gcrsky's quadrature."""
    prob, block, _ = _problem(0.0, 0.0)
    system = prob.system()
    nominal = _nominal_chi2(system, block)
    state, chain = _run(system, block, 150)
    fitted = _chi2(system, block, state.theta, state.sky)
    assert abs(nominal - 1.0) < 0.1 and abs(fitted - 1.0) < 0.1 and abs(fitted - nominal) < 0.1, (nominal, fitted)
    post = chain[50:]
    assert np.max(np.abs(post.mean(0))) < 0.04, np.max(np.abs(post.mean(0)))
