"""The draws of a run that samples the gains with the sky: a Markov chain, batch by batch into ``results.h5``.

With :class:`~gcrsky.run.RunSpec`'s ``gains`` (``gcrsky run --data F --gains sample``) the run
draws from the joint posterior of the sky ``a``, the per-antenna gain perturbations ``theta``
and the overall amplitude ``q(nu)`` (:mod:`gcrsky.model.gains`,
:func:`gcrsky.inference.joint_gain_step`) instead of the sky's alone at fixed calibration:

1. **Set-up** (stage ``wiener``): the gain layout of the problem's rows
   (:func:`gcrsky.model.gain_model`; rows must be antenna pairs, not redundant groups), the
   gain prior (:func:`gcrsky.inference.gain_setup`, ``applied`` the starting amplitude), the
   sky's data term (:func:`gcrsky.inference.gibbs_setup`: dense Cholesky up to
   :data:`GAIN_DENSE_MAX_N` parameters per channel, matrix-free CG above);
2. **burn-in**: ``gains.burn`` sweeps in two halves, the linearisation point moved to the
   current gains after each (:func:`gcrsky.inference.recentre`: the linearised model's bias
   is second order about it, ``docs/gains.md``); the chain then stays at that point;
3. the **Wiener filter** recorded is the sky's posterior mean given the gains at that point
   (and the burn-in's last amplitude); the goodness of fit (:mod:`gcrsky.run.fit`) tests the
   data against the same model;
4. the **draws**: batch ``b`` is ``batch`` kept states, one every ``gains.thin`` sweeps, from
   the state the previous batch ended in.  Each batch appends the sky draws (``draws``),
   the gains (``gain_draws``), their coefficients and the amplitude, and replaces the
   chain's state (``gains/state``) before the batch counts as done, so a killed run resumes
   exactly where it stopped (the draws equal an uninterrupted run's).

Key scheme (:data:`GAIN_KEY_SCHEME`): burn-in halves ``fold_in(key, 2**31 - 1)`` and
``fold_in(key, 2**31 - 2)``, batch ``b`` ``fold_in(key, b)``, each split into one key per
kept state, that into one per sweep.  The draws are a Markov chain's: consecutive draws are
correlated (the summary gives the amplitude's effective sample size).

``results.h5`` of a gain run (besides the standard datasets):

* ``gain_draws`` (ndraws, Nf, Nt, U) complex: the units' gains ``g_u = gbar_u sqrt(q(nu)) (1 + x_u)``
  of each draw (:func:`gcrsky.model.gains.unit_gains`; ``gbar`` the linearisation point), relative to
  the data as gcrsky read them (after ``--cal``), overall phase fixed by the gauge;
* ``gain_theta`` (ndraws, P), ``gain_scale`` (ndraws, Kf), ``gain_info/gauge_accept`` (ndraws,);
* ``gains/units`` (U, 2) (antenna index into the file's ``antenna_numbers``, feed: 0 one gain per
  antenna, 1 x, 2 y), ``gains/antenna_numbers`` (U,), ``gains/basis_f`` (Nf, Kf),
  ``gains/basis_t`` (Nt, Kt), ``gains/linearisation`` (Nf, Nt, U), ``gains/pair_gains``
  (Nf, Nt, Nbl), ``gains/prior_mean`` (P,), ``gains/prior_inv_var`` (P,),
  ``gains/setup_factor`` (Nf, Nt, Nbl) (the model's gain factor at the Wiener filter), and the
  chain's last state ``gains/state/{sky, theta, scale}``.
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

from ..inference.api import prepare
from ..inference.gains import gain_init, gain_setup, joint_gain_step, recentre
from ..inference.gibbs import gibbs_setup
from ..model.gains import gain_model, perturbations, scale_profile, unit_gains
from ..solvers.options import CGOptions, CholeskyOptions
from ..solvers.plan import choose_path
from .draws import append_chain_batch, read_chain, record_setup
from .output import GAIN_FILE, OpenRun
from .resume import options_json
from .stages import StageTimer, Watch

__all__ = ["DEFAULT_GAIN_BASIS", "GAIN_DENSE_MAX_N", "GAIN_KEY_SCHEME", "GainChain", "beam_gain_summary", "burn_in",
           "default_gain_modes", "gain_chain_setup", "gain_draws", "gain_layout_arrays", "gain_summary", "gained_problem",
           "noise_at", "read_gain_chain", "stored_gain_factor", "write_gain_products"]

log = logging.getLogger(__name__)

#: Parameters per channel up to which the sky step rebuilds and factorises its dense data term each
#: sweep (``~8 Nf Nbl n^2`` flop); above, matrix-free CG (nothing rebuilt, a stale preconditioner).
GAIN_DENSE_MAX_N = 2500
#: The key scheme of a gain run's chain (module doc).
GAIN_KEY_SCHEME = ("gains-v1: burn-in halves fold_in(key, 2**31-1), fold_in(key, 2**31-2); batch b fold_in(key, b); "
                   "each split per kept state, then per sweep")
_BURN = (2**31 - 1, 2**31 - 2)

_GAIN_DRAWS_SHAPE = "(ndraws, nfreq, ntimes, nunits) complex: g_u = gbar_u sqrt(q(nu)) (1 + x_u(nu, t))"


#: The gain modes' basis when none is asked for (:func:`default_gain_modes`: why Legendre).
DEFAULT_GAIN_BASIS = "legendre"
#: Fractional bandwidth per frequency mode beyond the linear one (:func:`default_gain_modes`).
BAND_PER_MODE = 0.2
#: Time span (hours) from which the default time modes add a curvature (:func:`default_gain_modes`).
LONG_SPAN_H = 12.0
#: The most modes per axis :func:`default_gain_modes` gives (more: ask for them).
MAX_DEFAULT_MODES = 4


def default_gain_modes(freqs_hz, lsts_rad) -> tuple[int, int]:
    """``(Kf, Kt)``, the gain modes that follow a selection's channels and time span, on the
    :data:`DEFAULT_GAIN_BASIS` (Legendre) basis: what ``gcrsky run --gains sample`` uses when
    ``--gain-modes`` is not given.

    * **Legendre polynomials**: a gain's slow drift across the band and the night is, to leading
      order, linear, and polynomials hold a linear drift exactly with two modes, where DPSS and
      Fourier modes leave 49 % and 61 % of it outside three modes on 12 samples
      (``tests/test_gains_files.py``): on ``gcrsky.checks.gainsim``'s defaults (5 % / 5 deg, linear
      in frequency and time) one constant DPSS gain per antenna is rejected by the fit (chi2/dof 62
      in issue 38; ``tests/test_gains_defaults.py``), the linear Legendre modes pass.
    * **frequency**: ``Kf = 2`` (constant and slope) for a band narrower than :data:`BAND_PER_MODE`
      (20 %) of its centre, one more for each further 20 % (a bandpass is not linear over a wide
      band: the H1C file's autos against the GSM's fall 16x from 133 to 194 MHz, 37 %, which takes a
      curvature), at most :data:`MAX_DEFAULT_MODES` and never more than the channels (one channel: 1).
    * **time**: ``Kt = 2`` (constant and drift), 3 for a span of :data:`LONG_SPAN_H` (12 h) or more
      (a night's thermal drift is not linear), never more than the integrations (one: 1).

    A mode the data do not need stays near its prior (``--gain-sigma``); a mode they need and the
    model lacks is a rejected fit: the rule errs on the side of a mode too many.

    Args:
        freqs_hz: (Nf,) the selection's channel frequencies, Hz.
        lsts_rad: (Nt,) its times as LSTs (Earth rotation angles), radians (the span is taken
            unwrapped: sidereal hours, within 0.3 % of solar).

    Returns:
        ``(Kf, Kt)``, each between 1 and :data:`MAX_DEFAULT_MODES`.
    """
    f = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    t = np.unwrap(np.atleast_1d(np.asarray(lsts_rad, np.float64)))
    band = float(np.ptp(f) / np.mean(f)) if f.size > 1 else 0.0
    span_h = float(np.ptp(t)) * 12.0 / np.pi if t.size > 1 else 0.0
    kf = min(f.size, MAX_DEFAULT_MODES, 2 + int(np.floor(band / BAND_PER_MODE)))
    kt = min(t.size, MAX_DEFAULT_MODES, 2 + int(span_h >= LONG_SPAN_H))
    return kf, kt


class GainChain(NamedTuple):
    """The chain's fixed parts and its state (:func:`gain_chain_setup`, :func:`read_gain_chain`).

    Attributes:
        fixed: the sky's data term (:class:`gcrsky.inference.gibbs.GibbsFixed`).
        block: the gain block (:class:`gcrsky.inference.gains.GainBlock`), about the linearisation point.
        lin: (Nf, Nt, U) complex, the units' gains at the linearisation point.
        state: the chain's :class:`gcrsky.inference.GainState`.
    """

    fixed: object
    block: object
    lin: np.ndarray
    state: object


def gain_chain_setup(prob, gains, *, tol: float | None = None, factor=None) -> GainChain:
    """The gain layout, prior and the sky's data term of ``prob``; the chain at the prior mean, gains 1.

    Args:
        prob: the :class:`~gcrsky.model.Problem`; its rows are antenna pairs (read without
            redundant compression).
        gains: :class:`~gcrsky.run.GainSampling`.
        tol: the CG tolerance of the sky step where it runs matrix-free (posterior sigma).
        factor: the gain factor (Nf, Nt, Nbl) at which the sky part of the noise is evaluated
            (:func:`noise_at`); default ``applied^2``, the starting point.

    Raises:
        ValueError: rows that are redundant groups, or a layout the gains cannot have.
    """
    cfg = prob.config
    if getattr(cfg, "compressed", False):
        raise ValueError("gains are per antenna, but the problem's rows are redundant groups (averages of baselines "
                         "with different gains): read the file without compression (compress=False, --no-compress)")
    nf, nt, _ = prob.data.shape
    model = gain_model(prob.antpairs, nf, nt, gains.modes, basis=gains.basis, pols=prob.pols)
    lin = np.full((nf, nt, model.units.shape[0]), gains.applied, complex)
    block = gain_setup(model, sigma=gains.sigma, gbar=lin, scale_sd=gains.scale_sd)
    if prob.n <= GAIN_DENSE_MAX_N:
        options = CholeskyOptions()
    else:
        options = CGOptions(dense=False) if tol is None else CGOptions(dense=False, tol=tol)
    system = noise_at(prob, gains.applied**2 if factor is None else factor).system()
    fixed = gibbs_setup(system, options=options)
    return GainChain(fixed, block, lin, gain_init(system.prior.mean, block))


def noise_at(prob, factor):
    """``prob`` with the sky part of its noise (``prob.sigma_sky``: the sky above lmax, marginalised) passed
    through the gain factor ``D`` (Nf, Nt, Nbl) or a scalar: ``sigma^2 = sigma_rad^2 + |D|^2 sigma_sky^2``.

    The unmodelled sky goes through the antennas' gains as the modelled one does; the radiometer noise
    does not.  Evaluated at a fixed ``D`` (the linearisation point), so that the gains' conditionals stay
    Gaussian: an approximation of the same order as the linearisation.  ``prob`` as it is without ``sigma_sky``.
    """
    if prob.sigma_sky is None:
        return prob
    s2, k2 = np.asarray(prob.sigma) ** 2, np.asarray(prob.sigma_sky) ** 2
    rad2 = np.maximum(s2 - k2, 0.0)
    return eqx.tree_at(lambda p: p.sigma, prob, jnp.asarray(np.sqrt(rad2 + np.abs(np.asarray(factor)) ** 2 * k2)))


def _factor(chain: GainChain) -> np.ndarray:
    """The model's gain factor ``q(nu) G`` (Nf, Nt, Nbl) at the chain's linearisation point (``theta = 0``)."""
    block = chain.block
    return np.asarray(scale_profile(block.model, chain.state.scale)[:, None, None] * block.pair_gains)


@functools.partial(jax.jit, static_argnames=("n", "thin", "moves"))
def _segment(fixed, block, state, key, *, n: int, thin: int, moves: int):
    """``n`` kept states, one every ``thin`` sweeps: (last state, (states, gauge acceptance, sky SolveInfo))."""

    def sweep(s, k):
        return joint_gain_step(k, s, fixed, block, gauge_moves=moves)

    def keep(s, k):
        s, info = jax.lax.scan(sweep, s, jax.random.split(k, thin))
        return s, (s, jnp.mean(info.gauge_accept), jax.tree_util.tree_map(lambda x: x[-1], info.solve))

    return jax.lax.scan(keep, state, jax.random.split(key, n))


def burn_in(key: jax.Array, chain: GainChain, gains, prob=None) -> GainChain:
    """``gains.burn`` sweeps in two halves, re-centred after each (the linearisation point follows the chain);
    with ``prob`` given and its ``sigma_sky`` set, the sky part of the noise is re-evaluated there too."""
    half = gains.burn // 2
    fixed, block, lin, state = chain
    for fold, n in zip(_BURN, (half, gains.burn - half)):
        state, _ = _segment(fixed, block, state, jax.random.fold_in(key, fold), n=n, thin=1, moves=gains.gauge_moves)
        lin = np.asarray(lin * (1.0 + perturbations(block.model, state.theta)))
        block, state = recentre(block, state)
        if prob is not None and prob.sigma_sky is not None:
            D = _factor(GainChain(fixed, block, lin, state))
            fixed = gibbs_setup(noise_at(prob, D).system(), options=fixed.options)
    return GainChain(fixed, block, lin, state)


def gained_problem(prob, factor, amplitude=None):
    """``prob`` with the gain factor ``D`` (Nf, Nt, Nbl) divided out: data ``d / D``, noise
    ``sigma_rad / |D|`` for the radiometer part and ``sigma_sky`` unchanged for the sky part
    (:func:`noise_at`; weight 0 where ``D = 0``): the sky's likelihood given those gains, for the
    Wiener filter and the fit.  ``amplitude`` (Nf,): a further factor ``u`` of the model kept in its response
    (a beam run's), through which the sky part of the noise goes too (``|u|`` times ``sigma_sky``)."""
    D = np.asarray(factor, complex)
    zero = np.abs(D) == 0
    Ds = np.where(zero, 1.0, D)
    data = np.where(zero, 0.0, np.asarray(prob.data) / Ds)
    sky = Ds if amplitude is None else Ds * np.asarray(amplitude)[:, None, None]
    sigma = np.asarray(noise_at(prob, sky).sigma) / np.abs(Ds)
    weights = np.where(zero, 0.0, np.asarray(prob.weights))
    return eqx.tree_at(lambda p: (p.data, p.sigma, p.weights), prob,
                       (jnp.asarray(data), jnp.asarray(sigma), jnp.asarray(weights)))


def _layout_arrays(prob, chain: GainChain, setup_factor) -> dict:
    return gain_layout_arrays(prob, chain.block, chain.lin, setup_factor)


def gain_layout_arrays(prob, block, lin, setup_factor) -> dict:
    """The ``gains/`` layout datasets of a run that samples the gains (module doc): the units, bases, linearisation
    point ``lin`` (Nf, Nt, U), ``block``'s pair gains and prior, and the Wiener filter's gain factor."""
    model = block.model
    nums = np.asarray((getattr(prob.config, "conventions", None) or {}).get("antenna_numbers",
                                                                             np.arange(prob.antpairs.max() + 1)))
    return {"gains/units": np.asarray(model.units), "gains/antenna_numbers": nums[np.asarray(model.units)[:, 0]],
            "gains/basis_f": np.asarray(model.basis_f), "gains/basis_t": np.asarray(model.basis_t),
            "gains/linearisation": np.asarray(lin), "gains/pair_gains": np.asarray(block.pair_gains),
            "gains/prior_mean": np.asarray(block.prior_mean), "gains/prior_inv_var": np.asarray(block.prior_inv_var),
            "gains/param_mode": np.asarray(model.param_mode), "gains/setup_factor": np.asarray(setup_factor)}


def _per_draw(prob, chain: GainChain) -> dict:
    nf, nt, nu = chain.lin.shape
    P, kf = chain.state.theta.size, chain.state.scale.size
    return {"gain_draws": ((nf, nt, nu), "c16", _GAIN_DRAWS_SHAPE), "gain_theta": ((P,), "f8", "(ndraws, P)"),
            "gain_scale": ((kf,), "f8", "(ndraws, Kf): q(nu) = basis_f s"),
            "gain_info/gauge_accept": ((), "f8", "(ndraws,) mean gauge-move acceptance over the thin sweeps")}


def _state_arrays(state) -> dict:
    return {"gains/state/sky": np.asarray(state.sky), "gains/state/theta": np.asarray(state.theta),
            "gains/state/scale": np.asarray(state.scale)}


def read_gain_chain(prob, gains, h5, *, tol: float | None = None) -> GainChain:
    """The chain of a ``results.h5`` written by a gain run: its linearisation point and last state."""
    import h5py

    chain = gain_chain_setup(prob, gains, tol=tol, factor=stored_gain_factor(h5))
    with h5py.File(h5, "r") as h:
        block = chain.block._replace(pair_gains=jnp.asarray(h["gains/pair_gains"][()]),
                                     prior_mean=jnp.asarray(h["gains/prior_mean"][()]))
        state = chain.state._replace(**{k: jnp.asarray(h[f"gains/state/{k}"][()]) for k in ("sky", "theta", "scale")})
        lin = h["gains/linearisation"][()]
    return GainChain(chain.fixed, block, lin, state)


def _setup(prob, spec, run: OpenRun, key) -> GainChain:
    """New run: set up, burn in, record the Wiener filter given the gains; resumed: the recorded chain."""
    gains, tol = spec.gains, spec.solver.tol
    if run.state is not None:
        return read_gain_chain(prob, gains, run.h5, tol=tol)
    chain = burn_in(key, gain_chain_setup(prob, gains, tol=tol), gains, prob)
    D0 = _factor(chain)
    prob_g = gained_problem(prob, D0)
    options = choose_path(prob_g.system(), spec.solver.method, tol=tol, ndraws=1)
    prepared = prepare(prob_g, options=options)
    a_wf = np.asarray(jax.block_until_ready(prepared.a_wf))
    record_setup(prob, spec, run, a_wf, prepared.wiener, rank=getattr(prepared, "kept", None),
                 method=_method_name(chain), options=options, key_scheme=GAIN_KEY_SCHEME,
                 per_draw=_per_draw(prob, chain), arrays={**_layout_arrays(prob, chain, D0),
                                                          **_state_arrays(chain.state)})
    log.info("gain chain: burn-in of %d sweeps done; Wiener filter by %s (%s)", gains.burn, prepared.method,
             options_json(options))
    return chain


def _method_name(chain: GainChain) -> str:
    return "gains+" + ("cholesky" if chain.fixed.data_term is not None else "cg")


def gain_draws(prob, spec, run: OpenRun, st: StageTimer, watch: Watch) -> str:
    """The ``wiener`` stage (set-up, burn-in, Wiener filter) and the chain's batches from ``run.start``.

    Returns the name of what ran (``"gains+cholesky"`` or ``"gains+cg"``); leaves the ``draws`` stage
    running, as :func:`gcrsky.run.draws.joint_draws`.
    """
    d, g = spec.draws, spec.gains
    key = jax.random.PRNGKey(d.seed)
    st.start("wiener")
    chain = _setup(prob, spec, run, key) if run.start < d.n_batches else None
    method = _method_name(chain) if chain is not None else str(run.state.attrs["method"])
    st.stop()
    st.start("draws")
    batches = range(run.start, d.n_batches)
    state = None if chain is None else chain.state
    for b in watch.progress(batches) if watch.progress is not None else batches:
        t0 = time.perf_counter()
        state, (states, accept, info) = _segment(chain.fixed, chain.block, state, jax.random.fold_in(key, b),
                                                 n=d.batch, thin=g.thin, moves=g.gauge_moves)
        take = min(d.batch, d.nsamples - b * d.batch)
        gdraws = jax.vmap(lambda t, s: unit_gains(chain.block.model, t, s, chain.lin))(states.theta[:take],
                                                                                         states.scale[:take])
        extra = {"gain_draws": np.asarray(gdraws), "gain_theta": np.asarray(states.theta)[:take],
                 "gain_scale": np.asarray(states.scale)[:take], "gain_info/gauge_accept": np.asarray(accept)[:take]}
        append_chain_batch(run, b, take, states.sky, info, extra, _state_arrays(state), t0)
    return method


def stored_gain_factor(h5) -> np.ndarray:
    """The gain factor (Nf, Nt, Nbl) at which a gain run's Wiener filter was computed (``gains/setup_factor``)."""
    import h5py

    with h5py.File(h5, "r") as h:
        return h["gains/setup_factor"][()]



def _read_gain_draws(h5) -> dict:
    """The gain chain's draws and layout (``gain_scale`` and the gauge acceptance only where the gains carry the
    amplitude: a beam run's do not, :mod:`gcrsky.run.beams`)."""
    return read_chain(h5, ("gain_draws", "gain_theta"),
                      ("gains/units", "gains/basis_f", "gains/prior_inv_var", "gains/basis_t", "gains/param_mode"),
                      optional_per_draw=("gain_scale", "gain_info/gauge_accept"))


def _interval(x) -> dict:
    lo, hi = np.percentile(x, [2.5, 97.5])
    return {"mean": float(np.mean(x)), "sd": float(np.std(x, ddof=1)) if x.size > 1 else 0.0,
            "ci95": [float(lo), float(hi)]}


def gain_summary(prob, gains, h5) -> dict:
    """``summary.json``'s ``gains`` block: the overall flux scale the crosses say (against the autos'
    check), the phase gradients' posterior against their prior, the chain's gauge acceptance and ESS.

    ``chain`` is :func:`gcrsky.inference.chain_diagnostics` of every sampled scalar: the amplitude
    ``q(nu)`` per channel (``flux_scale[i]``), its modes ``s`` (``scale_modes[k]``) and every gain
    coefficient (``gain_theta[p]``), against the ESS floor (:data:`gcrsky.inference.diagnostics.ESS_FLOOR`).
    Below it the block's ``warnings`` holds :func:`gcrsky.inference.diagnostics_warning`'s line (also
    logged), which the run adds to the summary's warnings.
    """
    from ..inference.collapsed import effective_sample_size

    g = _read_gain_draws(h5)
    nd = g["gain_scale"].shape[0]
    q = g["gain_scale"] @ g["basis_f"].T  # (ndraws, Nf): q(nu) of each draw
    flux = q * gains.applied**2
    checks = (getattr(prob.config, "checks", None) or {}).get("flux_scale") or {}
    ratio = checks.get("ratio")
    out = {
        "settings": gains.to_dict(), "units": int(g["units"].shape[0]), "parameters": int(g["gain_theta"].shape[1]),
        "ndraws": nd, "gauge_accept": float(np.mean(g["gauge_accept"])) if nd else None,
        "flux_scale": [{"freq_hz": float(f), **_interval(flux[:, i])} for i, f in enumerate(np.asarray(prob.freqs_hz))],
        "flux_scale_ess": float(effective_sample_size(q[None, :, 0])) if nd > 3 else None,
        "autos_flux_ratio": None if ratio is None else float(ratio),
        "calibration_file": GAIN_FILE,
        "note": ("flux_scale: the posterior of q(nu) x applied^2, the factor by which the cross-correlations exceed "
                 "the sky model (the flux-scale check's ratio is the autocorrelations' view of the same); "
                 "phase_gradients: posterior sd of the tip-tilt directions against their prior sd (ratio near 1: "
                 "prior-dominated). The draws are a Markov chain's (flux_scale_ess: effective sample size of the "
                 "first channel's; chain: that of every sampled scalar against a floor; warnings: the chain's, when "
                 "below it)."),
    }
    return _chain_and_gradients(out, prob, gains, g, {"flux_scale": q, "scale_modes": g["gain_scale"],
                                                      "gain_theta": g["gain_theta"]})


def _chain_and_gradients(out: dict, prob, gains, g, scalars: dict) -> dict:
    """``out`` with ``chain`` (:func:`gcrsky.inference.chain_diagnostics` of ``scalars``), ``warnings`` (its line,
    also logged) and, where they can be computed, ``phase_gradients``."""
    from ..inference.diagnostics import chain_diagnostics, diagnostics_warning

    out["chain"] = chain_diagnostics(scalars)
    line = diagnostics_warning(out["chain"], "the gain chain")
    out["warnings"] = [] if line is None else [line]
    if line is not None:
        log.warning(line.removeprefix("WARNING: "))
    gradients = _phase_gradients(prob, gains, g)
    if gradients is not None:
        out["phase_gradients"] = gradients
    return out


def _phase_gradients(prob, gains, g) -> list | None:
    """The posterior sd of the gains' tip-tilt (phase gradient) directions against their prior sd, East and North
    (None: the problem has no antenna positions, or fewer than two draws)."""
    from ..model.gains import phase_gradient_directions

    if prob.antpos_enu_m is None or g["gain_theta"].shape[0] < 2:
        return None
    nf, nt = g["basis_f"].shape[0], g["basis_t"].shape[0]
    model = gain_model(prob.antpairs, nf, nt, gains.modes, basis=gains.basis, pols=prob.pols)
    T = phase_gradient_directions(model, np.asarray(prob.antpos_enu_m)[g["units"][:, 0]])
    prior_sd = np.sqrt(np.sum(T**2 / g["prior_inv_var"][None, :], axis=1))
    proj = g["gain_theta"] @ T.T
    return [{"direction": name, "posterior_sd": float(proj[:, i].std(ddof=1)), "prior_sd": float(prior_sd[i]),
             "ratio": float(proj[:, i].std(ddof=1) / prior_sd[i])} for i, name in enumerate(("east", "north"))]


def beam_gain_summary(prob, gains, h5) -> dict:
    """``summary.json``'s ``gains`` block of a beam run that samples the gains (:mod:`gcrsky.run.beams`): the settings,
    the phase gradients' posterior against their prior, and :func:`gcrsky.inference.chain_diagnostics` of every gain
    coefficient with its warning (the amplitude is the ``flux_scale`` block's)."""
    g = _read_gain_draws(h5)
    out = {"settings": gains.to_dict(), "units": int(g["units"].shape[0]), "parameters": int(g["gain_theta"].shape[1]),
           "ndraws": int(g["gain_theta"].shape[0]), "calibration_file": GAIN_FILE,
           "note": ("gains sampled with the beams and the sky, about the linearisation point found in the burn-in "
                    "(gains/linearisation); the overall amplitude is the flux_scale block's (or 1: calibrated data); "
                    "phase_gradients: posterior sd of the tip-tilt directions against their prior sd")}
    return _chain_and_gradients(out, prob, gains, g, {"gain_theta": g["gain_theta"]})



def write_gain_products(prob, gains, out, h5) -> str | None:
    """The posterior-mean gains as ``gains.calh5`` in ``out`` (atomically; pyuvdata reads it back), or None
    (with a log line) for a problem that does not record its antennas, times and site (a simulation).

    The gains are the mean of ``gain_draws``: relative to the data as gcrsky read them (after ``--cal``:
    apply them after that file, e.g. pyuvdata's ``uvcalibrate`` twice), ``gain_convention`` "divide".
    """
    from ..io.atomic import atomic_path
    from ..io.gaincal import write_gain_calibration

    conv = getattr(prob.config, "conventions", None) or {}
    need = ("antenna_numbers", "antenna_names", "times_jd", "site_lat_lon_alt")
    if any(k not in conv for k in need) or prob.antpos_enu_m is None:
        log.info("gains: no %s written (the problem does not record its antennas, times and site)", GAIN_FILE)
        return None
    g = _read_gain_draws(h5)
    nf, nt = g["basis_f"].shape[0], g["basis_t"].shape[0]
    model = gain_model(prob.antpairs, nf, nt, gains.modes, basis=gains.basis, pols=prob.pols)
    lat, lon, alt = conv["site_lat_lon_alt"]
    path = out / GAIN_FILE
    with atomic_path(path) as tmp:
        write_gain_calibration(tmp, g["gain_draws"].mean(axis=0), model, antenna_numbers=conv["antenna_numbers"],
                               antenna_names=conv["antenna_names"], antpos_enu_m=np.asarray(prob.antpos_enu_m),
                               freqs_hz=np.asarray(prob.freqs_hz), times_jd=conv["times_jd"], latitude_deg=lat,
                               longitude_deg=lon, altitude_m=alt, telescope_name=conv.get("telescope_name", "gcrsky"),
                               overwrite=True)
    return GAIN_FILE
