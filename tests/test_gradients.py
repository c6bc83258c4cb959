"""Gradients through every solve: the Wiener filter, the draws, the Gibbs step (issue 11).

References, independent of gcrsky's solvers: the Wiener filter's derivative from
dense NumPy algebra (``da = P^-1 (db - dP a)``), and central finite differences of
gcrsky's own functions where no closed form is simpler (draws, the Gibbs chain).

Tolerances: the dense paths and CG at tol 1e-12 agree with the closed form to ~1e-10
relative (1e-7 allowed); central differences with h = 1e-5 have truncation error
~h^2 ~ 1e-10 relative and rounding ~1e-16 / h, plus the solves' tolerance divided by
h (1e-12 / 1e-5 = 1e-7), hence the 1e-6 used for them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _hyper_fixtures import PATHS, THETA, central, dense_wiener_derivative, scaled, small_problem

import gcrsky
from gcrsky.solvers import CGOptions


@pytest.fixture(scope="module")
def base():
    return small_problem().system()


@pytest.mark.parametrize("path", list(PATHS))
def test_wiener_filter_gradient_equals_dense_numpy(base, path):
    jac = jax.jacfwd(lambda t: gcrsky.wiener_filter_system(scaled(base, t), options=PATHS[path])[0])(THETA)
    ref = np.moveaxis(dense_wiener_derivative(base, THETA), 0, -1)
    assert np.max(np.abs(np.asarray(jac) - ref)) < 1e-7 * np.max(np.abs(ref))
    g = jax.grad(lambda t: jnp.sum(gcrsky.wiener_filter_system(scaled(base, t), options=PATHS[path])[0] ** 2))(THETA)
    a = gcrsky.wiener_filter_system(scaled(base, THETA), options=PATHS[path])[0]
    ref_g = np.einsum("fk,fkt->t", 2 * np.asarray(a), ref)
    assert np.max(np.abs(np.asarray(g) - ref_g)) < 1e-7 * np.max(np.abs(ref_g))


@pytest.mark.parametrize("path", list(PATHS))
def test_draw_gradients_equal_finite_differences(base, path):
    key = jax.random.PRNGKey(3)
    weights = jnp.asarray(np.random.default_rng(1).standard_normal((2, 3, base.prior.mean.shape[1])))

    @jax.jit
    def f(t):
        return jnp.sum(weights * gcrsky.sample_system(key, scaled(base, t), 3, options=PATHS[path])[0])

    g = np.asarray(jax.jit(jax.grad(f))(THETA))
    fd = central(lambda t: float(f(jnp.asarray(t))), np.asarray(THETA))
    assert np.max(np.abs(g - fd)) < 1e-6 * np.max(np.abs(fd)), (g, fd)


def test_fixed_key_draw_gradients_depend_on_the_path(base):
    """Different reparameterisations of the same distribution: documented, and checked."""
    key = jax.random.PRNGKey(3)
    grads = {p: np.asarray(jax.grad(lambda t: jnp.sum(gcrsky.sample_system(key, scaled(base, t), 2, options=PATHS[p])[0]))(THETA))
             for p in ("cg", "cholesky", "eigh")}
    assert np.abs(grads["cg"] - grads["cholesky"]).max() > 1e-3 * np.abs(grads["cg"]).max()
    assert np.abs(grads["cholesky"] - grads["eigh"]).max() > 1e-3 * np.abs(grads["cg"]).max()


def test_gcr_step_in_scan_differentiates(base):
    key = jax.random.PRNGKey(5)

    @jax.jit
    def chain_mean(t):
        sys_t = scaled(base, t)

        def body(state, k):
            state, _ = gcrsky.gcr_step(k, state, sys_t, options=CGOptions(tol=1e-12, dense=False))
            return state, state.position

        _, pos = jax.lax.scan(body, gcrsky.gcr_init(sys_t.prior.mean), jax.random.split(key, 4))
        return jnp.sum(pos**2)

    g = np.asarray(jax.jit(jax.grad(chain_mean))(THETA))
    fd = central(lambda t: float(chain_mean(jnp.asarray(t))), np.asarray(THETA))
    assert np.max(np.abs(g - fd)) < 1e-6 * np.max(np.abs(fd))


def test_jvp_vmap_and_jit_over_hyperparameters(base):
    f = jax.jit(lambda t: gcrsky.wiener_filter_system(scaled(base, t), options=CGOptions(tol=1e-12))[0])
    thetas = jnp.stack([THETA, THETA + 0.1, THETA - 0.1])
    batched = jax.vmap(f)(thetas)
    for i in range(3):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(f(thetas[i])), rtol=1e-9, atol=0)
    _, tangent = jax.jvp(f, (THETA,), (jnp.array([1.0, 0.0]),))
    ref = dense_wiener_derivative(base, THETA)[0]
    assert np.max(np.abs(np.asarray(tangent) - ref)) < 1e-7 * np.max(np.abs(ref))


@pytest.mark.parametrize("path", ["cg", "cholesky", "mmode"])
def test_gradients_reach_every_floating_leaf_of_the_system(base, path):
    """Directional derivatives along random directions of the data, inverse noise, prior mean,
    prior inverse variance and the response (real and imaginary parts) equal central differences."""
    rng = np.random.default_rng(8)
    leaves, treedef = jax.tree_util.tree_flatten(base)
    dirs = [jnp.asarray(rng.standard_normal(np.shape(x)) + (1j * rng.standard_normal(np.shape(x))
                                                            if jnp.iscomplexobj(x) else 0.0)) * 1e-2 * jnp.abs(x).mean()
            for x in leaves]
    names = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(base)[0]]
    if path == "mmode":  # m-mode is exact for time-stationary noise: perturb it that way (see solvers.mmode)
        k = names.index(".inv_noise")
        dirs[k] = jnp.broadcast_to(dirs[k][:, :1], dirs[k].shape)
    weights = jnp.asarray(rng.standard_normal(base.prior.mean.shape))

    @jax.jit  # one compilation for every leaf: the direction is an argument (zero but for one leaf)
    def along(eps, direction):
        moved = [x + eps * d for x, d in zip(leaves, direction)]
        return jnp.sum(weights * gcrsky.wiener_filter_system(jax.tree_util.tree_unflatten(treedef, moved),
                                                             options=PATHS[path])[0])

    grad_along = jax.jit(jax.grad(along))
    checked = []
    for k, name in enumerate(names):
        if name.endswith(".angles"):  # rotation angles differentiate too, but are not a posterior input here
            continue
        direction = [d if i == k else jnp.zeros_like(d) for i, d in enumerate(dirs)]
        g = float(grad_along(0.0, direction))
        fd = float((along(1e-5, direction) - along(-1e-5, direction)) / 2e-5)
        assert abs(g - fd) <= 1e-6 * max(abs(fd), 1e-12), (name, g, fd)
        checked.append(name)
    assert {".data", ".inv_noise", ".prior.mean", ".prior.inv_var", ".op.response"} <= set(checked), checked
