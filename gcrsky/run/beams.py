"""The draws of a run that samples every antenna's beam with the sky: a Markov chain, batch by batch into ``results.h5``.

With :class:`~gcrsky.run.RunSpec`'s ``sampling`` a :class:`~gcrsky.run.Beams` (``gcrsky run --data F --beams
sample``) the run draws from the joint posterior of the sky ``a`` and each antenna's beam perturbation
``theta`` (:mod:`gcrsky.inference.beams`; the model and its basis: :mod:`gcrsky.instrument.beammodes`,
``docs/beams.md``) instead of the sky's alone under the nominal beams:

1. **Set-up** (stage ``wiener``): the response sets of every mode pair (:func:`gcrsky.instrument.beammodes.
   mode_responses`, one per baseline: no redundant compression), checked against the problem's own
   response (their unperturbed set must equal it); the beam prior (:func:`gcrsky.inference.beam_setup`);
   then **Laplace's approximation** of the beams' marginal posterior ``p(theta | d)`` (the sky integrated
   out exactly, :func:`gcrsky.inference.beam_log_evidence`), which gives both the evidence of the block
   against the nominal beams (the summary's ``beams.evidence``) and the chain's proposal;
2. the **Wiener filter** recorded is the sky's posterior mean given the beams at the marginal's maximum; the
   goodness of fit (:mod:`gcrsky.run.fit`) tests the data against the same model, and the summary's
   ``beams.fit_nominal`` the nominal beams' fit (the same test without the block);
   The fit starts from :data:`WARM_START_STEPS` conditional-mode steps (:func:`gcrsky.inference.beam_warmup_step`)
   and ends with Newton steps on the exact Hessian;
3. **warm-up**: from a draw of the proposal (not from the maximum: an independence sampler started at the
   state of largest weight ``p / q``, ~``exp(0.2 K)`` above a typical one for ``K`` coefficients, stays there),
   ``beams.burn`` steps of the chain, discarded;
4. the **draws**: the collapsed chain (:func:`gcrsky.inference.beam_collapsed_step`: the beams by an
   independence Metropolis-Hastings move from their exact marginal with the Laplace Gaussian, widened by
   :data:`PROPOSAL_WIDEN`, as proposal; then the sky given them, exact).  Batch ``b`` is ``batch`` kept
   states, one every ``beams.thin`` steps, from the state the previous batch ended in; each batch appends
   the sky draws, the beam coefficients and the acceptance and replaces the chain's state, so a killed run
   resumes where it stopped.  This is the kernel that passed simulation-based calibration
   (``tests/test_beam_block.py``); the alternating one (sky, then beams given the sky) did not.

The exact marginal factorises a dense matrix per channel, in whichever form is smaller
(:func:`marginal_options`): the sky's precision (``n x n``, :class:`~gcrsky.solvers.CholeskyOptions`) or the
data-space matrix (``N_d x N_d``, ``N_d = 2 Nt Nbl`` real data values, :class:`~gcrsky.solvers.DataSpaceOptions`:
the whole sky to a file's reach, e.g. H1C's 10 integrations at lmax 200); a beam run is limited to
:data:`BEAM_DENSE_MAX_N` for the smaller.

Key scheme (:data:`BEAM_KEY_SCHEME`): warm-up ``fold_in(key, 2**31 - 1)``, batch ``b`` ``fold_in(key, b)``,
each split into one key per kept state, that into one per step.

``results.h5`` of a beam run (besides the standard datasets):

* ``beam_theta`` (ndraws, Nant, M, Q): each antenna's coefficients ``theta_ikq`` (``c_ik(nu) = sum_q theta_ikq
  B_q(nu)``: the voltage beam ``A_i = A_0 (1 + sum_k c_ik f_k)``); ``beam_info/accept`` (ndraws,) the mean
  acceptance of the independence move over the ``thin`` steps;
* ``beams/antenna_numbers`` (Nant,), ``beams/orders`` (M, 2) the Zernike ``(n, m)``, ``beams/basis_f`` (Nf, Q),
  ``beams/radius_rad`` (Nf,), ``beams/prior_inv_var`` (M, Q), ``beams/mean_inv_var`` (M, Q),
  ``beams/laplace_theta`` (Nant, M, Q), ``beams/proposal_mean`` (K,), ``beams/proposal_chol`` (K, K),
  ``beams/log_z`` (), ``beams/log_z_nominal`` (), ``beams/laplace_converged`` (), ``beams/setup_response``
  (Nf, Nbl, n) the response at ``laplace_theta`` (the Wiener filter's and the fit's), and the chain's last
  state ``beams/state/{sky, theta}``.
"""

from __future__ import annotations

import functools
import logging
import time
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..inference.amplitude import local_modes, log_evidence_over_u
from ..inference.api import prepare
from ..inference.beam_gains import BeamGainState, beam_gain_log_evidence, beam_gain_step, gain_row_factor, with_gains
from ..inference.beams import (
    beam_coefficients,
    beam_collapsed_step,
    beam_init,
    beam_log_evidence,
    beam_setup,
    beam_system,
    beam_warmup_step,
    check_amplitude_identified,
    refold_gram,
)
from ..inference.gains import GainState, gain_setup, recentre
from ..instrument.beammodes import beam_modes, combine_responses, disc_radius, mode_responses
from ..model.gains import gain_model, mode_basis, n_gain_params, perturbations, unit_gains
from ..solvers.plan import choose_path
from .amplitude import autos_ratio, draw_c
from .draws import append_chain_batch, read_chain, record_setup
from .gains import gain_layout_arrays, gained_problem, noise_at
from .output import BEAM_DIR, OpenRun
from .resume import options_json
from .stages import StageTimer, Watch

__all__ = ["BEAM_DENSE_MAX_N", "BEAM_GAIN_KEYS", "BEAM_KEY_SCHEME", "PROPOSAL_WIDEN", "BeamChain", "beam_chain_setup",
           "beam_draws", "beam_fit_problem", "beam_summary", "beamed_problem", "fit_without_gains", "modes_of",
           "write_beam_products"]

