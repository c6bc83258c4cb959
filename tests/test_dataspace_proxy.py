"""The data-space path with a frame map by the stationary proxy and preconditioned CG (issue 24 item 3).

A 10-antenna hexagon, compressed, 3 observing times over 1 h, lmax 12, an isotropic prior, a real
ICRS -> CIRS frame map (:func:`gcrsky.sphere.icrs_to_cirs_map` through ``build_problem(times=...)``),
some samples flagged.  References, independent of the proxy code:

* the general construction of the data-space path (``DataSpaceOptions(proxy=False)``: D from the
  per-time rows with the frame map, its Cholesky factor; exact to rounding, ~1e-13) for the Wiener
  filter and the draws (same keys: the same normals, the same Hoffman-Ribak formula);
* the dense posterior precision P (n = 169): errors measured in posterior-sigma units as the P-norm
  ``sqrt(e^T P e)``, which the reported bound must exceed;
* central finite differences of fresh set-ups for the implicit derivatives.

Negative control: the proxy's ``D0^-1`` used as if it were ``D^-1`` (no CG) misses the reference by far
more than the tolerance, so the CG with the true D is what makes the answer exact.
"""

from __future__ import annotations

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gcrsky.inference import log_evidence
from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array
from gcrsky.model import build_problem, compress_problem, isotropic_prior
from gcrsky.model.system import precision_matrix
from gcrsky.solvers import DataSpaceOptions
from gcrsky.solvers.dataspace import (
    _condition_dataspace,
    _proxy_precond,
    _whitened_residual,
    data_size,
    dataspace_matrix,
    draw_dataspace,
    lag_structure,
    prepare_dataspace,
    sqrt_weights,
    whitened_adjoint,
)
from gcrsky.solvers.dataspace_proxy import anisotropy, stationary_proxy, truncation_index
from gcrsky.solvers.registry import path_of
from gcrsky.sphere.frames import frame_lmax
from gcrsky.sphere.modes import mode_table
from gcrsky.sphere.rotation import wigner_band_shapes

log = logging.getLogger(__name__)

LMAX = 12
TOL = 1e-9  # posterior sigma: the CG's stop, ||r||_2 <= TOL
MAX_ITERATIONS = 25  # a generous cap: measured 3-4 per solve here


def _system(prior_fn=None):
    import astropy.units as u
    from astropy.coordinates import EarthLocation
    from astropy.time import Time

    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    n, nf = (LMAX + 1) ** 2, 2
    cl = 50.0 / (1.0 + np.arange(LMAX + 1)) ** 2
    prior = isotropic_prior(np.stack([cl, 2 * cl]), n)
    rng = np.random.default_rng(1)
    prior = prior._replace(mean=np.asarray(prior.inv_var) ** -0.5 * rng.standard_normal((nf, n)))
    truth = np.asarray(prior.mean) + np.asarray(prior.inv_var) ** -0.5 * rng.standard_normal((nf, n))
    times = Time("2026-03-01T00:00:00") + np.linspace(0.0, 1.0, 3) * u.hour
    loc = EarthLocation.from_geodetic(21.4283, HERA_LATITUDE_DEG, 1073.0)
    prob = build_problem(arr, [100e6, 101e6], None, LMAX, 32, a_true=truth, sigma=0.05, prior=prior,
                         key=jax.random.PRNGKey(1), times=times, location=loc)
    sys0 = compress_problem(prob, arr).system()
    flags = np.zeros(sys0.inv_noise.shape, bool)
    flags[0, 1, :2] = True
    flags[1, 2, 4] = True
    return sys0._replace(inv_noise=jnp.where(flags, 0.0, sys0.inv_noise), data=jnp.where(flags, 1e3 + 0j, sys0.data))


@pytest.fixture(scope="module")
def system():
    return _system()


@pytest.fixture(scope="module")
def reference(system):
    """The general construction (D with the frame map, its Cholesky factor) and the dense P."""
    ref = prepare_dataspace(system, DataSpaceOptions(proxy=False))
    assert ref.gram is not None and not ref.options.proxy
    return ref, np.asarray(precision_matrix(system))


