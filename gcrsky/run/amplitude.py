"""The draws of a run whose overall amplitude (bandpass) is inferred with the sky (DESIGN section 14).

With :class:`~gcrsky.run.sampling.Amplitude` (``gcrsky run --data F`` on data that are not
absolutely calibrated, ``--amplitude infer``) the data are ``d_f = q_f D X a_f + n`` with ``q_f``
per channel unknown, the sky ``a = c (a0 + delta)`` a sky model ``a0`` in K (the GSM) known up to
an overall factor ``c ~ N(1, model_sd^2)``, and ``D`` the per-antenna gains when they are sampled
(:mod:`gcrsky.inference.amplitude`):

1. **Set-up** (stage ``wiener``): the data-space Gram matrix of every channel
   (:func:`gcrsky.inference.amplitude.amplitude_setup`); with gains their layout and prior
   (:func:`gcrsky.inference.gain_setup`) and ``gains.burn`` sweeps of burn-in in :data:`RECENTRES`
   segments, re-centred after each (the linearisation point follows the chain, as :mod:`gcrsky.run.gains`);
2. the **Wiener filter** recorded is ``a0 + E[delta | u_med, d]`` at the median amplitude of a pilot
   of :data:`PILOT` draws (``c = 1``), and the goodness of fit tests the data against the model
   ``u_med D X (a0 + delta_wf)`` (``amplitude/setup_factor``);
3. the **draws**: without gains every draw is independent (``u_f`` from its exact marginal by the
   grid, ``c`` from its prior, ``delta`` exactly given ``u``), so the ESS is the number of draws; with
   gains batch ``b`` is ``batch`` sweeps (one kept state every ``gains.thin``) of the chain
   ``theta | q a``, ``(u, delta) | theta`` from the state the previous batch ended in (stored with each
   batch, so a killed run resumes exactly).

Key scheme (:data:`AMPLITUDE_KEY_SCHEME`): pilot ``fold_in(key, 2**31 - 3)``; the settling sweeps (with gains:
:data:`SETTLE` of the burn-in before it, the amplitude held at the autos' ratio while the gains settle) in
:data:`RECENTRES` segments, segment ``i`` ``fold_in(fold_in(key, 2**31 - 4), i)``; the burn-in likewise
from ``fold_in(key, 2**31 - 1)``; batch ``b`` ``fold_in(key, b)`` split into one
key per kept state (then per sweep), each split into the sweep's and ``c``'s.

``results.h5`` (besides the standard datasets, ``draws`` the sky ``a = c (a0 + delta)`` in K):
``amplitude_q`` (ndraws, Nf) the amplitude ``q = u / c`` (data = q x the model in K, as Jy by
Rayleigh-Jeans: what multiplies a calibrated visibility), ``amplitude_u`` (ndraws, Nf) ``u = q c`` (what
the data measure), ``amplitude_c`` (ndraws,); with gains ``gain_draws`` (ndraws, Nf, Nt, U) the units'
gains ``sqrt(q) gbar (1 + x)`` relative to the data as read, ``gain_theta`` (ndraws, P), the layout under
``gains/`` and the chain's state under ``amplitude/state``.
"""

from __future__ import annotations

import functools
import logging
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.memory import check_memory
from ..inference.amplitude import (
    AmplitudeState,
    amplitude_eigen,
    amplitude_memory_bytes,
    amplitude_setup,
    amplitude_sweep,
    draw_log_u,
    sky_given,
    wiener_given,
)
from ..inference.diagnostics import ESS_FLOOR
from ..inference.gains import GainState, gain_setup, recentre
from ..io.results import append_batch
from ..model.gains import gain_factor, gain_model, n_gain_params, perturbations
from ..solvers.info import direct_info
from ..solvers.options import DEFAULT_TOL
from .draws import kill_hook, record_setup
from .gains import gained_problem, noise_at
from .output import OpenRun
from .stages import StageTimer, Watch

__all__ = ["AMPLITUDE_KEY_SCHEME", "ESS_FLOOR", "PILOT", "RECENTRES", "SETTLE", "AmplitudeChain", "amplitude_chain_setup", "amplitude_draws",
           "amplitude_summary", "autos_ratio", "draw_c", "stored_setup_factor"]

log = logging.getLogger(__name__)