log = logging.getLogger(__name__)

#: The size of the dense matrix per channel up to which a beam run goes (the beams' exact marginal factorises it,
#: ``~Nf N^3 / 3`` flop, twice per step): the sky's precision (``n``, ``lmax <= 49``) or the data space's
#: (``N_d = 2 Nt Nbl``), whichever is smaller (:func:`marginal_options`).
BEAM_DENSE_MAX_N = 2500
#: The key scheme of a beam run's chain (module doc).
BEAM_KEY_SCHEME = ("beams-v2: Laplace fit from conditional modes fold_in(key, 2**31-2); start a proposal draw "
                   "fold_in(key, 2**31-3); warm-up fold_in(key, 2**31-1); batch b fold_in(key, b); each split per "
                   "kept state, then per step; collapsed independence MH; with the amplitude the sky model's scale c "
                   "of batch b from fold_in(fold_in(key, b), 2**31-1)")
#: What a beam run that samples the gains adds to :data:`BEAM_KEY_SCHEME`.
BEAM_GAIN_KEYS = ("; gains: fitted with the beams (no keys), the start and every move joint in (theta, log_u, gains)")
#: Joint Laplace fits of the beams, amplitude and gains in a run that samples the gains, the gains' linearisation
#: point moved to each fit's maximum before the next (:func:`_gain_fit`).
GAIN_FITS = 2
#: The proposal's covariance is the Laplace covariance times ``PROPOSAL_WIDEN**2`` (heavier than the marginal's
#: bulk, so that the importance weights stay bounded where the marginal is not quite Gaussian).
PROPOSAL_WIDEN = 1.1
#: Acceptance of the independence move below which the summary warns (the chain then sticks).
LOW_ACCEPT = 0.1
_WARM = 2**31 - 1
_START = 2**31 - 2
_SCALE = 2**31 - 1  # folded into a batch's key: the sky model's scale c of its kept states
#: Steps to the beams' conditional mode (:func:`gcrsky.inference.beam_warmup_step`) from which the Laplace fit
#: starts (from the nominal beams BFGS stalls far from the maximum: on a 7-dish twin at an indefinite Hessian).
WARM_START_STEPS = 5
#: Newton steps after BFGS in the Laplace fit (:func:`gcrsky.inference.beam_log_evidence`; it stops earlier once
#: at the maximum).
NEWTON_STEPS = 30
#: Relative difference between the response sets' unperturbed set and the problem's response that is refused.
RESPONSE_RTOL = 1e-8


def modes_of(sampling):
    """The :class:`~gcrsky.instrument.beammodes.BeamModes` of a :class:`~gcrsky.run.BeamSampling`."""
    return beam_modes(sampling.nmax, piston=sampling.piston)


class BeamChain(NamedTuple):
    """The chain's fixed parts and state (:func:`beam_chain_setup`).

    Attributes:
        system: the sky's linear system (raw data, noise, prior; its response is replaced per step).
        block: the :class:`gcrsky.inference.BeamBlock`.
        proposal: ``(mean (K,), chol (K, K))`` of the independence move.
        state: the :class:`gcrsky.inference.BeamState`.
        radius: (Nf,) the modes' disc radius, radians.
        options: the marginal's path (:func:`marginal_options`) for the sky draws (and BFGS).
        gram: the data-space Grams of the response sets (:func:`gcrsky.inference.beam_gram`): the marginal of every
            MH step and Newton step from them; None where they do not fit the memory (then ``options``' path).
        noise_log_u: (Nf,) the amplitude at which the sky part of the system's noise is evaluated (the fit's
            start), or None (the amplitude not inferred).
        gains: the gain block (:class:`gcrsky.inference.gains.GainBlock`) about the linearisation point where the
            gains are sampled, else None; ``block`` is then the beams' own, the gains' factor folded in per step.
        lin: (Nf, Nt, U) complex, the units' gains at the linearisation point (None without gains).
        gain_theta: (P,) the gain perturbations of the chain's state (None without gains).
    """

    system: object
    block: object
    proposal: tuple
    state: object
    radius: np.ndarray
    options: object = None
    gram: object = None
    noise_log_u: object = None
    gains: object = None
    lin: object = None
    gain_theta: object = None


def _site_latitude(prob) -> float:
    conv = getattr(prob.config, "conventions", None) or {}
    if "site_lat_lon_alt" not in conv:
        raise ValueError("a beam run needs the array's site (a problem read from a file records it)")
    return float(conv["site_lat_lon_alt"][0])


def data_values(prob) -> int:
    """``N_d``: the real data values per channel (``2 Nt Nbl``), the data-space matrix's size."""
    return 2 * int(prob.data.shape[1]) * int(prob.data.shape[2])


def marginal_options(prob):
    """The path of the beams' exact marginal (and the sky draws given the beams): the dense Cholesky of the sky's
    precision where ``n <= N_d``, else the data space (:data:`BEAM_DENSE_MAX_N` bounds the smaller)."""
    from ..solvers.options import CholeskyOptions, DataSpaceOptions

    return CholeskyOptions() if prob.n <= data_values(prob) else DataSpaceOptions()


