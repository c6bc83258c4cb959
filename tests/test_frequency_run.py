"""A run whose channels share a frequency prior (``RunSpec.frequency``, ``--freq-prior``; issue 25, items 3 and 5).

The problem: the shared 10-antenna hexagon, lmax 4, 4 channels 100-106 MHz, the isotropic prior
``C_l(nu) = C_l(nu0) (nu/nu0)^(2 beta)`` per channel (beta = -2.5), a truth drawn from the
kernel prior over the channels, radiometer noise, and channel 1 fully flagged (weights 0).
What is checked: the run's Wiener filter and draws are exactly the joint solvers' (the same
key scheme, bit for bit), the path is chosen by coverage (dense for 6 h, m-mode for the full
day, equal to the dense one to 1e-8 posterior sigma), the flagged channel is inpainted (its
posterior is narrower than its prior) and marked in summary.json and results.h5, and an
independent run of the same problem says its flagged channel is the prior's alone.  The
prior's spectral index is recovered from the per-channel prior variances exactly (a power
law by construction), and bad options are refused by name.
"""

from __future__ import annotations

import json

import equinox as eqx
import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gcrsky import cli
from gcrsky.model import build_problem, isotropic_prior
from gcrsky.model.spectral import log_frequency_kernel, mode_variance
from gcrsky.run import Draws, JointFrequency, Output, RunSpec, execute
from gcrsky.run.frequency import (
    FREQ_KEY_SCHEME,
    channel_flags,
    frequency_prior_of,
    joint_system_of,
)
from gcrsky.run.spec import FrequencyModel, sampling_of
from gcrsky.solvers.joint import (
    draw_joint_dense,
    joint_precision_matrix,
    joint_wiener_info,
    prepare_joint_dense,
    prepare_joint_mmode,
    whitened_solve,
)
from gcrsky.solvers.plan import choose_joint_path

LMAX = 4
N = (LMAX + 1) ** 2
FREQS = np.array([100e6, 102e6, 104e6, 106e6])
BETA = -2.5
MODEL = FrequencyModel("kernel", beta=BETA, xi=0.05)
FLAGGED = 1


