"""Simulation-based calibration (SBC) of the posterior samplers (Talts et al. 2018).

If ``a ~ prior``, ``d ~ likelihood(. | a)`` and ``a_1..a_L`` are exact, independent
posterior draws given ``d``, then for any fixed functional ``f`` the rank
``r = #{l : f(a_l) < f(a)}`` is uniform on ``{0, ..., L}`` (ties have probability
zero), and ranks of independent replicates are independent.  A sampler that is
too narrow piles ranks at 0 and L, one too wide piles them in the middle, a
biased one tilts them.

Exact tests.  Each rank is turned into a *randomised* probability integral
transform ``u = (r + V) / (L + 1)`` with ``V ~ U(0, 1)`` independent, which is
exactly ``U(0, 1)`` under the null (Czado, Gneiting & Held 2009), and
``z = Phi^-1(u)`` is exactly ``N(0, 1)``.  Per functional, over M replicates:

* uniformity: one-sample Kolmogorov-Smirnov test of ``u``, exact p-value
  (``scipy.stats.kstest(..., method="exact")``);
* dispersion: ``sum z^2 ~ chi2(M)`` exactly, two-sided (too narrow a sampler
  makes it large, too wide small);
* bias: ``sum z / sqrt(M) ~ N(0, 1)`` exactly, two-sided.

A functional's p-value is ``min(1, 3 * min(three))`` and the family p-value
``min(1, F * min over the F functionals)`` (Bonferroni, valid whatever the
dependence between functionals of one replicate), so
``P(p_family <= alpha) <= alpha`` for every ``alpha`` under the null.  Pearson's
chi-square on the rank histogram is reported as well (``p_chi2``) but its
chi-square null is only asymptotic, so it is not part of ``p_family``.

Functionals (:func:`default_functionals`) are fixed before any data are seen:
eigenvectors of the data term in prior-whitened coordinates,
``H = S^1/2 X^T W X S^1/2`` (eigenvalue ``lam``: the data carry ``lam / (1 + lam)``
of the posterior precision along it), largest (data-dominated), smallest
(prior-dominated) and nearest ``lam = 1``, plus individual coefficients.

Everything here is pure (no printing); the :class:`SBCResult` is meant to be
tabulated by the caller (``benchmarks/calibration.py``).
"""

from __future__ import annotations

import logging
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from ..inference.posterior import sample_system
from ..instrument.antennas import HERA_LATITUDE_DEG, hex_array, make_array
from ..instrument.beams import gaussian_beam
from ..model.noise import clean_data, draw_noise, weights_from_flags
from ..model.operator import apply
from ..model.prior import isotropic_prior
from ..model.problem import build_problem
from ..model.system import LinearSystem, fluctuation_rhs, precision_matrix, wiener_rhs
from ..solvers.registry import SolverOptions
from ..sphere.frames import hours_to_rad
from ..sphere.modes import lmax_from_nparams, mode_table

__all__ = [
    "GCRSampler",
    "SBCResult",
    "default_functionals",
    "posterior_ranks",
    "rank_pvalues",
    "run_sbc",
    "simulate_replicates",
    "flagged_example_problem",
    "reference_bug_sampler",
]

log = logging.getLogger(__name__)


class GCRSampler(NamedTuple):
    """gcrsky's exact sampler (:func:`gcrsky.sample_system`) as a hashable callable.

    Any sampler for :func:`run_sbc` is a callable ``(key, system, ndraws) ->
    (draws (Nf, ndraws, n), ok)`` (``ok`` a scalar bool: every solve converged),
    traceable by JAX and hashable (it is a static argument of a jitted function).

    Attributes:
        method: the exact path (``"cholesky"``, ``"cg"``, ``"eigh"``; ``"mmode"`` only
            for systems that pass :func:`gcrsky.solvers.mmode_check`).
        options: the path's options (:mod:`gcrsky.solvers.options`), or None for its
            defaults (CG under a trace: the Nystrom preconditioner).
    """

    method: str = "cholesky"
    options: SolverOptions | None = None

    def __call__(self, key: jax.Array, system: LinearSystem, ndraws: int):
        draws, info = sample_system(key, system, ndraws, method=self.method, options=self.options)
        ok = jnp.all(info.draws.converged) & jnp.all(info.wiener.converged)
        return draws, ok


