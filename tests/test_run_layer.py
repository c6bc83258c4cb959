"""The run layer (gcrsky.run): its specification, its summary, and report hooks.

* :class:`RunSpec` refuses bad values with a ``ValueError`` that names the field, and its
  settings are exactly :func:`run_settings` of its fields (what ``results.h5`` records).
* :class:`RunSummary` round-trips ``summary.json``: reading a run's file and writing it
  back gives the same bytes.
* A run without report hooks (lmax 8, nside 32, 6 draws in batches of 4) writes the draws,
  the products and a summary with no paper metrics; the same run with the paper's hook
  (:func:`gcrsky.paper.pipeline.paper_hooks`) has bit-identical draws and adds the
  metrics, which must equal :mod:`gcrsky.paper.metrics` applied to the stored maps.
* Hooks are merged in order (:func:`collect_metrics`); a hook that reports another
  number of channels is an error.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from gcrsky.io import read_draws, write_json
from gcrsky.run import (
    Draws,
    FigureReport,
    FrequencyModel,
    Gains,
    GainSampling,
    Independent,
    Joint,
    JointFrequency,
    Output,
    ReportHook,
    RunSpec,
    RunSummary,
    RunView,
    Solver,
    execute,
    read_summary,
    run_maps,
    run_settings,
)
from gcrsky.run.report import collect_figures, collect_metrics
from gcrsky.run.spec import sampling_of

NSAMPLES, BATCH = 6, 4
PRODUCTS = ("posterior_mean.fits", "posterior_std.fits", "posterior_mean_alm.fits", "posterior_mean.skyh5")


# ---------------------------------------------------------------- the specification


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: Draws(0), "draws.nsamples"),
        (lambda: Draws(5, seed=-1), "draws.seed"),
        (lambda: Draws(5, batch=0), "draws.batch"),
        (lambda: Draws(2.5), "draws.nsamples"),
        (lambda: Draws(True), "draws.nsamples"),
        (lambda: Solver(method="lu"), "solver.method"),
        (lambda: Solver(tol=0.0), "solver.tol"),
        (lambda: Solver(tol=float("nan")), "solver.tol"),
        (lambda: Output("runs/x", existing="append"), "output.existing"),
        (lambda: Output("runs/x", plots="yes"), "output.plots"),
        (lambda: Output(""), "output.out"),
        (lambda: RunSpec(Draws(5), Output("x"), Solver(), Independent("threads")), "sampling.channels"),
        (lambda: RunSpec(Draws(5), Output("x"), sampling="loop"), "sampling must be a DrawStage"),
        (lambda: sampling_of("loop", GainSampling()), "channels and gains were both given.*drop channels"),
        (lambda: sampling_of("loop", None, FrequencyModel()), "channels and frequency.*sampled together"),
        (lambda: sampling_of(None, GainSampling(), FrequencyModel()), "gains and frequency.*--gains sample"),
        (lambda: RunSpec(Draws(5), Output("x"), argv="run --seed 1"), "argv"),
        (lambda: RunSpec(Draws(5), Output("x"), extra={"seed": 3}), "extra setting 'seed'"),
        (lambda: RunSpec(Draws(5), "x"), "output must be a Output"),
        (lambda: RunSpec(Draws(5), Output("x"), scenario=7), "scenario"),
    ],
)
def test_spec_refuses_bad_values_naming_them(make, field):
    with pytest.raises(ValueError, match=field):
        make()


def test_spec_settings_and_types():
    spec = RunSpec(Draws(np.int64(20), 1, 8), Output("runs/x", "resume", False), Solver("cg", 1e-8),
                   Independent("loop"), scenario="B1", argv=["run", "--seed", "1"], extra={"data_file": "f.uvh5"})
    assert type(spec.draws.nsamples) is int and spec.draws.n_batches == 3
    assert spec.output.out == Path("runs/x") and spec.argv == ("run", "--seed", "1")
    from gcrsky.parallel import CHANNEL_KEY_SCHEME

    want = run_settings({"lmax": 8}, nsamples=20, seed=1, batch=8, method="cg", tol=1e-8, scenario="B1",
                        extra={"data_file": "f.uvh5", "channels": "loop", "channel_key_scheme": CHANNEL_KEY_SCHEME})
    assert spec.settings({"lmax": 8}) == want
    assert list(want)[-3:] == ["data_file", "channels", "channel_key_scheme"]
    with pytest.raises(AttributeError):  # frozen
        spec.draws.nsamples = 3

# The settings each kind of run recorded before RunSpec held one draw stage (gcrsky 87d15d9, computed with
# RunSpec(channels=..., gains=..., frequency=...)): a run recorded then must still resume, so its settings
# must be equal, key for key and in the same order.
SETTINGS_BEFORE_COMMON = {'config': {'lmax': 6, 'nside': 32}, 'nsamples': 20, 'seed': 3, 'batch': 8, 'method': 'cg', 'tol': 1e-08, 'scenario': 'B1', 'key_scheme': 'batch b: jax.random.fold_in(jax.random.PRNGKey(seed), b); full batches, last truncated', 'data': 'f.uvh5'}
SETTINGS_BEFORE = {'joint': {}, 'loop': {'channels': 'loop', 'channel_key_scheme': 'channel f (index in the full channel list): key_f = jax.random.fold_in(key, f) on the one-channel system freq_slice(system, f); batch b of channel f: jax.random.fold_in(key_f, b); full batches, last truncated'}, 'devices': {'channels': 'devices', 'channel_key_scheme': 'channel f (index in the full channel list): key_f = jax.random.fold_in(key, f) on the one-channel system freq_slice(system, f); batch b of channel f: jax.random.fold_in(key_f, b); full batches, last truncated'}, 'processes': {'channels': 'processes', 'channel_key_scheme': 'channel f (index in the full channel list): key_f = jax.random.fold_in(key, f) on the one-channel system freq_slice(system, f); batch b of channel f: jax.random.fold_in(key_f, b); full batches, last truncated'}, 'gains': {'gains': {'modes': [2, 3], 'basis': 'fourier', 'sigma': 0.1, 'burn': 10, 'thin': 2, 'gauge_moves': 1, 'applied': 1.5}}, 'kernel': {'frequency': {'prior': 'kernel', 'beta': None, 'xi': 0.1, 'nbasis': 3, 'basis_sigma': 0.1, 'nugget': 1e-06, 'fit': False}}, 'basis': {'frequency': {'prior': 'basis', 'beta': -2.5, 'xi': 0.1, 'nbasis': 2, 'basis_sigma': 0.2, 'nugget': 0.001, 'fit': False}}}


@pytest.mark.parametrize("kind", list(SETTINGS_BEFORE))
def test_settings_of_each_draw_stage_equal_those_recorded_before(kind):
    stages = {
        "joint": Joint(), "loop": Independent("loop"), "devices": Independent("devices"),
        "processes": Independent("processes"),
        "gains": Gains(GainSampling(modes=(2, 3), basis="fourier", sigma=0.1, burn=10, thin=2, gauge_moves=1,
                                    applied=1.5)),
        "kernel": JointFrequency(FrequencyModel()),
        "basis": JointFrequency(FrequencyModel(prior="basis", beta=-2.5, nbasis=2, basis_sigma=0.2)),
    }
    spec = RunSpec(Draws(20, 3, 8), Output("x"), Solver("cg", 1e-8), stages[kind], scenario="B1", argv=("run",),
                   extra={"data": "f.uvh5"})
    got = spec.settings({"lmax": 6, "nside": 32})
    want = {**SETTINGS_BEFORE_COMMON, **SETTINGS_BEFORE[kind]}
    assert got == want and list(got) == list(want)
    assert json.dumps(got) == json.dumps(want)  # the recorded text too
    # the convenience views of the one sampling choice
    assert spec.channels == (kind if kind in ("loop", "devices", "processes") else None)
    assert (spec.gains is None) == (kind != "gains") and (spec.frequency is None) == (kind not in ("kernel", "basis"))


def test_every_draw_stage_file_is_a_run_file():
    from gcrsky.run.output import RUN_FILES
    from gcrsky.run.sampling import STAGES

    assert all(f in RUN_FILES for stage in STAGES for f in stage.files)
    assert Gains.files == ("gains.calh5",) and Joint.files == ()


# ---------------------------------------------------------------- runs with and without hooks


@pytest.fixture(scope="module")
def problem():
    from gcrsky.sim import Config, problem_from_config

    return problem_from_config(Config(lmax=8, nside=32).validate())


@pytest.fixture(scope="module")
def runs(problem, tmp_path_factory):
    """The same draws twice: without report hooks (figures asked for), and with the paper's hook."""
    from gcrsky.paper.pipeline import paper_hooks

    bare, paper = tmp_path_factory.mktemp("bare"), tmp_path_factory.mktemp("paper")
    a = execute(problem, RunSpec(Draws(NSAMPLES, 0, BATCH), Output(bare, plots=True), Solver("cholesky")))
    b = execute(problem, RunSpec(Draws(NSAMPLES, 0, BATCH), Output(paper, plots=False), Solver("cholesky")),
                hooks=paper_hooks(problem))
    return (bare, *a), (paper, *b)


