"""A run whose channels share one frequency-coupled prior (``RunSpec.frequency``; DESIGN section 13).

The problem's per-channel prior (e.g. the GSM's ``C_l(nu)``) gives the mode variances ``c_k`` at
the reference channel (the middle one, ``nu0``) and, through the ratio of every channel's prior
variance to the reference one's, the spectral index ``beta`` of the prior's standard deviation
(least squares in log-log, unless given).  :func:`frequency_prior_of` builds the separable
:class:`~gcrsky.model.spectral.FrequencyPrior` ``S = R (x) diag(c)`` of
:class:`~gcrsky.run.sampling.FrequencyModel` from them (template, basis or kernel ``R``), and
records how far its per-channel variances ``c_k R_ff`` are from the independent prior's.

The draws (:func:`frequency_draws`) are those of the joint posterior over all channels, by an
exact joint path (a path of :data:`gcrsky.solvers.registry.PATHS` with a joint flavour, planned by
:func:`gcrsky.solvers.plan.choose_joint_path`): per order of m for uniform full-day coverage, else dense; in the a-space (:mod:`gcrsky.solvers.joint`) or the data space
(:mod:`gcrsky.solvers.joint_dataspace`), whichever factor is narrower and fits in memory.  Key scheme
:data:`FREQ_KEY_SCHEME`: batch ``b`` is ``draw(fold_in(PRNGKey(seed), b), batch)``, so a
resumed run ends with the draws of an uninterrupted one.  The Wiener filter's accuracy is
measured from its true residual (:func:`gcrsky.solvers.joint.joint_wiener_info`), and the
draws carry it, as every direct path's do.

Flagged channels.  A channel without a single unflagged sample has no data term; its posterior
comes through ``R`` from its neighbours (inpainting).  :func:`channel_flags` says which channels
are fully or partly flagged; every run records it (``results.h5`` ``channels/``, the summary's
``channels`` block), and an independent run says that such channels are its prior's alone.
"""

from __future__ import annotations

import json
import logging

import jax
import jax.numpy as jnp
import numpy as np

from ..model.spectral import (
    FrequencyPrior,
    log_frequency_kernel,
    spectral_basis_cov,
)
from ..solvers.joint import JointSystem
from ..solvers.plan import choose_joint_path
from ..solvers.registry import LEGACY_JOINT_NAMES, path_of
from .draws import append_batches, record_setup
from .output import OpenRun
from .stages import StageTimer, Watch

__all__ = ["FREQ_KEY_SCHEME", "channel_flags", "frequency_draws", "frequency_prior_of", "joint_system_of"]

log = logging.getLogger(__name__)

#: The key scheme of a frequency-coupled run's draws (recorded in ``results.h5``).
FREQ_KEY_SCHEME = "joint-frequency-v1: batch b = draw_joint(fold_in(PRNGKey(seed), b), batch), (ndraws, Nf, n)"

def channel_flags(inv_noise) -> dict:
    """Which channels have data: ``{"flagged": [...], "partly_flagged": [...], "data_fraction": [...]}``.

    Args:
        inv_noise: (Nf, Nt, Nbl) per-component inverse noise variance (0 = flagged).

    Returns:
        ``flagged``: channels without a single unflagged sample; ``partly_flagged``: channels with
        some samples flagged, not all; ``data_fraction``: (Nf,) the unflagged fraction per channel.
    """
    w = np.asarray(inv_noise)
    frac = (w > 0).reshape(w.shape[0], -1).mean(axis=1)
    return {"flagged": [int(i) for i in np.flatnonzero(frac == 0)],
            "partly_flagged": [int(i) for i in np.flatnonzero((frac > 0) & (frac < 1))],
            "data_fraction": [float(x) for x in frac]}


def _fit_beta(freqs: np.ndarray, var: np.ndarray, f0: int) -> float:
    """The index of ``sqrt(median_k var_fk / var_f0k)`` against ``nu / nu0`` (least squares in log-log)."""
    if freqs.size < 2:
        return 0.0
    ratio = np.median(var / var[f0][None, :], axis=1)
    x, y = np.log(freqs / freqs[f0]), 0.5 * np.log(ratio)
    return float(np.sum(x * y) / np.sum(x * x))