#: The key scheme of an amplitude run (module doc).
AMPLITUDE_KEY_SCHEME = ("amplitude-v2: pilot fold_in(key, 2**31-3); settling segment i fold_in(fold_in(key, 2**31-4), i), "
                        "burn-in segment i fold_in(fold_in(key, 2**31-1), i); batch b fold_in(key, b), split per kept "
                        "state, then (sweeps, c)")
_PILOT, _BURN, _SETTLE = 2**31 - 3, 2**31 - 1, 2**31 - 4
#: Fraction of the burn-in (before it, with gains) run with the amplitude held at the autos' ratio.
SETTLE = 0.1
#: Segments of the settling sweeps and of the burn-in, each followed by a re-centring of the gains'
#: linearisation point at the segment's mean gains (re-centred at single draws, the point random-walks
#: along the directions the sky absorbs and the fit degrades): the linearised model's neglected second-order term
#: (``x_i conj(x_j)``, ~1 % of a visibility at 5 % / 5 deg gains: many noise sigma at high signal to
#: noise) is a misfit that the amplitude's marginal would absorb by a sky (and ``u``) far too bright.
RECENTRES = 8
#: What ``results.h5`` records as the path's options (no solver path's: the data-space eigendecomposition).
OPTIONS_JSON = '{"method": "amplitude", "fields": {"path": "data space, eigendecomposition per channel"}}'
#: Draws of ``u`` whose median sets the Wiener filter's (and the fit's) amplitude.
PILOT = 256


class AmplitudeChain(NamedTuple):
    """The fixed parts and the state of an amplitude run.

    Attributes:
        fixed: :class:`gcrsky.inference.amplitude.AmplitudeFixed` (the noise at ``setup_factor``).
        block: the gain block (about the linearisation point), or None without gains.
        lin: (Nf, Nt, U) the units' gains at the linearisation point, or None.
        state: :class:`gcrsky.inference.amplitude.AmplitudeState`.
        u_med: (Nf,) the pilot's median ``u``.
    """

    fixed: object
    block: object
    lin: np.ndarray | None
    state: AmplitudeState
    u_med: np.ndarray


def _lin_factor(block, nf, nt, nbl) -> np.ndarray:
    return np.ones((nf, nt, nbl), complex) if block is None else np.asarray(block.pair_gains)


def _fixed_at(prob, factor):
    """The data-space set-up with the sky part of the noise (if any) through ``factor`` (Nf, Nt, Nbl)."""
    return amplitude_setup(noise_at(prob, factor).system())


@jax.jit
def _eigen_at(fixed, block, theta):
    """The eigendecomposition at the gain perturbation ``theta`` (``block`` None: no gains)."""
    factor = None if block is None else gain_factor(block.model, theta, 1.0) * block.pair_gains
    return amplitude_eigen(fixed, factor)


@functools.partial(jax.jit, static_argnames=("n",))
def _log_u_draws(key, fixed, eig, *, n: int):
    return draw_log_u(key, fixed, eig, n)


def _pilot(key, fixed, block, theta) -> tuple[np.ndarray, object]:
    """The median ``u`` (Nf,) of :data:`PILOT` draws at ``theta``, and the eigendecomposition there."""
    eig = _eigen_at(fixed, block, theta)
    return np.exp(np.median(np.asarray(_log_u_draws(key, fixed, eig, n=PILOT)), axis=0)), eig