def _p_norm(P, e):
    """``sqrt(e^T P e)`` per channel (and draw): e (Nf, ..., n)."""
    return np.sqrt(np.abs(np.einsum("f...k,fkj,f...j->f...", e, P, e)))


def test_fixture_is_a_frame_mapped_data_space_problem(system):
    assert data_size(system) < system.prior.mean.shape[-1]
    assert system.op.frame is not None and lag_structure(system) is None
    assert np.any(np.asarray(system.inv_noise) == 0)


def test_proxy_is_the_truncated_stationary_system(system):
    """The proxy: the response's l <= lmax columns (the lmax layout), frame None, stationary; its D0 differs
    from the true D by aberration only: 0 to rounding with aberration replaced by the embedding."""
    proxy = stationary_proxy(system)
    lin, lout = frame_lmax(system.op.frame)
    idx = truncation_index(lin, lout)
    tin, tout = mode_table(lin), mode_table(lout)
    for f in ("ell", "m", "is_imag"):
        np.testing.assert_array_equal(getattr(tout, f)[idx], getattr(tin, f))
    assert proxy.op.frame is None and proxy.op.response.shape[-1] == (lin + 1) ** 2
    lags = lag_structure(proxy)
    assert lags is not None
    D0 = np.asarray(dataspace_matrix(proxy, lags=lags))
    D = np.asarray(dataspace_matrix(system))
    rel = np.abs(D - D0).max() / np.abs(D).max()
    log.info("|D - D0| / |D| = %.2e (aberration, lmax %d)", rel, lin)
    assert 1e-7 < rel < 1e-2
    A = np.zeros(system.op.frame.aberration.shape)
    A[:, np.arange(lin + 1), np.arange(lin + 1)] = 1.0  # aberration -> the embedding: a pure rotation
    rotated = system._replace(op=system.op._replace(frame=system.op.frame._replace(aberration=jnp.asarray(A))))
    D_rot = np.asarray(dataspace_matrix(rotated))
    np.testing.assert_allclose(D_rot, D0, rtol=0, atol=1e-12 * np.abs(D0).max())


@pytest.mark.parametrize("in_place", [False, True])
def test_wiener_filter_and_draws_equal_the_general_construction(system, reference, in_place):
    """Same answer as the exact factor of D to TOL posterior sigma, the bound above the measured error, few
    iterations (logged)."""
    ref, P = reference
    st = prepare_dataspace(system, DataSpaceOptions(tol=TOL, in_place=in_place))
    assert st.options.proxy and st.gram is None and st.rows is None and st.options.in_place == in_place
    err = _p_norm(P, np.asarray(st.a_wf - ref.a_wf))
    w = st.wiener
    assert bool(np.all(w.converged)) and np.all(err <= TOL) and np.all(err <= w.err_sigma + 1e-11)
    key = jax.random.PRNGKey(7)
    d_ref, _ = draw_dataspace(key, ref, 6)
    d, info = draw_dataspace(key, st, 6)
    derr = _p_norm(P, np.asarray(d - d_ref))  # (Nf, ndraws)
    it = np.asarray(info.draws.iterations)
    log.info("proxy (in_place=%s): Wiener %s iterations, draws %s; errors %.1e / %.1e posterior sigma", in_place,
             np.asarray(w.iterations).tolist(), it.tolist(), err.max(), derr.max())
    assert info.draws.iterations.shape == (2, 6) and bool(np.all(info.draws.converged))
    assert np.all(derr <= TOL) and np.all(derr <= np.asarray(info.draws.err_sigma) + 1e-11)
    assert 0 < it.max() <= MAX_ITERATIONS and 0 < np.asarray(w.iterations).max() <= MAX_ITERATIONS


@pytest.mark.parametrize("tol", [1e-4])  # one loose tolerance: the error is measurable there
def test_the_bound_holds_where_cg_stops_early(system, reference, tol):
    """At loose tolerances the error is measurable (not rounding) and below the reported ||r||_2."""
    ref, P = reference
    st = prepare_dataspace(system, DataSpaceOptions(tol=tol))
    key = jax.random.PRNGKey(3)
    d_ref, _ = draw_dataspace(key, ref, 8)
    d, info = draw_dataspace(key, st, 8)
    err = np.concatenate([_p_norm(P, np.asarray(st.a_wf - ref.a_wf))[:, None], _p_norm(P, np.asarray(d - d_ref))], 1)
    bound = np.concatenate([np.asarray(st.wiener.err_sigma)[:, None], np.asarray(info.draws.err_sigma)], 1)
    log.info("tol %.0e: error / bound max %.2f, errors up to %.1e", tol, (err / bound).max(), err.max())
    assert np.all(err <= bound * (1 + 1e-6) + 1e-12) and np.all(bound <= tol)
    assert err.max() > 1e-9 * tol  # measurable: the test is not passing on rounding alone


