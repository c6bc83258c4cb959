"""One object per solver path, one registry: a new path is its own module plus one registry line.

The check: a toy path defined here (a Cholesky factor of the prior-whitened precision, with its own
options and state types) is added to ``gcrsky.solvers.registry.PATHS`` and nothing else; the user
tier, the system tier, new data, the evidence, the planner and the channel code then use it.  The
reference is the built-in Cholesky path (same posterior: Wiener filter to 1e-10 relative, evidence
to 1e-9).  A negative control: without the registry line, its options are refused by name.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import isotropic_problem

import gcrsky
from gcrsky.inference import condition
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.parallel import sample_channels
from gcrsky.parallel.channels import resolve_channel_path
from gcrsky.solvers import PATHS, CholeskyOptions, EvidenceParts, SolveInfo, SolverPath, plan_sampler
from gcrsky.solvers.info import DrawInfo, direct_info, exact_info
from gcrsky.solvers.options import DEFAULT_TOL


@dataclasses.dataclass(frozen=True)
class WhitenedOptions:
    throw: bool = False
    tol: float = DEFAULT_TOL
    method = "whitened"


class WhitenedState(eqx.Module):
    system: gcrsky.LinearSystem
    a_wf: jax.Array
    wiener: SolveInfo
    chol: jax.Array  # of S^1/2 P S^1/2
    method: ClassVar[str] = "whitened"


def _wiener(system, L):
    sh = 1.0 / jnp.sqrt(system.prior.inv_var)
    b = wiener_rhs(system)
    a = sh * jax.vmap(lambda l, v: jax.scipy.linalg.cho_solve((l, True), v))(L, sh * b)
    r = b - jnp.einsum("fij,fj->fi", precision_matrix(system), a)
    err = jnp.sqrt(jnp.abs(jnp.sum(r * sh * jax.vmap(lambda l, v: jax.scipy.linalg.cho_solve((l, True), v))(L, sh * r),
                                   axis=-1)))
    return a, direct_info(err, jnp.linalg.norm(r, axis=-1) / jnp.linalg.norm(b, axis=-1),
                          jnp.all(jnp.isfinite(L), axis=(1, 2)), DEFAULT_TOL)


class WhitenedPath(SolverPath):
    """A toy path: Cholesky of the whitened precision, written against SolverPath only."""

    name = "whitened"
    options_type = WhitenedOptions
    state_type = WhitenedState

    def memory_bytes(self, system, options, ndraws=1):
        nf, n = system.prior.mean.shape
        return 3.0 * 8 * nf * n * n

    def cost_flop(self, system, options, ndraws):
        return 1.0  # cheaper than anything: the planner must pick it

    def prepare(self, system, options):
        sh = 1.0 / jnp.sqrt(system.prior.inv_var)
        L = jnp.linalg.cholesky(sh[:, :, None] * precision_matrix(system) * sh[:, None, :])
        a, info = _wiener(system, L)
        return WhitenedState(system, a, info, L)

    def draw(self, key, state, ndraws):
        nf, n = state.a_wf.shape
        z = jax.random.normal(key, (nf, n, ndraws))
        sh = 1.0 / jnp.sqrt(state.system.prior.inv_var)
        delta = jax.vmap(lambda l, zz: jax.scipy.linalg.solve_triangular(l, zz, lower=True, trans="T"))(state.chol, z)
        d = state.a_wf[:, None, :] + sh[:, None, :] * jnp.moveaxis(delta, -1, 1)
        return d, DrawInfo(state.wiener, exact_info(state.wiener, jnp.all(jnp.isfinite(d), -1), (nf, ndraws)),
                           state.a_wf)

    def condition(self, state, data):
        system = state.system._replace(data=data)
        a, info = _wiener(system, state.chol)
        return WhitenedState(system, a, info, state.chol)

    def state_evidence_parts(self, state, terms, *, slq=None, key=None):
        logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(state.chol, axis1=-2, axis2=-1)), axis=-1)
        chi2 = terms["rWr"] - jnp.sum(terms["b_res"] * (state.a_wf - state.system.prior.mean), axis=-1)
        return EvidenceParts(chi2, logdet, jnp.zeros(logdet.shape), state.wiener)

    def evidence_parts(self, system, options, terms, *, slq=None, key=None):
        return self.state_evidence_parts(self.prepare(system, options), terms)


@pytest.fixture(scope="module")
def system(small_array, small_response):
    return isotropic_problem(small_array, small_response, np.linspace(0.0, 2.0, 9), 3).system()


def test_a_new_path_is_one_module_plus_one_registry_line(system, monkeypatch, getkey):
    with pytest.raises(TypeError, match="expected a path name, options"):  # not registered: refused by name
        gcrsky.prepare(system, options=WhitenedOptions())
    monkeypatch.setitem(PATHS, "whitened", WhitenedPath())  # the one registry line

    ref = gcrsky.prepare(system, method="cholesky")
    st = gcrsky.prepare(system, options=WhitenedOptions())
    assert type(st) is WhitenedState
    scale = np.abs(np.asarray(ref.a_wf)).max()
    assert np.abs(np.asarray(st.a_wf) - np.asarray(ref.a_wf)).max() < 1e-10 * scale
    draws, info = gcrsky.draw(getkey(), st, 5)
    assert draws.shape == (2, 5, system.prior.mean.shape[-1]) and bool(np.all(np.asarray(info.draws.converged)))
    d2 = system.data * 1.1
    assert np.abs(np.asarray(condition(st, d2).a_wf) - np.asarray(condition(ref, d2).a_wf)).max() \
        < 1e-10 * scale
    np.testing.assert_allclose(np.asarray(gcrsky.log_evidence(st)), np.asarray(gcrsky.log_evidence(system)),
                               rtol=1e-9)
    np.testing.assert_allclose(np.asarray(gcrsky.log_evidence(system, options=WhitenedOptions())),
                               np.asarray(gcrsky.log_evidence(system)), rtol=1e-9)
    assert plan_sampler(system).method == "whitened"  # the planner sees it (the cheapest by its cost model)
    opts = resolve_channel_path(system, options=WhitenedOptions())
    ch = sample_channels(getkey(), system, 3, options=opts)
    assert np.abs(ch.a_wf - np.asarray(ref.a_wf)).max() < 1e-10 * scale
    assert isinstance(CholeskyOptions(), PATHS["cholesky"].options_type)


# ---------------------------------------------------------------- a toy path through plan, RunSpec, CLI, joint run

TOY_ARGV = ["--lmax", "4", "--nside", "16", "--nsamples", "4", "--batch", "2", "--no-plots", "--no-progress"]


def _cli_draws(out, *argv):
    import h5py

    from gcrsky import cli

    assert cli.main(["run", "--out", str(out), *TOY_ARGV, *argv]) == 0
    with h5py.File(out / "results.h5", "r") as h:
        return str(h.attrs["method"]), np.asarray(h["draws"]), np.asarray(h["wiener_filter"])


def test_a_toy_path_in_the_registry_is_planned_and_run(system, monkeypatch, tmp_path):
    """tests/_toy_path.py's path plus one registry entry: accepted by the planner and by ``RunSpec``, run by the
    CLI per channel and jointly (``--freq-prior kernel``), its draws those of the cholesky path for the same key
    (it wraps the same factor: equal bit for bit).  Negative control: unknown before the registry entry."""
    from _toy_path import ToyOptions, ToyPath

    from gcrsky.run import Solver
    from gcrsky.solvers import choose_path, registry

    with pytest.raises(ValueError, match="solver.method"):
        Solver(method="toy")
    monkeypatch.setitem(registry.PATHS, "toy", ToyPath())  # the one registry entry
    assert isinstance(choose_path(system, "toy"), ToyOptions)
    assert plan_sampler(system).method != "toy"  # auto never takes it (its own limits)
    assert Solver(method="toy").method == "toy"
    for argv in ((), ("--freq-prior", "kernel")):
        name, toy, wf = _cli_draws(tmp_path / ("toy" + "".join(argv)), "--method", "toy", *argv)
        ref_name, ref, ref_wf = _cli_draws(tmp_path / ("cholesky" + "".join(argv)), "--method", "cholesky", *argv)
        assert (name, ref_name) == ("toy", "cholesky"), argv
        assert toy.shape == ref.shape and np.array_equal(toy, ref) and np.array_equal(wf, ref_wf), argv


def test_a_toy_path_in_the_registry_is_a_gibbs_step(system, monkeypatch):
    """The Gibbs part of the toy-path check: with its one registry entry, ``gcr_step`` and the Gibbs kernel's sky
    block (``gibbs_setup`` / ``sky_step``) take the toy path's options; its step is the cholesky path's step for
    the same key (it wraps the same factor and draw: equal bit for bit).  Negative control: refused before the
    entry is added."""
    from _toy_path import ToyOptions, ToyPath

    from gcrsky.solvers import registry

    key = jax.random.PRNGKey(7)
    state = gcrsky.gcr_init(system.prior.mean)
    with pytest.raises((TypeError, ValueError)):
        gcrsky.gcr_step(key, state, system, options=ToyOptions())
    monkeypatch.setitem(registry.PATHS, "toy", ToyPath())
    toy, _ = gcrsky.gcr_step(key, state, system, options=ToyOptions())
    ref, _ = gcrsky.gcr_step(key, state, system, options=CholeskyOptions())
    assert np.array_equal(np.asarray(toy.position), np.asarray(ref.position))
    assert not np.array_equal(np.asarray(toy.position), np.asarray(system.prior.mean))
    fixed = gcrsky.inference.gibbs_setup(system, options=ToyOptions())
    a, info = gcrsky.inference.sky_step(key, fixed)
    assert a.shape == system.prior.mean.shape and bool(np.all(np.isfinite(np.asarray(a))))
    assert bool(np.all(np.asarray(info.converged)))
    # the sky block on the toy path is the toy path's own draw (prepare, then draw one, same key)
    path = registry.path_of(ToyOptions())
    one, _ = path.draw(key, path.prepare(system, ToyOptions()), 1)
    np.testing.assert_allclose(np.asarray(a), np.asarray(one)[:, 0], rtol=0, atol=1e-12 * float(np.abs(one).max()))