class SBCResult(NamedTuple):
    """Outcome of :func:`run_sbc` (F functionals, M replicates, L draws each).

    Attributes:
        names: (F,) functional names.
        ranks: (M, F) int ranks of the truth among the draws, in 0..L.
        n_draws: L.
        converged: (M,) every solve of the replicate converged.
        pit: (M, F) randomised PIT values, exactly U(0, 1) under the null.
        mean_z2: (F,) mean of ``z^2`` (1 under the null; about 2 for draws with half
            the right variance, 0.5 for twice).
        p_ks, p_dispersion, p_bias: (F,) exact p-values of the three tests.
        p_chi2: (F,) Pearson chi-square on the rank histogram (asymptotic null; diagnostic).
        p_functional: (F,) ``min(1, 3 min(p_ks, p_dispersion, p_bias))``.
        p_family: ``min(1, F min(p_functional))``: reject calibration at level alpha
            when ``p_family <= alpha`` (false-alarm rate <= alpha, exactly bounded).
    """

    names: tuple
    ranks: np.ndarray
    n_draws: int
    converged: np.ndarray
    pit: np.ndarray
    mean_z2: np.ndarray
    p_ks: np.ndarray
    p_dispersion: np.ndarray
    p_bias: np.ndarray
    p_chi2: np.ndarray
    p_functional: np.ndarray
    p_family: float


def _coeff_name(tab, i: int) -> str:
    ell, m = int(tab.ell[i]), int(tab.m[i])
    if m == 0:
        return f"a_{ell}{m}"
    return f"{'Im' if tab.is_imag[i] else 'Re'} a_{ell}{m}"


def default_functionals(
    system: LinearSystem,
    *,
    freq: int = 0,
    n_data: int = 3,
    n_prior: int = 2,
    n_middle: int = 1,
    coefficients=(0,),
):
    """Fixed linear functionals ``f(a) = sum_{f,i} G[k, f, i] a[f, i]`` for SBC.

    In prior-whitened coordinates ``y = S^-1/2 (a - a0)`` the posterior precision is
    ``I + H`` with ``H = S^1/2 X^T W X S^1/2``; for a unit eigenvector ``u`` of H the
    functional is ``u . y`` (weights ``G = u / S^1/2``).  Needs a proper prior and a
    dense P (small problems).

    Args:
        system: the linear system (its data are not used: the functionals depend only
            on the operator, the noise weights and the prior).
        freq: frequency index the functionals act on (others get zero weight).
        n_data: number of eigenvectors with the largest eigenvalues (data-dominated).
        n_prior: number with the smallest eigenvalues (prior-dominated).
        n_middle: number with eigenvalues closest to 1 (data and prior equal).
        coefficients: indices of single realified coefficients to add.

    Returns:
        (G (F, Nf, n) float64 numpy array, names tuple of F strings, lam (F,)
        whitened data-term eigenvalue of each functional, NaN for coefficients).
    """
    iv = np.asarray(system.prior.inv_var, np.float64)
    if np.any(iv <= 0):
        raise ValueError("SBC functionals need a proper prior (S^-1 > 0 in every mode)")
    nf, n = iv.shape
    P = np.asarray(precision_matrix(system))[freq]
    s = 1.0 / np.sqrt(iv[freq])
    H = s[:, None] * (P - np.diag(iv[freq])) * s[None, :]
    lam, U = np.linalg.eigh(0.5 * (H + H.T))
    picks = []
    top = list(range(n - 1, n - 1 - n_data, -1))
    bottom = list(range(n_prior))
    by_balance = np.argsort(np.abs(np.log(np.maximum(lam, 1e-300))))  # nearest lam = 1 first
    middle = [int(k) for k in by_balance if k not in top + bottom]
    picks += [("data-dominated", k) for k in top]
    picks += [("balanced", k) for k in middle[:n_middle]]
    picks += [("prior-dominated", k) for k in bottom]
    G, names, lams = [], [], []
    for kind, k in picks:
        g = np.zeros((nf, n))
        g[freq] = U[:, k] / s
        G.append(g)
        names.append(f"{kind} eig {k} (lam={lam[k]:.3g})")
        lams.append(lam[k])
    tab = mode_table(lmax_from_nparams(n))
    for i in coefficients:
        g = np.zeros((nf, n))
        g[freq, int(i)] = 1.0
        G.append(g)
        names.append(_coeff_name(tab, int(i)))
        lams.append(np.nan)
    return np.stack(G), tuple(names), np.asarray(lams)


