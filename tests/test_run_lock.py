"""One run per output directory (issue 26 item 2): the lock, its stale form, and two CLI runs at once.

Before the lock, two runs into one ``--out`` raced: in 6 of 15 trials the final
``results.h5`` said "complete", named one seed and held the other run's draws, and an
``--overwrite`` while another run wrote killed that run with ``FileNotFoundError``.  Here the
first run is frozen (SIGSTOP) while it holds the directory, so the second and third runs
meet it mid-run deterministically; then it continues and must finish with its own draws.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gcrsky import cli
from gcrsky.io import read_draws, read_results_state
from gcrsky.run import LOCK_FILE, RunExistsError, RunLockedError, check_unlocked, lock_owner, run_lock
from gcrsky.run import lock as lockmod

REPO = Path(__file__).resolve().parents[1]
SMALL = ["--lmax", "8", "--nside", "32", "--nsamples", "20", "--batch", "8", "--no-plots", "--no-progress"]


def _hold(out: Path, seconds: float) -> subprocess.Popen:
    """Another process holding ``out``'s lock (prints ``held`` once it does)."""
    code = ("import sys, time; from gcrsky.run import run_lock\n"
            "with run_lock(sys.argv[1], ['run', '--out', sys.argv[1]]):\n"
            "    print('held', flush=True); time.sleep(float(sys.argv[2]))\n")
    p = subprocess.Popen([sys.executable, "-c", code, str(out), str(seconds)], stdout=subprocess.PIPE, text=True,
                         env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert p.stdout.readline().strip() == "held"
    return p


def test_lock_excludes_and_names_its_owner(tmp_path):
    out = tmp_path / "run"
    with run_lock(out, ["run", "--seed", "7"]) as path:
        assert path == out / LOCK_FILE and path.exists()
        owner = json.loads(path.read_text())
        assert owner["pid"] == os.getpid() and owner["argv"] == ["run", "--seed", "7"]
        with pytest.raises(RunLockedError, match=f"in use by another gcrsky run \\(pid {os.getpid()} on host"):
            with run_lock(out):  # a second open file description: flock excludes it even in this process
                pass
        assert lock_owner(out)["pid"] == os.getpid()
        with pytest.raises(RunExistsError):  # what the CLI's refusal handlers catch
            check_unlocked(out)
    assert not path.exists() and lock_owner(out) is None
    check_unlocked(out)
    with run_lock(out):  # free again
        pass


def test_lock_held_by_another_process(tmp_path):
    p = _hold(tmp_path, 60)
    try:
        with pytest.raises(RunLockedError) as e:
            with run_lock(tmp_path):
                pass
        assert e.value.owner["pid"] == p.pid and "--out" in str(e.value)
    finally:
        p.kill()
        p.wait()
    with run_lock(tmp_path):  # the kernel dropped the dead holder's lock: stale, taken over
        pass


def test_stale_lock_is_taken_over_with_a_warning(tmp_path, caplog):
    """A lock file whose owner died (no flock on it any more) is stale: taken over, and the log says whose."""
    (tmp_path / LOCK_FILE).write_text(json.dumps({"pid": 999999999, "host": "elsewhere", "argv": ["run"]}))
    with caplog.at_level(logging.WARNING, logger="gcrsky.run.lock"):
        with run_lock(tmp_path):
            assert json.loads((tmp_path / LOCK_FILE).read_text())["pid"] == os.getpid()
    assert "stale lock" in caplog.text and "999999999" in caplog.text
    assert not (tmp_path / LOCK_FILE).exists()


def test_without_flock_the_lock_is_an_exclusive_file(tmp_path, monkeypatch, caplog):
    """Where flock is unavailable: an exclusively created file; stale when its pid on this host is dead."""
    monkeypatch.setattr(lockmod, "_flock", lambda fd: None)
    with run_lock(tmp_path):
        with pytest.raises(RunLockedError, match=f"pid {os.getpid()}"):
            with run_lock(tmp_path):
                pass
    assert not (tmp_path / LOCK_FILE).exists()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    host = lockmod.socket.gethostname()
    (tmp_path / LOCK_FILE).write_text(json.dumps({"pid": int(dead.stdout), "host": host}))
    with caplog.at_level(logging.WARNING, logger="gcrsky.run.lock"):
        with run_lock(tmp_path):
            pass
    assert "stale lock" in caplog.text
    # a live pid on this host, or any pid on another host, is trusted: refused
    for owner in ({"pid": os.getppid(), "host": host}, {"pid": 999999999, "host": "elsewhere"}):
        (tmp_path / LOCK_FILE).write_text(json.dumps(owner))
        with pytest.raises(RunLockedError):
            with run_lock(tmp_path):
                pass
    # negative control of the fallback itself: with flock back, the same file (nobody holds it) is stale
    monkeypatch.undo()
    with run_lock(tmp_path):
        pass


def test_cli_refuses_a_directory_another_process_holds(tmp_path, capsys):
    """Refused before anything is built, whatever --overwrite / --resume say; nothing in --out touched."""
    keep = tmp_path / "notes.txt"
    keep.write_text("mine")
    p = _hold(tmp_path, 120)
    try:
        for extra in ([], ["--overwrite"], ["--resume"]):
            t0 = time.perf_counter()
            assert cli.main(["run", "--out", str(tmp_path), *SMALL, *extra]) == cli.EXIT_REFUSED
            err = capsys.readouterr().err
            assert f"in use by another gcrsky run (pid {p.pid}" in err and "Traceback" not in err
            assert time.perf_counter() - t0 < 30  # before the problem is built
    finally:
        p.kill()
        p.wait()
    assert sorted(f.name for f in tmp_path.iterdir()) == [LOCK_FILE, "notes.txt"] and keep.read_text() == "mine"


@pytest.mark.slow
def test_two_cli_runs_into_one_directory(tmp_path):
    """Run A holds --out (frozen mid-run by SIGSTOP); run B (another seed) and run C (--overwrite) are refused
    with exit 3 naming A; A then finishes with its own seed and draws, nothing of B or C in it."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    a = subprocess.Popen([sys.executable, "-m", "gcrsky", "run", "--out", str(tmp_path), *SMALL, "--seed", "1"],
                         env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 300
        while not (tmp_path / LOCK_FILE).exists() and a.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        a.send_signal(signal.SIGSTOP)
        assert a.poll() is None, "run A ended before it could be met"
        for extra in (["--seed", "2"], ["--seed", "2", "--overwrite"]):
            b = subprocess.run([sys.executable, "-m", "gcrsky", "run", "--out", str(tmp_path), *SMALL, *extra],
                               env=env, capture_output=True, text=True, timeout=600)
            assert b.returncode == cli.EXIT_REFUSED, b.stderr[-2000:]
            assert f"in use by another gcrsky run (pid {a.pid}" in b.stderr and "Traceback" not in b.stderr
        a.send_signal(signal.SIGCONT)
        out, err = a.communicate(timeout=600)
    finally:
        a.send_signal(signal.SIGCONT)
        a.kill() if a.poll() is None else None
    assert a.returncode == 0, err[-2000:]
    state = read_results_state(tmp_path / "results.h5")
    assert state.complete and state.settings["seed"] == 1
    assert json.loads((tmp_path / "summary.json").read_text())["run"]["seed"] == 1
    assert read_draws(tmp_path / "results.h5").draws.shape[1] == 20
    assert not (tmp_path / LOCK_FILE).exists()
