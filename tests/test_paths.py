"""One options object and one typed state per solver path; the planner; batches; the build steps.

References: every path is exact, so each one's Wiener filter must equal a dense NumPy
solve of the same system (to 1e-8 posterior sigma; CG runs at tol 1e-10, the direct
paths are solves with their factor, measured ~1e-12), and the library's batched draws
must follow the documented key scheme bit for bit.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gcrsky
from gcrsky.inference import draw, draw_batches, draw_exactly, prepare_system, wiener_filter_system
from gcrsky.inference.batches import KEY_SCHEME, batch_key
from gcrsky.instrument import antpairs
from gcrsky.model import build_problem, isotropic_prior, simulate_data
from gcrsky.model.problem import assemble_problem, observation_geometry, problem_responses
from gcrsky.model.system import wiener_rhs
from gcrsky.solvers import (
    CGOptions,
    CGState,
    CholeskyOptions,
    CholeskyState,
    EighOptions,
    EighState,
    MModeOptions,
    MModeState,
    choose_path,
)
from gcrsky.solvers.registry import method_of, options_for

SOLVE = 1e-8  # posterior sigma


@pytest.fixture(scope="module")
def full_day(small_array, small_response):
    """Uniform full-day coverage (m-mode applies) with an isotropic prior and a simulated truth."""
    lmax, nside, freqs = small_response.lmax, small_response.nside, small_response.freqs_hz
    n, nf = (lmax + 1) ** 2, freqs.size
    cl = np.tile(50.0 / (1.0 + np.arange(lmax + 1)) ** 2, (nf, 1))
    prior = isotropic_prior(cl, n)
    truth = np.asarray(prior.inv_var) ** -0.5 * np.random.default_rng(2).standard_normal((nf, n))
    nt = 2 * lmax + 3
    lsts = 2 * np.pi * np.arange(nt) / nt
    return build_problem(small_array, freqs, lsts, lmax, nside, a_true=truth, sigma=0.05, prior=prior,
                         key=jax.random.PRNGKey(4))


def _dense(problem):
    P = np.asarray(problem.precision_matrix())
    b = np.asarray(wiener_rhs(problem.system()))
    a = np.stack([np.linalg.solve(P[f], b[f]) for f in range(P.shape[0])])
    sig = np.stack([np.sqrt(np.diag(np.linalg.inv(P[f]))) for f in range(P.shape[0])])
    return a, sig


@pytest.mark.parametrize(
    "options,state",
    [(CGOptions(tol=1e-10), CGState), (CGOptions(tol=1e-10, dense=False, preconditioner="mblock"), CGState),
     (CholeskyOptions(), CholeskyState), (EighOptions(), EighState), (MModeOptions(), MModeState)],
    ids=["cg-dense-auto", "cg-mf-mblock", "cholesky", "eigh", "mmode"],
)
def test_every_path_has_its_state_and_the_exact_answer(full_day, options, state, getkey):
    system = full_day.system()
    prepared = prepare_system(system, options=options)
    assert type(prepared) is state and prepared.method == method_of(options)
    a_ref, sig = _dense(full_day)
    assert np.max(np.abs(np.asarray(prepared.a_wf) - a_ref) / sig) < SOLVE
    a, info = wiener_filter_system(system, options=options)
    assert np.max(np.abs(np.asarray(a) - a_ref) / sig) < SOLVE and bool(np.all(np.asarray(info.converged)))
    draws, dinfo = draw(getkey(), prepared, 3)
    assert draws.shape == (2, 3, full_day.n) and bool(np.all(np.asarray(dinfo.draws.converged)))
    if isinstance(prepared, CGState):  # the options travel with the state (static)
        assert prepared.options.preconditioner in ("nystrom", "mblock")


def test_states_are_pytrees_that_jit_accepts(full_day, getkey):
    prepared = gcrsky.prepare(full_day, method="cholesky")
    key = getkey()
    eager, _ = draw(key, prepared, 2)
    jitted, _ = jax.jit(draw, static_argnums=2)(key, prepared, 2)
    np.testing.assert_array_equal(np.asarray(eager), np.asarray(jitted))
    with pytest.raises(TypeError, match="a prepared state"):
        draw(key, prepared.a_wf, 2)


@pytest.mark.parametrize(
    "make,needle",
    [(lambda: CGOptions(tol=0.0), "tol must be a positive"), (lambda: CGOptions(maxiter=2.5), "maxiter"),
     (lambda: CGOptions(preconditioner="jacobi"), "preconditioner must be"),
     (lambda: CGOptions(pc_dtype="float16"), "pc_dtype"), (lambda: CGOptions(dense=1), "dense must be"),
     (lambda: EighOptions(rcond=1.5), "rcond"), (lambda: MModeOptions(atol=-1.0), "atol")],
)
def test_bad_options_name_the_field(make, needle):
    with pytest.raises(ValueError, match=needle):
        make()


def test_options_are_hashable_and_belong_to_one_path():
    assert hash(CGOptions()) == hash(CGOptions()) and CGOptions() != CGOptions(tol=1e-8)
    assert options_for("cg", tol=1e-9) == CGOptions(tol=1e-9)
    assert options_for("cholesky", tol=1e-9) == CholeskyOptions()  # direct paths are exact: tol unused
    with pytest.raises(ValueError, match="method='cholesky' was given CGOptions"):
        options_for("cholesky", CGOptions())
    with pytest.raises(ValueError, match="method must be one of"):
        options_for("lu")


def test_choose_path_resolves_method_options_and_tol(full_day):
    system = full_day.system()
    assert choose_path(system) == MModeOptions()  # auto: uniform full day
    chosen = choose_path(system, options=CGOptions(dense=False), tol=1e-9)  # options select their path
    assert chosen == CGOptions(tol=1e-9, dense=False, preconditioner="nystrom")
    assert choose_path(system, "cg") == CGOptions(preconditioner="nystrom")
    with pytest.raises(ValueError, match="was given EighOptions"):
        choose_path(system, "cg", options=EighOptions())


def test_auto_preconditioner_is_resolved_host_side_and_under_jit(full_day):
    system = full_day.system()
    flat = system._replace(prior=system.prior._replace(inv_var=jnp.zeros_like(system.prior.inv_var)))
    from gcrsky.solvers.cg import resolve_cg_options

    assert resolve_cg_options(system).preconditioner == "nystrom"
    assert resolve_cg_options(flat).preconditioner == "mblock"
    with pytest.raises(ValueError, match="needs S\\^-1 > 0"):
        resolve_cg_options(flat, CGOptions(preconditioner="nystrom"))

    seen = []  # under a trace the prior's values are unknown: Nystrom
    jax.jit(lambda s: seen.append(resolve_cg_options(s).preconditioner) or 0)(system)
    assert seen == ["nystrom"]


def test_gcr_step_options(full_day, getkey):
    """The step's default is matrix-free CG; a dense P gives the same conditional draw (same key)."""
    system = full_day.system()
    state = gcrsky.gcr_init(system.prior.mean)
    key = getkey()
    s1, i1 = gcrsky.gcr_step(key, state, system, tol=1e-10)
    s2, i2 = gcrsky.gcr_step(key, state, system, options=CGOptions(tol=1e-10, dense=True))
    _, sig = _dense(full_day)
    assert bool(np.all(np.asarray(i1.converged))) and bool(np.all(np.asarray(i2.converged)))
    assert np.max(np.abs(np.asarray(s1.position) - np.asarray(s2.position)) / sig) < SOLVE