def frequency_prior_of(system, freqs_hz, model) -> tuple[FrequencyPrior, dict]:
    """The frequency-coupled prior of ``model`` built on a problem's own per-channel prior.

    Args:
        system: the problem's :class:`~gcrsky.model.LinearSystem` (its prior: mean (Nf, n), a
            proper ``inv_var`` (Nf, n)).
        freqs_hz: (Nf,) channel frequencies, Hz, increasing or not, distinct.
        model: the :class:`~gcrsky.run.sampling.FrequencyModel`.

    Returns:
        ``(FrequencyPrior, info)``; ``info`` (JSON-able): the prior's name, ``nu0_mhz``, ``beta``
        (and whether it was fitted), the kernel or basis settings, and ``variance_ratio``: the
        range over channels and modes of ``c_k R_ff`` over the independent prior's variance.

    Raises:
        ValueError: the prior is not proper on every mode (a flat prior has no variance to couple).
    """
    prior = system.prior
    inv = np.asarray(prior.inv_var, np.float64)
    freqs = np.asarray(freqs_hz, np.float64)
    if not np.all(np.isfinite(inv) & (inv > 0)):
        raise ValueError("a frequency prior couples the prior variances of the channels, so it needs a proper prior "
                         "on every mode (this one is flat or zero on some): use --prior gsm or a prior file, or "
                         "--freq-prior independent")
    if np.unique(freqs).size != freqs.size:
        raise ValueError("a frequency prior needs distinct channel frequencies")
    var = 1.0 / inv
    f0 = freqs.size // 2
    nu0 = float(freqs[f0])
    fitted = model.beta is None
    beta = _fit_beta(freqs, var, f0) if fitted else model.beta
    info = {"prior": model.prior, "nu0_mhz": nu0 / 1e6, "reference_channel": f0, "beta": beta,
            "beta_fitted_to_prior": fitted, "nugget": model.nugget}
    if model.prior == "kernel":
        R = log_frequency_kernel(freqs, nu0, 1.0, beta, model.xi, nugget=model.nugget)
        info["xi"] = model.xi
    else:
        k = 1 if model.prior == "template" else model.nbasis
        R = spectral_basis_cov(freqs, nu0, beta, model.basis_sigma ** (2.0 * np.arange(k)), nugget=model.nugget)
        if k > 1:
            info.update(nbasis=k, basis_sigma=model.basis_sigma)
    fp = FrequencyPrior(mean=jnp.asarray(prior.mean), mode_var=jnp.asarray(var[f0]), freq_cov=jnp.asarray(R))
    ratio = np.diag(np.asarray(R))[:, None] * var[f0][None, :] / var
    info["variance_ratio"] = [float(ratio.min()), float(ratio.max())]
    return fp, info


def joint_system_of(prob, model) -> tuple[JointSystem, dict]:
    """The :class:`~gcrsky.solvers.joint.JointSystem` of a problem under ``model`` (and the prior's info).

    With ``model.fit`` the kernel's amplitude, index and correlation length are first fitted by the
    exact joint evidence (:func:`fit_kernel`) and the prior built at the fit.
    """
    system = prob.system()
    fp, info = frequency_prior_of(system, prob.freqs_hz, model)
    joint = JointSystem(system.op, system.data, system.inv_noise, fp)
    if model.fit:
        joint, info = fit_kernel(joint, prob.freqs_hz, model, info)
        ratio = (np.diag(np.asarray(joint.prior.freq_cov))[:, None] * np.asarray(joint.prior.mode_var)[None, :]
                 * np.asarray(system.prior.inv_var))
        info["variance_ratio"] = [float(ratio.min()), float(ratio.max())]
    return joint, info