def check_beam_problem(prob, sampling) -> None:
    """Refuse what the beam block cannot model, naming it: redundant groups as rows, autocorrelation rows, a
    problem without antenna positions, or both the coefficients and the data values per channel more than
    :data:`BEAM_DENSE_MAX_N` (:func:`marginal_options`)."""
    if getattr(prob.config, "compressed", False):
        raise ValueError("beams are per antenna, but the problem's rows are redundant groups (averages of baselines "
                         "whose beams differ): read the file without compression (--no-compress)")
    if prob.antpos_enu_m is None:
        raise ValueError("a beam run needs the antennas' positions (a problem read from a file records them)")
    pairs = np.asarray(prob.antpairs)
    if np.any(pairs[:, 0] == pairs[:, 1]):
        raise ValueError("the beam block models cross-correlations only, but the problem has autocorrelation rows")
    nd = data_values(prob)
    if min(prob.n, nd) > BEAM_DENSE_MAX_N:
        lmax = int(np.floor(np.sqrt(BEAM_DENSE_MAX_N))) - 1
        raise ValueError(f"--beams sample integrates the sky out exactly (a dense matrix per channel: the sky's "
                         f"precision or the data space's, whichever is smaller): at most {BEAM_DENSE_MAX_N}, but lmax "
                         f"{prob.lmax} has {prob.n} coefficients and the data {nd} values per channel "
                         f"({prob.data.shape[1]} times x {prob.data.shape[2]} baselines x 2): give --lmax {lmax} or "
                         "less, or fewer times or baselines (--lst-range, --antennas)")


def beam_chain_setup(prob, beams, sampling) -> BeamChain:
    """The response sets, the beam prior and the chain at the prior mean (no Laplace fit yet).

    Args:
        prob: the :class:`~gcrsky.model.Problem` (rows: antenna pairs, every baseline).
        beams: the nominal beams, one per antenna of ``prob.antpos_enu_m`` (as the problem was built with).
        sampling: the :class:`~gcrsky.run.BeamSampling`.

    Raises:
        ValueError: :func:`check_beam_problem`'s refusals, a beam count that is not the antennas', or response
            sets whose unperturbed set differs from the problem's response (other beams, frame or rows).
    """
    from ..instrument import make_array

    check_beam_problem(prob, sampling)
    nant = np.asarray(prob.antpos_enu_m).shape[0]
    if len(beams) != nant:
        raise ValueError(f"{len(beams)} nominal beams for {nant} antennas")
    modes = modes_of(sampling)
    array = make_array(np.asarray(prob.antpos_enu_m), _site_latitude(prob), list(beams))
    lmax_resp = int(round(np.sqrt(prob.response.shape[-1]))) - 1
    freqs = np.asarray(prob.freqs_hz)
    stack = mode_responses(array, np.asarray(prob.antpairs), freqs, lmax_resp, prob.nside, modes,
                           lst_ref_rad=prob.lst_ref_rad, pols=None if prob.pols is None else list(prob.pols))
    ref = np.asarray(prob.response)
    diff = float(np.max(np.abs(np.asarray(stack[:, 0]) - ref)) / max(float(np.max(np.abs(ref))), 1e-300))
    if not diff < RESPONSE_RTOL:
        raise ValueError(f"the beam modes' unperturbed response differs from the problem's by {diff:.2g} (relative): "
                         "the problem was not built with these beams, rows or quadrature")
    basis_f = mode_basis(freqs.size, min(sampling.freq_modes, freqs.size), "legendre")
    block = beam_setup(stack, np.asarray(prob.antpairs), basis_f, sigma=sampling.sigma,
                       mean_sigma=sampling.mean_sigma, n_ant=nant)
    k = block.prior_mean.size + (freqs.size if sampling.amplitude is not None else 0)
    zero = (jnp.zeros(k), jnp.eye(k))
    log_u = None if sampling.amplitude is None else jnp.full(freqs.size, np.log(autos_ratio(prob) or 1.0))
    system = _noise_system(prob, log_u)
    chain = BeamChain(system, block, zero, beam_init(system.prior.mean, block, log_u=log_u),
                      disc_radius(beams[0], freqs, modes), marginal_options(prob))
    if sampling.gains is None:
        return chain
    g = sampling.gains
    nt = prob.data.shape[1]
    model = gain_model(prob.antpairs, freqs.size, nt, g.modes, basis=g.basis, pols=prob.pols)
    lin = np.ones((freqs.size, nt, model.units.shape[0]), complex)
    return chain._replace(gains=gain_setup(model, sigma=g.sigma, gbar=lin), lin=lin,
                          gain_theta=jnp.zeros(n_gain_params(model)))


def _noise_system(prob, log_u, factor=None):
    """The sky's system, the sky part of its noise (``--band-limit marginalise``) through the amplitude ``exp(log_u)``
    (Nf,) where inferred and the gains' factor (Nf, Nt, Nbl) where sampled (it is the sky's:
    :func:`gcrsky.run.gains.noise_at`)."""
    if log_u is None and factor is None:
        return prob.system()
    u = 1.0 if log_u is None else np.exp(np.asarray(log_u))[:, None, None]
    return noise_at(prob, u * (1.0 if factor is None else np.asarray(factor))).system()


def _gain_factor(chain: BeamChain):
    """The gains' factor (Nf, Nt, Nbl) at the linearisation point, or None without gains."""
    return None if chain.gains is None else np.asarray(chain.gains.pair_gains)


def _fit_block(chain: BeamChain):
    """The beam block with the gains' factor at their linearisation point folded in (the Laplace fit's and the Wiener
    filter's model); the block itself without gains."""
    if chain.gains is None:
        return chain.block
    return with_gains(chain.block, chain.gains, jnp.zeros_like(chain.gain_theta))


def _joint_state(chain: BeamChain):
    """The chain's state as its kernel takes it: the :class:`BeamState`, or with gains a :class:`BeamGainState`."""
    return chain.state if chain.gains is None else BeamGainState(chain.state, chain.gain_theta)


#: Fraction of the free memory the data-space Grams of a beam run may take (else the marginal takes the sky draws'
#: path at every step).
GRAM_MEMORY_FRACTION = 0.25


