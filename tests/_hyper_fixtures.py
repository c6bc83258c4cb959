"""Shared small problems and helpers of the gradient and evidence tests."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array
from gcrsky.model import build_problem, dense_matrix, isotropic_prior
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.solvers import CGOptions, CholeskyOptions, EighOptions, MModeOptions

LMAX, NSIDE = 4, 16
PATHS = {
    "cg": CGOptions(tol=1e-12),
    "cg-matrix-free": CGOptions(tol=1e-12, dense=False),
    "cg-jax-engine": CGOptions(tol=1e-12, engine="jax"),
    "cholesky": CholeskyOptions(),
    "eigh": EighOptions(),
    "mmode": MModeOptions(),
}


def small_problem(*, flags=None, nf=2, nt=None, seed=0, lmax=LMAX):
    """The 10-antenna hexagon at ``lmax`` (default 4), nside 16, ``nf`` channels, an isotropic
    prior whose mean is itself a prior draw, a truth drawn around it, sigma = 0.05."""
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    n = (lmax + 1) ** 2
    cl = 50.0 / (1.0 + np.arange(lmax + 1)) ** 2
    prior = isotropic_prior(np.stack([cl * (1 + f) for f in range(nf)]), n)
    rng = np.random.default_rng(seed)
    prior = prior._replace(mean=np.asarray(prior.inv_var) ** -0.5 * rng.standard_normal((nf, n)))
    truth = np.asarray(prior.mean) + np.asarray(prior.inv_var) ** -0.5 * rng.standard_normal((nf, n))
    nt = 2 * lmax + 3 if nt is None else nt
    lsts = 2 * np.pi * np.arange(nt) / nt  # uniform full day: m-mode applies (without flags)
    return build_problem(arr, 100e6 + 1e6 * np.arange(nf), lsts, lmax, NSIDE, a_true=truth, sigma=0.05,
                         prior=prior, flags=flags, key=jax.random.PRNGKey(seed))


def scaled(system, t):
    """theta = (log noise-variance scale, log prior-variance scale)."""
    return system._replace(
        inv_noise=system.inv_noise * jnp.exp(-t[0]),
        prior=system.prior._replace(inv_var=system.prior.inv_var * jnp.exp(-t[1])),
    )


THETA = jnp.array([0.3, -0.2])


def dense_wiener_derivative(system, t):
    """d a_wf / d theta by dense NumPy algebra: da = P^-1 (db - dP a)."""
    s0 = system
    A = np.asarray(precision_matrix(s0)) - np.stack([np.diag(v) for v in np.asarray(s0.prior.inv_var)])
    c = np.asarray(wiener_rhs(s0)) - np.asarray(s0.prior.inv_var * s0.prior.mean)
    D = np.asarray(s0.prior.inv_var)
    a0 = np.asarray(s0.prior.mean)
    e0, e1 = np.exp(-float(t[0])), np.exp(-float(t[1]))
    out = np.zeros((2,) + a0.shape)
    for f in range(a0.shape[0]):
        P = e0 * A[f] + e1 * np.diag(D[f])
        b = e0 * c[f] + e1 * D[f] * a0[f]
        a = np.linalg.solve(P, b)
        out[0, f] = np.linalg.solve(P, -e0 * c[f] + e0 * A[f] @ a)
        out[1, f] = np.linalg.solve(P, -e1 * D[f] * a0[f] + e1 * D[f] * a)
    return out


def central(f, t, h=1e-5):
    """Central differences of a scalar function of a 1-d array."""
    return np.array([(f(t + h * e) - f(t - h * e)) / (2 * h) for e in np.eye(t.size)])


def numpy_log_evidence(system):
    """scipy's multivariate normal log density of the realified unflagged data."""
    X = np.asarray(dense_matrix(system.op))  # (Nf, Nt, Nbl, n)
    out = []
    for f in range(X.shape[0]):
        W = np.asarray(system.inv_noise[f])
        m = W > 0
        Xf = X[f][m]
        Xr = np.concatenate([Xf.real, Xf.imag])
        d = np.asarray(system.data[f])[m]
        cov = Xr @ np.diag(1.0 / np.asarray(system.prior.inv_var[f])) @ Xr.T + np.diag(np.concatenate([1 / W[m]] * 2))
        out.append(stats.multivariate_normal(Xr @ np.asarray(system.prior.mean[f]), cov).logpdf(
            np.concatenate([d.real, d.imag])))
    return np.array(out)
