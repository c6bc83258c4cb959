"""The m-mode blocks split over devices (issue 24 item 4) equal the single-device path.

The device count is fixed when JAX's backend starts, so the check runs in a subprocess with two
forced host devices (:func:`gcrsky.parallel.host_devices_env`, as tests/test_sharding.py does).
A full day (30 equally spaced LSTs > 2 lmax) of the 10-antenna hexagon at lmax 12 with buckets
of 4 orders (several buckets, alternating between the two devices); references: the
single-device :func:`gcrsky.solvers.prepare_mmode` / :func:`~gcrsky.solvers.draw_mmode` in the
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

from gcrsky.parallel import host_devices_env

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 300

CHECK = r'''
import json, sys
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array
from gcrsky.model import build_problem, isotropic_prior, precision_matrix, wiener_rhs
from gcrsky.parallel.mblocks import draw_mmode_on, prepare_mmode_on
from gcrsky.solvers import MModeOptions, draw_mmode, prepare_mmode

lmax, nt = 12, 30
arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
n = (lmax + 1) ** 2
prior = isotropic_prior((50.0 / (1.0 + np.arange(lmax + 1)) ** 2)[None], n)
truth = np.asarray(prior.inv_var) ** -0.5 * np.random.default_rng(0).standard_normal((1, n))
prob = build_problem(arr, [100e6], np.arange(nt) * 2 * np.pi / nt, lmax, 32, a_true=truth, sigma=0.05,
                     prior=prior, key=jax.random.PRNGKey(0))
system = prob.system()
opts = MModeOptions(bucket=4)
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