def test_draw_batches_key_scheme(full_day, getkey):
    prepared = gcrsky.prepare(full_day, method="cholesky")
    key = getkey()
    few = draw_batches(key, prepared, 5, 3)
    many = draw_batches(key, prepared, 11, 3)
    assert few.draws.shape == (2, 5, full_day.n) and many.draws.shape == (2, 11, full_day.n)
    np.testing.assert_array_equal(few.draws, many.draws[:, :5])  # the first draws do not depend on the total
    b1, _ = draw_exactly(batch_key(key, 1), prepared, 3)  # batch 1 = draws 3..5
    np.testing.assert_array_equal(np.asarray(b1), many.draws[:, 3:6])
    assert np.asarray(many.info.converged).shape == (2, 11) and len(many.batch_seconds) == 4
    assert "fold_in" in KEY_SCHEME
    seen = []
    draw_batches(key, prepared, 4, 2, progress=lambda it: (seen.append(b) or b for b in it))
    assert seen == [0, 1]
    with pytest.raises(ValueError, match="batch must be a positive integer"):
        draw_batches(key, prepared, 4, 0)


def test_scalar_sigma_means_independent_noise_in_every_sample(small_array, small_response):
    """A scalar sigma once drew a single noise value for the whole data set (regression)."""
    lmax, nside, freqs = small_response.lmax, small_response.nside, small_response.freqs_hz
    geom = observation_geometry(small_array, lmax, lsts_rad=np.linspace(0.0, 1.0, 20))
    resp = problem_responses(small_array, freqs, geom.lmax_response, nside)
    zero = jnp.zeros((2, (lmax + 1) ** 2))
    data, sigma = simulate_data(*resp, geom.lsts_rad, geom.frame, zero, np.asarray(antpairs(10)), sigma=0.5,
                                key=jax.random.PRNGKey(1))
    assert np.shape(sigma) == np.shape(data) and np.all(np.asarray(sigma) == 0.5)
    noise = np.asarray(data)  # the sky is zero: data are noise only, 2 x 20 x 45 complex samples
    assert np.unique(noise.real).size == noise.size
    # each component is N(0, sigma^2) (model.draw_noise): 1800 samples, 4 sigma on the std is ~7%
    assert abs(np.std(noise.real) / 0.5 - 1) < 0.07 and abs(np.std(noise.imag) / 0.5 - 1) < 0.07


