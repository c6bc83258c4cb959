"""Runs that survive: draws appended batch by batch, ``--resume``, refusal / ``--overwrite``, atomic writes.

The reference is an uninterrupted run (lmax 8, nside 32, 20 draws in batches of 8, so
three batches, the last truncated).  An interrupted run (stopped in-process after its
first batch, or killed with SIGKILL in a subprocess by the documented test hook
``GCRSKY_TEST_KILL_AFTER_BATCH``) and then resumed must end with exactly its draws:
compared bit for bit (``tobytes``), not to a tolerance.  Controls: a resume with
another batch size or seed, or of other inputs, is refused; so is a second run into
a directory that holds one.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from gcrsky import cli
from gcrsky.io import append_batch, atomic_path, finalize_results_h5, read_draws, read_results_state, write_json
from gcrsky.run import (
    PRODUCT_FILES,
    Draws,
    Output,
    ResumeError,
    RunExistsError,
    RunSpec,
    Watch,
    check_output,
    execute,
    existing_run_files,
    remove_run_files,
    run_settings,
)

NSAMPLES, BATCH = 20, 8
SMALL = ["--lmax", "8", "--nside", "32", "--nsamples", str(NSAMPLES), "--batch", str(BATCH), "--no-plots",
         "--no-progress"]
REPO = Path(__file__).resolve().parents[1]


class Interrupt(Exception):
    """Stands for a kill between two batches (raised by the progress wrapper)."""


def stop_after(k):
    """A ``progress`` wrapper that lets ``k`` batches through, then interrupts the run."""

    def wrap(it):
        for i, b in enumerate(it):
            if i == k:
                raise Interrupt
            yield b

    return wrap


def run(prob, out, *, nsamples=NSAMPLES, seed=0, batch=BATCH, existing="refuse", progress=None):
    """The run layer without report hooks (the draws, maps and products are its own)."""
    spec = RunSpec(Draws(nsamples, seed, batch), Output(out, existing, plots=False))
    return execute(prob, spec, watch=Watch(progress=progress))


def same_bits(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


@pytest.fixture(scope="module")
def problem():
    from gcrsky.sim import Config, problem_from_config

    return problem_from_config(Config(lmax=8, nside=32).validate())


@pytest.fixture(scope="module")
def reference(problem, tmp_path_factory):
    """An uninterrupted run (what every resumed run must reproduce)."""
    out = tmp_path_factory.mktemp("reference")
    run(problem, out)
    return out


def copy_run(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


# ---------------------------------------------------------------- the draws survive


@pytest.mark.slow
def test_pipeline_batches_follow_the_key_scheme(problem, reference):
    """The run layer's batch loop gives exactly gcrsky.inference.draw_batches' draws (the documented scheme)."""
    import jax

    from gcrsky import prepare
    from gcrsky.inference import draw_batches

    prepared = prepare(problem, method="cholesky", ndraws=BATCH)
    ref = draw_batches(jax.random.PRNGKey(0), prepared, NSAMPLES, BATCH).draws
    assert same_bits(read_draws(reference / "results.h5").draws, ref)


@pytest.mark.slow
def test_interrupted_run_resumes_bit_for_bit(problem, reference, tmp_path):
    with pytest.raises(Interrupt):
        run(problem, tmp_path, progress=stop_after(1))
    state = read_results_state(tmp_path / "results.h5")
    assert (state.batches_complete, state.n_batches, state.ndraws_complete, state.complete) == (1, 3, 8, False)
    assert existing_run_files(tmp_path) == ["results.h5"]  # no summary, no products yet
    assert same_bits(read_draws(tmp_path / "results.h5").draws, read_draws(reference / "results.h5").draws[:, :8])
    # a kill in the middle of the next append: rows beyond the count (garbage) must be ignored and redone
    with h5py.File(tmp_path / "results.h5", "r+") as h:
        h["draws"].resize(13, axis=1)
        h["draws"][:, 8:13] = 1e30
    assert read_draws(tmp_path / "results.h5").draws.shape[1] == 8
    summary, prods = run(problem, tmp_path, existing="resume")
    assert prods.resumed_at_batch == 1 and not prods.already_complete
    assert summary.run["resumed_at_batch"] == 1
    a, b = read_draws(reference / "results.h5"), read_draws(tmp_path / "results.h5")
    assert same_bits(b.draws, a.draws)
    assert same_bits(b.wiener_filter, a.wiener_filter)
    with h5py.File(reference / "results.h5", "r") as ha, h5py.File(tmp_path / "results.h5", "r") as hb:
        assert hb.attrs["complete"] and hb["draws"].shape == ha["draws"].shape
        for name in ("maps/std", "maps/mean", "maps/wiener", "mode_z"):
            assert same_bits(hb[name][()], ha[name][()]), name
    assert len(summary.timings_s["draw_batches_s"]) == 3
    assert sorted(existing_run_files(tmp_path)) == sorted(existing_run_files(reference))


@pytest.mark.slow
def test_resume_keeps_the_path_auto_chose(problem, tmp_path, monkeypatch):
    """auto -> matrix-free CG (forced here): the resumed run must use those options, not "cg"'s dense default."""
    import gcrsky.solvers.dense as dense

    monkeypatch.setattr(dense, "DENSE_MAX_N", 10)  # n = 81: auto now picks CG
    ref, out = tmp_path / "ref", tmp_path / "run"
    run(problem, ref, nsamples=6, batch=2)
    with pytest.raises(Interrupt):
        run(problem, out, nsamples=6, batch=2, progress=stop_after(1))
    with h5py.File(out / "results.h5", "r") as h:
        opts = json.loads(h.attrs["solver_options_json"])
    assert opts["method"] == "cg" and opts["fields"]["dense"] is False
    summary, _ = run(problem, out, nsamples=6, batch=2, existing="resume")
    assert summary.solver["method"] == "cg" and summary.solver["draws"]["iterations_max"] > 0
    assert same_bits(read_draws(out / "results.h5").draws, read_draws(ref / "results.h5").draws)