def amplitude_chain_setup(key, prob, amp) -> AmplitudeChain:
    """Set up (and with gains burn in) the chain of ``prob`` (:class:`~gcrsky.run.sampling.AmplitudeSampling`).

    Raises:
        ValueError: with gains, rows that are redundant groups; a prior without a finite variance.
    """
    nf, nt, nbl = prob.data.shape
    t0 = time.perf_counter()
    ratio = autos_ratio(prob)
    u0 = ratio if ratio is not None else 1.0
    fixed = _fixed_at(prob, np.full((nf, nt, nbl), u0))
    g = amp.gains
    block = lin = None
    theta = jnp.zeros(0)
    if g is not None:
        if getattr(prob.config, "compressed", False):
            raise ValueError("gains are per antenna, but the problem's rows are redundant groups: read the file "
                             "without compression (compress=False, --no-compress)")
        model = gain_model(prob.antpairs, nf, nt, g.modes, basis=g.basis, pols=prob.pols)
        lin = np.ones((nf, nt, model.units.shape[0]), complex)
        block = gain_setup(model, sigma=g.sigma, gbar=lin)
        theta = jnp.zeros(n_gain_params(model))
    log.info("amplitude: data-space set-up of %d channels (N_d = %d) in %.1f s", nf, fixed.y.shape[1],
             time.perf_counter() - t0)
    if g is None:
        u_med, eig = _pilot(jax.random.fold_in(key, _PILOT), fixed, block, theta)
    else:  # the chain starts at the autos' amplitude, held while the gains settle (SETTLE of the burn-in)
        u_med = np.full(nf, u0)
    delta = jax.jit(wiener_given)(fixed, _eigen_at(fixed, block, theta), jnp.asarray(u_med))
    state = AmplitudeState(jnp.log(jnp.asarray(u_med)), delta, theta)
    if g is not None:
        settle = max(1, int(SETTLE * g.burn))
        for fold, free_u, n in ((_SETTLE, False, settle), (_BURN, True, g.burn)):
            for i, m in enumerate(_pieces(n)):
                state, kept = _segment(fixed, block, state, jax.random.fold_in(jax.random.fold_in(key, fold), i),
                                       n=m, thin=1, free_u=free_u)
                centre = jnp.mean(kept.theta, axis=0)  # the segment's mean: one draw's noise would walk the point
                lin = np.asarray(lin * (1.0 + perturbations(block.model, centre)))
                block, gs = recentre(block, GainState(None, centre, None))
                state = state._replace(theta=gs.theta)
        log.info("amplitude: burn-in of %d sweeps done at %.1f s", g.burn, time.perf_counter() - t0)
        u_med, eig = _pilot(jax.random.fold_in(key, _PILOT), fixed, block, state.theta)
    if prob.sigma_sky is not None:  # the sky above lmax through the amplitude (and gains) found
        fixed = _fixed_at(prob, u_med[:, None, None] * _lin_factor(block, nf, nt, nbl))
    return AmplitudeChain(fixed, block, lin, state, u_med)


