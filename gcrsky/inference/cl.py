"""Angular power spectra given the sky: ``sigma_l``, the ``C_l | a`` draw, a power-law family.

For an isotropic Gaussian prior ``a_lm ~ N(0, C_l)`` (fluctuations about the prior
mean), the realified coefficients of degree l are ``2l + 1`` independent normals
(``Var(a_l0) = C_l``, ``Var(Re a_lm) = Var(Im a_lm) = C_l / 2`` for m > 0, see
:func:`gcrsky.prior_from_cl`), and the sufficient statistic is

    sigma_l = (a_l0^2 + 2 sum_{m>0} (Re^2 + Im^2)) / (2l + 1)     (healpy's alm2cl).

Conditionals (``../shared/DESIGN.md`` section 6; Wandelt et al. 2004):

- uniform prior on C_l: ``C_l | a`` is inverse-gamma with scale ``(2l+1) sigma_l / 2``
  and shape ``(2l-1)/2``, i.e. ``(2l+1) sigma_l / C_l ~ chi^2_{2l-1}``;
- Jeffreys prior ``1/C_l``: shape ``(2l+1)/2``, ``chi^2_{2l+1}``.

- a conjugate inverse-gamma prior ``C_l ~ IG(k_l, s_l)`` (``prior="inverse_gamma"``,
  ``hyper=(k, s)``): shape ``k_l + (2l+1)/2``, scale ``s_l + (2l+1) sigma_l / 2``.  Jeffreys
  and uniform are its limits ``(0, 0)`` and ``(-1, 0)``; being proper, it is the one a
  simulation-based calibration can draw ``C_l`` from.

Which prior: the conditionals are proper for every one, but the *posterior* ``p(C_l | d)``
need not be.  With partial sky coverage the data leave some of a degree's modes
unconstrained, so ``p(d | C_l)`` stays finite as ``C_l -> 0`` and the Jeffreys prior
``1/C_l`` makes the posterior improper there: a Gibbs chain drifts to ``C_l = 0``
(measured on the standard case: to 1e-10 of the sky's ``sigma_l``).  Use the uniform
prior (proper there as long as the data constrain a few modes per degree) or a proper
inverse-gamma prior for partial coverage; Jeffreys suits full-sky, well-measured data.

The uniform prior's l = 0 conditional (shape -1/2) is improper: :func:`sample_cl`
then keeps ``C_0`` at the value the caller passes as ``monopole`` (and refuses to run
without one).  The monopole of a radio sky is usually its mean, better modelled by the
prior mean than by a variance.

Power law ``C_l = A (l+1)^-alpha`` (l >= ``lmin``): with the scale-free prior ``1/A``,
``A | alpha, a`` is inverse-gamma with shape ``N/2`` and scale
``S(alpha) = sum_l (2l+1) sigma_l (l+1)^alpha / 2`` (``N = sum_l (2l+1)``), and ``A``
integrates out analytically:

    log p(alpha | a) = log p(alpha) + (alpha / 2) sum_l (2l+1) log(l+1) - (N/2) log S(alpha).

:func:`sample_power_law` draws ``alpha`` from that one-dimensional marginal by slice
sampling (Neal 2003; an exact-invariant MCMC move started at the current alpha) under
a uniform prior on ``alpha_range``, then ``A`` exactly.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..sphere.modes import lmax_from_nparams, mode_table

__all__ = ["CL_PRIORS", "cl_hat", "power_law_log_marginal", "sample_cl", "sample_power_law"]

#: The C_l priors :func:`sample_cl` knows, and the shape offset of each (shape = (2l + 1 + offset) / 2).
CL_PRIORS = {"uniform": -2, "jeffreys": 0}


def _weights(lmax: int):
    tab = mode_table(lmax)
    return tab.ell, np.where(tab.m == 0, 1.0, 2.0)


def cl_hat(a: jax.Array) -> jax.Array:
    """``sigma_l`` of realified coefficients: (..., n) -> (..., lmax+1), K^2.

    Equal to ``healpy.alm2cl`` of the complex (unrealified) coefficients.
    """
    a = jnp.asarray(a)
    lmax = lmax_from_nparams(a.shape[-1])
    ell, w = _weights(lmax)
    sums = jax.ops.segment_sum(jnp.moveaxis(w * a**2, -1, 0), jnp.asarray(ell), num_segments=lmax + 1)
    return jnp.moveaxis(sums, 0, -1) / (2.0 * jnp.arange(lmax + 1) + 1.0)


def sample_cl(
    key: jax.Array, a: jax.Array, *, prior: str = "jeffreys", monopole=None, mean=None, hyper=None
) -> jax.Array:
    """One draw of ``C_l | a`` for every l: (Nf, n) or (n,) -> (Nf, lmax+1) or (lmax+1,), K^2.

    Args:
        key: PRNG key.
        a: realified coefficients (K).
        prior: ``"jeffreys"`` (``1/C_l``; shape ``(2l+1)/2``), ``"uniform"``
            (flat in C_l; shape ``(2l-1)/2``, improper at l = 0) or ``"inverse_gamma"``
            (conjugate; ``hyper``).
        hyper: ``(shape, scale)`` of the inverse-gamma prior (scalars or (lmax+1,);
            scale in K^2), for ``prior="inverse_gamma"`` only.
        monopole: ``C_0`` to keep fixed (scalar or (Nf,)); required for ``"uniform"``,
            optional for ``"jeffreys"`` (None: C_0 is drawn like the others).
        mean: prior mean subtracted first (the spectrum describes ``a - mean``).

    Returns:
        C_l, inverse-gamma draws (scale ``(2l+1) sigma_l / 2`` for the two reference priors).
    """
    if prior not in (*CL_PRIORS, "inverse_gamma"):
        raise ValueError(f"prior must be one of {sorted(CL_PRIORS) + ['inverse_gamma']}, got {prior!r}")
    if (prior == "inverse_gamma") != (hyper is not None):
        raise ValueError("hyper=(shape, scale) goes with prior='inverse_gamma' and only with it")
    if prior == "uniform" and monopole is None:
        raise ValueError(
            "the uniform prior's l = 0 conditional is improper (inverse-gamma shape -1/2): pass monopole=C_0 "
            "to keep C_0 fixed, or use prior='jeffreys'"
        )
    a = jnp.asarray(a)
    if mean is not None:
        a = a - mean
    sig = cl_hat(a)
    lmax = sig.shape[-1] - 1
    two_l1 = 2.0 * jnp.arange(lmax + 1) + 1.0
    if prior == "inverse_gamma":
        shape = jnp.asarray(hyper[0], sig.dtype) + two_l1 / 2.0
        scale = jnp.asarray(hyper[1], sig.dtype) + two_l1 * sig / 2.0
        g = jax.random.gamma(key, jnp.broadcast_to(shape, sig.shape), dtype=sig.dtype)
        cl = scale / g
    else:
        # integer degrees of freedom: (2l+1) sigma_l / C_l ~ chi^2_dof as a sum of dof squared
        # normals (exact, and ~10x faster than jax.random.gamma's rejection loop)
        dof = np.arange(lmax + 1) * 2 + 1 + CL_PRIORS[prior]
        width = int(dof.max())
        z = jax.random.normal(key, sig.shape + (width,), sig.dtype)
        mask = jnp.asarray(np.arange(width)[None, :] < dof[:, None], sig.dtype)
        chi2 = jnp.sum(mask * z**2, axis=-1)
        chi2 = jnp.where(jnp.asarray(dof) > 0, chi2, 1.0)  # l = 0 under "uniform": the monopole below
        cl = two_l1 * sig / chi2
    if monopole is not None:
        cl = cl.at[..., 0].set(jnp.broadcast_to(jnp.asarray(monopole, cl.dtype), cl.shape[:-1]))
    return cl


def _power_law_stats(a, lmin: int):
    sig = cl_hat(a)
    lmax = sig.shape[-1] - 1
    ell = jnp.arange(lmax + 1, dtype=sig.dtype)
    use = ell >= lmin
    k = jnp.where(use, 2.0 * ell + 1.0, 0.0)  # degrees of freedom per l
    return k, k * sig, jnp.log1p(ell), use


def power_law_log_marginal(alpha, a, *, lmin: int = 1):
    """``log p(alpha | a)`` up to a constant, with ``A`` integrated out under ``1/A`` (module docstring).

    Args:
        alpha: slope, scalar (or broadcasting against ``a``'s batch shape).
        a: realified coefficients (..., n), the prior mean already subtracted.
        lmin: the power law covers ``l >= lmin`` (the others do not enter).
    """
    return _log_marginal(jnp.asarray(alpha), *_power_law_stats(a, lmin)[:3])


def _log_marginal(alpha, k, s, logl1):
    alpha = alpha[..., None]
    S = jnp.sum(s * jnp.exp(alpha * logl1), axis=-1) / 2.0
    return 0.5 * alpha[..., 0] * jnp.sum(k * logl1, axis=-1) - 0.5 * jnp.sum(k, axis=-1) * jnp.log(S)


def _slice_1d(key, logp, x0, lo, hi, width, max_steps):
    """One slice-sampling update of a scalar (stepping out, then shrinkage), bounded to [lo, hi]."""
    k_u, k_w, k_s = jax.random.split(key, 3)
    level = logp(x0) + jnp.log(jax.random.uniform(k_u, dtype=x0.dtype))
    left = x0 - width * jax.random.uniform(k_w, dtype=x0.dtype)
    right = left + width

    def out_cond(s):
        edge, i, step = s
        return (i < max_steps) & (edge > lo) & (edge < hi) & (logp(edge) > level)

    left = jax.lax.while_loop(out_cond, lambda s: (s[0] - width, s[1] + 1, s[2]), (left, 0, -1))[0]
    right = jax.lax.while_loop(out_cond, lambda s: (s[0] + width, s[1] + 1, s[2]), (right, 0, 1))[0]
    left, right = jnp.maximum(left, lo), jnp.minimum(right, hi)

    def shrink_cond(s):
        _, _, _, done, i, _ = s
        return (~done) & (i < 64)

    def shrink(s):
        left, right, x, _, i, key = s
        key, sub = jax.random.split(key)
        x = left + (right - left) * jax.random.uniform(sub, dtype=x0.dtype)
        ok = logp(x) > level
        left = jnp.where(~ok & (x < x0), x, left)
        right = jnp.where(~ok & (x >= x0), x, right)
        return left, right, x, ok, i + 1, key

    _, _, x, ok, _, _ = jax.lax.while_loop(shrink_cond, shrink, (left, right, x0, False, 0, k_s))
    return jnp.where(ok, x, x0)


def sample_power_law(
    key: jax.Array,
    a: jax.Array,
    alpha: jax.Array,
    *,
    lmin: int = 1,
    alpha_range: tuple[float, float] = (-2.0, 8.0),
    mean=None,
    width: float = 1.0,
):
    """One Gibbs move of ``(A, alpha) | a`` for ``C_l = A (l+1)^-alpha``, per frequency.

    ``alpha`` by one slice-sampling update of its marginal (``A`` integrated out;
    uniform prior on ``alpha_range``), started at the current ``alpha``; then
    ``A | alpha, a`` exactly (inverse-gamma, shape ``N/2``, prior ``1/A``).

    Args:
        key: PRNG key.
        a: realified coefficients (Nf, n) or (n,), K.
        alpha: current slopes (Nf,) or scalar.
        lmin: the power law covers ``l >= lmin``.
        alpha_range: bounds of the uniform prior on alpha.
        mean: prior mean subtracted from ``a`` first.
        width: the slice sampler's initial bracket (in alpha).

    Returns:
        ``(amplitude, alpha)`` like the batch shape of ``a``; amplitude in K^2.
    """
    a = jnp.asarray(a)
    if mean is not None:
        a = a - mean
    batch = a.shape[:-1]
    a2 = a.reshape((-1, a.shape[-1]))
    alpha = jnp.broadcast_to(jnp.asarray(alpha, a.dtype), batch).reshape(-1)
    lo, hi = (jnp.asarray(x, a.dtype) for x in alpha_range)
    keys = jax.random.split(key, a2.shape[0])

    def one(k, af, al):
        k1, k2 = jax.random.split(k)
        kk, s, logl1, _ = _power_law_stats(af, lmin)  # sufficient statistics, once
        new = _slice_1d(k1, lambda x: _log_marginal(x, kk, s, logl1), al, lo, hi, jnp.asarray(width, a.dtype), 32)
        scale = jnp.sum(s * jnp.exp(new * logl1)) / 2.0
        amp = scale / jax.random.gamma(k2, jnp.sum(kk) / 2.0, dtype=a.dtype)
        return amp, new

    amp, new = jax.vmap(one)(keys, a2, alpha)
    return amp.reshape(batch), new.reshape(batch)