@pytest.mark.slow
def test_kill_and_resume_cli(reference, tmp_path):
    """SIGKILL after the first batch (the test hook), then ``gcrsky run --resume``: the reference's draws."""
    env = dict(os.environ, GCRSKY_TEST_KILL_AFTER_BATCH="1", PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "gcrsky", "run", "--out", str(tmp_path), *SMALL], env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    state = read_results_state(tmp_path / "results.h5")
    assert state.batches_complete == 1 and not state.complete
    assert existing_run_files(tmp_path) == ["results.h5"]
    assert cli.main(["run", "--out", str(tmp_path), *SMALL]) == cli.EXIT_REFUSED  # not without --resume
    assert cli.main(["run", "--out", str(tmp_path), "--resume", *SMALL]) == 0
    assert same_bits(read_draws(tmp_path / "results.h5").draws, read_draws(reference / "results.h5").draws)
    assert json.loads((tmp_path / "summary.json").read_text())["run"]["resumed_at_batch"] == 1


# ---------------------------------------------------------------- complete runs, refusals, overwrite


@pytest.mark.slow
def test_resume_of_a_complete_run_rewrites_missing_files(problem, reference, tmp_path):
    out = copy_run(reference, tmp_path / "run")
    (out / PRODUCT_FILES["posterior_std_fits"]).unlink()
    (out / "summary.json").unlink()
    before = (out / "results.h5").stat().st_mtime_ns
    summary, prods = run(problem, out, existing="resume")
    assert prods.already_complete
    assert sorted(prods.written) == sorted(["posterior_std.fits", "summary.json"])
    assert (out / "results.h5").stat().st_mtime_ns == before  # untouched
    assert sorted(existing_run_files(out)) == sorted(existing_run_files(reference))
    import healpy as hp

    np.testing.assert_array_equal(hp.read_map(out / "posterior_std.fits", field=None, dtype=None),
                                  hp.read_map(reference / "posterior_std.fits", field=None, dtype=None))
    _, again = run(problem, out, existing="resume")
    assert again.already_complete and again.written == []


def test_second_run_is_refused(tmp_path, capsys):
    """A directory holding a run's files: refused before anything is built (exit 3, naming the options)."""
    (tmp_path / "summary.json").write_text("{}")
    assert cli.main(["run", "--out", str(tmp_path), *SMALL]) == cli.EXIT_REFUSED
    err = capsys.readouterr().err
    assert "--resume" in err and "--overwrite" in err and "summary.json" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]
    # --resume without a results.h5 to continue is refused too
    assert cli.main(["run", "--out", str(tmp_path), "--resume", *SMALL]) == cli.EXIT_REFUSED
    assert "nothing to resume" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # the two are exclusive
        cli.main(["run", "--out", str(tmp_path), "--resume", "--overwrite", *SMALL])
    assert e.value.code == 2