def _gram(chain: BeamChain):
    """The data-space Grams of the chain's system and block (:func:`gcrsky.inference.beam_gram`), or None with a log
    line where they would take more than :data:`GRAM_MEMORY_FRACTION` of the free memory."""
    from ..base.memory import available_memory_bytes, format_bytes
    from ..inference.beams import beam_gram, beam_gram_bytes

    need = beam_gram_bytes(chain.system, chain.block)
    if need > GRAM_MEMORY_FRACTION * available_memory_bytes():
        log.info("beams: the data-space Grams (%s) do not fit; the marginal takes the %s path at every step",
                 format_bytes(need), _path_name(chain.options))
        return None
    t0 = time.perf_counter()
    gram = jax.block_until_ready(jax.jit(beam_gram)(chain.system, chain.block))
    log.info("beams: data-space Grams of the response sets (%s) in %.1f s", format_bytes(need), time.perf_counter() - t0)
    return gram


def _fit_from(prob, chain: BeamChain, key, log_u):
    """The Laplace fit (:func:`gcrsky.inference.beam_log_evidence`) from :data:`WARM_START_STEPS` conditional-mode
    steps, the amplitude started (and the sky part of the noise evaluated) at ``log_u`` (None: not inferred)."""
    if log_u is not None:
        chain = chain._replace(system=_noise_system(prob, log_u, _gain_factor(chain)),
                               state=chain.state._replace(log_u=jnp.asarray(log_u)), noise_log_u=np.asarray(log_u))
    if chain.gram is None:
        chain = chain._replace(gram=_gram(chain))
    elif prob.sigma_sky is not None:  # the noise depends on u: the Grams' data and noise folded again (not the Grams)
        chain = chain._replace(gram=refold_gram(chain.gram, chain.system, chain.block))
    warm = jax.jit(lambda k, st, g: beam_warmup_step(k, st, chain.system, chain.block, options=chain.options,
                                                     gram=g)[0])
    start = chain.state
    for k in jax.random.split(jax.random.fold_in(key, _START), WARM_START_STEPS):
        start = warm(k, start, chain.gram)
    ev = beam_log_evidence(chain.system, chain.block, theta0=start.theta, amplitude=log_u is not None, log_u0=log_u,
                           options=chain.options, newton_steps=NEWTON_STEPS, gram=chain.gram)
    return ev, chain


def _laplace_fit(prob, chain: BeamChain, key):
    """The Laplace fit of the beams' marginal; with the amplitude inferred, from the nominal beams' most probable
    ``u`` and, where it differs, from the nominal's mode nearest the autos' ratio (a mis-specified nominal model
    can prefer an amplitude far from the truth: a large ``u``, where the prior no longer constrains the sky and
    an unconstrained sky absorbs the beams' misfit): the fit whose
    maximum is higher is kept, and the other's logged.  Returns ``(evidence, chain, log_u_fit)``: ``log_u_fit`` the
    nominal beams' mode nearest the block's amplitude (their goodness of fit's: :func:`beam_summary`), or None."""
    if chain.state.log_u is None:
        return (*_fit_from(prob, chain, key, None), None)
    nom = log_evidence_over_u(beam_system(chain.system, chain.block, jnp.zeros_like(chain.block.prior_mean)))
    check_amplitude_identified(nom)
    top = np.asarray(nom.log_u)
    near = local_modes(nom, np.log(autos_ratio(prob) or 1.0))
    log.info("beams: the nominal beams' amplitude u per channel %s (the mode nearest the autos' ratio %s: %s)",
             np.array2string(np.exp(top), precision=4), autos_ratio(prob), np.array2string(np.exp(near), precision=4))
    fits = [_fit_from(prob, chain, key, top)]
    if np.max(np.abs(near - top)) > 4 * float(np.max(np.asarray(nom.sd))):
        fits.append(_fit_from(prob, chain._replace(gram=fits[0][1].gram), key, near))
    scores = [float(ev.log_z) if np.isfinite(float(ev.log_z)) else -np.inf for ev, _ in fits]
    if len(fits) > 1:
        log.info("beams: Laplace log evidence from the nominal's maximum %.2f, from its mode nearest the autos' %.2f: "
                 "kept the %s", scores[0], scores[1], "first" if scores[0] >= scores[1] else "second")
    ev, chain = fits[int(np.argmax(scores))]
    return ev, chain, local_modes(nom, np.asarray(ev.log_u))


def beamed_problem(prob, response):
    """``prob`` with the response (Nf, Nbl, n) of perturbed beams: the sky's likelihood given them."""
    return eqx.tree_at(lambda p: p.response, prob, jnp.asarray(response))


def _proposal(mean, cov):
    cov = np.asarray(cov)
    cov = 0.5 * (cov + cov.T) * PROPOSAL_WIDEN**2
    try:
        chol = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise ValueError("the beams' Laplace covariance is not positive definite (the fit of their marginal did not "
                         "reach a maximum): give a smaller --beam-sigma or fewer --beam-modes") from None
    return jnp.asarray(np.asarray(mean).reshape(-1)), jnp.asarray(chol)


@functools.partial(jax.jit, static_argnames=("n", "thin", "options"))
def _segment(system, block, proposal, state, key, gram=None, gains=None, *, n: int, thin: int, options=None):
    """``n`` kept states, one every ``thin`` steps: (last state, (states, mean acceptance, sky SolveInfo)); with
    ``gains`` (a GainBlock; ``state`` a BeamGainState) the joint kernel with the gains
    (:func:`gcrsky.inference.beam_gains.beam_gain_step`), else the collapsed beam chain's."""

    def step(s, k):
        if gains is not None:
            return beam_gain_step(k, s, system, block, gains, proposal, options=options, gram=gram, with_info=True)
        return beam_collapsed_step(k, s, system, block, proposal, options=options, with_info=True, gram=gram)

    def keep(s, k):
        s, (acc, info) = jax.lax.scan(step, s, jax.random.split(k, thin))
        return s, (s, jnp.mean(acc.astype(jnp.float64)), jax.tree_util.tree_map(lambda x: x[-1], info))

    return jax.lax.scan(keep, state, jax.random.split(key, n))


