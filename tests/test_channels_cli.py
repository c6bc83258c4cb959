"""``gcrsky run`` with independent channels: --by-channel, --devices K and jax.distributed processes.

The reference is computed in this process, independently of the command:
:func:`gcrsky.parallel.sample_channels` on the same simulated problem
(``problem_from_config``) with the run's seed and batch size.  Every way of running the
channels must write exactly those draws to ``results.h5`` (the direct path: bitwise on one
and two CPU devices and two processes, measured; tolerance 1e-12 relative to allow for
XLA's fusion inside the sharded program).  A by-channel run killed after its first batch
and resumed ends with the same draws; resuming it as a joint run is refused.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from gcrsky import cli
from gcrsky.cli.options import channel_mode
from gcrsky.io.results import read_draws
from gcrsky.parallel import CHANNEL_KEY_SCHEME, sample_channels

REPO = Path(__file__).resolve().parents[1]
SMALL = ["--lmax", "8", "--nside", "32", "--nsamples", "10", "--batch", "4", "--no-plots", "--no-progress"]


def _cmd(out, *extra):
    return [sys.executable, "-m", "gcrsky", "run", "--out", str(out), *SMALL, *extra]


def _env(**extra):
    env = dict(os.environ, PYTHONPATH=str(REPO), GCRSKY_COMPILE_CACHE="off")
    env.pop("XLA_FLAGS", None)  # --devices sets its own
    env.update(extra)
    return env


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def reference():
    from gcrsky.sim.config import Config
    from gcrsky.sim.standard import problem_from_config

    prob = problem_from_config(Config(lmax=8, nside=32).validate())
    return sample_channels(jax.random.PRNGKey(0), prob.system(), 10, batch=4)


def _close(a, b):
    scale = np.max(np.abs(b))
    return np.max(np.abs(a - b)) <= 1e-12 * scale


@pytest.mark.slow
def test_by_channel_and_devices_write_the_library_draws(reference, tmp_path):
    for name, extra in (("loop", ["--by-channel"]), ("devices", ["--devices", "2"])):
        out = tmp_path / name
        proc = subprocess.run(_cmd(out, *extra), env=_env(), capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        stored = read_draws(out / "results.h5")
        assert _close(stored.draws, reference.draws), name
        assert _close(stored.wiener_filter, reference.a_wf), name
        settings = json.loads((out / "summary.json").read_text())["run"]
        assert settings["nsamples"] == 10
    import h5py

    with h5py.File(tmp_path / "devices" / "results.h5", "r") as h:
        assert h.attrs["key_scheme"] == CHANNEL_KEY_SCHEME
        assert json.loads(h.attrs["run_settings_json"])["channels"] == "devices"


@pytest.mark.slow
def test_two_processes_write_the_library_draws(reference, tmp_path):
    out = tmp_path / "dist"
    addr = f"127.0.0.1:{_free_port()}"
    procs = [subprocess.Popen(_cmd(out, "--coordinator", addr, "--num-processes", "2", "--process-id", str(i)),
                              env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for i in (0, 1)]
    try:
        outs = [p.communicate(timeout=600) for p in procs]
    finally:
        for p in procs:
            p.kill()
    for p, (so, se) in zip(procs, outs):
        assert p.returncode == 0, se[-3000:]
    assert "process 1 of 2: computed its channels" in outs[1][0]
    stored = read_draws(out / "results.h5")
    assert _close(stored.draws, reference.draws)


@pytest.mark.slow
def test_killed_by_channel_run_resumes_to_the_same_draws(reference, tmp_path):
    out = tmp_path / "killed"
    proc = subprocess.run(_cmd(out, "--by-channel"), env=_env(GCRSKY_TEST_KILL_AFTER_BATCH="1"),
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert cli.main(["run", "--out", str(out), "--resume", *SMALL]) == cli.EXIT_REFUSED  # joint != by channel
    assert cli.main(["run", "--out", str(out), "--resume", "--by-channel", *SMALL]) == 0
    assert _close(read_draws(out / "results.h5").draws, reference.draws)


def test_channel_options_are_checked(capsys):
    for bad in (["--coordinator", "h:1"], ["--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"]):
        with pytest.raises(SystemExit):
            cli.main(["run", "--out", "x", *bad])
        assert "--process-id" in capsys.readouterr().err
    p = cli.build_parser()
    assert channel_mode(p.parse_args(["run"])) is None
    assert channel_mode(p.parse_args(["run", "--by-channel"])) == "loop"
    assert channel_mode(p.parse_args(["run", "--devices", "2"])) == "devices"
    assert channel_mode(p.parse_args(["run", "--devices", "1", "--by-channel"])) == "loop"