@pytest.mark.slow
def test_overwrite_replaces_the_run(tmp_path, capsys):
    (tmp_path / "fig4_sky_maps.png").write_bytes(b"stale")  # a figure of an older run: must not survive
    (tmp_path / "notes.txt").write_text("mine")  # not a run file: left alone
    assert cli.main(["run", "--out", str(tmp_path), *SMALL]) == cli.EXIT_REFUSED
    assert cli.main(["run", "--out", str(tmp_path), "--overwrite", *SMALL]) == 0
    assert not (tmp_path / "fig4_sky_maps.png").exists()  # --no-plots: the stale figure is gone, not kept
    assert (tmp_path / "notes.txt").read_text() == "mine"
    assert read_results_state(tmp_path / "results.h5").complete
    assert cli.main(["run", "--out", str(tmp_path), *SMALL]) == cli.EXIT_REFUSED  # and again refused


@pytest.mark.slow
def test_resume_with_other_settings_is_refused(problem, reference, tmp_path, capsys, caplog):
    out = copy_run(reference, tmp_path / "run")
    argv = ["run", "--out", str(out), "--resume", *SMALL]
    assert cli.main([*argv, "--lmax", "6", "--batch", "4"]) == cli.EXIT_REFUSED  # the last --lmax / --batch win
    err = capsys.readouterr().err
    assert "--lmax (recorded 8, now 6)" in err and "--batch (recorded 8, now 4)" in err and "--overwrite" in err
    assert cli.main([*argv, "--data-seed", "3"]) == cli.EXIT_REFUSED
    assert "--data-seed (recorded 0, now 3)" in capsys.readouterr().err
    with pytest.raises(ResumeError) as e:  # the library names the settings too
        run(problem, out, seed=1, existing="resume")
    assert [d[0] for d in e.value.differences] == ["seed"]
    # same settings, other inputs: refused, after the problem is built, naming the input and by how much
    other = dataclasses.replace(problem, data=problem.data * (1 + 1e-9))
    with pytest.raises(ResumeError, match=r"inputs differ from those recorded \(data by 1e-09"):
        run(other, out, existing="resume")
    assert read_results_state(out / "results.h5").complete  # nothing was touched
    # inputs rebuilt with other rounding (a simulation rebuilt in another process differs by ~1 ulp): resumed
    rounded = dataclasses.replace(problem, data=problem.data * (1 + 4e-16))
    with caplog.at_level("INFO", logger="gcrsky.run.resume"):
        run(rounded, out, existing="resume")
    assert "floating-point rounding only" in caplog.text


def _nudged(prob, rel, *, geometry=False):
    """``prob`` with its data, noise and prior inverse variance (and, with ``geometry``, LSTs) changed by ``rel``."""
    out = dataclasses.replace(prob, data=prob.data * (1 + rel), sigma=prob.sigma * (1 - rel),
                              prior=prob.prior._replace(inv_var=prob.prior.inv_var * (1 + rel)))
    return dataclasses.replace(out, lsts_rad=prob.lsts_rad * (1 + rel)) if geometry else out