@pytest.mark.slow
def test_a_run_without_hooks_writes_products_and_no_paper_metrics(runs, problem):
    (out, summary, prods), _ = runs
    for name in ("results.h5", "summary.json", *PRODUCTS):
        assert (out / name).is_file(), name
    assert not list(out.glob("*.png")) and summary.figures == {}  # figures come only from hooks
    assert summary.per_frequency == [{"freq_hz": 100e6}, {"freq_hz": 102e6}]
    assert summary.metrics == {"freq_hz": 100e6} and summary.frac_diff_centre_median is None
    assert summary.region["centre_dec_deg"] == pytest.approx(-30.7215, abs=1e-3)  # the strip: the configuration's
    assert summary.region["fwhm_deg"] == [None, None] and summary.warnings == []
    assert summary.exit_status == 0 and summary.solver["method"] == "cholesky"
    assert prods.fwhm_deg is None and prods.truth_map is not None and prods.written[:2] == ["results.h5",
                                                                                           "summary.json"]
    with h5py.File(out / "results.h5", "r") as h:  # the run layer's own: maps and z-scores against the truth
        assert h.attrs["complete"] and "mode_z" in h and set(h["maps"]) == {"truth", "mean", "std", "wiener"}
        np.testing.assert_array_equal(h["mode_z"][0], prods.z)


