"""The overall amplitude (bandpass) inferred with the sky, collapsed and exact (DESIGN section 14).

Data that are not absolutely calibrated see the sky through an unknown amplitude per channel:
``d_f = q_f D_f X_f a_f + n_f`` with ``q_f > 0`` (``data = q x the model of the sky in K``: ``q`` is
what multiplies a calibrated visibility) and ``D`` the per-row gain factor (1, or the per-antenna
gains of :mod:`gcrsky.inference.gains`).  ``(q, a) -> (c q, a / c)`` is an exact symmetry; only the
prior on the sky breaks it.  The prior is a sky model in K known up to an overall factor:

    ``a_f = c (a0_f + delta_f)``,  ``delta_f ~ N(0, S_f)``,  ``c ~ N(1, sigma_c^2)`` (c > 0),

with ``a0`` the sky model's coefficients (the GSM through :func:`gcrsky.model.observed.default_prior`)
and ``S`` the prior's covariance (the power the model lacks at the data's scales).  The scale
``c`` multiplies the model's mean *and* its fluctuations: the sky model's brightness scale is
uncertain as a whole (the GSM's, about 10 %: module :mod:`gcrsky.run.amplitude`).  The data
then depend on ``u_f = q_f c`` and ``delta`` only, so the posterior factorises exactly:

* ``u_f | d`` per channel, 1-D, from its exact marginal (``delta`` integrated out): in the
  whitened data space (:mod:`gcrsky.solvers.dataspace`'s rows, ``y = W^1/2 d``,
  ``m = W^1/2 D X a0``, ``G = W^1/2 D X S X^T D^H W^1/2 = V diag(lambda) V^T``) ``y ~ N(u m, I + u^2 G)``,

      ``log p(d_f | u) = -1/2 sum_k [(y~_k - u m~_k)^2 / (1 + u^2 lambda_k) + log(1 + u^2 lambda_k)]
      - 1/2 [N_keep log 2 pi - log det W]``,

  ``y~ = V^T y``, ``m~ = V^T m``: ``O(N_d)`` per value after one ``eigh`` per channel.  The prior
  is uniform in ``log u`` over :data:`LOG_U_RANGE` (scale-free, proper).  It is drawn by inverting
  its CDF on a grid (:func:`draw_log_u`): independent draws, no chain;
* ``c`` from its prior (the data say nothing about it given ``u``): ``q_f = u_f / c``;
* ``delta | u, d`` exactly (Hoffman & Ribak in data space, :func:`sky_given`), ``a = c (a0 + delta)``.

With gains the per-antenna perturbations ``theta`` are a Gibbs block (:func:`amplitude_sweep`):
``theta | q a`` (:func:`gcrsky.inference.gains.theta_draw`), then ``(u, delta) | theta`` jointly as
above with ``D = D(theta)``: the amplitude-sky degeneracy is integrated out in every sweep, not
crawled along.

Grid accuracy: the density is evaluated on :data:`COARSE` points across :data:`LOG_U_RANGE`, then on
:data:`FINE` points across the coarse cells within :data:`GRID_DROP` of the maximum (at least one cell
each side), and sampled by linear interpolation of the trapezoid CDF: the draws' quantiles are exact
to ``O(h^2)`` of the fine spacing ``h`` (``tests/test_amplitude.py`` compares them with an independent
quadrature of the same marginal).

Everything is pure JAX (``jit``/``vmap``/``grad``); the set-up (:func:`amplitude_setup`) forms the
data-space Gram matrix ``(Nf, N_d, N_d)`` once (:func:`gcrsky.solvers.dataspace.dataspace_matrix`).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.system import LinearSystem
from ..solvers.dataspace import (
    check_proper_prior,
    dataspace_matrix,
    dataspace_memory_bytes,
    from_rows,
    sqrt_weights,
    to_rows,
    whitened_adjoint,
    whitened_apply,
)
from .gains import GainBlock, theta_draw

__all__ = [
    "COARSE",
    "FINE",
    "GRID_DROP",
    "LOG_U_RANGE",
    "MAX_LOG_U_SD",
    "AmplitudeEigen",
    "AmplitudeEvidence",
    "AmplitudeFixed",
    "AmplitudeState",
    "amplitude_eigen",
    "amplitude_log_prior",
    "amplitude_memory_bytes",
    "amplitude_setup",
    "amplitude_sweep",
    "draw_log_u",
    "log_evidence_over_u",
    "local_modes",
    "log_marginal",
    "scale_response",
    "sky_given",
    "wiener_given",
]

#: Support of the uniform prior on ``ln u`` (``u`` from 1e-9 to 1e4: raw correlator units to Jy per K x 1e4).
LOG_U_RANGE = (float(np.log(1e-9)), float(np.log(1e4)))
#: Points of the coarse and the fine grid of :func:`draw_log_u`.
COARSE = 2048
FINE = 4096
#: The fine grid spans the coarse cells whose log density is within this of the maximum.
GRID_DROP = 40.0


class AmplitudeFixed(eqx.Module):
    """The data-space quantities of the amplitude's marginal (:func:`amplitude_setup`; a PyTree).

    Attributes:
        system: the sky's system with the raw data ``d``, ``W`` and the prior ``(a0, S)`` (Nf, ...).
        gram: ``G = Y S Y^T`` (Nf, N_d, N_d), ``Y = W^1/2 X`` realified (rows of
            :func:`gcrsky.solvers.dataspace.to_rows`), no gains.
        y: (Nf, N_d) whitened data rows ``W^1/2 d`` (0 on flagged samples).
        m: (Nf, N_d) whitened model rows ``Y a0``.
        n_keep: (Nf,) unflagged real data values.
        logdet_w: (Nf,) ``log det W`` over them.
    """

    system: LinearSystem
    gram: jax.Array
    y: jax.Array
    m: jax.Array
    n_keep: jax.Array
    logdet_w: jax.Array


class AmplitudeEigen(NamedTuple):
    """``G_D = B G B^T = V diag(lam) V^T`` for a gain factor D, and the data and model in that basis.

    Attributes:
        lam: (Nf, N_d) eigenvalues (>= 0 up to rounding); vecs: (Nf, N_d, N_d);
        yt: (Nf, N_d) ``V^T y``; mt: (Nf, N_d) ``V^T B m``; factor: (Nf, Nt, Nbl) complex D (or None: 1).
    """

    lam: jax.Array
    vecs: jax.Array
    yt: jax.Array
    mt: jax.Array
    factor: jax.Array | None


class AmplitudeState(NamedTuple):
    """The chain (with gains): ``log_u`` (Nf,), ``delta`` (Nf, n) the sky's deviation from the model, ``theta`` (P,)."""

    log_u: jax.Array
    delta: jax.Array
    theta: jax.Array