@pytest.mark.slow
def test_resume_continues_from_the_recorded_inputs(problem, reference, tmp_path, caplog):
    """Rebuilt inputs that differ by rounding: the resumed batches are drawn from the *recorded* inputs, so the run
    ends with the uninterrupted run's draws bit for bit (drawn from the rebuilt ones they differ in the last bits:
    the control). Inputs that differ by more: refused, naming ``--trust-recorded``, which then continues from the
    recorded ones (bit for bit again); a geometry difference (the LSTs) is refused even then."""
    from gcrsky.run.resume import recorded_inputs

    ref = read_draws(reference / "results.h5").draws
    out = tmp_path / "a"
    with pytest.raises(Interrupt):
        run(problem, out, progress=stop_after(1))
    kept = tmp_path / "kept"
    shutil.copytree(out, kept)
    rounded = _nudged(problem, 3e-16)
    assert not same_bits(rounded.data, problem.data)
    run(rounded, out, existing="resume")
    assert same_bits(read_draws(out / "results.h5").draws, ref)
    # control: the rebuilt (rounded) inputs themselves give other bits in the batches after the first
    run(rounded, tmp_path / "control")
    fresh = read_draws(tmp_path / "control" / "results.h5").draws
    assert not same_bits(fresh[:, 8:], ref[:, 8:]) and np.allclose(fresh, ref, rtol=0, atol=1e-9 * np.abs(ref).max())
    # recorded_inputs restores the recorded arrays exactly (dtype and bits)
    back = recorded_inputs(kept / "results.h5", rounded)
    for a, b in ((back.data, problem.data), (back.sigma, problem.sigma), (back.lsts_rad, problem.lsts_rad),
                 (back.prior.inv_var, problem.prior.inv_var), (back.weights, problem.weights)):
        assert same_bits(a, b)
    # more than rounding: refused, the remedy named; with trust_recorded: continued from the recorded inputs
    other = tmp_path / "b"
    shutil.copytree(kept, other)
    with pytest.raises(ResumeError, match=r"data by 1e-0?6.*--resume --trust-recorded"):
        run(_nudged(problem, 1e-6), other, existing="resume")
    spec = RunSpec(Draws(NSAMPLES, 0, BATCH), Output(other, "resume", plots=False, trust_recorded=True))
    with caplog.at_level("WARNING", logger="gcrsky.run.resume"):
        execute(_nudged(problem, 1e-6), spec)
    assert "--trust-recorded" in caplog.text and "data by 1e-06" in caplog.text
    assert same_bits(read_draws(other / "results.h5").draws, ref)
    # the geometry must match even with trust_recorded (the response is rebuilt from the settings)
    third = tmp_path / "c"
    shutil.copytree(kept, third)
    spec = RunSpec(Draws(NSAMPLES, 0, BATCH), Output(third, "resume", plots=False, trust_recorded=True))
    with pytest.raises(ResumeError, match=r"lsts_rad by 1e-0?6") as e:
        execute(_nudged(problem, 1e-6, geometry=True), spec)
    assert "--trust-recorded continues" not in str(e.value)
    with pytest.raises(ValueError, match="existing='resume'"):
        Output(third, "refuse", trust_recorded=True)