def fit_kernel(joint: JointSystem, freqs_hz, model, info: dict) -> tuple[JointSystem, dict]:
    """The kernel prior at the maximum of the joint evidence (:func:`gcrsky.inference.spectral_hyper.
    fit_spectral_hyperparameters`, BFGS under its weak hyperprior), starting from ``info``'s ``beta`` and
    ``model.xi``.

    The run's prior mean is fixed per channel, so the evidence is that of the residual data
    ``d - X a0`` under a zero-mean prior; ``C_l(nu0)`` is read off the reference channel's variances
    (an isotropic prior: the m = 0 entries, checked to equal every m's).  The amplitude multiplies
    ``C_l(nu0)`` (1 = the problem's own prior at the reference channel).

    Returns:
        the system at the fit, and ``info`` with ``amplitude``, ``beta``, ``xi``, their Laplace errors,
        the log evidence and whether the fit converged (``fit``).

    Raises:
        ValueError: the reference channel's prior is not isotropic.
    """
    from ..inference.spectral_hyper import SpectralModel, fit_spectral_hyperparameters, spectral_prior
    from ..model.operator import apply
    from ..model.spectral import mode_variance
    from ..sphere.modes import mode_table

    c = np.asarray(joint.prior.mode_var)
    lmax = int(round(np.sqrt(c.size))) - 1
    tab = mode_table(lmax)
    cl = np.zeros(lmax + 1)
    cl[np.asarray(tab.ell)[np.asarray(tab.m) == 0]] = c[np.asarray(tab.m) == 0]
    if not np.allclose(np.asarray(mode_variance(jnp.asarray(cl))), c, rtol=1e-10, atol=0):
        raise ValueError("--freq-fit fits the amplitude of an isotropic C_l(nu0): the reference channel's prior is "
                         "not isotropic (its variance differs between m at one l)")
    nu0 = info["nu0_mhz"] * 1e6
    spec = SpectralModel(freqs_hz=jnp.asarray(freqs_hz, jnp.float64), nu0_hz=nu0, cl=jnp.asarray(cl),
                         nugget=model.nugget, mean0=None)
    resid = jnp.where(joint.inv_noise > 0, joint.data - apply(joint.op, joint.prior.mean), 0.0)
    start = {"log_amplitude": 0.0, "beta": float(info["beta"]), "log_xi": float(np.log(model.xi))}
    fit = fit_spectral_hyperparameters(joint._replace(data=resid), spec, start)
    theta = {k: float(v) for k, v in fit.theta.items()}
    fp = spectral_prior(spec, fit.theta)
    fp = fp._replace(mean=joint.prior.mean)
    sd = {k: float(v) for k, v in fit.std.items()}
    info = {**info, "beta": theta["beta"], "beta_fitted_to_prior": False, "xi": float(np.exp(theta["log_xi"])),
            "fit": {"amplitude": float(np.exp(theta["log_amplitude"])), "log_amplitude_sd": sd["log_amplitude"],
                    "beta_sd": sd["beta"], "log_xi_sd": sd["log_xi"], "log_evidence": float(fit.log_evidence),
                    "converged": bool(fit.converged), "steps": int(fit.num_steps),
                    "method": "maximum joint evidence (BFGS), Laplace errors, weak hyperprior"}}
    if not bool(fit.converged):
        log.warning("--freq-fit: the kernel's fit did not converge (%s); the prior is built where it stopped",
                    fit.message)
    return joint._replace(prior=fp), info


def _recorded_path(state) -> tuple[str, str]:
    """The path and joint form a resumed run recorded: ``(name, variant)``; runs before the joint paths
    joined the registry recorded ``joint-cholesky`` etc. (:data:`~gcrsky.solvers.registry.LEGACY_JOINT_NAMES`)."""
    method = str(state.attrs["method"])
    if method in LEGACY_JOINT_NAMES:
        return LEGACY_JOINT_NAMES[method]
    return method, str(json.loads(state.attrs["solver_options_json"])["variant"])


