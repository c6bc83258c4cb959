"""Automatic sampler-path choice and memory checks (gcrsky.solvers.plan, gcrsky.solvers.choose_path).

References: the dense Cholesky posterior (Wiener filter and covariance) of the same
problem.  Every path is exact, so whatever ``"auto"`` picks must reproduce the dense
Wiener filter to 1e-8 posterior sigma (the CG tolerance used here is 1e-10 sigma; the
m-mode and Cholesky paths are direct solves, measured ~1e-12).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

import gcrsky
from gcrsky.base import InsufficientMemoryError, available_memory_bytes
from gcrsky.instrument import response_matrix
from gcrsky.model import build_problem, flat_prior, isotropic_prior
from gcrsky.solvers import CGOptions, path_memory_bytes, plan_sampler
from gcrsky.solvers.mmode import mmode_memory
from gcrsky.solvers.plan import DENSE_MEMORY_FRACTION


def _problem(small_response, lsts, *, flat=False):
    arr, lmax, nside = small_response.array, small_response.lmax, small_response.nside
    freqs = small_response.freqs_hz
    n = (lmax + 1) ** 2
    nf = freqs.size
    cl = np.tile(100.0 / (1.0 + np.arange(lmax + 1)) ** 2, (nf, 1))
    prior = flat_prior(nf, n) if flat else isotropic_prior(cl, n)
    truth = np.asarray(gcrsky.isotropic_prior(cl, n).inv_var) ** -0.5 * np.random.default_rng(1).standard_normal((nf, n))
    nant = arr.positions_enu_m.shape[0]
    auto = response_matrix(arr, np.stack([np.arange(nant)] * 2, 1), freqs, lmax, nside)
    return build_problem(arr, freqs, lsts, lmax, nside, a_true=truth, sigma=0.05, prior=prior,
                         responses=(small_response.response, auto), key=jax.random.PRNGKey(5))


@pytest.fixture(scope="module")
def full_day(small_response):
    nt = 2 * small_response.lmax + 5
    return _problem(small_response, 2 * np.pi * np.arange(nt) / nt)


@pytest.fixture(scope="module")
def partial(small_response):
    return _problem(small_response, np.linspace(0.0, 2 * np.pi / 3, 10))


def _dense_wf_and_sigma(problem):
    P = np.asarray(problem.precision_matrix())
    b = np.asarray(gcrsky.model.system.wiener_rhs(problem.system()))
    a = np.stack([np.linalg.solve(P[f], b[f]) for f in range(P.shape[0])])
    sig = np.stack([np.sqrt(np.diag(np.linalg.inv(P[f]))) for f in range(P.shape[0])])
    return a, sig


@pytest.mark.parametrize("case,expect", [("full_day", "mmode"), ("partial", "cholesky")])
def test_auto_picks_the_cheapest_exact_path(request, case, expect, getkey):
    prob = request.getfixturevalue(case)
    plan = plan_sampler(prob.system())
    assert plan.method == expect, plan.reason
    prepared = gcrsky.prepare(prob, tol=1e-10)
    assert prepared.method == expect
    a_ref, sig = _dense_wf_and_sigma(prob)
    assert np.max(np.abs(np.asarray(prepared.a_wf) - a_ref) / sig) < 1e-8
    draws, info = gcrsky.draw(getkey(), prepared, 4)
    assert draws.shape == (2, 4, prob.n) and bool(np.all(np.asarray(info.draws.converged)))


def test_small_budget_falls_back_to_matrix_free_cg(partial, getkey):
    sysm = partial.system()
    dense = path_memory_bytes(sysm, "cholesky")
    budget = 0.95 * dense / DENSE_MEMORY_FRACTION  # dense needs <= DENSE_MEMORY_FRACTION of the budget: not met
    plan = plan_sampler(sysm, budget=budget)
    assert (plan.method, plan.options.dense, plan.options.preconditioner) == ("cg", False, "nystrom")
    assert "matrix-free" in plan.reason
    a_ref, sig = _dense_wf_and_sigma(partial)
    a = gcrsky.wiener_filter(partial, tol=1e-10, memory_budget=budget)
    assert np.max(np.abs(np.asarray(a) - a_ref) / sig) < 1e-8


def test_flat_prior_uses_the_eigen_sampler(small_response):
    prob = _problem(small_response, np.linspace(0.0, 2 * np.pi / 3, 10), flat=True)
    assert plan_sampler(prob.system()).method == "eigh"
    assert plan_sampler(prob.system(), budget=1.0 * path_memory_bytes(prob.system(), "cg", dense=False)).options.preconditioner == "mblock"


def test_memory_errors_name_size_and_alternative(partial):
    sysm = partial.system()
    with pytest.raises(InsufficientMemoryError, match=r"method='cholesky' needs ~.*KiB.*CGOptions\(dense=False\)"):
        gcrsky.prepare(partial, method="cholesky", memory_budget=1000.0)
    with pytest.raises(InsufficientMemoryError, match="matrix-free CG.*smaller batches"):
        plan_sampler(sysm, budget=1000.0)


def test_mmode_refused_with_reason(partial):
    with pytest.raises(ValueError, match="not uniform over the full day"):
        gcrsky.prepare(partial, method="mmode")


def test_estimates_cover_the_arrays_they_describe(partial, full_day):
    prepared = gcrsky.prepare(partial, method="cholesky")
    actual = prepared.precision.nbytes + prepared.chol.nbytes + prepared.chol_inv_t.nbytes
    est = path_memory_bytes(partial.system(), "cholesky")
    # the estimate is the set-up's peak: the three kept n x n arrays plus XLA's transients
    # (memory_analysis of the one program: 7.25 n^2 doubles in all)
    assert actual <= est <= 2.6 * actual
    pm = gcrsky.prepare(full_day, method="mmode")
    est = path_memory_bytes(full_day.system(), "mmode")
    # the bucketed factors exactly, plus the stages that follow one another (the estimate against
    # the process's measured peak: benchmarks/mmode_scale.py)
    s = full_day.system()
    mem = mmode_memory(*(int(x) for x in (s.data.shape[0], s.data.shape[2], s.data.shape[1])), full_day.lmax)
    assert mem.factors == pm.chol.nbytes and est == mem.peak
    assert pm.chol.nbytes < est == pm.chol.nbytes + mem.build + mem.products + mem.draws


def test_budget_environment_override(monkeypatch):
    monkeypatch.setenv("GCRSKY_MEMORY_BUDGET_GB", "0.5")
    assert available_memory_bytes() == 0.5 * 2**30
    monkeypatch.setenv("GCRSKY_MEMORY_BUDGET_GB", "lots")
    with pytest.raises(ValueError, match="GCRSKY_MEMORY_BUDGET_GB"):
        available_memory_bytes()
    monkeypatch.delenv("GCRSKY_MEMORY_BUDGET_GB")
    assert available_memory_bytes() > 1e8


@pytest.mark.parametrize("pc", ["nystrom", "mblock"])
def test_float32_preconditioner_keeps_the_answer_exact(partial, pc):
    """A float32 preconditioner changes only the iteration count: products, iterates and
    the stopping test stay float64, so the Wiener filter meets the same 1e-8 sigma bar."""
    from gcrsky.inference import wiener_filter_system
    from gcrsky.solvers.preconditioners import make_preconditioner

    sysm = partial.system()
    pc32 = make_preconditioner(sysm, pc, None, 32, "float32")
    leaves = [x for x in jax.tree_util.tree_leaves(pc32) if np.issubdtype(x.dtype, np.floating)]
    assert leaves and all(x.dtype == np.float32 for x in leaves)
    a_ref, sig = _dense_wf_and_sigma(partial)
    a, info = wiener_filter_system(sysm, options=CGOptions(tol=1e-10, maxiter=5000, dense=False, preconditioner=pc, pc_dtype="float32"))
    assert bool(np.all(np.asarray(info.converged)))
    assert np.asarray(a).dtype == np.float64
    assert np.max(np.abs(np.asarray(a) - a_ref) / sig) < 1e-8
    with pytest.raises(ValueError, match="pc_dtype"):
        make_preconditioner(sysm, pc, None, 32, "float16")


def test_blocked_triangular_product_equals_dense():
    """The Cholesky draws' block-row product skips only exact zeros (n >= 256 uses 4 blocks)."""
    from gcrsky.solvers.dense import upper_triangular_product

    rng = np.random.default_rng(3)
    for n in (10, 300):
        U = np.triu(rng.standard_normal((2, n, n)))
        z = rng.standard_normal((5, 2, n))
        got = np.asarray(upper_triangular_product(jax.numpy.asarray(U), jax.numpy.asarray(z)))
        ref = np.einsum("fij,dfj->fdi", U, z)
        assert got.shape == (2, 5, n)
        assert np.max(np.abs(got - ref)) < 1e-12 * np.abs(ref).max()