def _state_arrays(state) -> dict:
    """The chain's state as ``results.h5`` keeps it (``beams/state/``), a BeamState or a BeamGainState."""
    gain_theta = None
    if isinstance(state, BeamGainState):
        state, gain_theta = state.beam, state.gain_theta
    out = {"beams/state/sky": np.asarray(state.sky), "beams/state/theta": np.asarray(state.theta)}
    if state.log_u is not None:
        out["beams/state/log_u"] = np.asarray(state.log_u)
    if gain_theta is not None:
        out["beams/state/gain_theta"] = np.asarray(gain_theta)
    return out


def _per_draw(chain: BeamChain) -> dict:
    out = {"beam_theta": (tuple(chain.block.prior_mean.shape), "f8",
                          "(ndraws, Nant, M, Q): c_ik(nu) = sum_q theta_ikq B_q(nu); A_i = A_0 (1 + sum_k c_ik f_k)"),
           "beam_info/accept": ((), "f8", "(ndraws,) mean acceptance of the beams' independence move over thin steps")}
    if chain.state.log_u is not None:
        nf = chain.state.log_u.shape[0]
        out.update({"amplitude_q": ((nf,), "f8", "(ndraws, Nf): q = u / c, data = q x the sky model's visibilities "
                                                 "in K through the beams"),
                    "amplitude_u": ((nf,), "f8", "(ndraws, Nf): u = q c, what the data measure"),
                    "amplitude_c": ((), "f8", "(ndraws,): the sky model's scale, a = c (a0 + delta)")})
    if chain.gains is not None:
        nf, nt, nu = chain.lin.shape
        out.update({"gain_draws": ((nf, nt, nu), "c16", "(ndraws, Nf, Nt, U) complex: g_u = gbar_u sqrt(q) (1 + x_u), "
                                                        "q the amplitude (1 where not inferred)"),
                    "gain_theta": ((int(chain.gain_theta.size),), "f8", "(ndraws, P)")})
    return out


def _layout_arrays(prob, chain: BeamChain, sampling, ev, response, factor=None) -> dict:
    conv = getattr(prob.config, "conventions", None) or {}
    nant = chain.block.prior_mean.shape[0]
    nums = np.asarray(conv.get("antenna_numbers", np.arange(nant)))
    return {"beams/antenna_numbers": nums, "beams/orders": np.asarray(modes_of(sampling).orders, np.int64),
            "beams/basis_f": np.asarray(chain.block.basis_f), "beams/radius_rad": np.asarray(chain.radius),
            "beams/prior_inv_var": np.asarray(chain.block.prior_inv_var),
            "beams/mean_inv_var": np.asarray(chain.block.mean_inv_var), "beams/laplace_theta": np.asarray(ev.theta),
            "beams/proposal_mean": np.asarray(chain.proposal[0]), "beams/proposal_chol": np.asarray(chain.proposal[1]),
            "beams/log_z": np.asarray(ev.log_z), "beams/log_z_nominal": np.asarray(ev.log_z_nominal),
            "beams/laplace_converged": np.asarray(bool(ev.converged)), "beams/setup_response": np.asarray(response),
            **({} if ev.log_u is None else {"beams/laplace_log_u": np.asarray(ev.log_u),
                                             "beams/log_u_nominal": np.asarray(ev.log_u_nominal),
                                             "beams/noise_log_u": np.asarray(chain.noise_log_u)}),
            **({} if chain.gains is None else gain_layout_arrays(prob, chain.gains, chain.lin, factor))}


def _setup(prob, beams, spec, run: OpenRun, key) -> BeamChain:
    """New run: set up, fit the marginal (Laplace), with gains burn them in and fit it again at their linearisation
    point, record the Wiener filter given its maximum, warm up; resumed: the recorded proposal and state."""
    sampling = spec.sampling.beams
    chain = beam_chain_setup(prob, beams, sampling)
    if run.state is not None:
        return _read_chain(prob, chain, run.h5)
    t0 = time.perf_counter()
    ev, fitted, log_u_fit = _laplace_fit(prob, chain._replace(block=_fit_block(chain)), key)
    chain = fitted._replace(block=chain.block, proposal=_proposal(_best(ev), ev.covariance))
    log.info("beams: Laplace fit of the marginal in %.1f s: log Bayes factor %.2f against the nominal beams "
             "(converged: %s)", time.perf_counter() - t0, float(ev.log_bayes_factor), bool(ev.converged))
    factor = nominal_factor = None
    if chain.gains is not None:
        chain, ev = _gain_fit(prob, chain, ev)
        log_u_fit = None if ev.log_u is None else np.asarray(ev.log_u_nominal)
        factor = np.asarray(gain_row_factor(chain.gains, ev.gain_theta))  # the gains at the joint maximum
        nominal_factor = np.asarray(gain_row_factor(chain.gains, ev.gain_theta_nominal))
    response = combine_responses(chain.block.stack, chain.block.pairs, beam_coefficients(chain.block, ev.theta))
    if ev.log_u is not None:
        response = response * jnp.exp(ev.log_u)[:, None, None]
    prob_b = _model_problem(prob, response, ev.log_u, factor)
    options = choose_path(prob_b.system(), spec.solver.method, tol=spec.solver.tol, ndraws=1)
    prepared = prepare(prob_b, options=options)
    a_wf = np.asarray(jax.block_until_ready(prepared.a_wf))
    mean, chol = chain.proposal  # start from a proposal draw, not the maximum: the maximum has the largest
    z = jax.random.normal(jax.random.fold_in(key, _START - 1), mean.shape, mean.dtype)  # weight p/q of all (by
    x = mean + chol @ z  # ~e^{0.2 K})
    k, nu = ev.theta.size, 0 if ev.log_u is None else ev.log_u.size
    chain = chain._replace(state=beam_init(jnp.asarray(a_wf), chain.block, theta=x[:k].reshape(ev.theta.shape),
                                           log_u=None if ev.log_u is None else x[k:k + nu]))
    if chain.gains is not None:
        chain = chain._replace(gain_theta=x[k + nu:])
    if sampling.burn:
        state, _ = _segment(chain.system, chain.block, chain.proposal, _joint_state(chain),
                            jax.random.fold_in(key, _WARM), chain.gram, chain.gains, n=1, thin=sampling.burn,
                            options=chain.options)
        chain = _with_state(chain, state)
    record_setup(prob, spec, run, a_wf, prepared.wiener, rank=getattr(prepared, "kept", None), method=_method(chain),
                 options=options, key_scheme=BEAM_KEY_SCHEME + ("" if chain.gains is None else BEAM_GAIN_KEYS),
                 per_draw=_per_draw(chain),
                 arrays={**_layout_arrays(prob, chain, sampling, ev, response, factor),
                         **_state_arrays(_joint_state(chain)),
                         **({} if log_u_fit is None else {"beams/log_u_nominal_fit": np.asarray(log_u_fit)}),
                         **({} if nominal_factor is None else {"beams/nominal_gain_factor": nominal_factor})})
    log.info("beam chain: Wiener filter given the beams at the marginal's maximum by %s (%s); warm-up of %d steps",
             prepared.method, options_json(options), sampling.burn)
    return chain


