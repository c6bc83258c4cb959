"""Baseline sharding over 4 forced host CPU devices (gcrsky.sharding).

The device count is fixed when JAX's backend starts, so the real check runs in a
subprocess with ``--xla_force_host_platform_device_count=4``; it prints a JSON
summary that the test parses.  10 antennas give 45 baselines, not a multiple of 4,
so the zero-weight padding (to 48) is exercised.

Tolerances: a single product (apply, adjoint, P a, X^T W d) differs from one device
only in the order of the sum over baselines: a few eps (measured 2-5e-16), so 1e-13.
The CG solves (Wiener filter, draws) run the same iterations on both sides; rounding
differences of the products are propagated through the recurrence and the
preconditioner, so a few hundred eps (measured ~1-2e-13) and the bound is 1e-11,
still 3 orders below the CG tolerance (1e-8 posterior sigma) they are solved to.
Draws are compared with the *padded* system on one device: the fluctuation noise is
drawn with the padded shape, so the unpadded system gives a different (equally
exact) realisation from the same key (the summary records that difference, ~0.2).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from gcrsky.sharding import baseline_mesh, pad_baselines, shard_system

ROOT = Path(__file__).resolve().parents[1]

CHECK = r'''
import json, time
t0 = time.time()
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from gcrsky.instrument import HERA_LATITUDE_DEG, antpairs, gaussian_beam, hex_array, make_array
from gcrsky.response import response_matrix
from gcrsky.layout import n_params
from gcrsky.normal import LinearSystem, precision_apply, wiener_rhs
from gcrsky.operator import VisOperator, apply, adjoint
from gcrsky.prior import isotropic_prior
from gcrsky.sampler import sample_system
from gcrsky.sharding import baseline_mesh, pad_baselines, shard_system

assert jax.device_count() == 4, jax.devices()
lmax, nside, nf, nt = 6, 32, 2, 4
n = n_params(lmax)
arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
pairs = antpairs(arr.positions_enu_m.shape[0])
resp = jnp.asarray(response_matrix(arr, pairs, np.array([100e6, 102e6]), lmax, nside))
nbl = resp.shape[1]
angles = jnp.linspace(0.0, 1.5, nt)
op = VisOperator(resp, angles)
rng = np.random.default_rng(0)
cl = np.broadcast_to(100.0 / (1.0 + np.arange(lmax + 1)) ** 2, (nf, lmax + 1))
prior = isotropic_prior(cl, n)
a_true = rng.standard_normal((nf, n)) / np.sqrt(prior.inv_var)
sigma = 0.05 * float(jnp.max(jnp.abs(apply(op, jnp.asarray(a_true)))))
data = apply(op, jnp.asarray(a_true)) + sigma * (rng.standard_normal((nf, nt, nbl)) + 1j * rng.standard_normal((nf, nt, nbl)))
w = rng.uniform(0.5, 1.0, (nf, nt, nbl)); w[:, :, 3] = 0.0  # one flagged baseline
system = LinearSystem(op, jnp.asarray(data), jnp.asarray(w / sigma**2), prior)

mesh = baseline_mesh()
ssys = shard_system(system, mesh)
psys = pad_baselines(system, 4)
nbl_pad = ssys.op.response.shape[1]
a = jnp.asarray(rng.standard_normal((nf, n)))
v = jnp.asarray(rng.standard_normal((nf, nt, nbl)) + 1j * rng.standard_normal((nf, nt, nbl)))
v_pad = jnp.pad(v, [(0, 0), (0, 0), (0, nbl_pad - nbl)])
v_sh = jax.device_put(v_pad, ssys.data.sharding)

def rel(x, y):
    x, y = np.asarray(x), np.asarray(y)
    return float(np.max(np.abs(x - y)) / np.max(np.abs(y)))

out = {"devices": jax.device_count(), "nbl": nbl, "nbl_padded": nbl_pad,
       "response_devices": len(ssys.op.response.sharding.device_set),
       "response_spec": str(ssys.op.response.sharding.spec),
       "shard_shape": list(ssys.op.response.sharding.shard_shape(ssys.op.response.shape))}
Xa_s = apply(ssys.op, a)
out["apply_out_spec"] = str(Xa_s.sharding.spec) if hasattr(Xa_s.sharding, "spec") else str(Xa_s.sharding)
out["apply_out_devices"] = len(Xa_s.sharding.device_set)
out["apply"] = rel(Xa_s[..., :nbl], apply(system.op, a))
out["apply_pad_zero"] = float(np.max(np.abs(np.asarray(Xa_s[..., nbl:]))))
out["adjoint"] = rel(adjoint(ssys.op, v_sh), adjoint(system.op, v))
out["precision_apply"] = rel(jax.jit(precision_apply)(ssys, a), jax.jit(precision_apply)(system, a))
out["wiener_rhs"] = rel(wiener_rhs(ssys), wiener_rhs(system))
hlo = jax.jit(precision_apply).lower(ssys, a).compile().as_text()
out["hlo_all_reduce"] = hlo.count("all-reduce(") + hlo.count("all-reduce-start(")
out["hlo_all_gather"] = hlo.count("all-gather(") + hlo.count("all-gather-start(")
kw = dict(dense=False, preconditioner="nystrom", rank=32, tol=1e-8)
key = jax.random.PRNGKey(7)
d_s, i_s = sample_system(key, ssys, 3, **kw)
d_p, i_p = sample_system(key, psys, 3, **kw)
d_u, i_u = sample_system(key, system, 3, **kw)
out["wiener_cg"] = rel(i_s["a_wf"], i_u["a_wf"])
out["wiener_cg_vs_padded"] = rel(i_s["a_wf"], i_p["a_wf"])
out["draws_vs_padded"] = rel(d_s, d_p)
out["draws_unpadded_vs_padded_rel_diff"] = rel(d_u, d_p)
out["converged"] = bool(np.all(i_s["wiener"].converged) and np.all(i_s["draws"].converged))
out["iters_sharded"] = np.asarray(i_s["draws"].iterations).tolist()
out["iters_padded"] = np.asarray(i_p["draws"].iterations).tolist()
out["wiener_iters"] = [np.asarray(i_s["wiener"].iterations).tolist(), np.asarray(i_u["wiener"].iterations).tolist()]
out["draws_devices"] = len(d_s.sharding.device_set)
out["seconds"] = time.time() - t0
print("RESULT " + json.dumps(out))
'''


def _run_check() -> dict:
    env = {
        **os.environ,
        "XLA_FLAGS": "--xla_force_host_platform_device_count=4 --xla_cpu_multi_thread_eigen=false",
        "JAX_ENABLE_X64": "1",
        "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
    }
    # XLA CPU with 4 forced devices on a 2-core machine sometimes stalls (0% CPU, seen in
    # about half the runs here, in the sharded CG's collectives); a healthy run takes
    # ~25 s.  Retry once, then skip rather than hang the suite.
    res = None
    for _ in range(2):
        try:
            res = subprocess.run(
                [sys.executable, "-c", CHECK], check=False, env=env, cwd=ROOT,
                capture_output=True, text=True, timeout=100,
            )
            break
        except subprocess.TimeoutExpired:
            continue
    if res is None:
        pytest.skip("the 4-device XLA CPU subprocess stalled twice (known XLA CPU collective stall)")
    assert res.returncode == 0, res.stderr[-4000:]
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


@pytest.fixture(scope="module")
def summary() -> dict:
    # On this 2-core machine about half the 4-device runs sat at 0% CPU in the sharded
    # CG's collectives (cause not confirmed; likely 4 device threads rendezvousing on 2
    # cores).  Run it where there are >= 4 cores, or on demand: GCRSKY_TEST_MULTIDEVICE=1.
    if (os.cpu_count() or 1) < 4 and os.environ.get("GCRSKY_TEST_MULTIDEVICE") != "1":
        pytest.skip("4-device check runs on >= 4 cores (XLA CPU collectives stalled on 2 here); "
                    "set GCRSKY_TEST_MULTIDEVICE=1 to force it")
    return _run_check()


def test_really_sharded_over_four_devices(summary):
    assert summary["devices"] == 4
    assert summary["nbl"] == 45 and summary["nbl_padded"] == 48
    assert summary["response_devices"] == 4
    assert summary["response_spec"] == "P(None, 'bl')"
    assert summary["shard_shape"] == [2, 12, 49]  # 12 baselines per device
    # apply's output stays split over baselines; the adjoint's sum is an all-reduce
    assert summary["apply_out_devices"] == 4 and summary["apply_out_spec"] == "P(None, None, 'bl')"
    assert summary["hlo_all_reduce"] >= 1
    assert summary["draws_devices"] == 4


def test_products_match_one_device(summary):
    for name in ("apply", "adjoint", "precision_apply", "wiener_rhs"):
        assert summary[name] < 1e-13, (name, summary[name])
    assert summary["apply_pad_zero"] == 0.0


def test_cg_wiener_and_draws_match_one_device(summary):
    assert summary["converged"]
    assert summary["wiener_cg"] < 1e-11
    assert summary["wiener_cg_vs_padded"] < 1e-11
    assert summary["iters_sharded"] == summary["iters_padded"]
    assert summary["draws_vs_padded"] < 1e-11
    # same key, different noise shape -> a different realisation (documented)
    assert summary["draws_unpadded_vs_padded_rel_diff"] > 1e-3


def test_non_1d_mesh_rejected():
    dev = np.asarray(jax.devices()[:1], dtype=object).reshape(1, 1)
    mesh = jax.sharding.Mesh(dev, ("a", "b"))
    with pytest.raises(ValueError, match="1-d mesh"):
        shard_system(None, mesh)  # checked before the system is touched


def test_pad_baselines_exact_in_process(small_response):
    import jax.numpy as jnp

    from gcrsky.normal import LinearSystem, precision_apply
    from gcrsky.operator import VisOperator
    from gcrsky.prior import flat_prior

    resp = small_response.response
    nf, nbl, n = resp.shape
    op = VisOperator(resp, jnp.linspace(0.0, 1.0, 3))
    rng = np.random.default_rng(1)
    inv = jnp.asarray(rng.uniform(0.5, 1.0, (nf, 3, nbl)))
    system = LinearSystem(op, jnp.zeros((nf, 3, nbl), complex), inv, flat_prior(nf, n))
    padded = pad_baselines(system, 4)
    assert padded.op.response.shape[1] == 48 and padded.inv_noise.shape[2] == 48
    assert float(jnp.max(jnp.abs(padded.inv_noise[..., nbl:]))) == 0.0
    a = jnp.asarray(rng.standard_normal((nf, n)))
    np.testing.assert_allclose(precision_apply(padded, a), precision_apply(system, a), rtol=1e-12, atol=0)
    assert pad_baselines(system, 1) is system
    # one device: a 1-d mesh works and pads to a multiple of 1 (nothing)
    sh = shard_system(system, baseline_mesh(jax.devices()[:1]))
    assert sh.op.response.shape == resp.shape