#: Copies of the per-channel ``N_d x N_d`` Gram matrix an amplitude chain holds (the matrix, the gained
#: one, its eigenvectors and the eigendecomposition's workspace): XLA's memory analysis of a segment of
#: sweeps on the 64 H1C channels (N_d = 1120) gives 2.8-3.0 GB of temporaries at lmax 195-246, ~4.5 copies
#: beside the Gram matrix's own; 9 bounds it.
GRAM_COPIES = 9.0


def amplitude_memory_bytes(system: LinearSystem, kept: int = 1) -> float:
    """Estimated peak bytes (float64) of an amplitude run beyond the system: the data-space set-up
    (:func:`gcrsky.solvers.dataspace.dataspace_memory_bytes`), :data:`GRAM_COPIES` copies of the Gram
    matrices (``8 Nf N_d^2`` each) and ``kept`` states of the sky (``8 Nf n`` each, twice: the draws and
    the chain's copy)."""
    nf, nt, nbl = (int(x) for x in system.data.shape)
    nd, n = 2 * nt * nbl, int(system.prior.mean.shape[-1])
    return dataspace_memory_bytes(system) + GRAM_COPIES * 8.0 * nf * nd * nd + 2 * 8.0 * max(1, kept) * nf * n


def amplitude_setup(system: LinearSystem, chunk: int | None = None) -> AmplitudeFixed:
    """The Gram matrix and whitened rows of ``system`` (raw data, the sky model's prior).

    Raises:
        ValueError: a flat (improper) prior direction (``S`` must exist).
    """
    check_proper_prior(system)
    sw = sqrt_weights(system)
    G = dataspace_matrix(system, chunk) - jnp.eye(2 * system.data.shape[1] * system.data.shape[2])
    y = to_rows(jnp.where(system.inv_noise > 0, sw * system.data, 0.0))
    m = whitened_apply(system, sw, system.prior.mean)
    pos = system.inv_noise > 0
    n_keep = 2 * jnp.sum(pos, axis=(1, 2))
    logdet_w = 2 * jnp.sum(jnp.where(pos, jnp.log(jnp.where(pos, system.inv_noise, 1.0)), 0.0), axis=(1, 2))
    return AmplitudeFixed(system, G, y, m, n_keep, logdet_w)