@pytest.mark.slow
def test_the_paper_hook_adds_its_metrics(runs, problem):
    (bare, *_), (out, summary, prods) = runs
    assert read_draws(out / "results.h5").draws.tobytes() == read_draws(bare / "results.h5").draws.tobytes()
    from gcrsky.paper import metrics as M
    from gcrsky.paper.pipeline import simulated_fwhm_deg

    m = summary.metrics
    fwhm = simulated_fwhm_deg(problem.config, problem.freqs_hz)
    assert m["fwhm_deg"] == fwhm[0] and summary.region["fwhm_deg"] == list(fwhm) and prods.fwhm_deg == fwhm[0]
    with h5py.File(out / "results.h5", "r") as h:
        maps = {k: h["maps"][k][()] for k in h["maps"]}
        z = h["mode_z"][()]
    centre, ra = summary.region["centre_dec_deg"], tuple(summary.region["ra_range_deg"])
    for f, pf in enumerate(summary.per_frequency):
        want = M.summary_metrics(maps["mean"][f], maps["truth"][f], centre, fwhm[f], ra, std_map=maps["std"][f])
        assert {k: pf[k] for k in want} == want
        assert pf["wiener_frac_diff_centre_median"] == M.summary_metrics(
            maps["wiener"][f], maps["truth"][f], centre, fwhm[f], ra)["frac_diff_centre_median"]
        assert {k: pf[k] for k in ("std_centre_median", "std_fwhm_over_sky")} == {
            k: v for k, v in M.std_metrics(maps["std"][f], centre, fwhm[f], ra).items()
            if k in ("std_centre_median", "std_fwhm_over_sky")}
        assert pf["mode_z"] == M.z_score_stats(z[f])
    assert summary.frac_diff_centre_median == m["frac_diff_centre_median"] < 0.05


@pytest.mark.slow
def test_summary_round_trips_summary_json(runs, tmp_path):
    for out, summary, _ in runs:
        text = (out / "summary.json").read_text()
        back = read_summary(out / "summary.json")
        assert back == RunSummary.from_json(json.loads(text))
        assert list(back.to_json()) == list(json.loads(text))  # the same keys, in the same order
        write_json(tmp_path / "again.json", back.to_json())
        assert (tmp_path / "again.json").read_text() == text
    with pytest.raises(ValueError, match="not keys of a run summary: extra_key"):
        RunSummary.from_json({**json.loads(text), "extra_key": 1})


# ---------------------------------------------------------------- hooks, merged in order


class _Counter(ReportHook):
    def __init__(self, name, nchan=None):
        self.name, self.nchan = name, nchan

    def metrics(self, view):
        n = len(view.per_freq) if self.nchan is None else self.nchan
        return [{self.name: len(view.per_freq[i]) if i < len(view.per_freq) else 0} for i in range(n)]

    def figures(self, view, out, *, only_missing):
        return FigureReport({self.name: f"{self.name}.png"}, [f"NOTE: {self.name}"])


class _Nothing(ReportHook):
    """The protocol's defaults: nothing added."""