def frequency_draws(prob, spec, run: OpenRun, st: StageTimer, watch: Watch) -> str:
    """The ``wiener`` stage and the draws of a frequency-coupled run, from batch ``run.start``.

    Returns the path that ran; leaves the ``draws`` stage running (the caller stops it).
    """
    d = spec.draws
    st.start("wiener")
    joint, info = joint_system_of(prob, spec.frequency)
    if run.state is None:
        method, variant, _ = choose_joint_path(joint, spec.solver.method)
    else:
        method, variant = _recorded_path(run.state)
    path = path_of(method)
    state = path.joint_prepare(joint, spec.solver.tol, variant)
    a_wf = np.asarray(jax.block_until_ready(state.a_wf))
    winfo = state.wiener
    log.info("joint Wiener filter over %d channels by %s (%s): error <= %.3g posterior sigma", a_wf.shape[0], method,
             variant, float(winfo.err_sigma[0]))
    options = json.dumps({"method": method, "variant": variant, "frequency_prior": info})
    record_setup(prob, spec, run, a_wf, winfo, rank=None, method=method, options=options,
                 key_scheme=FREQ_KEY_SCHEME)
    st.stop()
    st.start("draws")
    key = jax.random.PRNGKey(d.seed)

    def draw_one(b):
        x, dinfo = path.joint_draw(jax.random.fold_in(key, b), state, d.batch)  # (Nf, batch, n)
        take = min(d.batch, d.nsamples - b * d.batch)
        return x[:, :take], jax.tree_util.tree_map(lambda v: v[:, :take], dinfo.draws)

    append_batches(run, d, watch, draw_one)
    return method


def _recorded_prior(h5) -> dict | None:
    """The frequency prior's settings a frequency-coupled run recorded in ``results.h5``."""
    import h5py

    with h5py.File(h5, "r") as f:
        text = f.attrs.get("solver_options_json")
    try:
        return json.loads(text).get("frequency_prior") if text else None
    except (TypeError, ValueError, AttributeError):
        return None


def channels_block(prob, model, h5, warnings: list) -> dict:
    """The summary's ``channels`` block (also ``results.h5``'s attribute ``channels_json``), and its note.

    Every run says which channels are fully or partly flagged and what their draws are: the
    prior's alone for independent channels (a NOTE in ``warnings``), inpainted through the
    frequency prior for a frequency-coupled run.

    Args:
        prob: the run's :class:`~gcrsky.model.Problem`; model: its frequency prior
        (:class:`~gcrsky.run.sampling.FrequencyModel`), or None for independent channels;
        h5: its ``results.h5``; warnings: the run's warnings (a note is appended).

    Returns:
        ``{"model", "freqs_mhz", "flagged", "partly_flagged", "data_fraction", "flagged_posterior",
        "frequency_prior"}`` (JSON-able).
    """
    flags = channel_flags(prob.system().inv_noise)
    freqs = np.asarray(prob.freqs_hz, np.float64)
    coupled = model is not None
    block = {"model": model.prior if coupled else "independent",
             "freqs_mhz": [float(f / 1e6) for f in freqs], **flags,
             "flagged_posterior": ("inpainted: the joint posterior through the frequency prior's coupling to the "
                                   "other channels" if coupled else "the prior alone (independent channels)"),
             "frequency_prior": _recorded_prior(h5) if coupled else None}
    if flags["flagged"]:
        mhz = ", ".join(f"{freqs[i] / 1e6:.3f}" for i in flags["flagged"])
        if coupled:
            warnings.append(f"NOTE: {len(flags['flagged'])} channel(s) fully flagged ({mhz} MHz): their draws and maps "
                            f"are inpainted through the {model.prior} frequency prior (marked in "
                            "summary.json's channels block and results.h5's channels_json).")
        else:
            warnings.append(f"NOTE: {len(flags['flagged'])} channel(s) fully flagged ({mhz} MHz): their draws and maps "
                            "are the prior's alone (independent channels); --freq-prior kernel inpaints them through "
                            "the neighbouring channels.")
    return block