def _pieces(n: int) -> list[int]:
    """``n`` sweeps in :data:`RECENTRES` segments (at most two distinct lengths: one compilation each)."""
    k = max(1, min(RECENTRES, n))
    return [n // k + (i < n % k) for i in range(k)]


def autos_ratio(prob) -> float | None:
    """The flux-scale check's ratio (the data's autos over the sky model's, :mod:`gcrsky.ingest.datachecks`), or None
    where it did not run or is not a positive number: where the amplitude's search starts."""
    ratio = ((getattr(prob.config, "checks", None) or {}).get("flux_scale") or {}).get("ratio")
    return float(ratio) if ratio is not None and np.isfinite(ratio) and ratio > 0 else None


def draw_c(key, sd: float, shape=()):
    """``c ~ N(1, sd^2)`` truncated to ``c > 0``."""
    return 1.0 + sd * jax.random.truncated_normal(key, -1.0 / sd, jnp.inf, shape, jnp.float64)


@functools.partial(jax.jit, static_argnames=("n", "thin", "free_u"))
def _segment(fixed, block, state, key, *, n: int, thin: int, free_u: bool = True):
    """``n`` kept states of the chain with gains, one every ``thin`` sweeps: (last state, kept states)."""

    def sweep(s, k):
        return amplitude_sweep(k, s, fixed, block, free_u)[0], None

    def keep(s, k):
        s, _ = jax.lax.scan(sweep, s, jax.random.split(k, thin))
        return s, s

    return jax.lax.scan(keep, state, jax.random.split(key, n))


@functools.partial(jax.jit, static_argnames=("n",))
def _independent(fixed, eig, key, *, n: int):
    """``n`` independent draws without gains: (log u (n, Nf), delta (n, Nf, n_par))."""
    keys = jax.random.split(key, n)

    def one(k):
        k_u, k_s = jax.random.split(k)
        lu = draw_log_u(k_u, fixed, eig, 1)[0]
        return lu, sky_given(k_s, fixed, eig, jnp.exp(lu))

    return jax.lax.map(one, keys)


def _batch(chain: AmplitudeChain, eig, key, n: int, amp):
    """Batch of ``n`` kept states: (state after, log_u (n, Nf), delta (n, Nf, p), theta (n, P), c (n,))."""
    k_draw, k_c = jax.random.split(key)
    if chain.block is None:
        lu, delta = _independent(chain.fixed, eig, k_draw, n=n)
        theta = jnp.zeros((n, 0))
        last = AmplitudeState(lu[-1], delta[-1], chain.state.theta)
    else:
        last, kept = _segment(chain.fixed, chain.block, chain.state, k_draw, n=n, thin=amp.gains.thin)
        lu, delta, theta = kept.log_u, kept.delta, kept.theta
    return last, lu, delta, theta, draw_c(k_c, amp.model_sd, (n,))


def _per_draw(prob, chain: AmplitudeChain) -> dict:
    nf = prob.data.shape[0]
    out = {"amplitude_q": ((nf,), "f8", "(ndraws, Nf): q = u / c, data = q x the sky model's visibilities in K"),
           "amplitude_u": ((nf,), "f8", "(ndraws, Nf): u = q c, what the data measure"),
           "amplitude_c": ((), "f8", "(ndraws,): the sky model's scale, a = c (a0 + delta)")}
    if chain.block is not None:
        nt, nu = chain.lin.shape[1:]
        out["gain_draws"] = ((nf, nt, nu), "c16", "(ndraws, Nf, Nt, U) complex: sqrt(q) gbar (1 + x)")
        out["gain_theta"] = ((int(chain.state.theta.size),), "f8", "(ndraws, P)")
    return out


def _state_arrays(chain: AmplitudeChain, state) -> dict:
    out = {"amplitude/state/log_u": np.asarray(state.log_u), "amplitude/state/delta": np.asarray(state.delta),
           "amplitude/state/theta": np.asarray(state.theta)}
    if chain.block is not None:
        out.update({"gains/pair_gains": np.asarray(chain.block.pair_gains),
                    "gains/prior_mean": np.asarray(chain.block.prior_mean), "gains/linearisation": chain.lin})
    return out


def _layout(prob, chain: AmplitudeChain, setup_factor) -> dict:
    out = {"amplitude/setup_factor": np.asarray(setup_factor), "amplitude/u_med": np.asarray(chain.u_med)}
    if chain.block is not None:
        model = chain.block.model
        nums = np.asarray((getattr(prob.config, "conventions", None) or {}).get(
            "antenna_numbers", np.arange(prob.antpairs.max() + 1)))
        out.update({"gains/units": np.asarray(model.units), "gains/antenna_numbers": nums[np.asarray(model.units)[:, 0]],
                    "gains/basis_f": np.asarray(model.basis_f), "gains/basis_t": np.asarray(model.basis_t),
                    "gains/prior_inv_var": np.asarray(chain.block.prior_inv_var),
                    "gains/param_mode": np.asarray(model.param_mode)})
    return out


def _read_chain(key, prob, amp, h5) -> AmplitudeChain:
    """The chain of a ``results.h5`` an amplitude run wrote: its set-up recomputed, its last state read."""
    import h5py

    chain = amplitude_chain_setup(key, prob, amp) if amp.gains is None else None
    with h5py.File(h5, "r") as h:
        st = AmplitudeState(*(jnp.asarray(h[f"amplitude/state/{k}"][()]) for k in ("log_u", "delta", "theta")))
        u_med = h["amplitude/u_med"][()]
        if amp.gains is None:
            return chain._replace(state=st, u_med=u_med)
        nf, nt, nbl = prob.data.shape
        g = amp.gains
        model = gain_model(prob.antpairs, nf, nt, g.modes, basis=g.basis, pols=prob.pols)
        lin = h["gains/linearisation"][()]
        block = gain_setup(model, sigma=g.sigma, gbar=None)._replace(
            pair_gains=jnp.asarray(h["gains/pair_gains"][()]), prior_mean=jnp.asarray(h["gains/prior_mean"][()]))
    nf, nt, nbl = prob.data.shape
    fixed = _fixed_at(prob, u_med[:, None, None] * np.asarray(block.pair_gains) if prob.sigma_sky is not None
                      else np.ones((nf, nt, nbl)))
    return AmplitudeChain(fixed, block, lin, st, u_med)


def stored_setup_factor(h5) -> np.ndarray:
    """The factor (Nf, Nt, Nbl) ``u_med D`` at which an amplitude run's Wiener filter and fit were computed."""
    import h5py

    with h5py.File(h5, "r") as h:
        return h["amplitude/setup_factor"][()]


def amplitude_draws(prob, spec, run: OpenRun, st: StageTimer, watch: Watch) -> str:
    """The ``wiener`` stage (set-up, burn-in, Wiener filter) and the batches from ``run.start`` (module doc).

    Returns the name of what ran (``"amplitude+dataspace"`` or ``"amplitude+gains+dataspace"``); leaves
    the ``draws`` stage running.
    """
    d, amp = spec.draws, spec.sampling.amplitude
    key = jax.random.PRNGKey(d.seed)
    method = "amplitude+" + ("gains+" if amp.gains is not None else "") + "dataspace"
    nf, nt, nbl = prob.data.shape
    kept = max(d.batch, -(-amp.gains.burn // RECENTRES) if amp.gains is not None else 1)
    check_memory(amplitude_memory_bytes(prob.system(), kept),
                 f"the amplitude run ({nf} channels, N_d = {2 * nt * nbl} data values per channel, "
                 f"n = {prob.system().prior.mean.shape[1]})",
                 "choose fewer channels (--freq-range, --chans), times (--lst-range) or antennas (--antennas), "
                 "a lower --lmax, or a smaller --batch")
    st.start("wiener")
    if run.state is None:
        chain = amplitude_chain_setup(key, prob, amp)
        eig = _eigen_at(chain.fixed, chain.block, chain.state.theta)
        a_wf = np.asarray(prob.system().prior.mean) + np.asarray(jax.jit(wiener_given)(chain.fixed, eig,
                                                                                       jnp.asarray(chain.u_med)))
        zeros = jnp.zeros(nf)
        winfo = direct_info(zeros, zeros, jnp.all(jnp.isfinite(jnp.asarray(a_wf)), axis=-1), DEFAULT_TOL)
        setup_factor = chain.u_med[:, None, None] * _lin_factor(chain.block, nf, nt, nbl)
        record_setup(prob, spec, run, a_wf, winfo, rank=None, method=method, options=OPTIONS_JSON,
                     key_scheme=AMPLITUDE_KEY_SCHEME, per_draw=_per_draw(prob, chain),
                     arrays={**_layout(prob, chain, setup_factor), **_state_arrays(chain, chain.state)})
        log.info("amplitude: median u per channel %s (pilot of %d draws)", np.array2string(chain.u_med, precision=4),
                 PILOT)
    elif run.start < d.n_batches:
        chain = _read_chain(key, prob, amp, run.h5)
        eig = _eigen_at(chain.fixed, None, None) if chain.block is None else None
    st.stop()
    st.start("draws")
    a0 = np.asarray(prob.system().prior.mean)
    batches = range(run.start, d.n_batches)
    for b in watch.progress(batches) if watch.progress is not None else batches:
        t0 = time.perf_counter()
        take = min(d.batch, d.nsamples - b * d.batch)
        state, lu, delta, theta, c = _batch(chain, eig, jax.random.fold_in(key, b), d.batch, amp)
        lu, delta, c = np.asarray(lu)[:take], np.asarray(jax.block_until_ready(delta))[:take], np.asarray(c)[:take]
        u = np.exp(lu)
        q = u / c[:, None]
        sky = c[:, None, None] * (a0[None] + delta)  # (take, Nf, n)
        finite = np.all(np.isfinite(sky), axis=-1).T
        zeros = jnp.zeros((nf, take))
        info = jax.tree_util.tree_map(np.asarray, direct_info(zeros, zeros, jnp.asarray(finite), DEFAULT_TOL))
        extra = {"amplitude_q": q, "amplitude_u": u, "amplitude_c": c}
        if chain.block is not None:
            th = np.asarray(theta)[:take]
            x = np.asarray(jax.vmap(lambda t: perturbations(chain.block.model, t))(th))  # (take, Nf, Nt, U)
            extra["gain_draws"] = np.sqrt(q)[:, :, None, None] * chain.lin[None] * (1.0 + x)
            extra["gain_theta"] = th
        kill_hook(append_batch(run.h5, b, np.swapaxes(sky, 0, 1), info, seconds=time.perf_counter() - t0,
                               extra=extra, replace=_state_arrays(chain, state)))
        chain = chain._replace(state=state)
    return method


def fit_problem(prob, h5):
    """``prob`` with the set-up's factor ``u_med D`` divided out (:func:`gcrsky.run.gains.gained_problem`)."""
    return gained_problem(prob, stored_setup_factor(h5))


def _ess(x: np.ndarray) -> float | None:
    """ESS of one chain (ndraws,) (:func:`gcrsky.inference.collapsed.effective_sample_size`); None below 4 draws."""
    from ..inference.collapsed import effective_sample_size

    return float(effective_sample_size(np.asarray(x)[None])) if x.shape[0] > 3 and np.std(x) > 0 else None


def amplitude_summary(prob, amp, h5, *, markov: bool | None = None, gain_theta: bool = True) -> dict:
    """``summary.json``'s blocks: ``flux_scale`` (per channel median and 95 % interval of ``q``, the autos' ratio
    beside it, the source) and ``amplitude`` (settings, ESS of every sampled scalar against :data:`ESS_FLOOR`).

    ``markov``: the draws are a Markov chain's (default: with gains; a beam run's are, without them), so
    every sampled scalar's chain diagnostics and their WARNING are given.  ``gain_theta`` False: the gains'
    draws (where recorded) are left to another block's diagnostics (a beam run's ``gains`` block)."""
    import h5py

    markov = amp.gains is not None if markov is None else markov

    with h5py.File(h5, "r") as h:
        rows = int(h["draws"].shape[1])
        q, u, c = h["amplitude_q"][:rows], h["amplitude_u"][:rows], h["amplitude_c"][:rows]
        theta = h["gain_theta"][:rows] if "gain_theta" in h and gain_theta else None
    checks = (getattr(prob.config, "checks", None) or {}).get("flux_scale") or {}
    autos = checks.get("ratio_per_channel") or [None] * q.shape[1]
    chans = []
    for i, f in enumerate(np.asarray(prob.freqs_hz)):
        lo, med, hi = np.percentile(q[:, i], [2.5, 50, 97.5]) if rows else (np.nan,) * 3
        chans.append({"freq_hz": float(f), "median": float(med), "lo95": float(lo), "hi95": float(hi),
                      "u_median": float(np.median(u[:, i])) if rows else None,
                      "autos_ratio": autos[i] if i < len(autos) else None})
    ess = {f"q[{i}]": _ess(q[:, i]) for i in range(q.shape[1])}
    if theta is not None and theta.shape[1]:
        th = {f"theta[{k}]": _ess(theta[:, k]) for k in range(theta.shape[1])}
        ok = {k: v for k, v in th.items() if v is not None}
        worst = sorted(ok, key=ok.get)[:5]
        ess.update({k: ok[k] for k in worst})
        ess_theta_min = min(ok.values()) if ok else None
    else:
        ess_theta_min = None
    low = sorted(k for k, v in ess.items() if v is not None and v < min(ESS_FLOOR, 0.5 * rows))
    chain = warning = None
    if markov and rows:  # a Markov chain: every sampled scalar's ESS and R-hat, and the WARNING
        from ..inference.diagnostics import chain_diagnostics, diagnostics_warning

        chain = chain_diagnostics({"amplitude_q": q, **({"gain_theta": theta} if theta is not None and theta.shape[1]
                                                        else {})},
                                  floor=ESS_FLOOR)
        warning = diagnostics_warning(chain, "the amplitude chain" if theta is None else "the amplitude and gain chain")
        if warning is not None:
            log.warning(warning.removeprefix("WARNING: "))
    flux = {"source": "inferred", "per_channel": chans,
            "autos_ratio": checks.get("ratio"),
            "model_sd": amp.model_sd,
            "definition": ("data = q x the visibilities of the sky model in K (Jy by Rayleigh-Jeans): q multiplies a "
                           "calibrated visibility; the sky a = c (a0 + delta) with c ~ N(1, model_sd^2) the sky model's "
                           "scale, so q's interval includes the model's own uncertainty"),
            "note": ("autos_ratio: the data's autocorrelations over the sky model's through the beam, an independent "
                     "check of the same number (it includes the receiver's noise)")}
    block = {"settings": amp.to_dict(), "ndraws": rows, "ess": ess, "ess_floor": ESS_FLOOR, "ess_low": low,
             "ess_theta_min": ess_theta_min, "c_mean": float(np.mean(c)) if rows else None,
             "independent_draws": not markov, "chain": chain, "warnings": [warning] if warning else []}
    return {"flux_scale": flux, "amplitude": block}