def test_negative_control_d0_as_if_it_were_d(system, reference):
    """The proxy's factor alone (x = D0^-1 r~, no CG) misses the Wiener filter by far more than TOL."""
    ref, P = reference
    st = prepare_dataspace(system, DataSpaceOptions(tol=TOL))
    sw = sqrt_weights(system)
    x0 = _proxy_precond(st.chol)(_whitened_residual(system, sw))
    a0 = system.prior.mean + whitened_adjoint(system, sw, x0) / system.prior.inv_var
    err = _p_norm(P, np.asarray(a0 - ref.a_wf))
    log.info("D0 as D: Wiener error %s posterior sigma", err)
    assert np.all(err > 1e3 * TOL)


def test_not_converged_is_reported(system):
    st = prepare_dataspace(system, DataSpaceOptions(tol=1e-14, maxiter=1))
    assert not bool(np.any(st.wiener.converged)) and np.all(np.asarray(st.wiener.result) == 1)
    _, info = draw_dataspace(jax.random.PRNGKey(0), st, 2)
    assert not bool(np.any(info.draws.converged))


def test_anisotropic_prior_has_no_proxy(system):
    """A prior that is not a C_l: no proxy (the general construction); proxy=True says why."""
    tab = mode_table(LMAX)
    iv = np.array(system.prior.inv_var)
    iv[:, (tab.ell == 5) & (tab.m == 2)] *= 1.5  # Re and Im alike: commutes with the pole, not isotropic
    aniso = system._replace(prior=system.prior._replace(inv_var=jnp.asarray(iv)))
    assert anisotropy(iv) and not anisotropy(system.prior.inv_var)
    assert stationary_proxy(aniso) is None
    st = prepare_dataspace(aniso)
    assert not st.options.proxy and st.gram is not None
    with pytest.raises(ValueError, match="proxy=True.*l = 5"):
        prepare_dataspace(aniso, DataSpaceOptions(proxy=True))
    no_frame = system._replace(op=system.op._replace(frame=None, response=stationary_proxy(system).op.response))
    assert stationary_proxy(no_frame) is None


# noise and prior derivatives, the jnp and the host factor: each once (~1 min of compilation a case)
@pytest.mark.parametrize("which,in_place", [("prior", False), ("noise", True)])
def test_wiener_filter_differentiates_implicitly(system, which, in_place):
    """d/d(scale) of a fixed projection of the Wiener filter, the proxy's factor (jnp or host) held at scale 1
    and D matrix-free at the traced scale: against central differences of fresh proxy set-ups (h = 1e-5)."""
    w = jnp.asarray(np.random.default_rng(4).standard_normal(system.prior.mean.shape))
    opts = DataSpaceOptions(tol=1e-12, in_place=in_place)

    def scaled(s):
        if which == "noise":
            return system._replace(inv_noise=system.inv_noise * s)
        return system._replace(prior=system.prior._replace(inv_var=system.prior.inv_var / s))

    base = prepare_dataspace(system, opts)

    def f(s):
        st = type(base)(scaled(s), base.a_wf, base.wiener, base.gram, base.chol, base.rows, base.options)
        return jnp.sum(w * _condition_dataspace(st, system.data).a_wf)

    g = jax.grad(f)(1.0)
    h = 1e-5
    fd = (jnp.sum(w * prepare_dataspace(scaled(1 + h), opts).a_wf)
          - jnp.sum(w * prepare_dataspace(scaled(1 - h), opts).a_wf)) / (2 * h)
    assert np.isfinite(g) and abs(float(g)) > 0
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_evidence_from_a_proxy_state_is_refused_with_the_reason(system):
    st = prepare_dataspace(system)
    assert st.options.proxy
    with pytest.raises(ValueError, match="log det D.*proxy.*log_evidence_system"):
        log_evidence(st)


