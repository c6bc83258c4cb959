"""Full Wigner-D rotations of realified coefficients (gcrsky.sphere.rotation) against healpy.

healpy's ``rotate_alm`` (HEALPix C++ Wigner recursion) is the independent
reference; gcrsky's blocks come from the eigenvectors of J_x (LAPACK), so
agreement to 1e-10 checks both the convention and the accuracy.
"""

import healpy as hp
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gcrsky.sphere import (
    euler_zyz,
    from_lm_grid,
    n_alm,
    n_params,
    realify,
    rotate,
    rotate_euler,
    rotate_euler_transpose,
    rotate_matrix,
    rotation_matrix_zyz,
    to_lm_grid,
    unrealify,
    wigner_blocks,
)

jax.config.update("jax_enable_x64", True)


def _random_alm(lmax, seed=0):
    rng = np.random.default_rng(seed)
    alm = rng.normal(size=n_alm(lmax)) + 1j * rng.normal(size=n_alm(lmax))
    alm[: lmax + 1] = alm[: lmax + 1].real
    return alm


@pytest.fixture(scope="module")
def blocks64():
    return wigner_blocks(64)


@pytest.mark.parametrize("lmax", [0, 1, 5, 20, 64])
@pytest.mark.parametrize("angles", [(0.3, 1.1, -2.0), (-2.9, 3.0, 1.4), (1e-3, 1e-9, 2.0), (0.7, np.pi, 0.0)])
def test_rotate_euler_matches_healpy(lmax, angles, blocks64):
    alm = _random_alm(lmax, seed=lmax)
    alpha, beta, gamma = angles
    out = unrealify(np.asarray(rotate_euler(jnp.asarray(realify(alm, lmax)), alpha, beta, gamma, blocks64)), lmax)
    ref = alm.copy()
    hp.rotate_alm(ref, psi=gamma, theta=beta, phi=alpha, lmax=lmax)
    assert np.abs(out - ref).max() < 1e-10 * np.abs(alm).max(), np.abs(out - ref).max()
    # and through a rotation matrix (healpy's matrix= path)
    ref2 = alm.copy()
    R = rotation_matrix_zyz(alpha, beta, gamma)
    hp.rotate_alm(ref2, matrix=R, lmax=lmax)
    out2 = unrealify(np.asarray(rotate_matrix(jnp.asarray(realify(alm, lmax)), R, blocks64)), lmax)
    assert np.abs(out2 - ref2).max() < 1e-10 * np.abs(alm).max()


def test_wrong_conventions_fail(blocks64):
    """The comparison has power: swapped or negated angles differ at O(1)."""
    lmax = 8
    alm = _random_alm(lmax, 1)
    out = unrealify(np.asarray(rotate_euler(jnp.asarray(realify(alm, lmax)), 0.3, 1.1, -2.0, blocks64)), lmax)
    for psi, theta, phi in [(0.3, 1.1, -2.0), (-0.3, -1.1, 2.0)]:
        ref = alm.copy()
        hp.rotate_alm(ref, psi=psi, theta=theta, phi=phi, lmax=lmax)
        assert np.abs(out - ref).max() > 0.1


def test_rotation_of_the_map_is_the_active_rotation(blocks64):
    """I'(n) = I(R^-1 n), checked by exact band-limited synthesis at arbitrary points."""
    lmax = 12
    a = realify(_random_alm(lmax, 2), lmax)
    R = rotation_matrix_zyz(0.4, 0.9, -1.3)
    b = np.asarray(rotate_matrix(jnp.asarray(a), R, blocks64))
    rng = np.random.default_rng(8)
    n = rng.normal(size=(3, 50))
    n /= np.linalg.norm(n, axis=0)
    np.testing.assert_allclose(_synth(b, lmax, R @ n), _synth(a, lmax, n), atol=1e-11)
    assert np.abs(_synth(b, lmax, n) - _synth(a, lmax, n)).max() > 0.1  # the rotation does something


def _synth(a, lmax, vec):
    """Band-limited synthesis at arbitrary unit vectors (3, P) via gcrsky's real basis."""
    from gcrsky.sphere import real_basis

    theta = np.arccos(np.clip(vec[2], -1, 1))
    phi = np.arctan2(vec[1], vec[0])
    return np.asarray(real_basis(lmax, theta, phi)) @ a