@partial(jax.jit, static_argnames=("n_replicates",))
def simulate_replicates(key: jax.Array, system: LinearSystem, n_replicates: int):
    """Truths from the prior and data from the likelihood, NaN where flagged.

    Truth ``a = a0 + S^1/2 z``; data ``X a + n`` with complex noise whose components
    are each ``N(0, 1 / inv_noise)`` (gcrsky's per-component convention, see
    :mod:`gcrsky.model.noise`; a fractional weight w means variance ``sigma^2 / w``).
    Samples with ``inv_noise == 0`` (flagged) get NaN, as real flagged data may.

    Returns:
        truths (M, Nf, n), data (M, Nf, Nt, Nbl) complex.
    """
    kt, kn = jax.random.split(key)
    mean, iv = system.prior.mean, system.prior.inv_var
    truths = mean + jax.random.normal(kt, (n_replicates,) + mean.shape, mean.dtype) / jnp.sqrt(iv)
    model = jax.vmap(lambda a: apply(system.op, a))(truths)
    flagged = ~(system.inv_noise > 0)
    sigma = 1.0 / jnp.sqrt(jnp.where(flagged, 1.0, system.inv_noise))
    noise = jax.vmap(lambda k: draw_noise(k, sigma))(jax.random.split(kn, n_replicates))
    data = jnp.where(flagged, jnp.nan + 0j, model + noise)
    return truths, data


@partial(jax.jit, static_argnames=("sampler", "n_draws", "batch_size"))
def posterior_ranks(
    key: jax.Array,
    posterior: LinearSystem,
    truths: jax.Array,
    data: jax.Array,
    functionals: jax.Array,
    sampler,
    n_draws: int,
    batch_size: int | None = None,
):
    """Ranks of the truths among ``n_draws`` posterior draws, replicate by replicate.

    Args:
        key: PRNG key; replicate m uses ``jax.random.split(key, M)[m]``.
        posterior: the system whose posterior is sampled; its data are replaced by
            each replicate's (cleaned, finite) data.
        truths: (M, Nf, n); data: (M, Nf, Nt, Nbl) complex, finite.
        functionals: (F, Nf, n) weights.
        sampler: hashable ``(key, system, ndraws) -> (draws (Nf, ndraws, n), ok)``.
        n_draws: L.
        batch_size: replicates vmapped together inside ``lax.map`` (None: one by one).

    Returns:
        ranks (M, F) int in 0..L; converged (M,) bool.
    """
    keys = jax.random.split(key, truths.shape[0])

    def one(args):
        k, a, d = args
        draws, ok = sampler(k, posterior._replace(data=d), n_draws)
        ft = jnp.einsum("kfn,fn->k", functionals, a)
        fd = jnp.einsum("kfn,fln->lk", functionals, draws)
        return jnp.sum(fd < ft[None, :], axis=0), ok

    return jax.lax.map(one, (keys, truths, data), batch_size=batch_size)