def test_trust_recorded_needs_resume(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--out", str(tmp_path), "--trust-recorded", *SMALL])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--trust-recorded continues a recorded run" in err and "with --resume" in err


SWEEP_BATCH = 4  # 20 draws in 5 batches: kills after 1 to 4 of them


@pytest.fixture(scope="module")
def reference_small_batches(problem, tmp_path_factory):
    out = tmp_path_factory.mktemp("reference4")
    run(problem, out, batch=SWEEP_BATCH)
    return read_draws(out / "results.h5").draws


@pytest.mark.slow
@pytest.mark.parametrize("sig,at,cache,resume_apart", [("KILL", 1, False, False), ("TERM", 2, True, False),
                                                       ("INT", 3, True, True), ("KILL", 4, True, True),
                                                       ("INT", 1, False, False)])
def test_kill_resume_sweep(reference_small_batches, tmp_path, sig, at, cache, resume_apart):
    """SIGKILL, SIGTERM (a batch system) and SIGINT (Ctrl-C) after several batches, with and without the persistent
    compile cache (the resumed process then reads the programs the killed one wrote), resumed in-process or in a
    process of its own: every time the uninterrupted run's draws, bit for bit. SIGTERM and SIGINT end with a line
    (exit 143 / 130), no traceback."""
    out = tmp_path / "run"
    argv = ["run", "--out", str(out), *SMALL, "--batch", str(SWEEP_BATCH)]
    env = dict(os.environ, GCRSKY_TEST_KILL_AFTER_BATCH=f"{at}:{sig}", PYTHONPATH=str(REPO),
               GCRSKY_COMPILE_CACHE=str(tmp_path / "cache") if cache else "off")
    proc = subprocess.run([sys.executable, "-m", "gcrsky", *argv], env=env, capture_output=True, text=True,
                          timeout=600)
    expect = {"KILL": -signal.SIGKILL, "TERM": cli.EXIT_TERMINATED, "INT": cli.EXIT_INTERRUPTED}[sig]
    assert proc.returncode == expect, proc.stderr[-2000:]
    if sig != "KILL":
        line = "terminated (SIGTERM)" if sig == "TERM" else "interrupted (Ctrl-C)"
        assert line in proc.stderr and "--resume" in proc.stderr and "Traceback" not in proc.stderr
    state = read_results_state(out / "results.h5")
    assert state.batches_complete == at and not state.complete
    if resume_apart:
        env.pop("GCRSKY_TEST_KILL_AFTER_BATCH")
        proc = subprocess.run([sys.executable, "-m", "gcrsky", *argv, "--resume"], env=env, capture_output=True,
                              text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-2000:]
    else:
        assert cli.main([*argv, "--resume"]) == 0
    assert same_bits(read_draws(out / "results.h5").draws, reference_small_batches)


def test_check_output(tmp_path):
    s = run_settings({"lmax": 8}, nsamples=4, seed=0, batch=2, method="auto", tol=1e-6)
    assert check_output(tmp_path / "nothing", s, "refuse") is None
    assert check_output(tmp_path, s, "resume") is None  # empty: a new run
    (tmp_path / "posterior_mean.fits").write_bytes(b"x")
    with pytest.raises(RunExistsError) as e:
        check_output(tmp_path, s, "refuse")
    assert e.value.files == ["posterior_mean.fits"]
    assert check_output(tmp_path, s, "overwrite") is None
    (tmp_path / "results.h5").write_bytes(b"not hdf5")
    with pytest.raises(ResumeError, match="cannot be read"):
        check_output(tmp_path, s, "resume")
    with pytest.raises(ValueError, match="existing must be"):
        check_output(tmp_path, s, "append")
    (tmp_path / ".results.tmp-1-abcd.h5").write_bytes(b"partial")
    assert sorted(remove_run_files(tmp_path)) == sorted(["results.h5", "posterior_mean.fits", ".results.tmp-1-abcd.h5"])
    assert not any(tmp_path.iterdir())


def test_scenarios_refuse_a_used_directory(tmp_path, capsys):
    (tmp_path / "B7").mkdir()
    (tmp_path / "B7" / "results.h5").write_bytes(b"x")
    assert cli.main(["scenarios", "B7", "--out", str(tmp_path), "--no-progress", "--no-plots"]) == cli.EXIT_REFUSED
    err = capsys.readouterr().err
    assert "--overwrite" in err and "B7" in err
    assert (tmp_path / "B7" / "results.h5").read_bytes() == b"x"


# ---------------------------------------------------------------- atomic writes


def test_atomic_path_leaves_no_partial_file(tmp_path):
    target = tmp_path / "out.json"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text('{"half": ')
            raise RuntimeError("killed mid-write")
    assert not any(tmp_path.iterdir())
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("new, half")
            raise RuntimeError("killed mid-write")
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["out.json"]
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".json" and not tmp.exists()
        tmp.write_text("new")
    assert target.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["out.json"]
    assert oct(target.stat().st_mode & 0o777) == oct(0o666 & ~_umask())  # ordinary permissions


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def test_interrupted_writers_leave_no_partial_file(tmp_path, monkeypatch):
    """The FITS and JSON writers, interrupted after writing part of their file."""
    import healpy as hp

    from gcrsky.io import write_healpix_fits

    def half_then_fail(filename, *a, **k):
        Path(filename).write_bytes(b"SIMPLE  =                    T" + b" " * 50)
        raise KeyboardInterrupt

    monkeypatch.setattr(hp, "write_map", half_then_fail)
    with pytest.raises(KeyboardInterrupt):
        write_healpix_fits(tmp_path / "m.fits", np.zeros((1, 12)), [1e8], frame="icrs", lmax=1, content="x")
    assert not any(tmp_path.iterdir())

    class Unencodable:  # json.dump streams: the first keys are in the file when this one fails
        def __str__(self):
            raise KeyboardInterrupt

    write_json(tmp_path / "s.json", {"a": 1})
    with pytest.raises(KeyboardInterrupt):
        write_json(tmp_path / "s.json", {"a": 2, "pad": "x" * 100_000, "b": Unencodable()})
    assert json.loads((tmp_path / "s.json").read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["s.json"]


@pytest.mark.slow
def test_interrupted_finalize_keeps_the_draws(reference, tmp_path):
    """finalize_results_h5 interrupted while writing the maps: results.h5 stays as it was, resumable."""
    out = copy_run(reference, tmp_path / "run")
    h5 = out / "results.h5"
    with h5py.File(h5, "r+") as h:  # as if the run had stopped before finalising
        h.attrs["complete"] = False
    before = h5.read_bytes()

    class Boom:
        def __array__(self, *a, **k):
            raise KeyboardInterrupt  # a kill while the maps are written (after the copy)

    with pytest.raises(KeyboardInterrupt):
        finalize_results_h5(h5, maps={"mean": np.zeros(3), "std": Boom()})
    assert h5.read_bytes() == before
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []
    assert not read_results_state(h5).complete


def _tiny_results(path, nsamples=5, batch=2):
    from types import SimpleNamespace

    from gcrsky.io import create_results_h5
    from gcrsky.model import Prior
    from gcrsky.sphere import mode_table

    nf, n = 1, 4
    prob = SimpleNamespace(
        a_true=None, prior=Prior(np.zeros((nf, n)), np.ones((nf, n))), modes=mode_table(1),
        freqs_hz=np.array([1e8]), lsts_rad=np.zeros(2), antpairs=np.array([[0, 1]]),
        data=np.zeros((nf, 2, 1), complex), sigma=np.ones((nf, 2, 1)), weights=np.ones((nf, 2, 1)),
    )
    return create_results_h5(path, prob, np.zeros((nf, n)), nsamples=nsamples, batch=batch, settings={"x": 1})


def test_append_waits_for_a_reader(tmp_path):
    """A reader holding results.h5 open between batches delays the append (HDF5 file lock), not kills the run."""
    h5 = _tiny_results(tmp_path / "r.h5")
    hold = ("import h5py, sys, time; f = h5py.File(sys.argv[1], 'r'); print('open', flush=True); "
            "time.sleep(float(sys.argv[2]))")
    for hold_s, wait_s, ok in ((1.0, 30.0, True), (30.0, 0.5, False)):
        p = subprocess.Popen([sys.executable, "-c", hold, str(h5), str(hold_s)], stdout=subprocess.PIPE, text=True)
        try:
            assert p.stdout.readline().strip() == "open"
            if ok:
                assert append_batch(h5, 0, np.zeros((1, 2, 4)), wait_s=wait_s) == 1
            else:
                with pytest.raises(OSError, match="held open by another process"):
                    append_batch(h5, 1, np.zeros((1, 2, 4)), wait_s=wait_s)
        finally:
            p.kill()
            p.wait()
    assert read_results_state(h5).batches_complete == 1


def test_append_batch_checks_order(tmp_path):
    """Batches go in order; the count rises only with the batch (io layer, a tiny fake problem)."""
    nf, n = 1, 4
    h5 = _tiny_results(tmp_path / "r.h5")
    with pytest.raises(ValueError, match="in order"):
        append_batch(h5, 1, np.zeros((nf, 2, n)))
    with pytest.raises(ValueError, match="shape"):
        append_batch(h5, 0, np.zeros((nf, 3, n)))
    assert read_results_state(h5).batches_complete == 0
    for b, take in ((0, 2), (1, 2), (2, 1)):
        assert append_batch(h5, b, np.full((nf, take, n), b, float), seconds=0.1) == b + 1
    st = read_results_state(h5)
    assert (st.ndraws_complete, st.draws_done, st.settings) == (5, True, {"x": 1})
    np.testing.assert_array_equal(read_draws(h5).draws[0, :, 0], [0, 0, 1, 1, 2])


def test_ctrl_c_is_a_line_not_a_traceback(tmp_path, capsys, monkeypatch):
    """Ctrl-C during a run: exit 130 and one line saying where the completed batches are (no traceback)."""

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("gcrsky.cli.cmd_run.execute_with_bars", interrupted)
    out = tmp_path / "run"
    assert cli.main(["run", "--out", str(out), *SMALL]) == cli.EXIT_INTERRUPTED == 130
    err = capsys.readouterr().err
    assert "interrupted (Ctrl-C)" in err and f"{out}/results.h5" in err and "--resume" in err
    assert "Traceback" not in err