def test_diagonal_case_equals_earth_rotation_phase(blocks64):
    lmax = 10
    a = jnp.asarray(realify(_random_alm(lmax, 3), lmax))
    # rotate(a, d) is I(RA + d), i.e. the active rotation by Rz(-d)
    np.testing.assert_allclose(rotate_euler(a, -0.37, 0.0, 0.0, blocks64), rotate(a, 0.37), atol=1e-13)


def test_transpose_is_the_adjoint_and_inverse_composes(blocks64):
    lmax = 15
    rng = np.random.default_rng(4)
    a, b = (jnp.asarray(rng.normal(size=n_params(lmax))) for _ in range(2))
    ang = (0.2, 2.1, -0.8)
    lhs = float(b @ rotate_euler(a, *ang, blocks64))
    rhs = float(a @ rotate_euler_transpose(b, *ang, blocks64))
    assert abs(lhs - rhs) < 1e-12 * abs(lhs) + 1e-12
    back = rotate_euler(rotate_euler(a, *ang, blocks64), -ang[2], -ang[1], -ang[0], blocks64)
    np.testing.assert_allclose(back, a, atol=1e-12)
    # composition: D(R1) D(R2) = D(R1 R2)
    R1, R2 = rotation_matrix_zyz(0.5, 0.3, 0.1), rotation_matrix_zyz(-1.0, 2.0, 0.4)
    np.testing.assert_allclose(
        rotate_matrix(rotate_matrix(a, R2, blocks64), R1, blocks64), rotate_matrix(a, R1 @ R2, blocks64), atol=1e-12
    )


def test_traced_angles_one_compilation_vmap_and_grad(blocks64):
    lmax = 10
    a = jnp.asarray(realify(_random_alm(lmax, 5), lmax))
    f = jax.jit(rotate_euler)
    outs = [f(a, x, 0.5 * x, -x, blocks64) for x in (0.1, 0.2, 0.3)]
    assert f._cache_size() == 1  # angles are traced: no recompilation per angle
    batch = jax.vmap(lambda x: rotate_euler(a, x, 0.5 * x, -x, blocks64))(jnp.array([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(batch, jnp.stack(outs), atol=1e-13)
    # derivative in beta against a central difference
    g = jax.grad(lambda b: jnp.sum(rotate_euler(a, 0.3, b, 0.2, blocks64) ** 2 * jnp.arange(a.size)))(0.7)
    h = 1e-5
    fd = (
        jnp.sum(rotate_euler(a, 0.3, 0.7 + h, 0.2, blocks64) ** 2 * jnp.arange(a.size))
        - jnp.sum(rotate_euler(a, 0.3, 0.7 - h, 0.2, blocks64) ** 2 * jnp.arange(a.size))
    ) / (2 * h)
    assert abs(float(g) - float(fd)) < 1e-6 * abs(float(fd))


@pytest.mark.parametrize(
    "angles", [(0.3, 1.1, -2.0), (-3.0, 0.2, 3.1), (1.0, 0.0, 0.0), (1.0, np.pi, 0.0), (0.0, 1e-13, 0.5)]
)
def test_euler_zyz_round_trip(angles):
    R = rotation_matrix_zyz(*angles)
    np.testing.assert_allclose(rotation_matrix_zyz(*euler_zyz(R)), R, atol=1e-12)


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="proper rotation"):
        euler_zyz(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="3x3"):
        euler_zyz(np.eye(2))
    with pytest.raises(ValueError, match="Wigner blocks go to lmax=2"):
        rotate_euler(jnp.zeros(n_params(3)), 0.0, 0.1, 0.0, wigner_blocks(2))
    with pytest.raises(MemoryError, match="GiB"):
        wigner_blocks(2000)


def test_lm_grid_round_trip():
    lmax = 7
    a = jnp.asarray(np.random.default_rng(6).normal(size=n_params(lmax)))
    g = to_lm_grid(a)
    assert g.shape == (lmax + 1, lmax + 1)
    assert float(jnp.abs(jnp.triu(g, 1)).max()) == 0.0  # m > l is empty
    np.testing.assert_array_equal(from_lm_grid(g), a)