def rank_pvalues(ranks, n_draws: int, seed: int = 0) -> dict:
    """Exact calibration tests of SBC ranks (see the module docstring).

    Args:
        ranks: (M, F) integer ranks in 0..n_draws, independent across replicates.
        n_draws: L, the number of draws each rank was taken among.
        seed: seed of the PIT randomisation (numpy Generator).

    Returns:
        dict of (F,) arrays ``pit`` (M, F), ``mean_z2``, ``p_ks``, ``p_dispersion``,
        ``p_bias``, ``p_chi2``, ``p_functional`` and the float ``p_family``.
    """
    r = np.asarray(ranks)
    if r.ndim != 2 or r.min() < 0 or r.max() > n_draws:
        raise ValueError(f"ranks must be (M, F) integers in 0..{n_draws}")
    M, F = r.shape
    u = (r + np.random.default_rng(seed).uniform(size=r.shape)) / (n_draws + 1)
    z = stats.norm.ppf(u)
    s = np.sum(z**2, axis=0)
    p_disp = np.minimum(1.0, 2 * np.minimum(stats.chi2.cdf(s, M), stats.chi2.sf(s, M)))
    p_bias = 2 * stats.norm.sf(np.abs(np.sum(z, axis=0)) / np.sqrt(M))
    p_ks = np.array([stats.kstest(u[:, k], "uniform", method="exact").pvalue for k in range(F)])
    # rank histogram in B bins (B divides L+1 where possible, >= 20 expected per bin)
    B = max(b for b in range(1, n_draws + 2) if (n_draws + 1) % b == 0 and M / b >= 20) if M >= 20 else 1
    binned = r * B // (n_draws + 1)
    counts = np.stack([np.bincount(binned[:, k], minlength=B) for k in range(F)])
    p_chi2 = stats.chisquare(counts, axis=1).pvalue if B > 1 else np.ones(F)
    p_fun = np.minimum(1.0, 3 * np.minimum(np.minimum(p_ks, p_disp), p_bias))
    return dict(
        pit=u,
        mean_z2=s / M,
        p_ks=p_ks,
        p_dispersion=p_disp,
        p_bias=p_bias,
        p_chi2=np.asarray(p_chi2),
        p_functional=p_fun,
        p_family=float(min(1.0, F * p_fun.min())),
    )


def run_sbc(
    key: jax.Array,
    system: LinearSystem,
    sampler,
    *,
    n_replicates: int,
    n_draws: int,
    functionals=None,
    names=None,
    posterior: LinearSystem | None = None,
    batch_size: int | None = 50,
) -> SBCResult:
    """Simulation-based calibration of ``sampler`` on ``system``'s model.

    Truths are drawn from ``system``'s prior, data from its likelihood (NaN under
    flags, cleaned by :func:`gcrsky.model.noise.clean_data` exactly as real data are), and
    the ranks come from ``sampler`` applied to ``posterior`` (default ``system``) with
    each replicate's data.  A ``posterior`` that differs from ``system`` (e.g. a noise
    variance off by 2) is a misspecification study: SBC should then fail.

    Args:
        key: PRNG key (fixed key, same result).
        system: the generative model (proper prior needed).
        sampler: e.g. :class:`GCRSampler`; see :func:`posterior_ranks`.
        n_replicates: M; n_draws: L.
        functionals, names: (F, Nf, n) weights and their names; default
            :func:`default_functionals` of ``system``.
        posterior: the system the sampler targets (same shapes as ``system``).
        batch_size: replicates vmapped together.

    Returns:
        :class:`SBCResult`.
    """
    if np.any(np.asarray(system.prior.inv_var) <= 0):
        raise ValueError("SBC draws truths from the prior: it must be proper (S^-1 > 0)")
    if functionals is None:
        functionals, names, _ = default_functionals(system)
    functionals = np.asarray(functionals, np.float64)
    names = tuple(names) if names is not None else tuple(f"f{k}" for k in range(functionals.shape[0]))
    posterior = system if posterior is None else posterior
    ksim, krank, kpit = jax.random.split(key, 3)
    truths, raw = simulate_replicates(ksim, system, int(n_replicates))
    data = clean_data(np.asarray(raw), np.asarray(posterior.inv_noise))
    ranks, ok = posterior_ranks(
        krank, posterior, truths, jnp.asarray(data), jnp.asarray(functionals), sampler, int(n_draws), batch_size
    )
    ranks, ok = np.asarray(ranks), np.asarray(ok)
    st = rank_pvalues(ranks, int(n_draws), seed=int(jax.random.randint(kpit, (), 0, 2**31 - 1)))
    log.info(
        "SBC %s: M=%d L=%d, family p = %.3g, min functional p = %.3g (%s), %d unconverged replicates",
        sampler,
        n_replicates,
        n_draws,
        st["p_family"],
        st["p_functional"].min(),
        names[int(np.argmin(st["p_functional"]))],
        int((~ok).sum()),
    )
    return SBCResult(names=names, ranks=ranks, n_draws=int(n_draws), converged=ok, **st)