def _problem(small_array, lsts, seed=0):
    nu0 = FREQS[FREQS.size // 2]
    cl0 = 30.0 / (1.0 + np.arange(LMAX + 1)) ** 2
    cl = cl0[None, :] * (FREQS / nu0)[:, None] ** (2 * BETA)
    R = np.asarray(log_frequency_kernel(FREQS, nu0, 1.0, BETA, MODEL.xi, nugget=MODEL.nugget))
    c = np.asarray(mode_variance(cl0))
    rng = np.random.default_rng(seed)
    mean = np.zeros((FREQS.size, N))
    mean[:, 0] = 300.0 * (FREQS / nu0) ** BETA  # a bright monopole: positive autos, the radiometer noise
    truth = mean + (np.linalg.cholesky(R) @ rng.standard_normal((FREQS.size, N))) * np.sqrt(c)[None, :]
    weights = np.ones((FREQS.size, lsts.size, 45))
    weights[FLAGGED] = 0.0
    return build_problem(small_array, FREQS, lsts, LMAX, 32, a_true=truth, prior=isotropic_prior(cl, N, mean=mean),
                         weights=weights, noise_scale=1e-4, key=jax.random.PRNGKey(seed))


@pytest.fixture(scope="module")
def partial(small_array):
    return _problem(small_array, np.linspace(0.0, 6 * np.pi / 12, 18))


def _spec(out, model=MODEL, nsamples=8, batch=4):
    return RunSpec(Draws(nsamples, seed=3, batch=batch), Output(out, plots=False), sampling=JointFrequency(model))


@pytest.fixture(scope="module")
def coupled_run(partial, tmp_path_factory):
    out = tmp_path_factory.mktemp("coupled")
    summary, _ = execute(partial, _spec(out))
    return out, summary


def test_the_run_draws_exactly_the_joint_posterior(partial, coupled_run):
    out, summary = coupled_run
    joint, _ = joint_system_of(partial, MODEL)
    state = prepare_joint_dense(joint)
    with h5py.File(out / "results.h5", "r") as h:
        assert h.attrs["method"] == "cholesky" and h.attrs["key_scheme"] == FREQ_KEY_SCHEME
        wf, draws = np.asarray(h["wiener_filter"]), np.asarray(h["draws"])
    np.testing.assert_array_equal(wf, np.asarray(state.a_wf))
    key = jax.random.PRNGKey(3)
    want = np.concatenate([np.asarray(draw_joint_dense(jax.random.fold_in(key, b), state, 4)) for b in (0, 1)])
    np.testing.assert_array_equal(draws, np.moveaxis(want, 0, 1))  # (Nf, ndraws, n), batch by batch
    assert summary.solver["all_converged"] and summary.run["method"] == "cholesky"
    # the measured bound is rounding: M's whitened residual (tolerance 1e-6 sigma, measured ~1e-9 here)
    assert summary.solver["wiener"]["err_sigma_max"] < 1e-6


def test_the_flagged_channel_is_inpainted_and_marked(partial, coupled_run):
    out, summary = coupled_run
    ch = summary.channels
    assert ch["model"] == "kernel" and ch["flagged"] == [FLAGGED] and ch["partly_flagged"] == []
    assert ch["data_fraction"] == [1.0, 0.0, 1.0, 1.0] and "inpainted" in ch["flagged_posterior"]
    assert ch["frequency_prior"]["beta"] == BETA and ch["frequency_prior"]["xi"] == MODEL.xi
    with h5py.File(out / "results.h5", "r") as h:
        assert json.loads(h.attrs["channels_json"]) == ch
    assert any("inpainted" in w and "102.000" in w for w in summary.warnings)
    # the inpainted channel's posterior variance, exactly: the joint precision's inverse restricted to it, against
    # its prior variance c_k R_ff.  No data can pin it below its prior variance given the other channels exactly,
    # 1 / (R^-1_ff R_ff) of it (analytic), and the modes the neighbours measure well come within 2x of that limit
    joint, _ = joint_system_of(partial, MODEL)
    cov = np.linalg.inv(np.asarray(joint_precision_matrix(joint)))
    post = np.diag(cov).reshape(FREQS.size, N)[FLAGGED]
    prior = np.asarray(joint.prior.mode_var) * float(joint.prior.freq_cov[FLAGGED, FLAGGED])
    R = np.asarray(joint.prior.freq_cov)
    limit = 1.0 / (np.linalg.inv(R)[FLAGGED, FLAGGED] * R[FLAGGED, FLAGGED])
    ratio = post / prior
    assert np.all(ratio < 1.0) and np.all(ratio > limit * (1 - 1e-9)) and ratio.min() < 2 * limit, (ratio, limit)


def test_an_independent_run_says_its_flagged_channel_is_the_prior(partial, tmp_path):
    summary, _ = execute(partial, RunSpec(Draws(4, seed=3, batch=4), Output(tmp_path, plots=False)))
    ch = summary.channels
    assert ch["model"] == "independent" and ch["flagged"] == [FLAGGED] and ch["frequency_prior"] is None
    assert "prior alone" in ch["flagged_posterior"]
    assert any("prior's alone" in w and "--freq-prior kernel" in w for w in summary.warnings)
    with h5py.File(tmp_path / "results.h5", "r") as h:
        wf = np.asarray(h["wiener_filter"])
    np.testing.assert_allclose(wf[FLAGGED], np.asarray(partial.prior.mean)[FLAGGED], atol=1e-12)


def test_full_day_coverage_takes_the_m_mode_path(small_array, tmp_path):
    prob = _problem(small_array, 2 * np.pi * np.arange(12) / 12, seed=1)
    # the m-mode path needs noise constant in time: the radiometer sigma, averaged over the day
    prob = eqx.tree_at(lambda p: p.sigma, prob, jnp.broadcast_to(prob.sigma.mean(axis=1, keepdims=True),
                                                                  prob.sigma.shape))
    joint, _ = joint_system_of(prob, MODEL)
    assert choose_joint_path(joint, "auto")[:2] == ("mmode", "mmode")
    summary, _ = execute(prob, _spec(tmp_path, nsamples=4))
    assert summary.run["method"] == "mmode" and summary.solver["all_converged"]
    with h5py.File(tmp_path / "results.h5", "r") as h:
        wf = np.asarray(h["wiener_filter"])
    e = (wf - np.asarray(prepare_joint_dense(joint).a_wf)).reshape(-1)
    # the m-mode filter against the dense one in posterior sigma, sqrt(e^T P e) with the explicit joint precision:
    # cond(P) = 5e8 here, and the dense, m-mode and NumPy solves agree pairwise to 2-3e-8 sigma (measured), the
    # rounding floor: tolerance 1e-7; and the run's own measured bound met its tolerance (1e-6)
    assert np.sqrt(e @ np.asarray(joint_precision_matrix(joint)) @ e) < 1e-7
    assert float(joint_wiener_info(joint, wf, 1e-6).err_sigma[0]) < 1e-6
    # M^-1 by the m-mode factor equals the dense factor's (the measured error uses it; cond(M) ~ 5e8: rtol 1e-6)
    v = np.random.default_rng(2).standard_normal(wf.shape)
    np.testing.assert_allclose(whitened_solve(prepare_joint_mmode(joint), v),
                               whitened_solve(prepare_joint_dense(joint), v), rtol=1e-6, atol=1e-9)


def test_the_prior_is_built_on_the_problem_s_own(partial):
    system = partial.system()
    fp, info = frequency_prior_of(system, FREQS, FrequencyModel("kernel", xi=0.05, nugget=0.0))
    assert info["beta_fitted_to_prior"] and abs(info["beta"] - BETA) < 1e-12  # an exact power law, recovered
    np.testing.assert_allclose(info["variance_ratio"], [1.0, 1.0], rtol=1e-12)  # c_k R_ff = the channel's variance
    _, tinfo = frequency_prior_of(system, FREQS, FrequencyModel("template", beta=-2.0))
    assert tinfo["variance_ratio"][0] < 1.0 < tinfo["variance_ratio"][1]  # another index: the variances differ
    fpb, binfo = frequency_prior_of(system, FREQS, FrequencyModel("basis", beta=BETA, nbasis=2))
    assert binfo["nbasis"] == 2 and np.all(np.linalg.eigvalsh(np.asarray(fpb.freq_cov)) > 0)
    flat = system._replace(prior=system.prior._replace(inv_var=jnp.zeros_like(system.prior.inv_var)))
    with pytest.raises(ValueError, match="proper prior"):
        frequency_prior_of(flat, FREQS, MODEL)


def test_channel_flags_counts_samples():
    w = np.ones((3, 2, 4))
    w[0] = 0.0
    w[2, 1, :2] = 0.0
    assert channel_flags(w) == {"flagged": [0], "partly_flagged": [2], "data_fraction": [0.0, 1.0, 0.75]}


def test_bad_frequency_settings_are_refused(partial, tmp_path, capsys):
    with pytest.raises(ValueError, match="frequency.prior"):
        FrequencyModel("spline")
    with pytest.raises(ValueError, match="frequency.xi"):
        FrequencyModel("kernel", xi=0.0)
    with pytest.raises(ValueError, match="needs prior 'kernel'"):
        FrequencyModel("basis", fit=True)
    with pytest.raises(ValueError, match="sampled together"):
        sampling_of("loop", None, MODEL)
    joint, _ = joint_system_of(partial, MODEL)
    with pytest.raises(ValueError, match="not --method eigh"):
        choose_joint_path(joint, "eigh")
    with pytest.raises(ValueError, match="m-mode path does not apply"):
        choose_joint_path(joint, "mmode")
    for argv, msg in ((["--freq-xi", "0.2"], "add --freq-prior"),
                      (["--freq-prior", "kernel", "--freq-nbasis", "2"], "do not apply to --freq-prior kernel"),
                      (["--freq-prior", "template", "--freq-fit"], "do not apply to --freq-prior template"),
                      (["--freq-prior", "kernel", "--by-channel"], "sampled together")):
        with pytest.raises(SystemExit) as e:
            cli.main(["run", "--out", str(tmp_path / "x"), *argv])
        assert e.value.code == 2
        assert msg in capsys.readouterr().err, argv


def test_the_measured_wiener_error_is_the_exact_one(partial):
    """``joint_wiener_info`` with the factor: ``sqrt(r^T M^-1 r)`` equals the exact M-norm of a planted error
    (explicit NumPy precision, rtol 1e-6: the planted error is 1e-3 sigma, far above rounding); without the
    factor, the bound ``||r||_2`` is at least it (M >= I)."""
    joint, _ = joint_system_of(partial, MODEL)
    state = prepare_joint_dense(joint)
    P = np.asarray(joint_precision_matrix(joint))
    rng = np.random.default_rng(5)
    e = rng.standard_normal(P.shape[0])
    e *= 1e-3 / np.sqrt(e @ P @ e)  # 1e-3 posterior sigma
    wrong = np.asarray(state.a_wf) + e.reshape(state.a_wf.shape)
    exact = joint_wiener_info(joint, wrong, 1e-6, solve=lambda v: whitened_solve(state, v))
    bound = joint_wiener_info(joint, wrong, 1e-6)
    np.testing.assert_allclose(float(exact.err_sigma[0]), 1e-3, rtol=1e-6)
    assert float(bound.err_sigma[0]) >= float(exact.err_sigma[0]) and not bool(exact.converged[0])


@pytest.mark.parametrize("full_day", [False, True])
def test_the_data_space_paths_run_the_same_posterior(small_array, partial, tmp_path, full_day):
    """``--method dataspace``: the dense data space (6 h) or per order (full day), the same Wiener filter as the
    a-space joint path in posterior sigma with the explicit joint precision, to the run's tolerance 1e-6 (measured
    1.4e-7 on 6 h, where D = I + Y S Y^T of these precise data has the larger condition number, and ~3e-8 on the
    full day), its own measured error within that tolerance."""
    from gcrsky.run import Solver

    prob = partial
    if full_day:
        prob = _problem(small_array, 2 * np.pi * np.arange(12) / 12, seed=1)
        prob = eqx.tree_at(lambda p: p.sigma, prob, jnp.broadcast_to(prob.sigma.mean(axis=1, keepdims=True),
                                                                      prob.sigma.shape))
    joint, _ = joint_system_of(prob, MODEL)
    want = "mmode" if full_day else "dense"
    assert choose_joint_path(joint, "dataspace")[:2] == ("dataspace", want)
    spec = RunSpec(Draws(4, seed=3, batch=4), Output(tmp_path, plots=False), Solver("dataspace"), JointFrequency(MODEL))
    summary, _ = execute(prob, spec)
    assert summary.run["method"] == "dataspace" and summary.solver["all_converged"]
    with h5py.File(tmp_path / "results.h5", "r") as h:
        assert json.loads(h.attrs["solver_options_json"])["variant"] == want  # the form, beside the path's name
        e = (np.asarray(h["wiener_filter"]) - np.asarray(prepare_joint_dense(joint).a_wf)).reshape(-1)
    assert np.sqrt(e @ np.asarray(joint_precision_matrix(joint)) @ e) < 1e-6


def test_without_memory_auto_takes_cg_and_a_direct_path_is_refused_by_name(partial, monkeypatch):
    from gcrsky.base.memory import InsufficientMemoryError

    joint, _ = joint_system_of(partial, MODEL)
    monkeypatch.setenv("GCRSKY_MEMORY_BUDGET_GB", "1e-6")
    assert choose_joint_path(joint, "auto")[:2] == ("cg", "cg")
    with pytest.raises(InsufficientMemoryError, match=r"joint path cholesky \(dense\) over 4 channels"):
        choose_joint_path(joint, "cholesky")


def test_the_cg_path_runs_the_same_posterior(partial, tmp_path):
    """``--method cg``: CG's Wiener filter equals the dense one to its tolerance (1e-6 posterior sigma, the run's
    default; CG's stop bounds the error's P-norm), its own per-draw bounds recorded, all converged."""
    from gcrsky.run import Solver

    joint, _ = joint_system_of(partial, MODEL)
    spec = RunSpec(Draws(4, seed=3, batch=4), Output(tmp_path, plots=False), Solver("cg"), JointFrequency(MODEL))
    summary, _ = execute(partial, spec)
    assert summary.run["method"] == "cg" and summary.solver["all_converged"]
    assert summary.solver["wiener"]["err_sigma_max"] <= 1e-6
    with h5py.File(tmp_path / "results.h5", "r") as h:
        e = (np.asarray(h["wiener_filter"]) - np.asarray(prepare_joint_dense(joint).a_wf)).reshape(-1)
        assert h["draw_info/iterations"].shape == (FREQS.size, 4)
    assert np.sqrt(e @ np.asarray(joint_precision_matrix(joint)) @ e) < 1e-6


def test_freq_fit_fits_the_kernel_by_the_joint_evidence(partial, tmp_path):
    """``FrequencyModel(fit=True)``: the kernel's amplitude, index and correlation length by the exact joint
    evidence of the residual data (the run's per-channel prior mean fixed), recorded with Laplace errors; the
    run samples the prior at the fit.  The data were drawn from the kernel (A = 1, beta = -2.5, xi = 0.05):
    each fitted value lies within 4 Laplace sigma of it (a 6e-5 false-alarm rate each, if Gaussian)."""
    model = FrequencyModel("kernel", beta=-2.0, xi=0.2, fit=True)  # started away from the truth
    joint, info = joint_system_of(partial, model)
    fit = info["fit"]
    assert fit["converged"] and fit["steps"] > 0
    assert abs(np.log(fit["amplitude"])) < 4 * fit["log_amplitude_sd"], fit
    assert abs(info["beta"] - BETA) < 4 * fit["beta_sd"], (info["beta"], fit)
    assert abs(np.log(info["xi"] / MODEL.xi)) < 4 * fit["log_xi_sd"], (info["xi"], fit)
    R = log_frequency_kernel(FREQS, FREQS[2], fit["amplitude"], info["beta"], info["xi"], nugget=model.nugget)
    np.testing.assert_allclose(np.asarray(joint.prior.freq_cov), np.asarray(R), rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(joint.prior.mean), np.asarray(partial.prior.mean))
    summary, _ = execute(partial, _spec(tmp_path, model=model, nsamples=4))
    assert summary.channels["frequency_prior"]["fit"] == fit


class _Interrupt(Exception):
    """Stands for a kill between two batches."""


def _stop_after(k):
    def wrap(it):
        for i, b in enumerate(it):
            if i == k:
                raise _Interrupt
            yield b

    return wrap


def test_a_run_recorded_under_an_old_joint_name_resumes_bit_for_bit(partial, coupled_run, tmp_path):
    """Runs before the joint paths joined the registry recorded ``method = "joint-cholesky"`` (and no form):
    interrupted after one batch and relabelled so, it resumes by the same path and ends with exactly the draws
    of the uninterrupted run (``coupled_run``), recorded under the path's own name from then on."""
    from gcrsky.run import Watch

    ref, _ = coupled_run
    with pytest.raises(_Interrupt):
        execute(partial, _spec(tmp_path), watch=Watch(progress=_stop_after(1)))
    with h5py.File(tmp_path / "results.h5", "r+") as h:
        assert h.attrs["method"] == "cholesky"
        opts = json.loads(h.attrs["solver_options_json"])
        assert opts.pop("variant") == "dense"
        h.attrs["method"] = "joint-cholesky"
        h.attrs["solver_options_json"] = json.dumps({**opts, "method": "joint-cholesky"})
    spec = RunSpec(Draws(8, seed=3, batch=4), Output(tmp_path, "resume", plots=False),
                   sampling=JointFrequency(MODEL))
    summary, prods = execute(partial, spec)
    assert prods.resumed_at_batch == 1 and summary.run["method"] == "cholesky"
    with h5py.File(ref / "results.h5", "r") as ha, h5py.File(tmp_path / "results.h5", "r") as hb:
        assert np.asarray(hb["draws"]).tobytes() == np.asarray(ha["draws"]).tobytes()
        assert hb.attrs["complete"]