def test_build_problem_is_its_four_steps(small_array, small_response):
    """build_problem == geometry -> responses -> simulation -> assembly, bit for bit."""
    lmax, nside, freqs = small_response.lmax, small_response.nside, small_response.freqs_hz
    n = (lmax + 1) ** 2
    truth = np.random.default_rng(0).standard_normal((2, n))
    truth[:, 0] = 100.0  # a positive sky, so the autos define radiometer noise
    lsts = np.linspace(0.0, 1.0, 4)
    key = jax.random.PRNGKey(3)
    ref = build_problem(small_array, freqs, lsts, lmax, nside, a_true=truth, key=key, noise_scale=4.0)
    geom = observation_geometry(small_array, lmax, lsts_rad=lsts)
    assert geom.frame is None and geom.lmax_response == lmax
    resp = problem_responses(small_array, freqs, geom.lmax_response, nside)
    data, sigma = simulate_data(*resp, geom.lsts_rad, geom.frame, jnp.asarray(truth), ref.antpairs, key=key,
                                noise_scale=4.0)
    prob = assemble_problem(small_array, freqs, geom, resp, lmax, nside, data, sigma, a_true=jnp.asarray(truth))
    for name in ("response", "auto_response", "data", "sigma", "weights", "lsts_rad"):
        np.testing.assert_array_equal(np.asarray(getattr(prob, name)), np.asarray(getattr(ref, name)), err_msg=name)
    np.testing.assert_array_equal(prob.antpos_enu_m, small_array.positions_enu_m)
    assert list(prob.beam_ids) == [0] * 10
    with pytest.raises(ValueError, match="precomputed responses have shapes"):
        problem_responses(small_array, freqs, lmax + 1, nside, responses=resp)
    with pytest.raises(ValueError, match="either times"):
        observation_geometry(small_array, lmax, lsts_rad=lsts, times=object())
    assert dataclasses.is_dataclass(prob)