def _best(ev):
    """The Laplace maximum as the proposal's mean: ``theta`` flattened, then ``log_u`` where inferred, then the gains'
    perturbations where sampled (a :class:`gcrsky.inference.beam_gains.BeamGainEvidence`)."""
    parts = [ev.theta.reshape(-1)] + ([] if ev.log_u is None else [ev.log_u])
    return jnp.concatenate(parts + ([ev.gain_theta] if hasattr(ev, "gain_theta") else []))


def _with_state(chain: BeamChain, state) -> BeamChain:
    """``chain`` with the kernel's state (a BeamState, or a BeamGainState with gains) as its own."""
    if isinstance(state, BeamGainState):
        return chain._replace(state=state.beam, gain_theta=state.gain_theta)
    return chain._replace(state=state)


def _read_chain(prob, chain: BeamChain, h5) -> BeamChain:
    """A resumed run's chain: the recorded proposal, state, amplitude of the noise and (with gains) linearisation."""
    import h5py

    with h5py.File(h5, "r") as h:
        proposal = (jnp.asarray(h["beams/proposal_mean"][()]), jnp.asarray(h["beams/proposal_chol"][()]))
        inferred = chain.state.log_u is not None
        state = chain.state._replace(sky=jnp.asarray(h["beams/state/sky"][()]),
                                     theta=jnp.asarray(h["beams/state/theta"][()]),
                                     log_u=jnp.asarray(h["beams/state/log_u"][()]) if inferred else None)
        noise_log_u = h["beams/noise_log_u"][()] if inferred else None
        if chain.gains is not None:
            gains = chain.gains._replace(pair_gains=jnp.asarray(h["gains/pair_gains"][()]),
                                         prior_mean=jnp.asarray(h["gains/prior_mean"][()]))
            chain = chain._replace(gains=gains, lin=h["gains/linearisation"][()],
                                   gain_theta=jnp.asarray(h["beams/state/gain_theta"][()]))
    chain = chain._replace(proposal=proposal, state=state, noise_log_u=noise_log_u,
                           system=_noise_system(prob, noise_log_u, _gain_factor(chain)))
    return chain._replace(gram=_gram(chain))


def _gain_fit(prob, chain: BeamChain, ev):
    """The beams, the amplitude (where inferred) and the gains fitted jointly (:func:`gcrsky.inference.beam_gains.
    beam_gain_log_evidence`: Laplace by Newton on their exact marginal, the sky integrated out), from the beams-only
    fit ``ev`` and the gains at their linearisation point; :data:`GAIN_FITS` times, the linearisation point moved
    to the maximum's gains before each further fit (:func:`gcrsky.inference.gains.recentre`: the linearised
    model's error is then second order in what is left).  Returns ``(chain, evidence)``: the chain's proposal the
    last fit's Gaussian, widened."""
    theta, log_u, gain_theta = ev.theta, ev.log_u, chain.gain_theta
    t0 = time.perf_counter()
    for i in range(GAIN_FITS):
        if i:  # the linearisation point to the last maximum's gains
            block, _ = recentre(chain.gains, GainState(None, gain_theta, None))
            lin = np.asarray(chain.lin * (1.0 + perturbations(block.model, gain_theta)))
            chain = chain._replace(gains=block, lin=lin)
            gain_theta = jnp.zeros_like(gain_theta)
            if prob.sigma_sky is not None:  # the sky part of the noise through the gains found
                chain = chain._replace(system=_noise_system(prob, chain.noise_log_u, _gain_factor(chain)))
        ev = beam_gain_log_evidence(chain.system, chain.block, chain.gains, theta0=theta, gain_theta0=gain_theta,
                                    log_u0=log_u, options=chain.options, gram=chain.gram, newton_steps=NEWTON_STEPS,
                                    nominal=i == GAIN_FITS - 1)  # the nominal model's fit only where it is used
        theta, log_u, gain_theta = ev.theta, ev.log_u, ev.gain_theta
        log.info("beams: joint fit %d/%d of the beams%s and gains: log evidence %.2f (against the nominal beams with "
                 "gains: %.2f), largest gain perturbation %.3g (converged: %s)", i + 1, GAIN_FITS,
                 "" if log_u is None else ", amplitude", float(ev.log_z), float(ev.log_bayes_factor),
                 float(jnp.max(jnp.abs(gain_theta))), bool(ev.converged))
    log.info("beams: joint fits with the gains in %.1f s", time.perf_counter() - t0)
    return chain._replace(proposal=_proposal(_best(ev), ev.covariance), gain_theta=ev.gain_theta), ev


def _model_problem(prob, response, log_u=None, factor=None):
    """``prob`` with the response (Nf, Nbl, n) of the beams (times the amplitude ``exp(log_u)`` where inferred) and the
    gains' factor (Nf, Nt, Nbl) divided out where sampled; the sky part of the noise through both: the sky's
    likelihood given them (the Wiener filter's and the goodness of fit's model)."""
    u = None if log_u is None else np.exp(np.asarray(log_u))
    if factor is not None:
        base = gained_problem(prob, factor, u)
    else:
        base = prob if u is None else noise_at(prob, u[:, None, None])
    return beamed_problem(base, response)


