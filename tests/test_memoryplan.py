"""The run's memory plan (gcrsky.run.memoryplan, issue 39): all channels at once where a direct path fits,
one channel at a time where only one channel's does, a refusal naming the command line's options where
not even that fits, before anything large is allocated.  The budgets are set from the planner's own
estimates (so the test follows them), and the by-channel run's Wiener filter is checked against dense
algebra."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from gcrsky.base import InsufficientMemoryError
from gcrsky.inference import gibbs_setup, gibbs_setup_bytes
from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array
from gcrsky.io.results import read_draws
from gcrsky.model import build_problem, isotropic_prior
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.run import Draws, Independent, Joint, Output, RunSpec, Solver, execute
from gcrsky.run.memoryplan import CLI_MEMORY_OPTIONS, fit_in_memory
from gcrsky.solvers import CGOptions
from gcrsky.solvers.cg import freq_slice
from gcrsky.solvers.path import AUTO_MEMORY_FRACTION
from gcrsky.solvers.plan import plan_sampler

NF = 4


@pytest.fixture(scope="module")
def prob():
    """lmax 12 (n = 169), 4 channels, 3 times, uncompressed 19-antenna hexagon."""
    lmax, n = 12, 169
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    cl = 40.0 / (1.0 + np.arange(lmax + 1)) ** 2
    prior = isotropic_prior(np.stack([cl * (1 + 0.1 * f) for f in range(NF)]), n)
    rng = np.random.default_rng(3)
    truth = np.asarray(prior.inv_var) ** -0.5 * rng.standard_normal((NF, n))
    return build_problem(arr, 100e6 + 1e6 * np.arange(NF), np.linspace(0.0, 0.4, 3), lmax, 16, a_true=truth,
                         sigma=0.5, prior=prior, key=jax.random.PRNGKey(0))


def _spec(tmp_path, method="auto", sampling=None):
    return RunSpec(Draws(8, batch=4), Output(tmp_path / "run"), Solver(method), sampling or Joint())


def _sizes(prob):
    system = prob.system()
    return plan_sampler(system, ndraws=4, budget=1e15), plan_sampler(freq_slice(system, 0), ndraws=4, budget=1e15)


def test_ample_memory_keeps_every_channel_at_once(prob, tmp_path):
    joint, _ = _sizes(prob)
    plan = fit_in_memory(prob, _spec(tmp_path), budget=1e15)
    assert isinstance(plan.spec.sampling, Joint) and plan.note is None
    assert plan.joint == (joint.method, joint.memory_bytes) and joint.method != "cg"


def test_one_channel_at_a_time_where_only_one_fits_a_direct_path(prob, tmp_path):
    joint, one = _sizes(prob)
    assert joint.memory_bytes > 2 * one.memory_bytes  # the fixture's joint direct set-up is several channels'
    budget = 1.5 * one.memory_bytes / AUTO_MEMORY_FRACTION  # one channel's direct path fits, all of them do not
    assert plan_sampler(prob.system(), ndraws=4, budget=budget).method == "cg"  # the joint plan falls back to CG
    plan = fit_in_memory(prob, _spec(tmp_path), budget=budget)
    assert plan.spec.sampling == Independent("loop")
    assert plan.per_channel[0] == plan_sampler(freq_slice(prob.system(), 0), ndraws=4, budget=budget).method != "cg"
    assert "one channel at a time" in plan.note and f"all {NF} channels" in plan.note
    # the run it plans: every channel's Wiener filter is the dense solve's (an exact direct path per channel)
    P, b = np.asarray(precision_matrix(prob.system())), np.asarray(wiener_rhs(prob.system()))
    execute(prob, plan.spec)
    a_wf = read_draws(tmp_path / "run" / "results.h5").wiener_filter
    for f in range(NF):
        ref = np.linalg.solve(P[f], b[f])
        assert np.max(np.abs(a_wf[f] - ref)) < 1e-8 * np.max(np.abs(ref))


def test_nothing_fits_is_refused_naming_the_command_line_options(prob, tmp_path):
    with pytest.raises(InsufficientMemoryError, match="not even one channel fits") as err:
        fit_in_memory(prob, _spec(tmp_path), budget=1e3)
    assert CLI_MEMORY_OPTIONS in str(err.value) and "--by-channel" in str(err.value)


def test_a_chosen_path_or_draw_stage_is_left_as_given(prob, tmp_path):
    for spec in (_spec(tmp_path, "cholesky"), _spec(tmp_path, sampling=Independent("loop"))):
        assert fit_in_memory(prob, spec, budget=1e3).spec is spec


def test_gibbs_setup_memory_is_checked_before_it_is_allocated(prob, monkeypatch):
    """The H1C case of issue 39 (64 channels, lmax 246, the CG sketch of 512): ~51 GB, XLA's failed allocation
    was 50950583536 bytes; here the budget is below the small fixture's estimate: refused, nothing built."""
    assert gibbs_setup_bytes(64, 247**2, CGOptions(dense=False)) > 50950583536
    system = prob.system()
    need = gibbs_setup_bytes(NF, system.prior.mean.shape[1])
    assert need == 3 * 8.0 * NF * 169**2
    monkeypatch.setenv("GCRSKY_MEMORY_BUDGET_GB", str(0.5 * need / 2**30))
    with pytest.raises(InsufficientMemoryError, match=r"gibbs_setup \(CholeskyOptions, Nf = 4, n = 169\)"):
        gibbs_setup(system)
    monkeypatch.setenv("GCRSKY_MEMORY_BUDGET_GB", str(2 * need / 2**30))
    gibbs_setup(system)  # fits: built