# ---------------------------------------------------------------- examples and negative controls


def flagged_example_problem(lmax: int = 4, nside: int = 16, nt: int = 6, seed: int = 0):
    """A small flagged problem for calibration studies, and its flags (1, nt, 45).

    The 10-antenna hexagon (14 m Gaussian dishes, HERA latitude), one channel at
    100 MHz, ``nt`` LSTs over 0-6 h, heterogeneous per-component noise sigma in
    [1.5, 3] x 1e-4, an isotropic prior C_l = 200 / (1 + l)^2, and flags: 20% of
    samples at random plus the whole time index 2 and the whole baseline index 7,
    with NaN in the flagged data (cleaned like real data).  Only the flags, sigma
    and prior matter for SBC: the data are re-simulated per replicate.
    """
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    n = (lmax + 1) ** 2
    prior = isotropic_prior((200.0 / (1.0 + np.arange(lmax + 1)) ** 2)[None], n)
    rng = np.random.default_rng(seed)
    sigma = rng.uniform(1.5e-4, 3e-4, (1, nt, 45))
    flags = rng.random((1, nt, 45)) < 0.2
    flags[:, 2, :] = True  # one whole time
    flags[:, :, 7] = True  # one whole baseline
    data = np.where(flags, np.nan + 0j, 0.0)  # only the flags and sigma matter for SBC
    prob = build_problem(
        arr,
        [100e6],
        hours_to_rad(np.linspace(0, 6, nt)),
        lmax,
        nside,
        data=data,
        sigma=sigma,
        weights=weights_from_flags(flags),
        prior=prior,
    )
    return prob, flags


def reference_bug_sampler(key, system, ndraws):
    """A deliberately *wrong* sampler, for power checks: the reference code's GCR: data-space fluctuation ``(randn + i randn) / sqrt 2`` with
    per-component inverse variances, i.e. the data term of the fluctuation rhs scaled by
    1/sqrt 2 (``fluctuation_rhs`` of a system with W/2).  Solved exactly (dense Cholesky)."""
    P = precision_matrix(system)
    C = jnp.linalg.cholesky(P)
    half = system._replace(inv_noise=system.inv_noise / 2.0)
    fl = jax.vmap(lambda k: fluctuation_rhs(k, half), out_axes=1)(jax.random.split(key, ndraws))  # (Nf, L, n)
    rhs = wiener_rhs(system)[:, None, :] + fl
    x = jax.vmap(lambda c, r: jax.scipy.linalg.cho_solve((c, True), r.T).T)(C, rhs)
    return x, jnp.all(jnp.isfinite(x))