def _gain_rows(factor, u, nt: int, nbl: int):
    """``B u``: the rows (..., N_d) of complex samples multiplied by ``factor`` (Nf, Nt, Nbl)."""
    return to_rows(factor * from_rows(u, nt, nbl))


def amplitude_eigen(fixed: AmplitudeFixed, factor=None) -> AmplitudeEigen:
    """The eigendecomposition of the gained Gram matrix per channel (``O(Nf N_d^3)``).

    Args:
        fixed: :func:`amplitude_setup`'s.
        factor: (Nf, Nt, Nbl) complex per-row gain factor ``D`` (without the amplitude), or None (1).
    """
    G, m = fixed.gram, fixed.m
    if factor is not None:
        _, nt, nbl = fixed.system.data.shape
        f = jnp.asarray(factor)[:, None]
        BGt = _gain_rows(f, jnp.swapaxes(G, -1, -2), nt, nbl)  # (B G)^T: B on each column of G
        G = _gain_rows(f, jnp.swapaxes(BGt, -1, -2), nt, nbl)  # (B G) B^T
        G = 0.5 * (G + jnp.swapaxes(G, -1, -2))
        m = _gain_rows(f[:, 0], m, nt, nbl)
    lam, V = jnp.linalg.eigh(G)
    yt = jnp.einsum("fkj,fk->fj", V, fixed.y)
    mt = jnp.einsum("fkj,fk->fj", V, m)
    return AmplitudeEigen(jnp.maximum(lam, 0.0), V, yt, mt, factor)


def log_marginal(fixed: AmplitudeFixed, eig: AmplitudeEigen, log_u) -> jax.Array:
    """``log p(d_f | u_f)`` (Nf,) with the sky integrated out (module docstring), normalised.

    Args:
        log_u: (Nf,) or (k, Nf) natural logarithm of ``u = q c``.
    """
    u2 = jnp.exp(2 * jnp.asarray(log_u))[..., None]
    u = jnp.exp(jnp.asarray(log_u))[..., None]
    den = 1.0 + u2 * eig.lam
    quad = jnp.sum((eig.yt - u * eig.mt) ** 2 / den, axis=-1)
    return -0.5 * (quad + jnp.sum(jnp.log(den), axis=-1) + fixed.n_keep * jnp.log(2 * jnp.pi) - fixed.logdet_w)


def _grid(logp_fn):
    """The two-level grid of ``exp(logp_fn)`` on :data:`LOG_U_RANGE` (module docstring): ``(xf, lf)`` the fine grid
    (:data:`FINE` points across the coarse cells within :data:`GRID_DROP` of the maximum) and its log density."""
    lo, hi = LOG_U_RANGE
    xc = jnp.linspace(lo, hi, COARSE)
    lc = logp_fn(xc)
    lc = jnp.where(jnp.isfinite(lc), lc, -jnp.inf)
    top = jnp.max(lc)
    idx = jnp.arange(COARSE)
    near = lc > top - GRID_DROP
    first = jnp.maximum(jnp.min(jnp.where(near, idx, COARSE)) - 1, 0)
    last = jnp.minimum(jnp.max(jnp.where(near, idx, -1)) + 1, COARSE - 1)
    xf = jnp.linspace(xc[first], xc[last], FINE)
    return xf, logp_fn(xf)


