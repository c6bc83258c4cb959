"""The m-mode blocks split over devices and over jax.distributed processes (issue 24 item 4) equal the
single-device path.

The device count is fixed when JAX's backend starts, so the check runs in a subprocess with two
forced host devices (:func:`gcrsky.parallel.runtime.host_devices_env`, as tests/test_sharding.py does).
A full day (30 equally spaced LSTs > 2 lmax) of the 10-antenna hexagon at lmax 12 with buckets
of 4 orders (several buckets, alternating between the two devices); references: the
single-device :func:`gcrsky.solvers.mmode.prepare_mmode` / :func:`~gcrsky.solvers.mmode.draw_mmode` in the
same process (the same operations on the same inputs: equal to 1e-13 relative) and a dense
solve of P for the Wiener filter (1e-8 posterior sigma).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from gcrsky.parallel.runtime import host_devices_env

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 300

#: The full-day problem both subprocess scripts build (10-antenna hexagon, lmax 12, 30 LSTs).
SYSTEM = r'''
lmax, nt = 12, 30
arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
n = (lmax + 1) ** 2
prior = isotropic_prior((50.0 / (1.0 + np.arange(lmax + 1)) ** 2)[None], n)
truth = np.asarray(prior.inv_var) ** -0.5 * np.random.default_rng(0).standard_normal((1, n))
prob = build_problem(arr, [100e6], np.arange(nt) * 2 * np.pi / nt, lmax, 32, a_true=truth, sigma=0.05,
                     prior=prior, key=jax.random.PRNGKey(0))
system = prob.system()
'''

CHECK = r'''
import json, sys
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array
from gcrsky.model import build_problem, isotropic_prior
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.parallel.mblocks import draw_mmode_on, prepare_mmode_on
from gcrsky.solvers import MModeOptions
from gcrsky.solvers.mmode import draw_mmode, prepare_mmode

''' + SYSTEM + r'''opts = MModeOptions(bucket=4)
one = prepare_mmode(system, opts)
d1, i1 = draw_mmode(jax.random.PRNGKey(3), one, 6)
devs = jax.local_devices()
two = prepare_mmode_on(system, devs, opts)
d2, i2 = draw_mmode_on(jax.random.PRNGKey(3), two, 6)
P = np.asarray(precision_matrix(system))[0]
a = np.linalg.solve(P, np.asarray(wiener_rhs(system))[0])
sig = np.sqrt(np.diag(np.linalg.inv(P)))
rel = lambda x, y: float(np.max(np.abs(np.asarray(x) - np.asarray(y))) / np.max(np.abs(np.asarray(y))))
out = dict(devices=len(devs), buckets=len(two.chol.arrays),
           bucket_devices=sorted({str(next(iter(L.devices()))) for L in two.chol.arrays}),
           wf_rel=rel(two.a_wf, one.a_wf), draws_rel=rel(d2, d1),
           wf_sigma=float(np.max(np.abs(np.asarray(two.a_wf)[0] - a) / sig)),
           converged=bool(np.all(np.asarray(two.wiener.converged)) and np.all(np.asarray(i2.draws.converged))),
           err_sigma=float(np.max(np.asarray(two.wiener.err_sigma))))
print("RESULT " + json.dumps(out))
'''


@pytest.mark.slow
def test_two_devices_equal_one():
    env = host_devices_env(2)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")
    try:
        res = subprocess.run([sys.executable, "-c", CHECK], env=env, cwd=ROOT, capture_output=True, text=True,
                             timeout=TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"the 2-device subprocess did not finish in {TIMEOUT_S} s: {str(exc.stderr)[-4000:]}")
    assert res.returncode == 0, res.stderr[-6000:]
    out = json.loads([ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")][-1][7:])
    assert out["devices"] == 2 and out["buckets"] >= 3
    assert len(out["bucket_devices"]) == 2  # the buckets really live on both devices
    assert out["wf_rel"] < 1e-13 and out["draws_rel"] < 1e-13, out
    assert out["wf_sigma"] < 1e-8 and out["converged"], out


# ---------------------------------------------------------------- 2 processes (jax.distributed)

PROCESS = r'''
import faulthandler, json, sys
faulthandler.dump_traceback_later(float(sys.argv[1]) - 20.0, exit=True)
port, pid, out_path = int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
from gcrsky.parallel import init_distributed
init_distributed(f"localhost:{port}", 2, pid, initialization_timeout=120)
from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array
from gcrsky.model import build_problem, isotropic_prior
from gcrsky.parallel.mblocks import draw_mmode_on, prepare_mmode_processes
from gcrsky.solvers import MModeOptions
from gcrsky.solvers.mmode import draw_mmode, prepare_mmode

''' + SYSTEM + r'''opts = MModeOptions(bucket=4)
one = prepare_mmode(system, opts)  # the single-process reference, computed by each process itself
d1, _ = draw_mmode(jax.random.PRNGKey(3), one, 6)
split = prepare_mmode_processes(system, opts)
d2, i2 = draw_mmode_on(jax.random.PRNGKey(3), split, 6)
mine = [i for i, a in enumerate(split.chol.arrays) if a is not None]
np.savez(out_path, wf=np.asarray(split.a_wf), wf1=np.asarray(one.a_wf), d=np.asarray(d2), d1=np.asarray(d1),
         err=np.asarray(split.wiener.err_sigma), err1=np.asarray(one.wiener.err_sigma))
print("RESULT " + json.dumps(dict(processes=jax.process_count(), index=jax.process_index(), mine=mine,
                                  buckets=len(split.chol.arrays),
                                  converged=bool(np.all(np.asarray(split.wiener.converged))
                                                 and np.all(np.asarray(i2.draws.converged))))))
'''


@pytest.mark.slow
def test_two_processes_equal_one(tmp_path):
    """Two ``jax.distributed`` localhost processes, each holding every other bucket: both end with the
    Wiener filter and draws of one process (1e-13 relative: the same operations on the same inputs)."""
    import numpy as np
    from _processes import free_port, run_processes

    port = free_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    outs = run_processes(PROCESS, [[TIMEOUT_S, port, pid, tmp_path / f"p{pid}.npz"] for pid in range(2)], env, TIMEOUT_S)
    assert [o["index"] for o in outs] == [0, 1] and all(o["processes"] == 2 for o in outs)
    nb = outs[0]["buckets"]
    assert nb >= 3 and outs[0]["mine"] == list(range(0, nb, 2)) and outs[1]["mine"] == list(range(1, nb, 2))
    rel = lambda x, y: float(np.max(np.abs(x - y)) / np.max(np.abs(y)))  # noqa: E731
    for pid in range(2):
        got = np.load(tmp_path / f"p{pid}.npz")
        assert outs[pid]["converged"]
        assert rel(got["wf"], got["wf1"]) < 1e-13 and rel(got["d"], got["d1"]) < 1e-13, pid
        assert got["err"].max() < 1e-8, got["err"]  # the true residual's bound, summed over the processes