def test_planner_accounts_for_the_proxy(system):
    """memory / cost / description of the path take the proxy (no rows, no exact D); proxy=False the general."""
    path = path_of("dataspace")
    auto, general = DataSpaceOptions(), DataSpaceOptions(proxy=False)
    assert path.memory_bytes(system, auto, 4) < path.memory_bytes(system, general, 4)
    # the proxy's cost: no N_d^2 n product for D, but (PROXY_ITERATIONS + 1) products with the true D per solve
    # (at this tiny size the general construction's is smaller; at 61 antennas, lmax 287, far larger)
    c0, c200 = path.cost_flop(system, auto, 0), path.cost_flop(system, auto, 200)
    assert 0 < c0 < c200 and c0 != path.cost_flop(system, general, 0)
    assert "stationary proxy" in path.describe(system, auto, 1.0)
    assert "stationary proxy" not in path.describe(system, general, 1.0)
    assert path.auto_limits(system, auto, 1e12, 1) == ""


def test_options_validate():
    for bad in (dict(proxy="yes"), dict(maxiter=0), dict(maxiter=1.5)):
        with pytest.raises(ValueError):
            DataSpaceOptions(**bad)


@pytest.mark.parametrize("ndraws", [1, 16])
def test_draw_memory_estimate_bounds_the_compiled_draws(system, ndraws):
    """proxy_draw_bytes bounds XLA's memory analysis of the compiled proxy draws (temporaries + outputs), and
    not by far (the frame map's Wigner copies and the per-draw vectors were calibrated on it at lmax 40)."""
    from gcrsky.solvers.dataspace_proxy import proxy_draw_bytes

    st = prepare_dataspace(system, DataSpaceOptions(in_place=True))
    ma = draw_dataspace.lower(jax.random.PRNGKey(0), st, ndraws).compile().memory_analysis()
    if ma is None:
        pytest.skip("this backend gives no memory analysis")
    used = ma.temp_size_in_bytes + ma.output_size_in_bytes
    est = proxy_draw_bytes(system, ndraws)
    log.info("proxy draws (%d): XLA %d bytes, estimate %d", ndraws, used, est)
    assert used <= est < 3 * used


def test_planner_chooses_the_proxy_for_a_61_antenna_file():
    """The shapes of ``benchmarks/cli_scale.py --n-side 5`` (108 rows, 30 times, lmax 287, frame pad 4; no
    arrays formed: broadcast zeros, the planner reads shapes): ``method="auto"`` takes the data space by the
    proxy within 8 GB, where the general construction needs 9.87 GiB (11.75 before the Wigner blocks were stored by band; its refusal sent the file to CG)."""
    from gcrsky.model.operator import VisOperator
    from gcrsky.model.system import LinearSystem
    from gcrsky.solvers.plan import plan_sampler
    from gcrsky.sphere.frames import FrameMap

    nrow, nt, lmax, lout = 108, 30, 287, 291
    n = (lmax + 1) ** 2

    class Blocks:  # the planner reads the Wigner blocks' shapes only
        bands = tuple(np.broadcast_to(np.zeros(1), sh) for sh in wigner_band_shapes(lout))

    frame = FrameMap(Blocks(), np.zeros(3), np.broadcast_to(np.zeros(1), (lout + 1, lout + 1, lmax + 1)), np.zeros(3))
    prior = isotropic_prior((1.0 / (1.0 + np.arange(lmax + 1)) ** 2)[None], n)
    op = VisOperator(np.broadcast_to(np.zeros(1, complex), (1, nrow, (lout + 1) ** 2)), np.linspace(0, 2.1, nt), frame)
    sys_ = LinearSystem(op, np.zeros((1, nt, nrow), complex), np.ones((1, nt, nrow)), prior)
    path = path_of("dataspace")
    assert path.memory_bytes(sys_, DataSpaceOptions(proxy=False), 50) > 8e9  # the general construction: 9.87 GiB
    plan = plan_sampler(sys_, ndraws=50, budget=8e9)
    assert plan.method == "dataspace" and "stationary proxy" in plan.reason
    assert plan.memory_bytes < 0.75 * 8e9
