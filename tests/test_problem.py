"""Problem assembly: the public API's shapes, overrides and simulation conventions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gcrsky
from gcrsky.instrument import HERA_LATITUDE_DEG, antpairs, gaussian_beam, hex_array, make_array, response_matrix
from gcrsky.model.noise import radiometer_sigma
from gcrsky.sphere import rotate

SMALL = dict(lmax=6, nside=32, n_lst=4)


@pytest.fixture(scope="module")
def prob():
    return gcrsky.standard_case(**SMALL)


def test_shapes_and_defaults(prob):
    n = 49
    assert prob.antpairs.shape == (45, 2)
    np.testing.assert_array_equal(prob.antpairs, antpairs(10))
    assert prob.data.shape == (2, 4, 45)
    assert prob.a_true.shape == (2, n)
    assert prob.precision_matrix().shape == (2, n, n)
    assert gcrsky.wiener_filter(prob).shape == (2, n)
    assert prob.config.latitude_deg == HERA_LATITUDE_DEG
    np.testing.assert_allclose(np.asarray(prob.freqs_hz), [100e6, 102e6])
    np.testing.assert_allclose(np.asarray(prob.lsts_rad), np.linspace(0, 8, 4) * 2 * np.pi / 24)


def test_visibilities_follow_antpairs_order(prob):
    """Problem.visibilities(a)[f, t, b] is the response of pair antpairs[b], built independently."""
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    pair = np.array([[2, 7]])
    b = int(np.flatnonzero((prob.antpairs == pair).all(1))[0])
    R = response_matrix(arr, pair, [100e6, 102e6], 6, 32)
    a = prob.a_true
    t = 2
    ref = jnp.einsum("fk,fk->f", R[:, 0], rotate(a, prob.lsts_rad[t]))
    got = prob.visibilities(a)[:, t, b]
    # summation order differs: roundoff relative to the largest visibility of the problem
    scale = float(np.abs(np.asarray(prob.visibilities(a))).max())
    np.testing.assert_allclose(np.asarray(got), np.asarray(ref), rtol=1e-10, atol=1e-12 * scale)
    # and a different pair's column really differs (the check can fail)
    other = int(np.flatnonzero((prob.antpairs == np.array([[0, 1]])).all(1))[0])
    assert np.abs(np.asarray(prob.visibilities(a)[:, t, other] - ref)).max() > 1e-6 * scale


def test_noise_is_radiometer_from_autos_and_scales(prob):
    autos = np.asarray(prob.auto_visibilities(prob.a_true))
    p = prob.antpairs
    sig = radiometer_sigma(autos[:, :, p[:, 0]], autos[:, :, p[:, 1]], 60.0, 1e6)
    np.testing.assert_allclose(np.asarray(prob.sigma), sig, rtol=1e-12)
    p2 = gcrsky.standard_case(noise_scale=100.0, **SMALL)
    np.testing.assert_allclose(np.asarray(p2.sigma), 10 * sig, rtol=1e-12)  # N x 100 -> sigma x 10
    resid = (np.asarray(prob.data) - np.asarray(prob.visibilities(prob.a_true))) / np.asarray(prob.sigma)
    # 2 x 2 x 4 x 45 = 720 unit normals: the sample variance is within 6 sigma of 1
    assert abs(np.var(np.concatenate([resid.real.ravel(), resid.imag.ravel()])) - 1) < 6 * np.sqrt(2 / 720)


def test_prior_variants(prob):
    iv = np.asarray(prob.prior.inv_var)
    flat = gcrsky.standard_case(flat_prior=True, **SMALL)
    assert np.all(np.asarray(flat.prior.inv_var) == 0)
    wide = gcrsky.standard_case(prior_scale=100.0, **SMALL)
    np.testing.assert_allclose(np.asarray(wide.prior.inv_var), iv / 100, rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(wide.prior.mean), np.asarray(prob.prior.mean))
    zero = gcrsky.standard_case(zero_prior_mean=True, **SMALL)
    assert np.all(np.asarray(zero.prior.mean) == 0)
    # same seed -> same data; another seed -> other noise
    np.testing.assert_array_equal(np.asarray(gcrsky.standard_case(**SMALL).data), np.asarray(prob.data))
    assert not np.allclose(np.asarray(gcrsky.standard_case(seed=1, **SMALL).data), np.asarray(prob.data))


def test_problem_is_a_pytree_usable_under_jit(prob):
    f = jax.jit(lambda p, a: p.visibilities(a))
    np.testing.assert_allclose(np.asarray(f(prob, prob.a_true)), np.asarray(prob.visibilities(prob.a_true)), rtol=1e-13)


def test_bad_overrides_are_clear_errors():
    with pytest.raises(TypeError, match="unknown standard_case overrides"):
        gcrsky.standard_case(lmax_typo=3)
    with pytest.raises(ValueError, match="nside"):
        gcrsky.standard_case(lmax=40, nside=8)
    with pytest.raises(ValueError, match="n_lst"):
        gcrsky.standard_case(n_lst=0)
    with pytest.raises(ValueError, match="ndraws"):
        gcrsky.sample(jax.random.PRNGKey(0), gcrsky.standard_case(**SMALL), 0)
