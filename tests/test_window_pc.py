"""The window preconditioner (gcrsky.solvers.window) and CG's rigorous prior-norm stop with it.

Checks: the banded matrix equals a slow dense reference of the formula (the lead's
prototype, ported below) and, untapered at full bandwidth, the data term of P; it is
symmetric positive definite with flags and time-varying weights; the block-tridiagonal
factor inverts it; CG with it meets the rigorous bound on the error's P-norm against a
dense solve at 2, 8 and 16 h of coverage, while the non-rigorous M-norm stop would not.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, groups_for_array, hex_array, make_array, unique_response
from gcrsky.model import LinearSystem, VisOperator, isotropic_prior
from gcrsky.model.system import precision_matrix
from gcrsky.solvers import CGOptions
from gcrsky.solvers.cg import draw_cg, pcg, prepare_cg, resolve_cg_options, solve_cg
from gcrsky.solvers.preconditioners import (
    inverse_bound,
    make_preconditioner,
    precondition_one,
    resolve_preconditioner,
    stop_norm,
)
from gcrsky.solvers.window import (
    auto_bandwidth,
    window_data_matrix,
    window_flop,
    window_memory_bytes,
    window_preconditioner,
    window_solve,
)
from gcrsky.sphere import n_params
from gcrsky.sphere.modes import mode_table

TOL = 1e-6


def _system(lmax: int, hours: float, nt: int = 30, *, snr: float = 10.0, flags: bool = False,
            varying: bool = False) -> LinearSystem:
    """10-antenna hexagon, 100 MHz, nt times over ``hours`` of LST, SNR ~``snr`` per visibility."""
    arr = make_array(hex_array((3, 4, 3), 14.6), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    g = groups_for_array(arr)
    R = unique_response(arr, g, np.array([100e6]), lmax, 32)
    n = n_params(lmax)
    lsts = np.linspace(0, hours * 2 * np.pi / 24, nt)
    cl = 100.0 / (1.0 + np.arange(lmax + 1)) ** 2
    prior = isotropic_prior(cl[None], n)
    std = 1 / np.sqrt(np.asarray(prior.inv_var))
    counts = np.asarray(g.counts, float)
    p = np.einsum("fbk,fk->fb", np.abs(np.asarray(R)) ** 2, std**2)
    sigma = np.sqrt(np.average(p, axis=1, weights=counts).mean()) / snr / np.sqrt(2)
    w = np.broadcast_to(counts / sigma**2, (1, nt, len(counts))).copy()
    rng = np.random.default_rng(3)
    if varying:
        w *= rng.uniform(0.3, 1.7, w.shape)
    if flags:
        w[rng.uniform(size=w.shape) < 0.25] = 0.0
        w[:, nt // 3 : nt // 2] = 0.0  # a gap in time
    op = VisOperator(R, jnp.asarray(lsts))
    return LinearSystem(op, jnp.zeros((1, nt, len(counts)), complex), jnp.asarray(w), prior)


def _band_reference(system: LinearSystem, B: int | None) -> np.ndarray:
    """Slow dense reference (the lead's prototype): Re(J^H H_B J), H_B with the Fejer-tapered kernel.

    ``B=None``: no taper (the exact data term of P).
    """
    R = np.asarray(system.op.response[0])
    w = np.asarray(system.inv_noise[0])
    th = np.asarray(system.op.angles)
    n = R.shape[1]
    L = int(round(np.sqrt(n))) - 1
    tab = mode_table(L)
    cidx = {}
    for mu in range(-L, L + 1):
        for ll in range(abs(mu), L + 1):
            cidx[(mu, ll)] = len(cidx)
    nc = len(cidx)
    gam = np.zeros((R.shape[0], nc), complex)
    J = np.zeros((nc, n), complex)
    re_of, im_of = {}, {}
    for k in range(n):
        (im_of if tab.is_imag[k] else re_of)[(int(tab.ell[k]), int(tab.m[k]))] = k
    for (ll, m), k in re_of.items():
        if m == 0:
            gam[:, cidx[(0, ll)]] = R[:, k]
            J[cidx[(0, ll)], k] = 1
        else:
            ki = im_of[(ll, m)]
            gam[:, cidx[(m, ll)]] = (R[:, k] - 1j * R[:, ki]) / 2
            gam[:, cidx[(-m, ll)]] = (R[:, k] + 1j * R[:, ki]) / 2
            J[cidx[(m, ll)], k], J[cidx[(m, ll)], ki] = 1, 1j
            J[cidx[(-m, ll)], k], J[cidx[(-m, ll)], ki] = 1, -1j
    mus = np.array([mu for (mu, _) in cidx])
    D = mus[None, :] - mus[:, None]
    taper = np.ones_like(D, float) if B is None else np.clip(1 - np.abs(D) / (B + 1), 0, None)
    H = np.zeros((nc, nc), complex)
    for b in range(R.shape[0]):
        Kb = np.exp(1j * D[..., None] * th) @ w[:, b]
        H += np.conj(gam[b][:, None]) * gam[b][None, :] * Kb * taper
    return (J.conj().T @ H @ J).real


@pytest.fixture(scope="module")
def small():
    return {"plain": _system(5, 8.0, 12), "flagged": _system(5, 5.0, 12, flags=True, varying=True)}


@pytest.mark.parametrize("case", ["plain", "flagged"])
@pytest.mark.parametrize("B", [0, 1, 3, 4, 7])
def test_band_equals_dense_formula(small, case, B):
    s = small[case]
    ref = _band_reference(s, B)
    got = np.asarray(window_data_matrix(s, B)[0])
    assert np.max(np.abs(got - ref)) <= 1e-12 * np.max(np.abs(ref))
    tab = mode_table(5)
    far = np.abs(tab.m[:, None] - tab.m[None, :]) > B
    assert np.all(got[far] == 0.0)  # block-banded in m with bandwidth B


@pytest.mark.parametrize("case", ["plain", "flagged"])
def test_untapered_full_band_is_the_data_term_of_P(small, case):
    s = small[case]
    lmax = 5
    data = np.asarray(precision_matrix(s)[0]) - np.diag(np.asarray(s.prior.inv_var[0]))
    got = np.asarray(window_data_matrix(s, 2 * lmax, taper=False)[0])
    assert np.max(np.abs(got - data)) <= 1e-12 * np.max(np.abs(data))
    assert np.max(np.abs(_band_reference(s, None) - data)) <= 1e-12 * np.max(np.abs(data))


@pytest.mark.parametrize("case", ["plain", "flagged"])
@pytest.mark.parametrize("B", [0, 1, 2, 4, 6])
def test_symmetric_positive_definite_and_inverted(small, case, B):
    s = small[case]
    data = np.asarray(window_data_matrix(s, B)[0])
    M = data + np.diag(np.asarray(s.prior.inv_var[0]))
    assert np.array_equal(M, M.T)
    ev = np.linalg.eigvalsh(data)
    assert ev.min() >= -1e-12 * ev.max()  # the tapered data term alone is PSD (Schur product)
    assert np.linalg.eigvalsh(M).min() > 0
    pc = window_preconditioner(s, B)
    r = np.random.default_rng(B).standard_normal(M.shape[0])
    y = np.asarray(window_solve(pc, 0, jnp.asarray(r)))
    assert np.allclose(y, np.linalg.solve(M, r), rtol=1e-9, atol=1e-9 * np.abs(y).max())


def test_estimates_and_layout():
    mem, fl = window_memory_bytes(64, 8, 63), window_flop(64, 8, 63)
    assert mem["peak"] >= mem["factor"] + mem["band"] > 0 and fl["band"] > 0 and fl["apply"] < fl["factor"]
    pc = window_preconditioner(_system(3, 8.0, 8), 2)  # super-blocks of 2 orders: 2 of them
    assert pc.chol.shape == (1, 2, 12, 12) and pc.low.shape == (1, 1, 12, 12)
    assert window_memory_bytes(3, 2, 7)["factor"] == 8.0 * 3 * 12**2


def _rhs(P: np.ndarray, seed: int = 0) -> np.ndarray:
    """b ~ N(0, P): the solution then has unit posterior-sigma scale, like a GCR draw's."""
    return np.linalg.cholesky(P) @ np.random.default_rng(seed).standard_normal(P.shape[0])


@pytest.fixture(scope="module")
def coverage():
    out = {}
    for hours in (2, 8, 16):
        s = _system(20, hours, 30)
        P = precision_matrix(s)
        b = jnp.asarray(_rhs(np.asarray(P[0])))
        out[hours] = (s, P, b, jnp.linalg.solve(P[0], b))
    return out


def _p_error(P, x, xs) -> float:
    e = x - xs
    return float(jnp.sqrt(e @ P[0] @ e))


@pytest.mark.parametrize("hours", [2, 8, 16])
@pytest.mark.parametrize("B", [2, 8])
def test_cg_meets_the_rigorous_bound(coverage, hours, B):
    s, P, b, xs = coverage[hours]
    opt = CGOptions(preconditioner="window", bandwidth=B, tol=TOL)
    pc = make_preconditioner(s, "window", bandwidth=B)
    x, info = solve_cg(s, P, pc, b[None], jnp.zeros((1, b.size)), opt)
    assert bool(info.converged[0]) and int(info.iterations[0]) > 0
    assert float(info.err_sigma[0]) <= TOL
    assert _p_error(P, x[0], xs) <= float(info.err_sigma[0]) + 1e-8  # the stop bounds the true error


def test_m_norm_stop_would_under_report(coverage):
    """Negative control: stopping on sqrt(r^T M^-1 r) (not a bound for this M) misses the tolerance."""
    worst = 0.0
    for hours in (2, 8, 16):
        s, P, b, xs = coverage[hours]
        pc = make_preconditioner(s, "window", bandwidth=4)
        prec = lambda r, pc=pc: precondition_one(pc, 0, r)  # noqa: E731
        mv = lambda x, P=P: P[0] @ x  # noqa: E731
        x, info = jax.jit(lambda b, mv=mv, prec=prec: pcg(mv, prec, b, jnp.zeros_like(b), tol=TOL, maxiter=5000))(b)
        assert bool(info.converged)  # it believes it met the tolerance ...
        worst = max(worst, _p_error(P, x, xs) / TOL)
        _, info2 = pcg(mv, prec, b, jnp.zeros_like(b), tol=TOL, maxiter=5000, stop=stop_norm(pc, 0))
        assert info2.iterations > info.iterations  # the rigorous stop costs iterations
    assert worst > 2.0  # ... but the true error exceeds it (measured 4-20x)


def test_matrix_free_draws_float32_and_jax_engine():
    s = _system(6, 12.0, 16)
    P = np.asarray(precision_matrix(s)[0])
    opt = CGOptions(preconditioner="window", bandwidth=3, dense=False)
    state = prepare_cg(s, opt)
    _, info = draw_cg(jax.random.PRNGKey(0), state, 3)
    assert bool(jnp.all(info.draws.converged)) and bool(jnp.all(info.wiener.converged))
    b = jnp.asarray(_rhs(P))[None]
    xs = np.linalg.solve(P, np.asarray(b[0]))
    for o in (dataclasses.replace(opt, pc_dtype="float32", dense=True), dataclasses.replace(opt, engine="jax")):
        pc = make_preconditioner(s, "window", pc_dtype=o.pc_dtype, bandwidth=3)
        x, inf = solve_cg(s, precision_matrix(s), pc, b, jnp.zeros_like(b), o)
        e = np.asarray(x[0]) - xs
        assert bool(inf.converged[0]) and np.sqrt(e @ P @ e) <= TOL
    assert pc.svar.dtype == jnp.float64
    assert float(inverse_bound(pc, 0)) == pytest.approx(float(jnp.max(pc.svar[0])))


def test_auto_bandwidth_and_options():
    lmax = 10
    full = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    assert auto_bandwidth(full, np.ones((1, 48, 3)), lmax) == 0  # full uniform day: K is a delta
    widths = [auto_bandwidth(np.linspace(0, h * 2 * np.pi / 24, 30), np.ones((1, 30, 3)), lmax) for h in (2, 8, 16)]
    assert widths[0] >= widths[1] >= widths[2] >= 1
    s = _system(4, 8.0, 10)
    opt = resolve_cg_options(s, CGOptions(preconditioner="window"))
    assert isinstance(opt.bandwidth, int) and opt.bandwidth == auto_bandwidth(s.op.angles, s.inv_noise, 4)
    with pytest.raises(ValueError, match="bandwidth"):
        CGOptions(preconditioner="window", bandwidth=-1)
    with pytest.raises(ValueError, match="bandwidth"):
        CGOptions(bandwidth=2.5)
    flat = s._replace(prior=s.prior._replace(inv_var=jnp.asarray(s.prior.inv_var).at[0, 0].set(0.0)))
    with pytest.raises(ValueError, match="window preconditioner needs"):
        resolve_preconditioner(flat, "window", warn=False)
    assert resolve_preconditioner(s, "auto") == "nystrom"  # "auto" never picks the window
    framed = s._replace(op=s.op._replace(frame=jnp.eye(s.prior.mean.shape[-1])))
    with pytest.raises(ValueError, match="frame"):
        window_preconditioner(framed, 2)