def _grid_draw(key, logp_fn, ndraws: int):
    """``ndraws`` draws of a scalar from ``exp(logp_fn(x))`` on :data:`LOG_U_RANGE` by the two-level grid."""
    xf, lf = _grid(logp_fn)
    p = jnp.exp(lf - jnp.max(lf))
    cum = jnp.concatenate([jnp.zeros(1), jnp.cumsum(0.5 * (p[1:] + p[:-1]) * jnp.diff(xf))])  # un-normalised CDF
    mass = jax.random.uniform(key, (ndraws,), xf.dtype) * cum[-1]
    k = jnp.clip(jnp.searchsorted(cum, mass, side="right") - 1, 0, FINE - 2)
    h = xf[k + 1] - xf[k]
    p0 = p[k]
    slope = (p[k + 1] - p0) / h
    left = mass - cum[k]
    # the density is linear in the cell: p0 t + slope t^2 / 2 = left, the root in [0, h]
    den = p0 + jnp.sqrt(jnp.maximum(p0**2 + 2 * slope * left, 0.0))
    t = jnp.where(den > 0, 2 * left / jnp.where(den > 0, den, 1.0), 0.5 * h)
    return xf[k] + jnp.clip(t, 0.0, h)


def draw_log_u(key: jax.Array, fixed: AmplitudeFixed, eig: AmplitudeEigen, ndraws: int) -> jax.Array:
    """``ndraws`` independent draws (ndraws, Nf) of ``ln u_f`` from ``p(u_f | d)`` (uniform prior in ``ln u``).

    Channel ``f`` uses ``jax.random.split(key, Nf)[f]``; the grid and its accuracy: module docstring.
    A channel without unflagged data draws from the prior's range (its density is flat).
    """
    nf = eig.lam.shape[0]

    def one(k, lam, yt, mt, nk, lw):
        e = AmplitudeEigen(lam[None], None, yt[None], mt[None], None)
        f = AmplitudeFixed(None, None, None, None, nk[None], lw[None])
        return _grid_draw(k, lambda x: log_marginal(f, e, x[:, None])[:, 0], ndraws)

    out = jax.vmap(one)(jax.random.split(key, nf), eig.lam, eig.yt, eig.mt, fixed.n_keep, fixed.logdet_w)
    return out.T


def _inverse_d(eig: AmplitudeEigen, u, r):
    """``(I + u^2 G_D)^-1 r`` for rows r (Nf, N_d) and u (Nf,)."""
    rt = jnp.einsum("fkj,fk->fj", eig.vecs, r) / (1.0 + (u**2)[:, None] * eig.lam)
    return jnp.einsum("fkj,fj->fk", eig.vecs, rt)


def _b(fixed, eig, rows, conj=False):
    if eig.factor is None:
        return rows
    _, nt, nbl = fixed.system.data.shape
    f = jnp.conj(eig.factor) if conj else eig.factor
    return _gain_rows(f, rows, nt, nbl)


def wiener_given(fixed: AmplitudeFixed, eig: AmplitudeEigen, u) -> jax.Array:
    """The posterior mean (Nf, n) of ``delta`` given ``u`` (Nf,) (and the eigen's gain factor):
    ``u S Y^T B^T (I + u^2 G_D)^-1 (y - u B m)``; the sky's is ``c (a0 + delta)``."""
    system = fixed.system
    s = 1.0 / system.prior.inv_var
    sw = sqrt_weights(system)
    x = _inverse_d(eig, u, fixed.y - u[:, None] * _b(fixed, eig, fixed.m))
    return u[:, None] * s * whitened_adjoint(system, sw, _b(fixed, eig, x, conj=True))