def test_hooks_are_merged_in_order(tmp_path):
    from types import SimpleNamespace

    from gcrsky.sphere import n_params

    lmax, nside = 2, 4
    rng = np.random.default_rng(0)
    prob = SimpleNamespace(freqs_hz=np.array([1e8, 2e8]), lmax=lmax, nside=nside, a_true=None, config=None)
    draws = rng.standard_normal((2, 3, n_params(lmax)))
    maps = run_maps(prob, draws, draws.mean(axis=1))
    assert maps.truth_maps is None and maps.mode_z is None and maps.centre_dec_deg is None
    view = RunView(prob, draws, maps, [], True, None)
    per_freq = collect_metrics(view, [_Counter("a"), _Nothing(), _Counter("b")])
    assert per_freq == [{"freq_hz": 1e8, "a": 1, "b": 2}, {"freq_hz": 2e8, "a": 1, "b": 2}]  # b saw a's
    assert collect_figures(view, [_Counter("a"), _Counter("b")], tmp_path, only_missing=True) == (
        {"a": "a.png", "b": "b.png"}, ["NOTE: a", "NOTE: b"])
    with pytest.raises(ValueError, match="metrics of 1 channels, the problem has 2"):
        collect_metrics(view, [_Counter("c", nchan=1)])


def test_the_core_holds_no_figure_names_and_a_hooks_files_are_run_files(tmp_path):
    """The paper's figures are the paper hook's files: run/output.py names none of them, yet a directory with
    one is refused, overwritten and cleared with the run when the hook's files are given."""
    import inspect

    import gcrsky.run.output as output
    from gcrsky.paper.report import FIGURE_FILES, PaperReport
    from gcrsky.run import RunExistsError, check_output, existing_run_files, remove_run_files
    from gcrsky.run.report import hook_files

    src = inspect.getsource(output)
    assert not any(name in src for name in FIGURE_FILES.values()) and "FIGURE_FILES" not in src
    figures = hook_files([PaperReport(), _Nothing(), PaperReport()])
    assert figures == tuple(FIGURE_FILES.values())  # each once, in the hook's order
    (tmp_path / "fig4_sky_maps.png").write_bytes(b"png")
    (tmp_path / "notes.txt").write_text("mine")
    assert existing_run_files(tmp_path) == [] and check_output(tmp_path, {}, "refuse") is None  # not a run file alone
    assert existing_run_files(tmp_path, figures) == ["fig4_sky_maps.png"]
    with pytest.raises(RunExistsError, match="fig4_sky_maps.png"):
        check_output(tmp_path, {}, "refuse", figures)
    (tmp_path / "gains.calh5").write_bytes(b"h5")  # a draw stage's file, after the hook's (the order of old)
    assert existing_run_files(tmp_path, figures) == ["fig4_sky_maps.png", "gains.calh5"]
    assert remove_run_files(tmp_path, figures) == ["fig4_sky_maps.png", "gains.calh5"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_stored_maps_are_typed_and_used_as_they_were(tmp_path, problem):
    """``stored_maps`` gives a StoredMaps (each map None where absent); ``run_maps`` uses the maps given."""
    from gcrsky.run.maps import StoredMaps, stored_maps

    rng = np.random.default_rng(3)
    draws = rng.normal(size=(problem.data.shape[0], 4, problem.n))
    fresh = run_maps(problem, draws, draws.mean(axis=1))
    path = tmp_path / "r.h5"
    with h5py.File(path, "w") as h:
        h["maps/mean"], h["maps/std"] = fresh.mean_maps + 1.0, fresh.std_maps
    got = stored_maps(path)
    assert isinstance(got, StoredMaps) and got.truth is None and got.wiener is None
    np.testing.assert_array_equal(got.mean, fresh.mean_maps + 1.0)
    again = run_maps(problem, draws, draws.mean(axis=1), maps=got)
    np.testing.assert_array_equal(again.mean_maps, fresh.mean_maps + 1.0)  # taken, not recomputed
    np.testing.assert_array_equal(again.wiener_maps, fresh.wiener_maps)  # absent: computed
    with h5py.File(tmp_path / "none.h5", "w"):
        pass
    assert stored_maps(tmp_path / "none.h5") == StoredMaps()


def test_sampling_of_gives_one_draw_stage_and_only_a_workers_share_runs_elsewhere():
    assert sampling_of() == Joint() and RunSpec(Draws(5), Output("x")).sampling == Joint()
    assert sampling_of("devices") == Independent("devices") and sampling_of(None, GainSampling()) == Gains()
    assert sampling_of(frequency=FrequencyModel("template")) == JointFrequency(FrequencyModel("template"))
    assert not any(s.elsewhere() for s in (Joint(), Independent("processes"), Gains()))  # this is process 0
    assert [type(s).name for s in (Joint(), Independent(), JointFrequency(), Gains())] == [
        "joint", "independent", "frequency", "gains"]