def beam_draws(prob, beams, spec, run: OpenRun, st: StageTimer, watch: Watch) -> str:
    """The ``wiener`` stage (set-up, Laplace fit, with gains their burn-in, Wiener filter, warm-up) and the chain's
    batches from ``run.start``; returns ``"beams+cholesky"`` or ``"beams+dataspace"`` (``"beams+gains+..."`` with
    gains; :func:`marginal_options`) and leaves the ``draws`` stage running."""
    d, sampling = spec.draws, spec.sampling.beams
    key = jax.random.PRNGKey(d.seed)
    st.start("wiener")
    chain = _setup(prob, beams, spec, run, key) if run.start < d.n_batches else None
    st.stop()
    st.start("draws")
    batches = range(run.start, d.n_batches)
    state = None if chain is None else _joint_state(chain)
    thin = sampling.thin if sampling.gains is None else sampling.gains.thin
    for b in watch.progress(batches) if watch.progress is not None else batches:
        t0 = time.perf_counter()
        state, (states, accept, info) = _segment(chain.system, chain.block, chain.proposal, state,
                                                 jax.random.fold_in(key, b), chain.gram, chain.gains, n=d.batch,
                                                 thin=thin, options=chain.options)
        take = min(d.batch, d.nsamples - b * d.batch)
        beam_states = states.beam if chain.gains is not None else states
        extra = {"beam_theta": np.asarray(beam_states.theta)[:take], "beam_info/accept": np.asarray(accept)[:take]}
        sky = beam_states.sky
        q = np.ones((d.batch, prob.data.shape[0]))
        if sampling.amplitude is not None:  # a = c a', q = u / c: c from the sky model's prior (module doc)
            c = np.asarray(draw_c(jax.random.fold_in(jax.random.fold_in(key, b), _SCALE), sampling.amplitude.model_sd,
                                  (d.batch,)))
            u = np.exp(np.asarray(beam_states.log_u))
            sky = c[:, None, None] * np.asarray(sky)
            q = u / c[:, None]
            extra.update({"amplitude_q": q[:take], "amplitude_u": u[:take], "amplitude_c": c[:take]})
        if chain.gains is not None:
            g = jax.vmap(lambda t: unit_gains(chain.gains.model, t, 1.0, chain.lin))(states.gain_theta[:take])
            extra.update({"gain_draws": np.sqrt(q[:take])[:, :, None, None] * np.asarray(g),
                          "gain_theta": np.asarray(states.gain_theta)[:take]})
        append_chain_batch(run, b, take, sky, info, extra, _state_arrays(state), t0)
    if chain is None:
        return "beams+" + ("gains+" if sampling.gains is not None else "") + _path_name(marginal_options(prob))
    return _method(chain)


def _path_name(options) -> str:
    from ..solvers.options import DataSpaceOptions

    return "dataspace" if isinstance(options, DataSpaceOptions) else "cholesky"


def _method(chain: BeamChain) -> str:
    """What ran: ``beams+cholesky`` or ``beams+dataspace`` (the marginal's path), ``beams+gains+...`` with gains."""
    return "beams+" + ("gains+" if chain.gains is not None else "") + _path_name(chain.options)


def beam_fit_problem(prob, h5):
    """The problem at a beam run's set-up: the response (Nf, Nbl, n) at the beams (and amplitude) of its Wiener
    filter (``beams/setup_response``), the gains' factor there divided out where they are sampled
    (``gains/setup_factor``), the sky part of the noise through both (``--band-limit marginalise``): the goodness
    of fit's model."""
    import h5py

    with h5py.File(h5, "r") as h:
        response = h["beams/setup_response"][()]
        log_u = h["beams/laplace_log_u"][()] if "beams/laplace_log_u" in h else None
        factor = h["gains/setup_factor"][()] if "gains/setup_factor" in h else None
    return _model_problem(prob, response, log_u, factor)


def _read(h5) -> dict:
    out = read_chain(h5, ("beam_theta", "beam_info/accept"),
                     tuple(f"beams/{k}" for k in ("antenna_numbers", "orders", "basis_f", "radius_rad", "prior_inv_var",
                                                  "laplace_theta", "log_z", "log_z_nominal", "laplace_converged")),
                     optional=("beams/log_u_nominal", "beams/log_u_nominal_fit", "beams/nominal_gain_factor"))
    out["theta"] = out.pop("beam_theta")
    return out


def _nominal_fit(prob, log_u=None, factor=None) -> dict:
    """The goodness of fit of the nominal beams (the same test as the run's, without the block), with the amplitude
    ``exp(log_u)`` (Nf,) where it is inferred: the nominal beams' most probable amplitude near the block's (their
    global maximum may be far away, where an unconstrained sky absorbs the beams' misfit); with the gains' factor
    (Nf, Nt, Nbl) where they are sampled: the gains the run found (with the beams)."""
    u = 1.0 if log_u is None else np.exp(np.asarray(log_u))[:, None, None]
    return _fit_of(_model_problem(prob, np.asarray(prob.response) * u, log_u, factor))


def fit_without_gains(prob, h5) -> dict:
    """The goodness of fit of a beam run that samples the gains, at its set-up's beams and amplitude but the file's
    gains (the gains' factor not divided out): whether the data ask for the gains, as ``fit_nominal`` says for the
    beams."""
    import h5py

    with h5py.File(h5, "r") as h:
        response = h["beams/setup_response"][()]
        log_u = h["beams/laplace_log_u"][()] if "beams/laplace_log_u" in h else None
    return _fit_of(_model_problem(prob, response, log_u, None))