def sky_given(key: jax.Array, fixed: AmplitudeFixed, eig: AmplitudeEigen, u) -> jax.Array:
    """One exact draw (Nf, n) of ``delta | u, D, d`` (Hoffman & Ribak): ``delta_u ~ N(0, S)``, ``z ~ N(0, I)``
    on the unflagged rows, ``delta = delta_u + u S Y^T B^T (I + u^2 G_D)^-1 (y - u B (m + Y delta_u) - z)``."""
    system = fixed.system
    nf, n = system.prior.mean.shape
    s = 1.0 / system.prior.inv_var
    sw = sqrt_weights(system)
    ka, kn = jax.random.split(key)
    delta = jnp.sqrt(s) * jax.random.normal(ka, (nf, n), fixed.y.dtype)
    keep = to_rows(jnp.where(system.inv_noise > 0, 1.0 + 1.0j, 0.0)).real
    z = keep * jax.random.normal(kn, fixed.y.shape, fixed.y.dtype)
    r = fixed.y - u[:, None] * _b(fixed, eig, fixed.m + whitened_apply(system, sw, delta)) - z
    x = _inverse_d(eig, u, r)
    return delta + u[:, None] * s * whitened_adjoint(system, sw, _b(fixed, eig, x, conj=True))


def amplitude_sweep(key: jax.Array, state: AmplitudeState, fixed: AmplitudeFixed, block: GainBlock | None,
                    free_u: bool = True):
    """One sweep of the chain with gains: ``theta | q a`` then ``(u, delta) | theta`` (the amplitude collapsed).

    ``block`` None: no gains (``theta`` stays empty and the sweep is an independent draw).  ``free_u``
    False holds ``u`` at the state's (a burn-in's first sweeps, while the gains settle from a start far
    from them: the data's misfit would otherwise push ``u`` anywhere).  Returns ``(state, eigen)`` (the
    eigendecomposition at the new ``theta``'s gain factor).
    """
    from ..model.gains import gain_factor

    k_t, k_u, k_s = jax.random.split(key, 3)
    system = fixed.system
    theta = state.theta
    factor = None
    if block is not None:
        u = jnp.exp(state.log_u)
        from ..model.operator import apply

        vis = u[:, None, None] * apply(system.op, system.prior.mean + state.delta)
        theta = theta_draw(k_t, block, system.data, system.inv_noise, vis, 1.0)
        factor = gain_factor(block.model, theta, 1.0) * block.pair_gains
    eig = amplitude_eigen(fixed, factor)
    log_u = draw_log_u(k_u, fixed, eig, 1)[0] if free_u else state.log_u
    delta = sky_given(k_s, fixed, eig, jnp.exp(log_u))
    return AmplitudeState(log_u, delta, theta), eig


def amplitude_log_prior(log_u) -> jax.Array:
    """The normalised log density of the amplitude's prior at ``log_u`` (Nf,): uniform in ``ln u`` over
    :data:`LOG_U_RANGE` per channel (-inf outside); what :func:`draw_log_u` samples under."""
    lo, hi = LOG_U_RANGE
    log_u = jnp.asarray(log_u)
    inside = jnp.all((log_u >= lo) & (log_u <= hi))
    return jnp.where(inside, -log_u.size * jnp.log(hi - lo), -jnp.inf)


def scale_response(system: LinearSystem, log_u) -> LinearSystem:
    """``system`` with its response (Nf, Nbl, n) multiplied by ``u_f = exp(log_u_f)`` per channel (the data
    ``u X a``: the amplitude is the response's, so the system's evidence is ``p(d | u)``)."""
    resp = system.op.response
    return system._replace(op=system.op._replace(response=resp * jnp.exp(jnp.asarray(log_u))[:, None, None]
                                                  .astype(resp.dtype)))


class AmplitudeEvidence(NamedTuple):
    """What :func:`log_evidence_over_u` returns (per channel, (Nf,)).

    Attributes:
        log_z: ``log int p(d_f | u) p(ln u) d ln u`` (the prior :func:`amplitude_log_prior`'s).
        log_u: the maximum of ``p(d_f | u)`` in ``ln u`` (on the fine grid).
        sd: the posterior standard deviation of ``ln u``.
        identified: the data determine ``u``: ``sd`` < :data:`MAX_LOG_U_SD` and the maximum at least 4 ``sd``
            inside the prior's range (else the modelled sky is below the noise and ``u`` runs to the range's
            end, a plateau: nothing may be Laplace-approximated in it).
        grid: (COARSE,) the coarse grid of ``ln u`` across the prior's range.
        grid_log_p: (Nf, COARSE) ``log p(d_f | u)`` on it (its local maxima: the modes a mis-specified model
            may have, e.g. a large ``u`` where the sky model no longer constrains the sky and an unconstrained
            sky absorbs what a wrong instrument model misses).
    """

    log_z: jax.Array
    log_u: jax.Array
    sd: jax.Array
    identified: jax.Array
    grid: jax.Array | None = None
    grid_log_p: jax.Array | None = None


