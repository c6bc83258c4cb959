"""Baseline sharding over 4 forced host CPU devices (gcrsky.parallel.sharding).

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

The subprocess's environment comes from :func:`gcrsky.parallel.runtime.host_devices_env`, which
sizes XLA's CPU thread pool (``PJRT_NPROC``).  Without it, on a 2-core host about half
the runs hung for good at 0% CPU: the Nystrom preconditioner's batched LAPACK calls
(replicated, so one per device at a time) each blocked a thread of the 4-thread pool
waiting for their own tasks on it (gdb: every ``tf_XLAEigen`` thread in
``lapack_dgesdd_ffi -> ParallelBatchMap -> BlockingCounter::Wait``; see
gcrsky/runtime.py).  The check runs on every host; a hang becomes a failure after
:data:`TIMEOUT_S`, with every thread's Python traceback and the last stage reached.
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

from gcrsky.parallel import baseline_mesh, shard_system
from gcrsky.parallel.runtime import (
    POOL_THREADS_PER_DEVICE,
    effective_pool_size,
    forced_device_count,
    host_devices_env,
    safe_pool_size,
)
from gcrsky.parallel.sharding import pad_baselines

ROOT = Path(__file__).resolve().parents[1]

#: Wall-clock limit of the 4-device subprocess.  A healthy run takes ~40 s on a 2-core
#: host (mostly compiling sample_system three times), 60-80 s with another job on the
#: cores and up to ~170 s under heavy load; a deadlocked one never ends.
TIMEOUT_S = 300

#: The system both subprocess checks build (10 antennas: 45 baselines, 2 channels, 4 times, lmax 6, one
#: flagged baseline); each snippet imports what it uses.
SYSTEM = r'''
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
'''

CHECK = r'''
import faulthandler, json, os, sys, time, warnings
t0 = time.time()
TIMEOUT_S = float(sys.argv[1])
# a hang must not outlive the parent's timeout silently: dump every thread and exit
faulthandler.dump_traceback_later(max(TIMEOUT_S - 20.0, 1.0), exit=True)
stages = {}
def stage(name):
    stages[name] = round(time.time() - t0, 2)
    print("STAGE", name, stages[name], file=sys.stderr, flush=True)
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from gcrsky.instrument import HERA_LATITUDE_DEG, antpairs, gaussian_beam, hex_array, make_array
from gcrsky.instrument import response_matrix
from gcrsky.sphere import n_params
from gcrsky.model import LinearSystem
from gcrsky.model.system import precision_apply, wiener_rhs
from gcrsky.model import VisOperator, adjoint, apply, isotropic_prior
from gcrsky.inference import sample_system
from gcrsky.solvers import CGOptions
from gcrsky.parallel import baseline_mesh, shard_system
from gcrsky.parallel.sharding import pad_baselines

assert jax.device_count() == 4, jax.devices()
''' + SYSTEM + r'''
from gcrsky.parallel.runtime import effective_pool_size
stage("setup")
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    mesh = baseline_mesh()
mesh_warnings = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
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
stage("products")
kw = dict(options=CGOptions(tol=1e-8, dense=False, preconditioner="nystrom", sketch_size=32))
key = jax.random.PRNGKey(7)
d_s, i_s = sample_system(key, ssys, 3, **kw)
d_s.block_until_ready()
stage("sample_sharded")
d_p, i_p = sample_system(key, psys, 3, **kw)
d_u, i_u = sample_system(key, system, 3, **kw)
d_u.block_until_ready()
stage("sample_one_device")
out["wiener_cg"] = rel(i_s["a_wf"], i_u["a_wf"])
out["wiener_cg_vs_padded"] = rel(i_s["a_wf"], i_p["a_wf"])
out["draws_vs_padded"] = rel(d_s, d_p)
out["draws_unpadded_vs_padded_rel_diff"] = rel(d_u, d_p)
out["converged"] = bool(np.all(i_s["wiener"].converged) and np.all(i_s["draws"].converged))
out["iters_sharded"] = np.asarray(i_s["draws"].iterations).tolist()
out["iters_padded"] = np.asarray(i_p.draws.iterations).tolist()
out["wiener_iters"] = [np.asarray(i_s["wiener"].iterations).tolist(), np.asarray(i_u["wiener"].iterations).tolist()]
out["draws_devices"] = len(d_s.sharding.device_set)
out["mesh_warnings"] = mesh_warnings
# the pool XLA really made (Linux thread names) vs the one the environment asks for
try:
    names = [open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")]
    out["pool_threads"] = sum(n == "tf_XLAEigen" for n in names)
except OSError:
    out["pool_threads"] = None
out["pool_expected"] = effective_pool_size(jax.device_count())
out["stages"] = stages
out["seconds"] = time.time() - t0
print("RESULT " + json.dumps(out))
'''


def _check_env() -> dict:
    env = host_devices_env(4)
    env["JAX_ENABLE_X64"] = "1"
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")
    return env


def _run_check() -> dict:
    try:
        res = subprocess.run(
            [sys.executable, "-c", CHECK, str(TIMEOUT_S)], check=False, env=_check_env(), cwd=ROOT,
            capture_output=True, text=True, timeout=TIMEOUT_S,
        )
    except subprocess.TimeoutExpired as exc:
        err = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        pytest.fail(f"the 4-device subprocess did not finish in {TIMEOUT_S} s (hang?); stderr tail:\n{err[-6000:]}")
    assert res.returncode == 0, (
        f"4-device subprocess failed (rc {res.returncode}; a faulthandler dump means it hung):\n{res.stderr[-6000:]}"
    )
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


@pytest.fixture(scope="module")
def summary() -> dict:
    return _run_check()


@pytest.mark.slow
def test_thread_pool_sized_for_four_devices(summary):
    # the pool XLA created is the one host_devices_env asked for, > 1 thread per device
    assert summary["pool_expected"] >= POOL_THREADS_PER_DEVICE * summary["devices"]
    if summary["pool_threads"] is not None:  # thread names are readable on Linux
        assert summary["pool_threads"] == summary["pool_expected"]
    assert summary["mesh_warnings"] == []


@pytest.mark.slow
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


@pytest.mark.slow
def test_products_match_one_device(summary):
    for name in ("apply", "adjoint", "precision_apply", "wiener_rhs"):
        assert summary[name] < 1e-13, (name, summary[name])
    assert summary["apply_pad_zero"] == 0.0


@pytest.mark.slow
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

    from gcrsky.model import LinearSystem, VisOperator, flat_prior
    from gcrsky.model.system import precision_apply

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


def test_host_devices_env_sizes_the_pool():
    base = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2 --foo", "PATH": "/bin"}
    env = host_devices_env(4, base)
    assert base["XLA_FLAGS"] == "--xla_force_host_platform_device_count=2 --foo"  # a copy
    assert forced_device_count(env["XLA_FLAGS"]) == 4
    assert env["XLA_FLAGS"].count("xla_force_host_platform_device_count") == 1
    assert "--foo" in env["XLA_FLAGS"] and "--xla_cpu_multi_thread_eigen=false" in env["XLA_FLAGS"]
    assert env["PATH"] == "/bin" and env["OPENBLAS_NUM_THREADS"] == "1"
    want = safe_pool_size(4)
    assert want >= POOL_THREADS_PER_DEVICE * 4 and int(env["PJRT_NPROC"]) == want
    assert effective_pool_size(4, env) == want
    # a user's own choices are kept where they are safe, raised where they are not
    big = host_devices_env(4, {"PJRT_NPROC": str(want + 3), "OPENBLAS_NUM_THREADS": "2"})
    assert big["PJRT_NPROC"] == str(want + 3) and big["OPENBLAS_NUM_THREADS"] == "2"
    small = host_devices_env(4, {"PJRT_NPROC": "1", "NPROC": "1"})
    assert effective_pool_size(4, small) == want
    # XLA's rule: PJRT_NPROC, else NPROC, else the cores; never fewer threads than devices
    assert effective_pool_size(4, {"PJRT_NPROC": "2"}) == 4
    assert effective_pool_size(2, {"PJRT_NPROC": "x", "NPROC": "7"}) == 7
    # one device: the pool too has room for blocked batched LAPACK calls
    one = host_devices_env(1, {})
    assert int(one["PJRT_NPROC"]) == safe_pool_size(1) and one["OPENBLAS_NUM_THREADS"] == "1"
    assert forced_device_count(one["XLA_FLAGS"]) == 1
    assert forced_device_count("") == 1
    with pytest.raises(ValueError, match="positive integer"):
        forced_device_count("--xla_force_host_platform_device_count=0")
    with pytest.raises(ValueError, match="positive integer"):
        host_devices_env(0)


def test_baseline_mesh_warns_about_an_undersized_pool():
    # the environment that hung: 4 devices, XLA's default pool of max(cores, 4) threads
    # on a small host (PJRT_NPROC=1 reproduces it on any host).  Only the warning is
    # checked here (no LAPACK), so this subprocess is cheap.
    code = (
        "import warnings, jax\n"
        "from gcrsky.parallel.sharding import baseline_mesh\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    baseline_mesh()\n"
        "    baseline_mesh(jax.devices()[:1])\n"
        "print('WARN', sum('thread pool' in str(x.message) for x in w))\n"
    )
    env = {**_check_env(), "PJRT_NPROC": "1", "NPROC": "1"}
    res = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True,
                         text=True, timeout=120, check=False)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "WARN 1" in res.stdout  # the 4-device mesh warns, the 1-device one does not


def test_use_safe_cpu_threading_sizes_the_pool(monkeypatch):
    from gcrsky.parallel import use_host_devices, use_safe_cpu_threading

    for key in ("PJRT_NPROC", "NPROC", "OPENBLAS_NUM_THREADS", "GCRSKY_FAST_THREADS"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("XLA_FLAGS", "")
    assert use_safe_cpu_threading()  # one device: the flag and a pool with room for blocked LAPACK calls
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_multi_thread_eigen=false"
    assert int(os.environ["PJRT_NPROC"]) == safe_pool_size(1) >= 8
    assert os.environ["OPENBLAS_NUM_THREADS"] == "1"
    monkeypatch.delenv("PJRT_NPROC")
    monkeypatch.delenv("OPENBLAS_NUM_THREADS")
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=4")
    monkeypatch.setenv("GCRSKY_FAST_THREADS", "1")  # opting out of the flag keeps the pool fix
    assert not use_safe_cpu_threading()
    assert int(os.environ["PJRT_NPROC"]) == safe_pool_size(4)
    assert os.environ["OPENBLAS_NUM_THREADS"] == "1"
    jax.devices()  # this process's backend has started: too late to change it
    with pytest.raises(RuntimeError, match="before JAX"):
        use_host_devices(4)


# ---------------------------------------------------------------- 2 processes (jax.distributed)

PROCESS = r'''
import faulthandler, json, sys
faulthandler.dump_traceback_later(float(sys.argv[1]) - 20.0, exit=True)
port, pid = int(sys.argv[2]), int(sys.argv[3])
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from gcrsky.parallel import init_distributed
init_distributed(f"localhost:{port}", 2, pid, initialization_timeout=120)
from jax.experimental.multihost_utils import process_allgather
from gcrsky.instrument import HERA_LATITUDE_DEG, antpairs, gaussian_beam, hex_array, make_array, response_matrix
from gcrsky.sphere import n_params
from gcrsky.model import LinearSystem, VisOperator, adjoint, apply, isotropic_prior
from gcrsky.model.system import precision_apply
from gcrsky.inference import sample_system
from gcrsky.solvers import CGOptions
from gcrsky.parallel import baseline_mesh, shard_system
from gcrsky.parallel.sharding import pad_baselines
''' + SYSTEM + r'''ssys = shard_system(system, baseline_mesh())  # every process's device: the baselines split over the processes
psys = pad_baselines(system, 2)  # the one-process reference: the same padded system, computed here
a = jnp.asarray(rng.standard_normal((nf, n)))
v = jnp.asarray(rng.standard_normal(psys.data.shape) + 1j * rng.standard_normal(psys.data.shape))
def rel(x, y):
    x, y = np.asarray(x), np.asarray(y)
    return float(np.max(np.abs(x - y)) / np.max(np.abs(y)))
gather = lambda x: process_allgather(x, tiled=True)
from gcrsky.parallel.sharding import _place
v_sh = _place(v, ssys.data.sharding)
out = {"processes": jax.process_count(), "index": jax.process_index(), "devices": jax.device_count(),
       "nbl_padded": int(ssys.op.response.shape[1]),
       "local_shard": [list(s.data.shape) for s in ssys.op.response.addressable_shards],
       "response_addressable": bool(ssys.op.response.is_fully_addressable)}
out["apply"] = rel(gather(apply(ssys.op, a)), apply(psys.op, a))
out["adjoint"] = rel(gather(adjoint(ssys.op, v_sh)), adjoint(psys.op, v))
out["precision_apply"] = rel(gather(jax.jit(precision_apply)(ssys, a)), jax.jit(precision_apply)(psys, a))
kw = dict(options=CGOptions(tol=1e-8, dense=False, preconditioner="nystrom", sketch_size=32))
key = jax.random.PRNGKey(7)
d_s, i_s = sample_system(key, ssys, 3, **kw)
d_p, i_p = sample_system(key, psys, 3, **kw)
out["wiener_cg"] = rel(gather(i_s.a_wf), i_p.a_wf)
out["draws"] = rel(gather(d_s), d_p)
out["iters"] = [np.asarray(gather(i_s.draws.iterations)).tolist(), np.asarray(i_p.draws.iterations).tolist()]
out["converged"] = bool(np.all(gather(i_s.wiener.converged)) and np.all(gather(i_s.draws.converged)))
print("RESULT " + json.dumps(out), flush=True)
'''


@pytest.mark.slow
def test_two_processes_equal_one_process():
    """The baselines split over two ``jax.distributed`` localhost processes (one CPU device each): the
    products and the matrix-free CG's Wiener filter and draws equal one process's on the same padded
    system (tolerances of the 4-device check above: 1e-13 for a product, 1e-11 through CG)."""
    from _processes import free_port, run_processes

    env = dict(os.environ, JAX_ENABLE_X64="1", PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    port = free_port()
    outs = run_processes(PROCESS, [[TIMEOUT_S, port, pid] for pid in range(2)], env, TIMEOUT_S)
    assert [o["index"] for o in outs] == [0, 1] and all(o["processes"] == 2 == o["devices"] for o in outs)
    for o in outs:
        assert o["nbl_padded"] == 46 and o["local_shard"] == [[2, 23, 49]]  # half the baselines each
        assert not o["response_addressable"]  # the response really is split over the processes
        for name in ("apply", "adjoint", "precision_apply"):
            assert o[name] < 1e-13, (name, o[name])
        assert o["converged"] and o["iters"][0] == o["iters"][1]
        assert o["wiener_cg"] < 1e-11 and o["draws"] < 1e-11, o