def _fit_of(prob) -> dict:
    """:func:`gcrsky.run.fit.goodness_of_fit` of ``prob``'s Wiener filter (the automatic path), its headline keys."""
    from .fit import goodness_of_fit

    options = choose_path(prob.system(), "auto", ndraws=1)
    prepared = prepare(prob, options=options)
    gof = goodness_of_fit(prob, np.asarray(prepared.a_wf), rank=getattr(prepared, "kept", None))
    return {k: gof[k] for k in ("chi2", "dof", "chi2_per_dof", "p_value", "p_value_low", "rejected",
                                "rejected_channels", "threshold_p")}


def beam_summary(prob, sampling, h5) -> dict:
    """``summary.json``'s ``beams`` block: the evidence of the block against the nominal beams (Laplace), the
    nominal beams' goodness of fit (the run's own ``goodness_of_fit`` is the block's), each antenna's
    posterior coefficients (mean and sd per mode, averaged over frequency modes' first: the constant), the
    acceptance, and :func:`gcrsky.inference.chain_diagnostics` of every coefficient with its warning."""
    from ..inference.diagnostics import chain_diagnostics, diagnostics_warning

    g = _read(h5)
    th = g["theta"]  # (ndraws, Nant, M, Q)
    nd = th.shape[0]
    names = [n for n in modes_of(sampling).names]
    z_max = None
    if nd > 1:
        sd = th.std(axis=0, ddof=1)
        z = np.abs(th.mean(axis=0)) / np.where(sd > 0, sd, np.inf)
        z_max = float(np.max(z))
    lbf = float(g["log_z"] - g["log_z_nominal"])
    out = {
        "settings": sampling.to_dict(), "modes": names, "antennas": int(th.shape[1]), "parameters": int(th[0].size),
        "ndraws": nd, "acceptance": float(np.mean(g["accept"])) if nd else None,
        "evidence": {"method": "Laplace (beams' exact marginal, the sky integrated out)",
                     "log_z": float(g["log_z"]), "log_z_nominal": float(g["log_z_nominal"]), "log_bayes_factor": lbf,
                     "converged": bool(g["laplace_converged"]),
                     "verdict": "the data ask for the beam block" if lbf > 0 else
                                "the nominal beams are preferred (the block is not needed)"},
        "fit_nominal": _nominal_fit(prob, g.get("log_u_nominal_fit"), g.get("nominal_gain_factor")),
        "coefficients": [{"antenna": int(a), **{n: {"mean": float(th[:, i, k, 0].mean()),
                                                    "sd": float(th[:, i, k, 0].std(ddof=1)) if nd > 1 else 0.0}
                                                for k, n in enumerate(names)}}
                         for i, a in enumerate(np.asarray(g["antenna_numbers"]))],
        "max_abs_mean_over_sd": z_max,
        "beam_files": None,
        "note": ("coefficients: the constant frequency mode of theta per antenna and mode (fractional change of the "
                 "voltage beam at the disc's edge); evidence: log p(d | block) - log p(d | nominal beams), Laplace "
                 "over the beam coefficients, exact over the sky; fit_nominal: the goodness of fit without the block "
                 "(goodness_of_fit: with it, at the marginal's maximum)"
                 + ("; with gains sampled both models have them: the evidence integrates them (Laplace) in each, "
                    "fit_nominal is at the nominal model's own maximum (gains and amplitude)." if "nominal_gain_factor"
                    in g else ".")),
    }
    if "log_u_nominal" in g:  # the amplitude inferred: where the nominal beams' evidence peaks, and their fit's
        out["evidence"]["u_nominal_max"] = np.exp(np.asarray(g["log_u_nominal"], float)).tolist()
        out["evidence"]["u_nominal_fit"] = np.exp(np.asarray(g["log_u_nominal_fit"], float)).tolist()
    out["chain"] = chain_diagnostics({"beam_theta": th.reshape(nd, -1)})
    warnings = []
    line = diagnostics_warning(out["chain"], "the beam chain")
    if line is not None:
        warnings.append(line)
    if nd and out["acceptance"] < LOW_ACCEPT:
        warnings.append(f"WARNING: the beam chain's independence move is accepted {100 * out['acceptance']:.1f} % of "
                        "the time: the Laplace proposal misses the beams' marginal (draws repeat; fewer --beam-modes or "
                        "more draws)")
    for w in warnings:
        log.warning(w.removeprefix("WARNING: "))
    out["warnings"] = warnings
    return out


def write_beam_products(prob, beams, sampling, out, h5) -> str | None:
    """The posterior-mean beams, one UVBeam power beam per antenna (``beams/ant<number>.beamfits`` in ``out``,
    written atomically as a directory; pyuvdata reads each back:
    :func:`gcrsky.instrument.beammodes.perturbed_power_beam`), or None with a log line when the problem does not
    record its antennas."""
    import shutil
    import tempfile
    from pathlib import Path

    from ..instrument.beammodes import perturbed_power_beam

    conv = getattr(prob.config, "conventions", None) or {}
    if "antenna_numbers" not in conv:
        log.info("beams: no %s written (the problem does not record its antennas)", BEAM_DIR)
        return None
    g = _read(h5)
    mean = g["theta"].mean(axis=0)  # (Nant, M, Q)
    coeffs = np.einsum("amq,fq->afm", mean, g["basis_f"])
    modes = modes_of(sampling)
    out = Path(out)
    tmp = Path(tempfile.mkdtemp(prefix=f".{BEAM_DIR}.tmp-", dir=out))
    try:
        for i, num in enumerate(np.asarray(g["antenna_numbers"])):
            uvb = perturbed_power_beam(beams[i], coeffs[i], np.asarray(prob.freqs_hz), modes,
                                       telescope_name=conv.get("telescope_name", "gcrsky"), antenna=str(int(num)))
            uvb.write_beamfits(str(tmp / f"ant{int(num)}.beamfits"), clobber=True)
        final = out / BEAM_DIR
        if final.exists():
            shutil.rmtree(final)
        tmp.rename(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return BEAM_DIR