#: Posterior sd of ``ln u`` above which :func:`log_evidence_over_u` says the amplitude is not identified.
MAX_LOG_U_SD = 1.0


def log_evidence_over_u(system: LinearSystem) -> AmplitudeEvidence:
    """The sky model's evidence with the overall amplitude per channel integrated out, exactly.

    ``log p(d_f) = log int p(d_f | u) p(ln u) d ln u`` with ``p(d_f | u)`` the exact marginal of the data-space
    form (:func:`log_marginal`; one eigendecomposition of the whitened data-space Gram matrix per channel,
    :func:`amplitude_setup`, then ``O(N_d)`` per value) and the prior uniform in ``ln u`` over :data:`LOG_U_RANGE`
    (:func:`amplitude_log_prior`), integrated by the trapezoid rule on :func:`draw_log_u`'s two-level grid across
    the whole range (the fine grid's spacing ``h``: ``O(h^2)``; ``tests/test_beam_amplitude.py`` checks it
    against the primal evidence, :func:`gcrsky.inference.log_evidence_system` of :func:`scale_response`, on a
    fine grid).  Costs ``O(N_d^3)`` per channel (memory ``8 Nf N_d^2`` bytes).

    Args:
        system: the sky's system (raw data, noise, prior; its response the amplitude's ``u = 1``; a proper prior).
    """
    fixed = amplitude_setup(system)
    eig = amplitude_eigen(fixed)
    lo, hi = LOG_U_RANGE

    def one(lam, yt, mt, nk, lw):
        e = AmplitudeEigen(lam[None], None, yt[None], mt[None], None)
        f = AmplitudeFixed(None, None, None, None, nk[None], lw[None])
        logp = lambda x: log_marginal(f, e, x[:, None])[:, 0]  # noqa: E731
        xf, lf = _grid(logp)
        top = jnp.max(lf)
        p = jnp.exp(lf - top)
        w = 0.5 * (p[1:] + p[:-1]) * jnp.diff(xf)
        mass = jnp.sum(w)
        mid = 0.5 * (xf[1:] + xf[:-1])
        mean = jnp.sum(w * mid) / mass
        sd = jnp.sqrt(jnp.maximum(jnp.sum(w * (mid - mean) ** 2) / mass, 0.0))
        mode = xf[jnp.argmax(lf)]
        ok = (sd < MAX_LOG_U_SD) & (mode - 4 * sd > lo) & (mode + 4 * sd < hi)
        return top + jnp.log(mass) - jnp.log(hi - lo), mode, sd, ok, logp(jnp.linspace(lo, hi, COARSE))

    lz, mode, sd, ok, lc = jax.jit(jax.vmap(one))(eig.lam, eig.yt, eig.mt, fixed.n_keep, fixed.logdet_w)
    return AmplitudeEvidence(lz, mode, sd, ok, jnp.linspace(lo, hi, COARSE), lc)


def local_modes(ev: AmplitudeEvidence, near) -> np.ndarray:
    """(Nf,) the ``ln u`` of each channel's local maximum of ``log p(d_f | u)`` on the coarse grid nearest to
    ``near`` ((Nf,) or scalar ``ln u``, e.g. the autos' ratio's): where a search for the maximum of a richer
    model should also start, when the global one may be a mis-specified model's."""
    lc = np.asarray(ev.grid_log_p)
    x = np.asarray(ev.grid)
    near = np.broadcast_to(np.asarray(near, np.float64), lc.shape[:1])
    out = np.empty(lc.shape[0])
    for f in range(lc.shape[0]):
        v = np.where(np.isfinite(lc[f]), lc[f], -np.inf)
        peak = np.flatnonzero((v[1:-1] >= v[:-2]) & (v[1:-1] >= v[2:])) + 1
        peak = peak if peak.size else np.array([int(np.argmax(v))])
        out[f] = x[peak[np.argmin(np.abs(x[peak] - near[f]))]]
    return out
