"""Channels one at a time, over devices and over processes (gcrsky.parallel.channels).

The system: the 10-dish hexagon at lmax 4 (n = 25), nside 16, 3 channels, 4 LSTs, an
isotropic prior, simulated data with one flagged baseline.  3 channels on 2 devices or 2
processes exercise the padding (devices: a copy of the last channel) and uneven blocks
(processes: channels 0-1 and 2).

Tolerances.  The per-channel key scheme makes channel f's draws a function of
``(key, f, freq_slice(system, f))`` only, so :func:`sample_channels` equals the
one-channel path called by hand *exactly* (same compiled programs, same inputs), and
rows do not change with the channel subset or order.  The Wiener filter of the joint
(all-channel) Cholesky path equals the per-channel one to 1e-10 relative: the same
formula per channel, batched LAPACK vs one matrix (measured 0 to a few eps).  The
sharded path (``shard_map`` + ``lax.map``) compiles the per-channel program inside a
loop body, which XLA may fuse differently: 1e-12 relative for Cholesky (measured
bitwise equal), 1e-10 for CG (rounding propagated through the iterations; measured
bitwise equal here, 9.6e-13 on 2 devices at lmax 10 with 16 channels).  Processes run the very programs one process runs: 1e-12 (measured
bitwise equal, which the summary records).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gcrsky.inference import draw_batches, draw_exactly, prepare_system, wiener_filter_system
from gcrsky.parallel import (
    CHANNEL_KEY_SCHEME,
    channel_key,
    channel_mesh,
    distributed_channels,
    sample_channels,
    sample_channels_sharded,
)
from gcrsky.parallel.channels import channel_blocks, resolve_channel_path
from gcrsky.parallel.runtime import host_devices_env
from gcrsky.solvers import CGOptions
from gcrsky.solvers.cg import freq_slice

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
TIMEOUT_S = 300
NDRAWS = 4
SEED = 11


def make_system(nf: int = 3, lmax: int = 4, nside: int = 16, nt: int = 4, flat_channel: int | None = None):
    """A small (nf, ...) LinearSystem (also imported by the subprocesses below)."""
    from gcrsky.instrument import HERA_LATITUDE_DEG, antpairs, gaussian_beam, hex_array, make_array, response_matrix
    from gcrsky.model import LinearSystem, VisOperator, apply, isotropic_prior
    from gcrsky.sphere import n_params

    n = n_params(lmax)
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    pairs = antpairs(arr.positions_enu_m.shape[0])
    freqs = 100e6 + 1e6 * np.arange(nf)
    resp = jnp.asarray(response_matrix(arr, pairs, freqs, lmax, nside))
    nbl = resp.shape[1]
    op = VisOperator(resp, jnp.linspace(0.0, 1.5, nt))
    rng = np.random.default_rng(0)
    cl = np.broadcast_to(100.0 / (1.0 + np.arange(lmax + 1)) ** 2, (nf, lmax + 1))
    prior = isotropic_prior(cl, n)
    a_true = rng.standard_normal((nf, n)) / np.sqrt(np.asarray(prior.inv_var))
    clean = apply(op, jnp.asarray(a_true))
    sigma = 0.05 * float(jnp.max(jnp.abs(clean)))
    data = clean + sigma * (rng.standard_normal((nf, nt, nbl)) + 1j * rng.standard_normal((nf, nt, nbl)))
    w = rng.uniform(0.5, 1.0, (nf, nt, nbl))
    w[:, :, 3] = 0.0  # one flagged baseline
    if flat_channel is not None:
        inv_var = np.array(prior.inv_var)
        inv_var[flat_channel] = 0.0
        prior = prior._replace(inv_var=jnp.asarray(inv_var))
    return LinearSystem(op, jnp.asarray(data), jnp.asarray(w / sigma**2), prior)


def rel(x, y) -> float:
    x, y = np.asarray(x), np.asarray(y)
    return float(np.max(np.abs(x - y)) / np.max(np.abs(y)))


@pytest.fixture(scope="module")
def system():
    return make_system()


#: The CG options of every CG check (tight, so the CG Wiener filter meets the Cholesky one to 1e-10).
CG = CGOptions(tol=1e-10, preconditioner="nystrom")


@pytest.fixture(scope="module")
def chol(system):
    return sample_channels(jax.random.PRNGKey(SEED), system, NDRAWS, "cholesky")


@pytest.fixture(scope="module")
def cg_ticks():
    return []


@pytest.fixture(scope="module")
def cg(system, cg_ticks):
    return sample_channels(jax.random.PRNGKey(SEED), system, NDRAWS, options=CG, progress=cg_ticks.append)


# ---------------------------------------------------------------- one process, one device


def test_sample_channels_is_the_one_channel_path(system, chol):
    key = jax.random.PRNGKey(SEED)
    nf, n = system.prior.mean.shape
    assert chol.draws.shape == (nf, NDRAWS, n) and chol.a_wf.shape == (nf, n)
    assert chol.info.converged.shape == (nf, NDRAWS) and chol.wiener.converged.shape == (nf,)
    assert chol.info.converged.all() and chol.wiener.converged.all()
    np.testing.assert_array_equal(chol.channels, np.arange(nf))
    for f in range(nf):
        state = prepare_system(freq_slice(system, f), method="cholesky")
        d, _ = draw_exactly(jax.random.fold_in(key, f), state, NDRAWS)
        np.testing.assert_array_equal(chol.draws[f], np.asarray(d[0]))  # exactly: the key scheme
        np.testing.assert_array_equal(chol.a_wf[f], np.asarray(state.a_wf[0]))
    # the joint (all channels at once) posterior mean is the same: channels are independent
    a_joint, _ = wiener_filter_system(system, method="cholesky")
    assert rel(chol.a_wf, a_joint) < 1e-10
    # and the draws scatter around it at the posterior's scale (not a copy of the mean)
    assert 1e-3 < rel(chol.draws[:, 0], chol.a_wf)
    assert "fold_in(key, f)" in CHANNEL_KEY_SCHEME


def test_rows_do_not_depend_on_the_split(system, chol):
    key = jax.random.PRNGKey(SEED)
    sub = sample_channels(key, system, NDRAWS, "cholesky", channels=[2, 0])
    np.testing.assert_array_equal(sub.channels, [2, 0])
    np.testing.assert_array_equal(sub.draws, chol.draws[[2, 0]])
    np.testing.assert_array_equal(sub.a_wf, chol.a_wf[[2, 0]])
    # negative control: the joint scheme (one (Nf, n) normal per draw) cannot be split,
    # its channel f depends on Nf; it gives different (equally exact) draws
    joint, _ = draw_exactly(key, prepare_system(system, method="cholesky"), NDRAWS)
    half, _ = draw_exactly(key, prepare_system(freq_slice(system, 2), method="cholesky"), NDRAWS)
    assert rel(np.asarray(joint[2]), np.asarray(half[0])) > 1e-3
    assert rel(np.asarray(joint), chol.draws) > 1e-3
    assert channel_key(key, 2).shape == key.shape


def test_batches_follow_draw_batches(system):
    key = jax.random.PRNGKey(SEED)
    got = sample_channels(key, system, 5, "cholesky", batch=2, channels=[1])
    ref = draw_batches(channel_key(key, 1), prepare_system(freq_slice(system, 1), method="cholesky"), 5, 2)
    np.testing.assert_array_equal(got.draws[0], ref.draws[0])
    assert got.info.converged.shape == (1, 5)


def test_progress_and_cg(system, chol, cg, cg_ticks):
    key = jax.random.PRNGKey(SEED)
    assert cg_ticks == [1, 1, 1]
    assert cg.wiener.converged.all() and cg.info.converged.all()
    assert rel(cg.a_wf, chol.a_wf) < 1e-10
    state = prepare_system(freq_slice(system, 1), options=CG)
    d, _ = draw_exactly(jax.random.fold_in(key, 1), state, NDRAWS)
    np.testing.assert_array_equal(cg.draws[1], np.asarray(d[0]))


def test_sharded_on_one_device_equals_the_loop(system, chol):
    key = jax.random.PRNGKey(SEED)
    ticks = []
    mesh = channel_mesh(jax.local_devices()[:1])
    sh = sample_channels_sharded(key, system, NDRAWS, "cholesky", mesh=mesh, step=2, progress=ticks.append)
    assert ticks == [2, 1]  # 3 channels in steps of 2 (the last padded with a copy of channel 2)
    np.testing.assert_array_equal(sh.channels, chol.channels)
    assert rel(sh.draws, chol.draws) < 1e-12 and rel(sh.a_wf, chol.a_wf) < 1e-12
    assert sh.info.converged.all() and sh.seconds.shape == (3,)
    sub = sample_channels_sharded(key, system, 5, "cholesky", mesh=mesh, channels=[1], batch=2)
    ref = sample_channels(key, system, 5, "cholesky", channels=[1], batch=2)
    assert rel(sub.draws, ref.draws) < 1e-12


def test_one_process_distributed_is_the_loop(system, chol):
    # without jax.distributed there is one process: its block is every channel, nothing gathered
    assert jax.process_count() == 1
    got = distributed_channels(jax.random.PRNGKey(SEED), system, NDRAWS, "cholesky")
    np.testing.assert_array_equal(got.draws, chol.draws)
    np.testing.assert_array_equal(got.a_wf, chol.a_wf)
    with pytest.raises(ValueError, match="channels"):
        distributed_channels(jax.random.PRNGKey(SEED), system, NDRAWS, "cholesky", channels=[5])


def test_path_resolved_on_every_channel():
    # channel 2 alone has a flat prior: one-channel sizing picks Nystrom from channel 0,
    # the whole-system check must switch CG to m-blocks (Nystrom needs S^-1 > 0)
    sys_flat = make_system(flat_channel=2)
    assert resolve_channel_path(sys_flat, "cg").preconditioner == "mblock"
    assert resolve_channel_path(make_system(), "cg").preconditioner == "nystrom"
    with pytest.raises(ValueError, match="S\\^-1 > 0"):
        resolve_channel_path(sys_flat, options=CGOptions(preconditioner="nystrom"))
    # 4 LSTs over 1.5 rad: not block-diagonal in m, so the m-mode path is refused
    with pytest.raises(ValueError, match="block-diagonal"):
        resolve_channel_path(make_system(), "mmode")


def test_argument_checks(system):
    key = jax.random.PRNGKey(0)
    with pytest.raises(ValueError, match="channels"):
        sample_channels(key, system, 2, "cholesky", channels=[3])
    with pytest.raises(ValueError, match="channels"):
        sample_channels(key, system, 2, "cholesky", channels=[])
    with pytest.raises(ValueError, match="ndraws"):
        sample_channels(key, system, 0, "cholesky")
    with pytest.raises(ValueError, match="batch"):
        sample_channels(key, system, 2, "cholesky", batch=0)


def test_channel_blocks():
    assert channel_blocks(3, 2) == [range(0, 2), range(2, 3)]
    assert channel_blocks(64, 3) == [range(0, 22), range(22, 43), range(43, 64)]
    assert channel_blocks(2, 4) == [range(0, 1), range(1, 2), range(2, 2), range(2, 2)]
    with pytest.raises(ValueError):
        channel_blocks(3, 0)


# ---------------------------------------------------------------- 2 forced host devices

DEVICES = r'''
import faulthandler, json, sys, time
faulthandler.dump_traceback_later(float(sys.argv[1]) - 20.0, exit=True)
out_path = sys.argv[3]
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
sys.path.insert(0, sys.argv[2])
from test_channels import CG, NDRAWS, SEED, make_system
from gcrsky.parallel import channel_mesh, sample_channels_sharded
from gcrsky.parallel.channels import _per_channel, _shared, _sharded_program, resolve_channel_path
from jax.sharding import NamedSharding, PartitionSpec as P
assert jax.device_count() == 2, jax.devices()
system = make_system()
key = jax.random.PRNGKey(SEED)
mesh2, mesh1 = channel_mesh(), channel_mesh(jax.devices()[:1])
out = {"devices": len(mesh2.devices.ravel())}
x = jax.device_put(np.asarray(system.op.response)[[0, 1, 2, 2]], NamedSharding(mesh2, P("freq")))
out["shard_shape"] = list(x.sharding.shard_shape(x.shape))
arrays = {}
runs = (("cholesky2", mesh2, dict(method="cholesky")), ("cholesky1", mesh1, dict(method="cholesky")),
        ("cg2", mesh2, dict(options=CG)))
for name, mesh, kw in runs:
    t0 = time.time()
    res = sample_channels_sharded(key, system, NDRAWS, mesh=mesh, **kw)
    out[name + "_s"] = time.time() - t0
    arrays[name + "_draws"], arrays[name + "_wf"] = res.draws, res.a_wf
    arrays[name + "_converged"] = res.info.converged & res.wiener.converged[:, None]
    arrays[name + "_channels"] = res.channels
# the compiled per-step program: no cross-device communication
opts = resolve_channel_path(system, "cholesky")
shared = _shared(system)
fn = _sharded_program(mesh2, opts, NDRAWS, None, 1, jax.tree_util.tree_structure(shared))
idx = np.array([0, 1, 2, 2], np.int32)
per = tuple(np.asarray(a)[idx] for a in _per_channel(system))
hlo = fn.lower(idx, key, per, shared).compile().as_text()
out["collectives"] = sum(hlo.count(op) for op in ("all-gather", "all-reduce", "all-to-all", "collective-permute"))
np.savez(out_path, **arrays)
print("RESULT " + json.dumps(out))
'''


def _run(code: str, env: dict, *args) -> dict:
    try:
        res = subprocess.run([sys.executable, "-c", code, str(TIMEOUT_S), str(HERE), *map(str, args)], env=env,
                             cwd=ROOT, capture_output=True, text=True, timeout=TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"subprocess did not finish in {TIMEOUT_S} s: {str(exc.stderr)[-4000:]}")
    assert res.returncode == 0, res.stderr[-6000:]
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def _env(n_devices: int) -> dict:
    env = host_devices_env(n_devices)
    env["JAX_ENABLE_X64"] = "1"
    env["JAX_PLATFORMS"] = "cpu"
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")
    return env


@pytest.mark.slow
def test_two_devices_equal_one(chol, cg, tmp_path):
    out = _run(DEVICES, _env(2), tmp_path / "dev.npz")
    got = np.load(tmp_path / "dev.npz")
    assert out["devices"] == 2 and out["shard_shape"][0] == 2  # 3 channels padded to 4, 2 per device
    assert out["collectives"] == 0  # each device runs its own channels
    # 2 devices against 1 device of the same mesh code, and against the one-channel loop here
    checks = (("cholesky2", "cholesky1", None, 1e-12), ("cholesky2", None, chol, 1e-12), ("cg2", None, cg, 1e-10))
    for name, other, ref, tol in checks:
        assert got[name + "_converged"].all()
        np.testing.assert_array_equal(got[name + "_channels"], [0, 1, 2])
        want_d = got[other + "_draws"] if other else ref.draws
        want_wf = got[other + "_wf"] if other else ref.a_wf
        assert rel(got[name + "_draws"], want_d) < tol, (name, other, rel(got[name + "_draws"], want_d))
        assert rel(got[name + "_wf"], want_wf) < tol, (name, other, rel(got[name + "_wf"], want_wf))


# ---------------------------------------------------------------- 2 processes (jax.distributed)

PROCESS = r'''
import faulthandler, json, sys, time
faulthandler.dump_traceback_later(float(sys.argv[1]) - 20.0, exit=True)
port, nproc, pid, out_path = int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]), sys.argv[6]
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
from gcrsky.parallel import init_distributed, distributed_channels
init_distributed(f"localhost:{port}", nproc, pid, initialization_timeout=120)
sys.path.insert(0, sys.argv[2])
from test_channels import CG, NDRAWS, SEED, make_system
system = make_system()
key = jax.random.PRNGKey(SEED)
out = {"process_count": jax.process_count(), "process_index": jax.process_index(),
       "global_devices": jax.device_count(), "local_devices": jax.local_device_count()}
arrays = {}
for name, kw in (("cholesky", dict(method="cholesky")),
                 ("cg", dict(options=CG)),
                 ("cholesky_sharded", dict(method="cholesky", sharded=True))):
    t0 = time.time()
    res = distributed_channels(key, system, NDRAWS, **kw)
    out[name + "_s"] = time.time() - t0
    arrays[name + "_draws"], arrays[name + "_wf"] = res.draws, res.a_wf
    arrays[name + "_converged"] = res.info.converged
    arrays[name + "_channels"] = res.channels
np.savez(out_path, **arrays)
print("RESULT " + json.dumps(out))
'''


@pytest.mark.slow
def test_two_processes_equal_one(chol, cg, tmp_path):
    from _processes import free_port, run_processes

    env = _env(1)
    port = free_port()
    args = [[TIMEOUT_S, HERE, port, 2, pid, tmp_path / f"p{pid}.npz"] for pid in range(2)]
    outs = run_processes(PROCESS, args, env, TIMEOUT_S)
    assert [o["process_index"] for o in outs] == [0, 1]
    assert all(o["process_count"] == 2 and o["global_devices"] == 2 and o["local_devices"] == 1 for o in outs)
    for pid in range(2):
        got = np.load(tmp_path / f"p{pid}.npz")
        for name, ref in (("cholesky", chol), ("cg", cg), ("cholesky_sharded", chol)):
            np.testing.assert_array_equal(got[name + "_channels"], [0, 1, 2])
            assert got[name + "_converged"].all()
            assert rel(got[name + "_draws"], ref.draws) < 1e-12, (pid, name)
            assert rel(got[name + "_wf"], ref.a_wf) < 1e-12, (pid, name)