def test_the_command_line_names_its_options_for_any_memory_refusal():
    """A library refusal (it names library options) gets the command line's; XLA's own out-of-memory error (an
    allocation no estimate foresaw: issue 39's raw RESOURCE_EXHAUSTED traceback) becomes the same kind of message;
    other runtime errors stay bugs."""
    from gcrsky.cli.errors import error_message, out_of_memory

    msg = error_message(InsufficientMemoryError("gibbs_setup (CGOptions, Nf = 64, n = 61009) needs ~47 GiB"))
    assert msg.endswith(CLI_MEMORY_OPTIONS) and "--lmax" in msg
    xla = jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 50950583536 bytes.")
    oom = out_of_memory(xla)
    assert isinstance(oom, MemoryError) and "47.45 GiB" in str(oom) and oom.__cause__ is xla
    assert "--by-channel" in error_message(oom)
    assert out_of_memory(jax.errors.JaxRuntimeError("INTERNAL: something else")) is None
    assert out_of_memory(ValueError("Out of memory")) is None


def test_an_amplitude_run_that_does_not_fit_is_refused_before_its_set_up(prob, tmp_path, monkeypatch):
    """The amplitude's data-space chain (issue 38's default on uncalibrated files) checks its estimate
    (gcrsky.inference.amplitude.amplitude_memory_bytes) before the set-up: nothing is written."""
    from gcrsky.inference.amplitude import GRAM_COPIES, amplitude_memory_bytes
    from gcrsky.run.sampling import Amplitude

    system = prob.system()
    nf, nt, nbl = system.data.shape
    need = amplitude_memory_bytes(system, 4)
    assert need > GRAM_COPIES * 8.0 * nf * (2 * nt * nbl) ** 2
    monkeypatch.setenv("GCRSKY_MEMORY_BUDGET_GB", str(0.5 * need / 2**30))
    with pytest.raises(InsufficientMemoryError, match=r"the amplitude run \(4 channels, N_d = "):
        execute(prob, _spec(tmp_path, sampling=Amplitude()))
    assert not (tmp_path / "run" / "results.h5").exists()


def test_products_show_the_first_channel_with_data_and_say_their_units(prob, tmp_path):
    """Issue 39: with channel 0 fully flagged (100 MHz on H1C), the top-level metrics, RunProducts and the
    figures use channel 1 (the first with data) and say so; the maps carry their unit in summary.json and in
    the FITS headers.  Negative control: without the flags, channel 0 is shown."""
    import dataclasses

    import h5py
    from astropy.io import fits

    w = np.asarray(prob.weights).copy()
    w[0] = 0.0
    flagged = dataclasses.replace(prob, weights=w)
    assert not np.any(np.asarray(flagged.system().inv_noise)[0] > 0)
    summary, products = execute(flagged, _spec(tmp_path))
    assert summary.shown_channel["index"] == 1 and "first channel with data" in summary.shown_channel["why"]
    assert summary.metrics == summary.per_frequency[1] != summary.per_frequency[0]
    with h5py.File(tmp_path / "run" / "results.h5") as h:
        mean = {k: h[k][()] for k in ("maps/mean",) if k in h} or {"maps/mean": h["mean_maps"][()]}
    np.testing.assert_array_equal(products.mean_map, mean["maps/mean"][1])
    assert summary.units == {"maps": "K", "flux_scale": "simulation", "note": summary.units["note"]}
    header = fits.getheader(tmp_path / "run" / "posterior_mean.fits", 1)
    assert header["MAPUNIT"] == "K" and header["FLUXSCAL"] == "simulation"
    control, _ = execute(prob, _spec(tmp_path / "control"))
    assert control.shown_channel["index"] == 0 and control.metrics == control.per_frequency[0]


@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf"])
def test_a_memory_budget_that_is_not_a_positive_number_is_refused(value, monkeypatch):
    from gcrsky.base.memory import available_memory_bytes

    monkeypatch.setenv("GCRSKY_MEMORY_BUDGET_GB", value)
    with pytest.raises(ValueError, match="positive, finite number of GiB"):
        available_memory_bytes()
    monkeypatch.setenv("GCRSKY_MEMORY_BUDGET_GB", "1.5")  # the control
    assert available_memory_bytes() == 1.5 * 2**30
